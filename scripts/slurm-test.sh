#!/usr/bin/env bash
# Integration test of `palpate slurm` against a real Slurm (no mock):
#   1. installs Debian's slurmctld, slurmd, slurm-client and munge when absent
#      (needs root and Debian's package archive);
#   2. starts a single-node cluster on this machine (munged, slurmctld, slurmd,
#      one partition `debug` with this host's CPUs) in a scratch folder;
#   3. writes the Slurm scripts for a small sweep (tests/data/cluster_sweep.toml,
#      8 points) with `palpate slurm --array-size 4`, submits the 4-task array and
#      its merge job (afterok), and waits for both;
#   4. runs the same sweep in one process and compares the merged report with it:
#      sweep.csv and sweep.json byte for byte, and every frontier row's accuracy
#      columns (timing columns differ between any two runs);
#   5. stops the daemons.
#
#   scripts/slurm-test.sh                 # builds palpate (release) first
#   PALPATE=path/to/palpate scripts/slurm-test.sh
#
# Exit 0: passed. Exit 1: failed. Exit 3: Slurm cannot be installed or started
# here (printed as SKIPPED with the reason); .ci/parts/50-slurm.sh turns that
# into a clear skip only when the package archive is unreachable.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)

skip() { echo "SKIPPED: $*"; exit 3; }

if [ -z "${PALPATE:-}" ]; then
  cargo build --release --quiet --bin palpate
  PALPATE="${CARGO_TARGET_DIR:-$root/target}/release/palpate"
fi
PALPATE=$(realpath "$PALPATE")

if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null || ! command -v sbatch >/dev/null \
   || ! command -v munged >/dev/null; then
  [ "$(id -u)" = 0 ] || skip "Slurm is not installed and this user cannot install it (not root)"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq >/dev/null 2>&1 || skip "apt-get update failed (no package archive reachable)"
  apt-get install -y -qq slurmctld slurmd slurm-client munge >/dev/null 2>&1 \
    || skip "apt-get install slurmctld slurmd slurm-client munge failed"
fi

work=$(mktemp -d /tmp/palpate-slurm.XXXXXX)
host=$(hostname -s)
cpus=$(nproc)
mem=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 / 2 ))
mkdir -p "$work"/{state,spool,log,run}

cleanup() {
  for p in slurmd slurmctld; do
    [ -f "$work/run/$p.pid" ] && kill "$(cat "$work/run/$p.pid")" 2>/dev/null || true
  done
  [ -f "$work/run/munged.pid" ] && kill "$(cat "$work/run/munged.pid")" 2>/dev/null || true
}
trap cleanup EXIT

# munge: a fresh key, a daemon with its own socket.
mkdir -p /etc/munge /var/lib/munge /var/log/munge /run/munge
[ -s /etc/munge/munge.key ] || dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
chown -R munge:munge /etc/munge /var/lib/munge /var/log/munge /run/munge 2>/dev/null || true
chmod 0400 /etc/munge/munge.key
if ! pgrep -x munged >/dev/null; then
  if id munge >/dev/null 2>&1; then
    runuser -u munge -- munged --pid-file="$work/run/munged.pid" 2>"$work/log/munged.err" \
      || munged -f --pid-file="$work/run/munged.pid" 2>>"$work/log/munged.err" \
      || skip "munged does not start: $(cat "$work/log/munged.err")"
  else
    munged -f --pid-file="$work/run/munged.pid" 2>"$work/log/munged.err" \
      || skip "munged does not start: $(cat "$work/log/munged.err")"
  fi
fi

conf="$work/slurm.conf"
cat > "$conf" <<EOF
ClusterName=palpate-test
SlurmctldHost=$host
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$work/state
SlurmdSpoolDir=$work/spool
SlurmctldPidFile=$work/run/slurmctld.pid
SlurmdPidFile=$work/run/slurmd.pid
SlurmctldLogFile=$work/log/slurmctld.log
SlurmdLogFile=$work/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
ReturnToService=2
MpiDefault=none
SlurmctldPort=16817
SlurmdPort=16818
NodeName=$host CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
export SLURM_CONF="$conf"

slurmctld -f "$conf" 2>"$work/log/slurmctld.err" || skip "slurmctld does not start: $(tail -5 "$work/log/slurmctld.err")"
slurmd -f "$conf" 2>"$work/log/slurmd.err" || skip "slurmd does not start: $(tail -5 "$work/log/slurmd.err")"

# Wait for the node to be idle.
for _ in $(seq 1 60); do
  state=$(sinfo -h -N -o '%t' 2>/dev/null | head -1 || true)
  case "$state" in idle*|mix*) break ;; esac
  sleep 1
done
case "${state:-}" in
  idle*|mix*) ;;
  *) echo "--- slurmctld.log"; tail -20 "$work/log/slurmctld.log" || true
     echo "--- slurmd.log"; tail -20 "$work/log/slurmd.log" || true
     skip "the Slurm node never became idle (state '${state:-none}')" ;;
esac
echo "slurm: node $host up ($cpus CPUs)"

graph=tests/data/cluster_sweep.toml
single="$work/single"
sharded="$work/sharded"

"$PALPATE" slurm "$graph" --out "$sharded" --array-size 4 --cpus 1 --time 00:20:00 --partition debug
sh "$sharded/slurm/submit.sh"
read -r array_id merge_id < "$sharded/slurm/jobs.txt"

# Wait for both jobs to leave the queue (20 min at most).
for _ in $(seq 1 1200); do
  if [ -z "$(squeue -h -j "$array_id,$merge_id" 2>/dev/null)" ]; then break; fi
  sleep 1
done
if [ -n "$(squeue -h -j "$array_id,$merge_id" 2>/dev/null)" ]; then
  echo "FAILED: Slurm jobs still queued after 20 min"; squeue; exit 1
fi
for f in "$sharded"/slurm/logs/*.out; do echo "--- $f"; tail -5 "$f"; done

tasks=$(ls "$sharded"/slurm/logs/shard-*.out 2>/dev/null | wc -l)
[ "$tasks" = 4 ] || { echo "FAILED: expected 4 array task logs, found $tasks"; exit 1; }
[ -f "$sharded/sweep.csv" ] || { echo "FAILED: the merge job wrote no sweep.csv"; exit 1; }

"$PALPATE" run "$graph" --out "$single" --threads 2 > "$work/single.log"

status=0
for f in sweep.csv sweep.json; do
  if cmp -s "$single/$f" "$sharded/$f"; then
    echo "same: $f"
  else
    echo "FAILED: $f differs between the single run and the Slurm merge"; diff "$single/$f" "$sharded/$f" | head -20
    status=1
  fi
done
python3 - "$single/frontier.json" "$sharded/frontier.json" <<'PY' || status=1
import json, sys
# Columns that measure time, or depend on which points shared a process's cache.
TIMING = {"compute_ms", "estimator_ms", "source_ms", "train_s_per_fold", "cached_stages",
          "on_frontier_compute", "on_own_frontier_compute"}
def acc(path):
    rows = json.load(open(path))
    return [{k: v for k, v in r.items() if k not in TIMING} for r in rows]
a, b = acc(sys.argv[1]), acc(sys.argv[2])
if a != b:
    print("FAILED: frontier accuracy columns differ"); sys.exit(1)
print(f"same: frontier.json accuracy columns ({len(a)} rows)")
PY
[ "$status" = 0 ] && echo "PASSED: Slurm array (4 tasks) + merge equals the single-process run"
exit "$status"
