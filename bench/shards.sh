#!/usr/bin/env bash
# Per-task costs of sharded runs (docs/guide/scale.md): `gonio sim btf` and PVMF of a
# fibonacci:$VIEWS × $SIZE² BTF in 1 process and in 2 and 4 shards run one after the
# other (so each shard's time is its own, not a share of a contended CPU), plus the merges.
# Prints one JSON line per run. Usage: bench/shards.sh [VIEWS] [SIZE] (default 16 64).
set -euo pipefail
cd "$(dirname "$0")/.."
VIEWS=${1:-16}
SIZE=${2:-64}
cargo build -q -p gonio --bin gonio
G=$PWD/target/debug/gonio
W=$(mktemp -d /tmp/gonio-shards.XXXXXX)
trap 'rm -rf "$W"' EXIT
now() { date +%s.%N; }
line() { echo "{\"task\": \"$1\", \"shards\": $2, \"shard\": $3, \"seconds\": $4}"; }
BTF=(sim btf --sweep "fibonacci:$VIEWS" --size "$SIZE" --json)
PVMF=(--method pvmf -c 8 --no-eval --json)
t=$(now); "$G" "${BTF[@]}" --out "$W/full" >/dev/null; line sim_btf 1 1 "$(echo "$(now) - $t" | awk '{print $1 - $3}')"
t=$(now); "$G" compress "$W/full" "${PVMF[@]}" --out "$W/full.gbtf" >/dev/null; line pvmf 1 1 "$(echo "$(now) - $t" | awk '{print $1 - $3}')"
for n in 2 4; do
  parts=() gparts=()
  for i in $(seq 1 "$n"); do
    t=$(now); "$G" "${BTF[@]}" --shard "$i/$n" --out "$W/b$n-$i" >/dev/null; line sim_btf "$n" "$i" "$(echo "$(now) - $t" | awk '{print $1 - $3}')"
    parts+=("$W/b$n-$i")
  done
  t=$(now); "$G" merge "${parts[@]}" --out "$W/m$n" >/dev/null; line merge_dataset "$n" 0 "$(echo "$(now) - $t" | awk '{print $1 - $3}')"
  for i in $(seq 1 "$n"); do
    t=$(now); "$G" compress "$W/full" "${PVMF[@]}" --shard "$i/$n" --out "$W/g$n-$i.gbtf" >/dev/null; line pvmf "$n" "$i" "$(echo "$(now) - $t" | awk '{print $1 - $3}')"
    gparts+=("$W/g$n-$i.gbtf")
  done
  t=$(now); "$G" merge "${gparts[@]}" --out "$W/m$n.gbtf" >/dev/null; line merge_gbtf "$n" 0 "$(echo "$(now) - $t" | awk '{print $1 - $3}')"
  cmp -s "$W/full.gbtf" "$W/m$n.gbtf" && echo "{\"check\": \"pvmf $n shards merged = single\", \"ok\": true}"
done
du -sb "$W/full" "$W/full.gbtf" | awk '{print "{\"bytes\": " $1 ", \"path\": \"" $2 "\"}"}'
