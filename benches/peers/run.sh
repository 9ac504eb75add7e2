#!/usr/bin/env bash
# Peer comparison, both sides: palpate exports and times its kernels, then
# Brian2 and scikit-learn run on the same arrays (benches/peers/README.md).
#
#   benches/peers/run.sh [--seed N] [-- run.py options]
#
# Uses benches/peers/.venv (created and filled from requirements.txt when
# missing) and writes benches/peers/work/ plus benches/peers/RESULTS-peers.md.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
seed=1
py_args=()
while [[ $# -gt 0 ]]; do
    case "$1" in
        --seed) seed="$2"; shift 2 ;;
        --) shift; py_args=("$@"); break ;;
        *) echo "usage: $0 [--seed N] [-- run.py options]" >&2; exit 2 ;;
    esac
done
venv="$here/.venv"
if [[ ! -x "$venv/bin/python" ]]; then
    python3 -m venv "$venv"
    "$venv/bin/pip" install -r "$here/requirements.txt"
fi
work="$here/work"
mkdir -p "$work"
# One thread for the numeric libraries and for palpate's rayon pool (the SVM
# trains its pairwise machines in parallel, the Gram matrix by rows): both
# sides fit and predict on one core.
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 RAYON_NUM_THREADS=1
cd "$root"
cargo run --release --example peers -- --out "$work" --seed "$seed"
"$venv/bin/python" "$here/run.py" --work "$work" \
    --command "benches/peers/run.sh --seed $seed${py_args[*]:+ -- ${py_args[*]}}" "${py_args[@]}"
