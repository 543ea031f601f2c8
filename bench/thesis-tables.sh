#!/usr/bin/env bash
# The thesis' Table 7.1 (PVMF at every c) and Table 8.1 (median cut: 256 balanced,
# 256 unbalanced, 400 unbalanced) re-measured with gonio on a full ground-truth BTF.
# Usage: bench/thesis-tables.sh DATASET [GONIO] [OUTDIR]
#   DATASET  e.g. the default sample's full truth: `gonio sim btf --out DATASET` (6561 × 256²)
# Prints one markdown row per run: errors on 8-bit sRGB codes /255 (as the thesis), ratio
# against the raw 8-bit images, encode seconds, and the machine's load average at the end.
set -euo pipefail
ds=${1:?usage: bench/thesis-tables.sh DATASET [GONIO] [OUTDIR]}
gonio=${2:-target/release/gonio}
out=${3:-$(mktemp -d)}
mkdir -p "$out"
row() { # label, then compress arguments
  local label=$1; shift
  "$gonio" compress "$ds" "$@" --out "$out/run.gbtf" --json > "$out/run.json"
  python3 - "$label" "$out/run.json" <<'PY'
import json, os, sys
d = json.load(open(sys.argv[2]))
print(f"| {sys.argv[1]} | {d['mean_abs_8bit']:.4f} | {d['max_8bit']:.3f} | {d['rmse_8bit']:.4f} | "
      f"{d['psnr_8bit_db']:.2f} | {d['compression_ratio']:.1f} | {d['encode_seconds']:.1f} | {os.getloadavg()[0]:.1f} |")
PY
}
echo "| run | mean err /255 | max err /255 | RMSE /255 | PSNR dB | ratio | encode s | load |"
echo "|---|---|---|---|---|---|---|---|"
for c in 2 4 7 9 15 17 22 30; do
  row "PVMF c = $c" --method pvmf -c "$c"
  row "PVMF c = $c, 8-bit" --method pvmf -c "$c" --quantize 8
done
row "median cut 256 balanced" --method median-cut --boxes 256 --balanced
row "median cut 256 no balance" --method median-cut --boxes 256
row "median cut 400 no balance" --method median-cut --boxes 400
row "median cut 256 no balance, 8-bit" --method median-cut --boxes 256 --quantize 8
