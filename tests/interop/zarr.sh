#!/usr/bin/env bash
# Zarr v3 export read by zarr-python 3, xarray and dask.array (tests/interop/check_zarr.py):
# a simulated BTF exported in one process and in 3 shards (byte-identical stores), and an
# acquisition with skipped retro-reflection pairs (NaN + status 0), each checked bit for bit
# against the dataset's EXRs, and dask's mean image against gonio's `--mean-image`.
#
# Usage: tests/interop/zarr.sh [GONIO_BINARY]   (python: $GONIO_PYTHON, else python3)
# Called by tests/interop/run.sh. Skips with a message when the Python packages are missing
# (tests/interop/setup_python.sh installs them); under CI (CI set) that is a failure.
set -euo pipefail
cd "$(dirname "$0")/../.."
py=${GONIO_PYTHON:-python3}
# Absolute, for the import check that runs from /.
case $py in */*) py=$(realpath -ms "$py") ;; esac

# From /, not the checkout: `python -c` puts the working directory first on sys.path, and
# the workspace folder `sparse/` (the gonio-sparse crate) then shadows the optional `sparse`
# package that dask imports (see setup_python.sh).
if ! (cd / && "$py" -c 'import zarr, xarray, dask.array, OpenEXR') 2>/dev/null; then
  if [ -n "${CI:-}" ]; then
    echo "interop zarr: zarr/xarray/dask/OpenEXR missing in $py under CI: run tests/interop/setup_python.sh" >&2
    exit 1
  fi
  echo "interop zarr: SKIPPED (zarr, xarray, dask or OpenEXR not importable by $py; tests/interop/setup_python.sh VENV installs them)"
  exit 0
fi

gonio=${1:-}
if [ -z "$gonio" ]; then
  cargo build --quiet --bin gonio
  gonio=target/debug/gonio
fi
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

# 1. A simulated BTF (64 images of 64²: big enough that zarrs encodes a shard's images on
#    several threads, which once made shards differ): single process, then 3 concurrent shards into one store.
"$gonio" sim btf --sweep fibonacci:8 --size 64 --out "$work/btf" --json > /dev/null
"$gonio" export "$work/btf" --format zarr "$work/btf.zarr" --mean-image "$work/btf-mean.npy" --json > /dev/null
# The three parts run at the same time (no lock): each writes its views' shards and the
# same metadata bytes, renamed into place.
pids=()
for i in 2 3 1; do
  "$gonio" export "$work/btf" --format zarr "$work/btf-sharded.zarr" --shard "$i/3" --json > /dev/null &
  pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done
diff -r "$work/btf.zarr" "$work/btf-sharded.zarr" > /dev/null \
  || { echo "interop zarr: the 3-shard store differs from the single-process one" >&2; diff -rq "$work/btf.zarr" "$work/btf-sharded.zarr" >&2; exit 1; }
echo "interop zarr: 3 shards = single process, byte for byte ($(find "$work/btf.zarr" -type f | wc -l) files)"
"$py" tests/interop/check_zarr.py "$work/btf-sharded.zarr" "$work/btf" "$work/btf-mean.npy"

# 2. An acquisition whose retro-reflection pairs are skipped: those are NaN, status 0.
cat > "$work/sweep.toml" <<'TOML'
directions = [[0, 0], [15, 60], [30, 150], [45, 340], [60, 18], [75, 345]]
TOML
"$gonio" acquire --quiet --out "$work/acq" --sweep "$work/sweep.toml" --size 32x32 --json > /dev/null
"$gonio" export "$work/acq" --format zarr "$work/acq.zarr" --mean-image "$work/acq-mean.npy" --json > "$work/acq-zarr.json"
"$py" - "$work/acq-zarr.json" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
assert r["missing"] > 0, f"expected skipped pairs in the acquisition: {r}"
print(f"interop zarr: acquisition: {r['measured']} measured, {r['substituted']} substituted, {r['missing']} missing (NaN)")
PY
"$py" tests/interop/check_zarr.py "$work/acq.zarr" "$work/acq" "$work/acq-mean.npy"
