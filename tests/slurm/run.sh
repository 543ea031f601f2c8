#!/usr/bin/env bash
# Sharded gonio runs through a real Slurm: a one-node cluster from Debian's packages
# (slurmctld, slurmd, munge; all state, sockets and logs in a scratch directory, private
# ports), then `gonio batch slurm --submit` for
#   1. a sharded `gonio sim btf` (3 shards) whose shard 2 fails on its first attempt: the
#      array task retries it once, and the merged dataset must equal a single-process run
#      byte for byte (manifest: all but `created_unix`);
#   2. a sharded PVMF (`gonio compress --method pvmf`, 3 shards) of that dataset: the merged
#      .gbtf must equal the single-process file byte for byte;
#   3. a sharded PVMF whose shard 3 always fails: the retry fails too, the merge job still
#      runs (afterany) and its error names the missing part;
#   3b. sharded PCA (3 shards) and local PCA (4 shards, every pass merged as a tree of
#      2 groups of 2, --merge-fanout): a chain of one array and one merge (tree) per pass
#      over the views; the merged .gbtf must equal the single-process file;
#   3c. a sharded simulated acquisition (3 shards): images and plan equal one process's;
#   4. a dataset family (`gonio dataset generate`, 3 shards into one directory): the last
#      job's check finds every member complete, equal to a single-process run byte for byte.
# Per-task times of the shards and the merges are printed as `slurm:` lines.
#
# Usage: tests/slurm/run.sh        (root; Debian packages slurmctld slurmd slurm-client munge)
#        SLURM_REQUEUE=1 ...       also run case 1 with --retry-mode requeue (Slurm itself
#                                  restarts the failed task; ~3 more minutes: a requeued task
#                                  waits ~2 minutes before it is eligible again)
#        SLURM_KEEP=1 ...          keep the scratch directory (logs, parts, scripts)
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
log() { echo "slurm: $*" >&2; }
die() { echo "slurm: FAIL: $*" >&2; exit 1; }

for tool in slurmctld slurmd sbatch squeue scontrol munged; do
  command -v "$tool" >/dev/null || command -v "/usr/sbin/$tool" >/dev/null ||
    die "$tool not found: apt-get install -y --no-install-recommends slurmctld slurmd slurm-client munge"
done
[ "$(id -u)" = 0 ] || die "needs root (the one-node Slurm runs its daemons as root)"

# GONIO_BIN: the binary the test stage already built (tests/run.sh exports it); else build.
if [ -n "${GONIO_BIN:-}" ]; then
  GONIO=$GONIO_BIN
else
  cargo build -q -p gonio --bin gonio
  GONIO=$ROOT/target/debug/gonio
fi

S=$(mktemp -d /tmp/gonio-slurm.XXXXXX)
PIDS=()
cleanup() {
  for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done
  sleep 1
  if [ -z "${SLURM_KEEP:-}" ]; then rm -rf "$S"; else log "kept $S"; fi
}
trap cleanup EXIT

# --- one-node Slurm -------------------------------------------------------------------
mkdir -p "$S"/{state,spool,log,run}
head -c 1024 /dev/urandom >"$S/munge.key"
chmod 600 "$S/munge.key"
chown munge:munge "$S/munge.key" 2>/dev/null || true
mkdir -p "$S/munge" && chown munge:munge "$S/munge" 2>/dev/null || true
munged --force --key-file="$S/munge.key" --socket="$S/munge/munge.socket" \
  --pid-file="$S/munge/munged.pid" --log-file="$S/munge/munged.log" --seed-file="$S/munge/munged.seed"
for _ in $(seq 50); do [ -s "$S/munge/munged.pid" ] && break; sleep 0.1; done
PIDS+=("$(cat "$S/munge/munged.pid")")
HOST=$(hostname)
MEM=$(awk '/MemTotal/ {print int($2 / 1024 / 2)}' /proc/meminfo)
cat >"$S/slurm.conf" <<CONF
ClusterName=gonio-test
SlurmctldHost=$HOST(127.0.0.1)
SlurmctldPort=16817
SlurmdPort=16818
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
AuthInfo=socket=$S/munge/munge.socket
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
MpiDefault=none
ReturnToService=2
StateSaveLocation=$S/state
SlurmdSpoolDir=$S/spool
SlurmctldPidFile=$S/run/slurmctld.pid
SlurmdPidFile=$S/run/slurmd.pid
SlurmctldLogFile=$S/log/slurmctld.log
SlurmdLogFile=$S/log/slurmd.log
NodeName=$HOST NodeAddr=127.0.0.1 CPUs=2 RealMemory=$MEM State=UNKNOWN
PartitionName=debug Nodes=$HOST Default=YES State=UP MaxTime=INFINITE
CONF
export SLURM_CONF=$S/slurm.conf
slurmctld -i
slurmd
for _ in $(seq 100); do [ -s "$S/run/slurmctld.pid" ] && [ -s "$S/run/slurmd.pid" ] && break; sleep 0.1; done
PIDS+=("$(cat "$S/run/slurmd.pid")" "$(cat "$S/run/slurmctld.pid")")
for _ in $(seq 60); do
  sinfo -h -o %t 2>/dev/null | grep -qx idle && break
  sleep 1
done
sinfo -h -o %t | grep -qx idle || die "the node did not become idle: $(sinfo 2>&1); see $S/log"
log "one-node Slurm up ($(sinfo -V))"

# Wait until a job has left the queue (finished, failed or cancelled).
wait_job() {
  local id=$1 limit=${2:-300} t=0
  while squeue -h -j "$id" 2>/dev/null | grep -q .; do
    sleep 1
    t=$((t + 1))
    [ $t -lt "$limit" ] || die "job $id still queued after $limit s: $(squeue)"
  done
}
job_state() { scontrol show job "$1" 2>/dev/null | sed -n 's/.*JobState=\([A-Z_]*\).*/\1/p' | head -1; }
json_field() { sed -n "s/.*\"$2\": \"\{0,1\}\([^\",]*\)\"\{0,1\},\{0,1\}$/\1/p" "$1" | head -1; }
# Every file of two outputs by SHA-256; the manifest without its creation time.
same_tree() {
  local a=$1 b=$2
  diff <(cd "$a" && find . -type f ! -name manifest.json | sort | xargs sha256sum) \
    <(cd "$b" && find . -type f ! -name manifest.json | sort | xargs sha256sum) >&2 ||
    return 1
  diff <(grep -v '"created_unix"' "$a/manifest.json") <(grep -v '"created_unix"' "$b/manifest.json") >&2
}
# Shard and merge times from the logs ("… at <ISO time>" lines of the array script).
seconds_between() { echo $(($(date -d "$2" +%s) - $(date -d "$1" +%s))); }

# A gonio that fails the first attempt of shard 2 (a crash, then a good retry).
cat >"$S/flaky-gonio" <<EOF
#!/bin/bash
case " \$* " in
  *" 2/3 "*) if [ ! -e "$S/failed-once" ]; then touch "$S/failed-once"; echo "injected failure" >&2; exit 3; fi ;;
esac
exec "$GONIO" "\$@"
EOF
# A gonio whose shard 3 always fails.
cat >"$S/broken-gonio" <<EOF
#!/bin/bash
case " \$* " in *" 3/3 "*) echo "injected permanent failure" >&2; exit 4 ;; esac
exec "$GONIO" "\$@"
EOF
chmod +x "$S/flaky-gonio" "$S/broken-gonio"

BTF_ARGS=(sim btf --sweep fibonacci:9 --size 32 --json)
PVMF_ARGS=(--method pvmf -c 4 --no-eval --json)

# --- single-process references ----------------------------------------------------------
t0=$(date +%s.%N)
"$GONIO" "${BTF_ARGS[@]}" --out "$S/ref-btf" >/dev/null
t1=$(date +%s.%N)
log "single-process sim btf (9 × 9 × 32²): $(awk "BEGIN {printf \"%.2f\", $t1 - $t0}") s"

# --- 1. sharded sim btf, shard 2 fails once ----------------------------------------------
run_btf() { # mode work out
  "$GONIO" batch slurm --shards 3 --work "$2" --out "$3" --retry-mode "$1" --gonio "$S/flaky-gonio" \
    --submit --json -- "${BTF_ARGS[@]}" >"$2.json"
  local a m
  a=$(json_field "$2.json" array_job)
  m=$(json_field "$2.json" merge_job)
  [ -n "$a" ] && [ -n "$m" ] || die "no job ids in $(cat "$2.json")"
  wait_job "$m" 600
  [ "$(job_state "$m")" = COMPLETED ] || die "merge job $m: $(job_state "$m"); $(cat "$2/logs/merge.log")"
  grep -q "attempt 1 .*failed\|failed (exit 3); asking Slurm to requeue" "$2/logs/shard-2.log" ||
    die "shard 2 did not fail first: $(cat "$2/logs/shard-2.log")"
  grep -q "gonio shard 2/3: done" "$2/logs/shard-2.log" || die "shard 2 was not retried: $(cat "$2/logs/shard-2.log")"
  same_tree "$S/ref-btf" "$3" || die "merged sim btf ($3) differs from the single-process run"
  log "sim btf, 3 shards ($1 retry): shard 2 failed once and was retried; merged = single-process, byte for byte"
}
run_btf in-job "$S/w-btf" "$S/btf"
if [ -n "${SLURM_REQUEUE:-}" ]; then
  rm -f "$S/failed-once"
  run_btf requeue "$S/w-btf-requeue" "$S/btf-requeue"
fi

# --- 2. sharded PVMF of that dataset ----------------------------------------------------
"$GONIO" compress "$S/btf" "${PVMF_ARGS[@]}" --out "$S/ref.gbtf" >/dev/null
"$GONIO" batch slurm --shards 3 --work "$S/w-pvmf" --out "$S/pvmf.gbtf" --submit --json \
  -- compress "$S/btf" "${PVMF_ARGS[@]}" >"$S/w-pvmf.json"
m=$(json_field "$S/w-pvmf.json" merge_job)
wait_job "$m" 300
[ "$(job_state "$m")" = COMPLETED ] || die "PVMF merge job $m: $(cat "$S/w-pvmf/logs/merge.log")"
cmp "$S/ref.gbtf" "$S/pvmf.gbtf" || die "merged PVMF differs from the single-process file"
log "PVMF, 3 shards: merged .gbtf = single-process, byte for byte ($(stat -c %s "$S/pvmf.gbtf") bytes)"

# --- 3. a shard that fails for good: the merge names it ----------------------------------
"$GONIO" batch slurm --shards 3 --work "$S/w-broken" --out "$S/broken.gbtf" --gonio "$S/broken-gonio" \
  --submit --json -- compress "$S/btf" "${PVMF_ARGS[@]}" >"$S/w-broken.json"
m=$(json_field "$S/w-broken.json" merge_job)
wait_job "$m" 300
[ "$(job_state "$m")" = FAILED ] || die "merge of a broken array: job state $(job_state "$m")"
grep -q "shard 3/3: attempt 2 failed" "$S/w-broken/logs/shard-3.log" || die "shard 3 was not retried once"
grep -q "missing part(s) $S/w-broken/parts/part-3.gbtf" "$S/w-broken/logs/merge.log" ||
  die "the merge did not name the missing part: $(cat "$S/w-broken/logs/merge.log")"
[ ! -e "$S/broken.gbtf" ] || die "a merge with a missing part wrote an output"
log "PVMF, shard 3 failing for good: retried once, merge failed naming part-3.gbtf"

# --- 3b. sharded PCA: one array + merge per randomized-SVD pass, chained ---------------
PCA_ARGS=(--method pca -c 4 --no-eval --json)
"$GONIO" compress "$S/btf" "${PCA_ARGS[@]}" --out "$S/ref-pca.gbtf" >/dev/null
t0=$(date +%s.%N)
"$GONIO" batch slurm --shards 3 --work "$S/w-pca" --out "$S/pca.gbtf" --submit --json \
  -- compress "$S/btf" "${PCA_ARGS[@]}" >"$S/w-pca.json"
m=$(json_field "$S/w-pca.json" merge_job)
wait_job "$m" 600
t1=$(date +%s.%N)
# The chain's wall time: 4 rounds of (array → merge), so 8 dependent job starts; the tasks
# themselves take well under a second each at this size.
echo "slurm: PCA chain of 8 jobs: $(awk "BEGIN {printf \"%.1f\", $t1 - $t0}") s wall from submit to the last merge"
[ "$(job_state "$m")" = COMPLETED ] || die "PCA final merge job $m: $(job_state "$m"); $(cat "$S/w-pca/logs/"merge*.log)"
for r in 0 1 2; do
  [ -f "$S/w-pca/state-$r.gstate" ] || die "PCA round $r left no state"
done
cmp "$S/ref-pca.gbtf" "$S/pca.gbtf" || die "merged sharded PCA differs from the single-process file"
log "PCA, 3 shards × 4 passes (8 chained jobs): merged .gbtf = single-process, byte for byte"

# --- 3b'. sharded local PCA: nine passes over the views, each merged as a tree ----------
LPCA_ARGS=(--method local-pca -c 2 --clusters 3 --subspace 8 --in-passes --no-eval --json)
"$GONIO" compress "$S/btf" "${LPCA_ARGS[@]}" --out "$S/ref-lpca.gbtf" >/dev/null
t0=$(date +%s.%N)
"$GONIO" batch slurm --shards 4 --merge-fanout 2 --work "$S/w-lpca" --out "$S/lpca.gbtf" --submit --json \
  -- compress "$S/btf" "${LPCA_ARGS[@]}" >"$S/w-lpca.json"
m=$(json_field "$S/w-lpca.json" merge_job)
wait_job "$m" 900
t1=$(date +%s.%N)
echo "slurm: local PCA chain of 27 jobs: $(awk "BEGIN {printf \"%.1f\", $t1 - $t0}") s wall from submit to the last merge"
[ "$(job_state "$m")" = COMPLETED ] || die "local PCA final merge job $m: $(job_state "$m"); $(cat "$S/w-lpca/logs/"merge*.log)"
for g in 1 2; do
  [ -f "$S/w-lpca/parts/pass-8/group-$g.gpart" ] || die "the tree merge left no group part $g"
done
cmp "$S/ref-lpca.gbtf" "$S/lpca.gbtf" || die "merged sharded local PCA differs from the single-process file"
log "local PCA, 4 shards × 9 passes, merged as trees of 2 groups of 2 (27 chained jobs): merged .gbtf = single-process, byte for byte"

# --- 3c. a sharded simulated acquisition ------------------------------------------------
ACQ_ARGS=(acquire --sweep fibonacci:6 --size 24x24 --seed 7 --json)
"$GONIO" "${ACQ_ARGS[@]}" --out "$S/ref-acq" >/dev/null
"$GONIO" batch slurm --shards 3 --work "$S/w-acq" --out "$S/acq" --submit --json -- "${ACQ_ARGS[@]}" >"$S/w-acq.json"
m=$(json_field "$S/w-acq.json" merge_job)
wait_job "$m" 300
[ "$(job_state "$m")" = COMPLETED ] || die "acquisition merge job $m: $(cat "$S/w-acq/logs/merge.log")"
diff <(cd "$S/ref-acq" && sha256sum plan.json images/*) <(cd "$S/acq" && sha256sum plan.json images/*) >&2 ||
  die "merged sharded acquisition: images or plan differ from the single-process run"
log "acquisition, 3 shards: merged images and plan = single-process, byte for byte"

# --- 4. a dataset family: 3 shards render into one directory, the last job checks it -----
cat >"$S/family.toml" <<EOF
name = "tiny"
members = 3
seed = 5
sample = "leather"
sweep = "fibonacci:2"
size = 16
[[vary]]
key = "material.0.alpha"
log_uniform = [0.05, 0.5]
EOF
"$GONIO" dataset generate "$S/family.toml" --out "$S/ref-family" --json >/dev/null
"$GONIO" batch slurm --shards 3 --work "$S/w-family" --out "$S/family" --submit --json \
  -- dataset generate "$S/family.toml" >"$S/w-family.json"
m=$(json_field "$S/w-family.json" merge_job)
wait_job "$m" 300
[ "$(job_state "$m")" = COMPLETED ] || die "family check job $m: $(cat "$S/w-family/logs/merge.log")"
grep -q '"complete": 3' "$S/w-family/logs/merge.log" || die "family check: $(cat "$S/w-family/logs/merge.log")"
for f in family.json labels.csv family.toml; do
  cmp "$S/ref-family/$f" "$S/family/$f" || die "family $f differs from the single-process run"
done
for i in 0000 0001 0002; do
  same_tree "$S/ref-family/members/$i" "$S/family/members/$i" ||
    die "family member $i differs from the single-process run"
done
log "dataset family, 3 shards into one directory: checked complete; = single-process, byte for byte"

# --- per-task times (from the jobs' own logs) --------------------------------------------
for w in w-btf w-pvmf; do
  for i in 1 2 3; do
    f="$S/$w/logs/shard-$i.log"
    s=$(grep -o "attempt [0-9]* of [0-9]* at [^ ]*" "$f" | tail -1 | awk '{print $NF}')
    e=$(grep -o "done at [^ ]*" "$f" | awk '{print $NF}')
    echo "slurm: $w shard $i/3: $(seconds_between "$s" "$e") s (last attempt, whole seconds)"
  done
  echo "slurm: $w merge: $(grep -o '"seconds": [0-9.]*' "$S/$w/logs/merge.log" | awk '{print $2}') s"
done
log "PASS"
