#!/usr/bin/env bash
# A real single-node Slurm cluster runs a 4-task job array of a small sweep plus
# its merge job, and the merged report is compared with a single-process run
# (scripts/slurm-test.sh). Uses the debug binary `cargo test` already built.
set -euo pipefail
cd "$(dirname "$0")/../.."
bin="${CARGO_TARGET_DIR:-target}/debug/palpate"
[ -x "$bin" ] || cargo build --quiet --bin palpate
set +e
PALPATE="$bin" bash scripts/slurm-test.sh
code=$?
set -e
if [ "$code" = 3 ]; then
  # slurm-test.sh printed "SKIPPED: <why>". Skip only when the package archive
  # itself is unreachable; any other reason is a failure of our set-up.
  if apt-get update -qq >/dev/null 2>&1; then
    echo "Slurm could be installed but the test could not run: failing"
    exit 1
  fi
  exit 0
fi
exit "$code"
