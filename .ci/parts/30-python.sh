#!/usr/bin/env bash
# CI part: palpate's Python package. Builds python/ with maturin into a
# fresh venv, reusing the workspace's target/ (cargo's dev profile, whose
# dependencies `cargo test --workspace` just built), then runs its pytest suite,
# tonic and scikit-learn tests included, against the CLI binary the same build made.
set -euo pipefail
cd "$(dirname "$0")/../.."
root=$(pwd)

py=""
for c in python3 python; do
  if command -v "$c" >/dev/null 2>&1 && "$c" -c 'import sys; sys.exit(sys.version_info < (3, 9))'; then
    py=$c
    break
  fi
done
if [ -z "$py" ]; then
  if command -v apt-get >/dev/null 2>&1; then
    apt-get update -qq && apt-get install -y -qq python3 python3-venv python3-dev >/dev/null
    py=python3
  else
    echo "SKIPPED: no Python >= 3.9 and no apt-get to install one"
    exit 0
  fi
fi
if ! "$py" -c 'import venv, ensurepip' >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then
  apt-get update -qq && apt-get install -y -qq python3-venv >/dev/null
fi

venv="$root/target/py-venv"
[ -x "$venv/bin/python" ] || "$py" -m venv "$venv"
pip() { "$venv/bin/python" -m pip --disable-pip-version-check -q "$@"; }
pip install --upgrade pip
pip install "maturin>=1.5,<2" pytest numpy tonic scikit-learn matplotlib

# Same target dir and profile as the workspace build: only the pyo3 crates and
# the bindings compile here. PALPATE_CLI is the binary `cargo test` built.
export PATH="$venv/bin:$PATH"
export CARGO_TARGET_DIR="$root/target"
export MATURIN_PEP517_ARGS="--profile dev"
pip install --no-build-isolation "$root/python"

cargo build --bin palpate
export PALPATE_CLI="$root/target/debug/palpate"
export PALPATE_REQUIRE_TONIC=1 PALPATE_REQUIRE_SKLEARN=1

# Run from outside the source tree so the installed wheel is what is tested.
cd "$root/python/tests"
set +e
"$venv/bin/python" -m pytest -q -p no:cacheprovider .
rc=$?
set -e
if [ "$rc" -eq 5 ]; then
  echo "pytest collected no tests: failing" >&2
  exit 1
fi
if [ "$rc" -ne 0 ]; then
  exit "$rc"
fi

# The examples run as a user would run them.
cd "$root"
"$venv/bin/python" examples/python/python_stages.py > "$root/target/py-example.log"
grep -q "centroid" "$root/target/py-example.log"
# The quickstart example on a cut scene (2 trials per angle): it checks that the
# building blocks give the graph's WSS scores bit for bit, and draws its plot.
"$venv/bin/python" examples/python/quickstart.py --trials-per-angle 2 --out "$root/target/py-quickstart" > "$root/target/py-quickstart.log"
grep -q "bit for bit" "$root/target/py-quickstart.log"
test -s "$root/target/py-quickstart/wss_vs_sklearn.png"
