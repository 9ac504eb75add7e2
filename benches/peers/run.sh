#!/usr/bin/env bash
# Peer comparison, both sides: palpate exports and times its kernels, then
# Brian2 and scikit-learn run on the same arrays (benches/peers/README.md).
#
#   benches/peers/run.sh [--seed N] [--avx2] [-- run.py options]
#
# Uses benches/peers/.venv (created and filled from requirements.txt when
# missing) and writes benches/peers/work/ plus benches/peers/RESULTS-peers.md.
#
# --avx2: both sides as on a CPU with AVX2 but no AVX-512 (AMD Zen 2 and
# Zen 3, most Intel desktop parts), on a machine that has AVX-512: palpate's
# AVX-512 kernels off (PALPATE_NO_AVX512), numpy's AVX-512 loops off
# (NPY_DISABLE_CPU_FEATURES) and OpenBLAS on its Haswell (AVX2) kernels
# (OPENBLAS_CORETYPE); the table goes to RESULTS-peers-avx2.md.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
seed=1
avx2=""
py_args=()
while [[ $# -gt 0 ]]; do
    case "$1" in
        --seed) seed="$2"; shift 2 ;;
        --avx2) avx2=" --avx2"; shift ;;
        --) shift; py_args=("$@"); break ;;
        *) echo "usage: $0 [--seed N] [--avx2] [-- run.py options]" >&2; exit 2 ;;
    esac
done
md=()
if [[ -n "$avx2" ]]; then
    export PALPATE_NO_AVX512=1 OPENBLAS_CORETYPE=Haswell
    export NPY_DISABLE_CPU_FEATURES="AVX512F AVX512CD AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL AVX512_SPR"
    md=(--md "$here/RESULTS-peers-avx2.md")
fi
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
    --command "benches/peers/run.sh --seed $seed$avx2${py_args[*]:+ -- ${py_args[*]}}" "${md[@]}" "${py_args[@]}"
