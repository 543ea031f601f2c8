#!/usr/bin/env bash
# Real-browser tests of `gonio view` (tests/browser/check_pages.py): Debian's chromium,
# headless, WebGL2 through SwiftShader, driven by Python Playwright with executable_path
# (no browser download). Needs /usr/bin/chromium (.ci/run installs it with apt) and a
# Python with playwright, pillow and numpy (tests/interop/setup_python.sh installs them).
# Mandatory under CI; elsewhere skipped with a notice when either is missing.
set -euo pipefail
cd "$(dirname "$0")/../.."
py="${GONIO_PYTHON:-${GONIO_VENV:-$PWD/target/venv}/bin/python}"
# Absolute, for the import check that runs from /.
case $py in */*) py=$(realpath -ms "$py") ;; esac
if [ ! -x /usr/bin/chromium ] || ! (cd / && "$py" -c "import playwright, PIL, numpy") 2>/dev/null; then
  if [ -n "${CI:-}" ]; then
    echo "browser: /usr/bin/chromium or Playwright ($py) missing under CI (.ci/run and tests/interop/setup_python.sh install them)" >&2
    exit 1
  fi
  echo "browser: skipped (needs /usr/bin/chromium and Playwright in $py; run .ci/run)"
  exit 0
fi
# GONIO_BIN: the binary the test stage already built (tests/run.sh exports it); else build.
if [ -n "${GONIO_BIN:-}" ]; then
  gonio=$GONIO_BIN
else
  cargo build -q -p gonio
  gonio="$PWD/target/debug/gonio"
fi
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT
# A small simulated dataset (with its ground truth) and its PVMF, DFMF, local-PCA and PCA compressions.
"$gonio" -q acquire --size 32x32 --sweep fibonacci:12 --store-truth --out "$scratch/ds" >/dev/null
"$gonio" -q compress "$scratch/ds" --method pvmf -c 8 --out "$scratch/pvmf.gbtf" >/dev/null
"$gonio" -q compress "$scratch/ds" --method dfmf -c 8 --format btf --out "$scratch/dfmf.btf" >/dev/null
"$gonio" -q compress "$scratch/ds" --method local-pca --clusters 4 -c 4 --out "$scratch/lpca.gbtf" >/dev/null
"$gonio" -q compress "$scratch/ds" --method pca -c 8 --out "$scratch/pca.gbtf" >/dev/null
# The GPU decoders of src/view/gpu.rs: DFMF (log-YUV .btf above, f16 as Bonn stores it; RGB
# .btf in f32; CIELab .gbtf), median cut and homomorphic (with half-vector bins).
"$gonio" -q compress "$scratch/ds" --method dfmf -c 6 --color-model rgb --precision f32 --format btf --out "$scratch/dfmf-rgb.btf" >/dev/null
"$gonio" -q compress "$scratch/ds" --method dfmf -c 8 --chroma-components 3 --color-model lab --out "$scratch/dfmf-lab.gbtf" >/dev/null
"$gonio" -q compress "$scratch/ds" --method median-cut --boxes 16 --out "$scratch/mcut.gbtf" >/dev/null
"$gonio" -q compress "$scratch/ds" --method homomorphic --half-bins 4 --out "$scratch/homo.gbtf" >/dev/null
# Models that do not fit the dataset (`gonio view DS --model F` must refuse them): another
# texture size, other directions.
"$gonio" -q sim btf --size 16 --sweep fibonacci:12 --out "$scratch/small" >/dev/null
"$gonio" -q compress "$scratch/small" --method pca -c 2 --out "$scratch/small.gbtf" >/dev/null
"$gonio" -q sim btf --size 32 --sweep fibonacci:10 --out "$scratch/other" >/dev/null
"$gonio" -q compress "$scratch/other" --method pca -c 2 --out "$scratch/other.gbtf" >/dev/null
export GONIO_MISMATCHED_MODELS="$scratch/small.gbtf=texels,$scratch/other.gbtf=light directions"
# Screenshots go to docs/img/ (viewer-relight.png, viewer-monitor.png; docs/guide/viewer.md shows them).
"$py" tests/browser/check_pages.py "$gonio" "$scratch/ds" "$scratch/pvmf.gbtf" "$scratch" docs/img \
  "$scratch/dfmf.btf" "$scratch/lpca.gbtf" "$scratch/pca.gbtf" "$scratch/dfmf-rgb.btf" \
  "$scratch/dfmf-lab.gbtf" "$scratch/mcut.gbtf" "$scratch/homo.gbtf"
