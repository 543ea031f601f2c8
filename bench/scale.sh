#!/usr/bin/env bash
# The scale model's inputs and its check (docs/guide/scale.md, "Scale model"): per-task costs of
# `gonio sim btf`, PVMF and PCA (every pass of the randomized SVD) on a fibonacci:$VIEWS
# BTF of $SIZE² texels, in 1 process and in 2 and 4 shards run one after the other (so each
# shard's time is its own, not a share of a contended CPU), the merges, and the bytes.
# Prints one JSON line per timed task, then the model's fit and check (bench/scale_model.py).
# Usage: bench/scale.sh [VIEWS] [SIZE] [BUILD]   (default 16 64 release)
set -euo pipefail
cd "$(dirname "$0")/.."
VIEWS=${1:-16}
SIZE=${2:-64}
BUILD=${3:-release}
if [ "$BUILD" = release ]; then
  cargo build -q --release -p gonio --bin gonio
  G=$PWD/target/release/gonio
else
  cargo build -q -p gonio --bin gonio
  G=$PWD/target/debug/gonio
fi
W=$(mktemp -d /tmp/gonio-scale.XXXXXX)
trap 'rm -rf "$W"' EXIT
OUT=${SCALE_OUT:-$W/scale.jsonl}
: >"$OUT"
now() { date +%s.%N; }
# line TASK SHARDS SHARD PASS SECONDS
line() { echo "{\"task\": \"$1\", \"shards\": $2, \"shard\": $3, \"pass\": $4, \"seconds\": $5, \"views\": $VIEWS, \"lights\": $VIEWS, \"texels\": $((SIZE * SIZE))}" | tee -a "$OUT"; }
timed() { # TASK SHARDS SHARD PASS CMD…
  local task=$1 n=$2 i=$3 p=$4
  shift 4
  local t
  t=$(now)
  "$@" >/dev/null
  line "$task" "$n" "$i" "$p" "$(awk "BEGIN {print $(now) - $t}")"
}
BTF=(sim btf --sweep "fibonacci:$VIEWS" --size "$SIZE" --json)
PVMF=(--method pvmf -c 8 --no-eval --json)
PCA=(--method pca -c 8 --no-eval --json)
PASSES=4 # 2 + the default 2 power iterations

# One process without --shard ("shards": 0): the single-process references.
timed sim_btf 0 1 0 "$G" "${BTF[@]}" --out "$W/full"
timed pvmf 0 1 0 "$G" compress "$W/full" "${PVMF[@]}" --out "$W/full.gbtf"
timed pca 0 1 0 "$G" compress "$W/full" "${PCA[@]}" --out "$W/pca.gbtf"
for n in 1 2 4; do
  parts=() gparts=()
  for i in $(seq 1 "$n"); do
    timed sim_btf "$n" "$i" 0 "$G" "${BTF[@]}" --shard "$i/$n" --out "$W/b$n-$i"
    parts+=("$W/b$n-$i")
  done
  timed merge_dataset "$n" 0 0 "$G" merge "${parts[@]}" --out "$W/m$n"
  for i in $(seq 1 "$n"); do
    timed pvmf "$n" "$i" 0 "$G" compress "$W/full" "${PVMF[@]}" --shard "$i/$n" --out "$W/g$n-$i.gbtf"
    gparts+=("$W/g$n-$i.gbtf")
  done
  timed merge_gbtf "$n" 0 0 "$G" merge "${gparts[@]}" --out "$W/m$n.gbtf"
  state=()
  for p in $(seq 0 $((PASSES - 1))); do
    pparts=()
    for i in $(seq 1 "$n"); do
      timed pca_pass "$n" "$i" "$p" "$G" compress "$W/full" "${PCA[@]}" --shard "$i/$n" "${state[@]}" \
        --out "$W/pca$n-p$p-$i.gpart"
      pparts+=("$W/pca$n-p$p-$i.gpart")
    done
    if [ "$p" -lt $((PASSES - 1)) ]; then
      timed merge_pass "$n" 0 "$p" "$G" merge "${pparts[@]}" --out "$W/pca$n-s$p.gstate"
      state=(--state "$W/pca$n-s$p.gstate")
    else
      timed merge_pass "$n" 0 "$p" "$G" merge "${pparts[@]}" --out "$W/pca$n.gbtf"
    fi
  done
  cmp -s "$W/full.gbtf" "$W/m$n.gbtf" && echo "{\"check\": \"pvmf $n shards merged = single\", \"ok\": true}" | tee -a "$OUT"
  cmp -s "$W/pca.gbtf" "$W/pca$n.gbtf" && echo "{\"check\": \"pca $n shards merged = single\", \"ok\": true}" | tee -a "$OUT"
done
b() { stat -c %s "$1"; }
echo "{\"bytes\": {\"dataset\": $(du -sb "$W/full" | cut -f1), \"pvmf_gbtf\": $(b "$W/full.gbtf"), \"pca_gbtf\": $(b "$W/pca.gbtf"), \"pca_sum_part\": $(b "$W/pca2-p0-1.gpart"), \"pca_projection_part\": $(b "$W/pca2-p3-1.gpart"), \"pca_state\": $(b "$W/pca2-s0.gstate")}}" | tee -a "$OUT"
python3 bench/scale_model.py "$OUT"
