#!/usr/bin/env bash
# Runs every cargo-fuzz target of fuzz/ for a fixed number of executions
# (docs/resource-policy.md).
#
#   scripts/fuzz.sh [RUNS] [TARGET...]     default: 20000 runs, every target
#
# Each target starts from its committed seeds (fuzz/corpus/<target>/seed-*,
# written by fuzz/make_seeds.py) plus whatever earlier runs added, with a 2 GB
# memory cap (-rss_limit_mb=2048, also per allocation: -malloc_limit_mb) and a
# 10 s per-input timeout: a crash, an out-of-memory or a hang fails the script,
# leaving the input in fuzz/artifacts/<target>/. A summary line per target gives
# the executions done and the wall time. Stable toolchain only: cargo-fuzz needs
# nightly flags, which RUSTC_BOOTSTRAP=1 allows; no sanitizer (a Rust crate
# with no unsafe code of its own gains little from ASan, and the build is 3x
# shorter). Installs cargo-fuzz when missing. FUZZ_DEV=1 builds the targets
# unoptimized (cargo fuzz --dev): half the build time, for short passes such
# as CI's, where the build dominates; long runs use the optimized build.
set -euo pipefail
cd "$(dirname "$0")/.."
runs=${1:-20000}
shift || true
export RUSTC_BOOTSTRAP=1
export CARGO_TARGET_DIR=${FUZZ_TARGET_DIR:-$PWD/target/fuzz}
if ! cargo fuzz --version >/dev/null 2>&1; then
  cargo install cargo-fuzz --locked
fi
python3 fuzz/make_seeds.py >/dev/null
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
  mapfile -t targets < <(cd fuzz && cargo fuzz list)
fi
profile=()
if [ -n "${FUZZ_DEV:-}" ]; then
  profile=(--dev)
fi
# One build of every target (they share all dependencies).
(cd fuzz && cargo fuzz build "${profile[@]}" --sanitizer none)
status=0
for t in "${targets[@]}"; do
  mkdir -p "fuzz/corpus/$t" "fuzz/artifacts/$t"
  log=$(mktemp)
  t0=$(date +%s)
  if (cd fuzz && cargo fuzz run "${profile[@]}" --sanitizer none "$t" "corpus/$t" -- \
        -runs="$runs" -rss_limit_mb=2048 -malloc_limit_mb=2048 -timeout=10 \
        -max_len=65536 -print_final_stats=1 -artifact_prefix="artifacts/$t/") >"$log" 2>&1; then
    done_runs=$(grep -o 'Done [0-9]* runs' "$log" | tail -1 | grep -o '[0-9]*' || echo "?")
    echo "fuzz $t: ok, $done_runs executions in $(( $(date +%s) - t0 )) s"
  else
    echo "fuzz $t: FAILED after $(( $(date +%s) - t0 )) s; log:"
    grep -E 'ERROR|panicked|Test unit written|SUMMARY|deadly|out-of-memory|timeout|error' "$log" | head -20 || true
    status=1
  fi
  rm -f "$log"
done
exit $status
