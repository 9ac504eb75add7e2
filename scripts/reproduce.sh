#!/usr/bin/env bash
# Reproduces the paper's findings in one command:
#   1. builds the release binary,
#   2. runs every graph in graphs/paper/ (table2.toml included when present)
#      graphs/continuous.toml and graphs/shift/*.toml,
#      writing its reports into out/paper/<name>/,
#   3. runs graphs/accuracy_vs_time.toml (the accuracy-time frontier)
#      into out/accuracy_vs_time/ and the memory study (`cargo bench --bench
#      memory`, peak heap at 10/100/1000 s of input) into out/paper/memory.json,
#      and the WSS batch bench (criterion, one estimate per trial length),
#   4. runs scripts/results.py, which reads those reports and (re)writes
#      RESULTS.md and the plots in docs/results/,
# and prints the wall time of the whole run (also recorded in RESULTS.md).
#
#   scripts/reproduce.sh            # from anywhere inside the repository
#
# Honours CARGO_TARGET_DIR. Extra arguments are passed to every `palpate run`
# (e.g. `--threads 1`; results do not depend on it).
set -euo pipefail

cd "$(dirname "$0")/.."
OUT=out/paper
start=$(date +%s.%N)
load=$(cut -d" " -f1 /proc/loadavg 2>/dev/null || echo null)

echo "== building the release binary"
cargo build --release --quiet
target="${CARGO_TARGET_DIR:-target}"
bin="$target/release/palpate"
build_end=$(date +%s.%N)

mkdir -p "$OUT"
timings=()
for graph in graphs/paper/*.toml graphs/continuous.toml graphs/shift/*.toml; do
    name=$(basename "$graph" .toml)
    echo "== $graph -> $OUT/$name"
    "$bin" check "$graph"
    rm -rf "${OUT:?}/$name"
    t0=$(date +%s.%N)
    if ! "$bin" run "$graph" --out "$OUT/$name" "$@" > "$OUT/$name.log" 2>&1; then
        echo "FAILED: $graph (log: $OUT/$name.log)" >&2
        tail -20 "$OUT/$name.log" >&2
        exit 1
    fi
    t1=$(date +%s.%N)
    secs=$(printf '%.2f' "$(echo "$t1 - $t0" | bc)")
    printf '   %s s (log: %s)\n' "$secs" "$OUT/$name.log"
    timings+=("\"$name\": $secs")
done

# The paper's reproduction ends here (its wall time is the one recorded);
# the time study follows.
end=$(date +%s.%N)
total=$(printf '%.2f' "$(echo "$end - $start" | bc)")
extra=()
echo "== graphs/accuracy_vs_time.toml -> out/accuracy_vs_time"
rm -rf out/accuracy_vs_time
t0=$(date +%s.%N)
if ! "$bin" run graphs/accuracy_vs_time.toml --out out/accuracy_vs_time "$@" > out/accuracy_vs_time.log 2>&1; then
    echo "FAILED: graphs/accuracy_vs_time.toml (log: out/accuracy_vs_time.log)" >&2
    tail -20 out/accuracy_vs_time.log >&2
    exit 1
fi
t1=$(date +%s.%N)
extra+=("\"accuracy_vs_time\": $(printf '%.2f' "$(echo "$t1 - $t0" | bc)")")
echo "== memory study -> $OUT/memory.json"
cargo bench --quiet --bench memory -- --json "$OUT/memory.json" > "$OUT/memory.log" 2>&1
echo "== WSS batch bench (one estimate at 10, 45, 90 degrees) -> $target/criterion"
cargo bench --quiet --bench wss -- wss_batch > "$OUT/wss_bench.log" 2>&1
build=$(printf '%.2f' "$(echo "$build_end - $start" | bc)")
{
    printf '{"total_s": %s, "build_s": %s, "cores": %s, "load_at_start": %s, "graphs": {' \
        "$total" "$build" "$(nproc)" "$load"
    (IFS=,; printf '%s' "${timings[*]}")
    printf '}, "time_study": {'
    (IFS=,; printf '%s' "${extra[*]}")
    printf '}}\n'
} > "$OUT/timing.json"

echo "== writing RESULTS.md"
python3 scripts/results.py --out "$OUT" --results RESULTS.md --docs docs/results --criterion "$target/criterion"

end=$(date +%s.%N)
printf '== wall time of the whole run: %.0f s (graphs and build: %.0f s)\n' \
    "$(echo "$end - $start" | bc)" "$total"
