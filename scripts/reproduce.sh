#!/usr/bin/env bash
# Reproduces the paper's findings in one command:
#   1. builds the release binary,
#   2. runs every graph in graphs/paper/, graphs/continuous.toml and
#      graphs/shift/*.toml on the lab scene, writing its reports into
#      out/paper/<name>/; the paper graphs run over 5 seeds each (their
#      [sweep] repeats), since one seed is one simulated array;
#   3. runs the paper graphs again on the paper_sensor scene (the scene
#      calibrated on the paper's sensor-level evidence: Fig. 3a levels, Fig. 5
#      spike-time spreads) into out/paper_sensor/<name>/, by overriding
#      `stages.scene.file` -- same stages, same seeds; the Fig. 5 graphs,
#      seeds.toml and speed_error.toml are lab-only (fig5_paper_sensor.toml is
#      paper_sensor's Fig. 5);
#   4. runs graphs/accuracy_vs_time.toml (the accuracy-time frontier)
#      into out/accuracy_vs_time/ and the memory study (`cargo bench --bench
#      memory`, peak heap at 10/100/1000 s of input) into out/paper/memory.json,
#      and the WSS batch bench (criterion, one estimate per trial length),
#   5. runs scripts/results.py, which reads those reports and (re)writes
#      RESULTS.md and the plots in docs/results/,
# and prints the wall time of the whole run (also recorded in RESULTS.md).
#
#   scripts/reproduce.sh            # from anywhere inside the repository
#
# The graphs of steps 2 and 3 run in one `palpate batch`, REPRODUCE_JOBS at
# a time (default: the core count), sharing the stages they have in common,
# so each graph's recorded wall time is taken while another graph runs
# beside it; `REPRODUCE_JOBS=1 scripts/reproduce.sh` runs them one by one.
#
# Honours CARGO_TARGET_DIR. Extra arguments are passed to `palpate batch` and
# `palpate run` (e.g. `--threads 1`; results do not depend on it).
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

mkdir -p "$OUT" out/paper_sensor
# The graphs run in one `palpate batch` process, REPRODUCE_JOBS at a time
# (default: one per core), longest first by the previous run's timing.json
# (new graphs first: their cost is unknown), sharing one cache: the lab
# graphs all simulate and encode the same trials per seed before their own
# stages, and so do the paper_sensor ones, so each seed's front end runs
# once per scene instead of once per graph (see `palpate batch --help`).
# Each graph runs on its own pool of cores/REPRODUCE_JOBS threads (one on 2
# cores), so two graphs side by side keep both cores busy and never run
# inside each other's stages (see `palpate batch --help`, `--threads`).
# Each graph's wall time in timing.json is then measured on its share of
# the machine, and without the stages another graph computed first.
jobs_max="${REPRODUCE_JOBS:-$(nproc)}"
[[ "$jobs_max" =~ ^[1-9][0-9]*$ ]] || { echo "REPRODUCE_JOBS must be a positive integer, not '$jobs_max'" >&2; exit 2; }
# Each job: "graph|outdir|key|set" (set: an optional `--set` override).
queue=()
for graph in graphs/paper/*.toml graphs/continuous.toml graphs/shift/*.toml; do
    name=$(basename "$graph" .toml)
    queue+=("$graph|$OUT/$name|$name|")
done
for graph in graphs/paper/*.toml; do
    name=$(basename "$graph" .toml)
    case "$name" in fig5*|seeds|speed_error) continue ;; esac
    queue+=("$graph|out/paper_sensor/$name|paper_sensor/$name|stages.scene.file=../scenes/paper_sensor.toml")
done
keys=()
for job in "${queue[@]}"; do IFS='|' read -r _ _ key _ <<< "$job"; keys+=("$key"); done
# Indices of the queue, longest previous run first.
mapfile -t order < <(python3 - "$OUT/timing.json" "${keys[@]}" <<'PY'
import json, sys
try:
    prev = json.load(open(sys.argv[1])).get("graphs", {})
except (OSError, ValueError):
    prev = {}
keys = sys.argv[2:]
inf = float("inf")
for i in sorted(range(len(keys)), key=lambda i: (-prev.get(keys[i], inf), i)):
    print(i)
PY
)
jobs_file="$OUT/.jobs.toml"
times_file="$OUT/.times.json"
: > "$jobs_file"
for i in "${order[@]}"; do
    IFS='|' read -r graph dir key set <<< "${queue[$i]}"
    set_args=()
    [[ -n "$set" ]] && set_args=(--set "$set")
    "$bin" check "$graph" "${set_args[@]}" > /dev/null
    rm -rf "${dir:?}"
    {
        printf '[[job]]\ngraph = "%s"\nout = "%s"\nname = "%s"\nlog = "%s.log"\n' "$graph" "$dir" "$key" "$dir"
        [[ -n "$set" ]] && printf 'set = ["%s"]\n' "$set"
        echo
    } >> "$jobs_file"
done
rm -f "$times_file"
"$bin" batch "$jobs_file" --jobs "$jobs_max" --times "$times_file" "$@"
timings=()
for key in "${keys[@]}"; do
    timings+=("\"$key\": $(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))[sys.argv[2]])' "$times_file" "$key")")
done
rm -f "$jobs_file" "$times_file"

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
    printf '{"total_s": %s, "build_s": %s, "cores": %s, "jobs": %s, "shared_cache": true, "load_at_start": %s, "graphs": {' \
        "$total" "$build" "$(nproc)" "$jobs_max" "$load"
    (IFS=,; printf '%s' "${timings[*]}")
    printf '}, "time_study": {'
    (IFS=,; printf '%s' "${extra[*]}")
    printf '}}\n'
} > "$OUT/timing.json"

echo "== writing RESULTS.md"
python3 scripts/results.py --out "$OUT" --sensor-out out/paper_sensor --results RESULTS.md --docs docs/results --criterion "$target/criterion"

end=$(date +%s.%N)
printf '== wall time of the whole run: %.0f s (graphs and build: %.0f s)\n' \
    "$(echo "$end - $start" | bc)" "$total"
