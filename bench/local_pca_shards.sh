#!/usr/bin/env bash
# Sharded local PCA (docs/guide/scale.md, "Local PCA"): on a fibonacci:$VIEWS BTF of $SIZE²
# texels, local PCA (k = $K, c = $C, subspace $D) in one process, then all nine passes in
# 1, 2 and 4 shards run one after the other (so each shard's time is its own, not a share
# of a contended CPU), every merge, the bytes of every pass's part and state, and whether
# the merged file equals the single-process file. Prints one JSON line per timed task, then
# the per-pass model's fit and check (bench/local_pca_model.py).
# Usage: bench/local_pca_shards.sh [VIEWS] [SIZE] [BUILD]   (default 81 64 debug)
set -euo pipefail
cd "$(dirname "$0")/.."
VIEWS=${1:-81}
SIZE=${2:-64}
BUILD=${3:-debug}
K=${K:-32} C=${C:-8} D=${D:-64}
if [ "$BUILD" = release ]; then
  cargo build -q --release -p gonio --bin gonio
  G=$PWD/target/release/gonio
else
  cargo build -q -p gonio --bin gonio
  G=$PWD/target/debug/gonio
fi
W=$(mktemp -d /tmp/gonio-lpca.XXXXXX)
trap 'rm -rf "$W"' EXIT
OUT=${LPCA_OUT:-$W/lpca.jsonl}
: >"$OUT"
now() { date +%s.%N; }
# line TASK SHARDS SHARD PASS SECONDS [BYTES]
line() {
  echo "{\"task\": \"$1\", \"shards\": $2, \"shard\": $3, \"pass\": $4, \"seconds\": $5, \"bytes\": ${6:-0}, \"views\": $VIEWS, \"lights\": $VIEWS, \"texels\": $((SIZE * SIZE)), \"k\": $K, \"c\": $C, \"d\": $D}" |
    tee -a "$OUT"
}
timed() { # TASK SHARDS SHARD PASS OUTFILE CMD…
  local task=$1 n=$2 i=$3 p=$4 out=$5
  shift 5
  local t
  t=$(now)
  "$@" >/dev/null
  line "$task" "$n" "$i" "$p" "$(awk "BEGIN {print $(now) - $t}")" "$(stat -c %s "$out")"
}
LPCA_FUSED=(--method local-pca --clusters "$K" -c "$C" --subspace "$D" --no-eval --json)
LPCA=("${LPCA_FUSED[@]}" --in-passes)
PASSES=9

"$G" sim btf --sweep "fibonacci:$VIEWS" --size "$SIZE" --json --out "$W/full" >/dev/null
# One process without --shard ("shards": 0): the reference (--in-passes), and the fused
# encoder one process runs by default.
timed lpca 0 1 0 "$W/single.gbtf" "$G" compress "$W/full" "${LPCA[@]}" --out "$W/single.gbtf"
timed lpca_fused 0 1 0 "$W/fused.gbtf" "$G" compress "$W/full" "${LPCA_FUSED[@]}" --out "$W/fused.gbtf"
for n in 1 2 4; do
  state=()
  for p in $(seq 0 $((PASSES - 1))); do
    parts=()
    for i in $(seq 1 "$n"); do
      timed lpca_pass "$n" "$i" "$p" "$W/l$n-p$p-$i.gpart" \
        "$G" compress "$W/full" "${LPCA[@]}" --shard "$i/$n" "${state[@]}" --out "$W/l$n-p$p-$i.gpart"
      parts+=("$W/l$n-p$p-$i.gpart")
    done
    if [ "$p" -lt $((PASSES - 1)) ]; then
      timed merge_pass "$n" 0 "$p" "$W/l$n-s$p.gstate" "$G" merge "${parts[@]}" --out "$W/l$n-s$p.gstate"
      state=(--state "$W/l$n-s$p.gstate")
    else
      timed merge_pass "$n" 0 "$p" "$W/l$n.gbtf" "$G" merge "${parts[@]}" --out "$W/l$n.gbtf"
    fi
    rm -f "${parts[@]}" # the parts are read once; keep the disk small at large sizes
  done
  if cmp -s "$W/single.gbtf" "$W/l$n.gbtf"; then ok=true; else ok=false; fi
  echo "{\"check\": \"local pca $n shards merged = single\", \"ok\": $ok}" | tee -a "$OUT"
done
python3 bench/local_pca_model.py "$OUT"
