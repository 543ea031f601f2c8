#!/usr/bin/env bash
# Reproduces the measurements of docs/guide/synthesis.md (release build, 2 cores): needs
# target/release/gonio and gonio-bench beside it (`cargo build --release -p gonio`).
#   bash bench/synthesize.sh            # everything
#   STEPS="quality" bash bench/synthesize.sh
#   STEPS="quality" METHODS=tile,quilting,wei-levoy bash bench/synthesize.sh   # without the slow one
set -euo pipefail
G=${GONIO:-target/release/gonio}
W=${WORK:-/tmp/gonio-synth-bench}
STEPS=${STEPS:-"data quality speed memory"}
METHODS=${METHODS:-tile,quilting,wei-levoy,efros-leung}
mkdir -p "$W" docs/img
SWEEP=fibonacci:12

has() { [[ " $STEPS " == *" $1 "* ]]; }

if has data; then
  # Exemplar: 30 mm of leather at 128² (0.234 mm texels). Reference: the same procedural
  # material over 60 mm at 256² (same pitch, 4x the area; the exemplar is its centre).
  $G sim btf --sample bench/synthesis/leather-30mm.toml --sweep $SWEEP --size 128 --out "$W/ex" --force --json > "$W/sim-ex.json"
  $G sim btf --sample bench/synthesis/leather-60mm.toml --sweep $SWEEP --size 256 --out "$W/ref" --force --json > "$W/sim-ref.json"
  $G compress "$W/ex" --method pca -c 8 --out "$W/ex-pca8.gbtf" --json > "$W/compress-ex.json"
  # Speed exemplar: the built-in leather (60 mm at 256², same pitch).
  $G sim btf --sample leather --sweep $SWEEP --size 256 --out "$W/ex256" --force --json > "$W/sim-ex256.json"
  $G compress "$W/ex256" --method pca -c 8 --out "$W/ex256-pca8.gbtf" --json > "$W/compress-pca.json"
  $G compress "$W/ex256" --method median-cut --boxes 64 --out "$W/ex256-mc64.gbtf" --json > "$W/compress-mc.json"
  $G compress "$W/ex256" --method local-pca --clusters 8 -c 4 --out "$W/ex256-lpca.gbtf" --json > "$W/compress-lpca.json"
  $G compress "$W/ex256" --method pvmf -c 4 --out "$W/ex256-pvmf4.gbtf" --json > "$W/compress-pvmf.json"
  $G compress "$W/ex256" --method dfmf -c 4 --format btf --out "$W/ex256-dfmf4.btf" --json > "$W/compress-dfmf.json"
fi

if has quality; then
  $G bench synthesize --exemplar "$W/ex-pca8.gbtf" --reference "$W/ref" --methods "$METHODS" \
    --md "$W/quality.md" --plot docs/img/synthesis-error-time.svg --picture docs/img/synthesis.png
fi

if has speed; then
  for model in pca8 mc64 lpca pvmf4; do
    for m in tile quilting wei-levoy; do
      $G synthesize "$W/ex256-$model.gbtf" --method $m --size 1024x1024 --out "$W/out-$model-$m.gbtf" --json \
        > "$W/speed-$model-$m.json"
      python3 -c "import json,sys; r=json.load(open(sys.argv[1])); print(sys.argv[2], sys.argv[3], 'k', r['k'], 'features', round(r['feature_seconds'],2), 'synthesis', round(r['synthesis_seconds'],2), 's write', round(r['write_seconds'],2), 's bytes', r['out']['bytes'], 'peak MiB', (r['peak_memory_bytes'] or 0)>>20)" \
        "$W/speed-$model-$m.json" $model $m
      rm -f "$W/out-$model-$m.gbtf"
    done
  done
  # A UBO2014 DFMF .btf exemplar gives a .btf of the same model.
  for m in quilting wei-levoy; do
    $G synthesize "$W/ex256-dfmf4.btf" --method $m --size 1024x1024 --out "$W/out-dfmf4-$m.btf" --json \
      > "$W/speed-dfmf4-$m.json"
    python3 -c "import json,sys; r=json.load(open(sys.argv[1])); print('dfmf4.btf', sys.argv[2], 'k', r['k'], 'features', round(r['feature_seconds'],2), 'synthesis', round(r['synthesis_seconds'],2), 's write', round(r['write_seconds'],2), 's bytes', r['out']['bytes'], 'peak MiB', (r['peak_memory_bytes'] or 0)>>20)" \
      "$W/speed-dfmf4-$m.json" $m
    rm -f "$W/out-dfmf4-$m.btf"
  done
  # Efros–Leung is exhaustive per texel: its time is in the quality table (256² from 128²).
fi

if has memory; then
  # 4096² output (16.8 M texels) by quilting from the median-cut exemplar: peak RSS.
  $G synthesize "$W/ex256-mc64.gbtf" --method quilting --size 4096x4096 --out "$W/out-4096.gbtf" --json > "$W/mem-4096.json"
  python3 -c "import json; r=json.load(open('$W/mem-4096.json')); print('4096² quilting: synthesis', round(r['synthesis_seconds'],1), 's, file', r['out']['bytes'], 'B, peak', (r['peak_memory_bytes'] or 0)>>20, 'MiB')"
  rm -f "$W/out-4096.gbtf"
  # The same from the UBO2014 DFMF .btf exemplar: a .btf output is built in memory.
  $G synthesize "$W/ex256-dfmf4.btf" --method quilting --size 4096x4096 --out "$W/out-4096.btf" --json > "$W/mem-4096-btf.json"
  python3 -c "import json; r=json.load(open('$W/mem-4096-btf.json')); print('4096² quilting from .btf: synthesis', round(r['synthesis_seconds'],1), 's, file', r['out']['bytes'], 'B, peak', (r['peak_memory_bytes'] or 0)>>20, 'MiB')"
  rm -f "$W/out-4096.btf"
fi
