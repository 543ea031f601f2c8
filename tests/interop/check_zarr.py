#!/usr/bin/env python3
"""Read a `gonio export --format zarr` store with zarr-python 3, xarray and dask.array and
check it bit for bit against the dataset it was exported from.

Usage: check_zarr.py STORE.zarr DATASET_DIR MEAN.npy

* Reference values: the dataset's own EXR images, read with the OpenEXR Python bindings
  (the images are RGB half floats, so the Zarr float16 values must equal them bit for bit).
  Measured and substituted pairs must match; missing pairs (status 0) must be NaN.
* zarr-python: the array's layout (shape, dtype, shard and inner-chunk shapes, dimension
  names, NaN fill value) and values.
* xarray (`open_zarr(consolidated=False, zarr_format=3)`): dimensions, the direction
  coordinates along `view`/`light`, units, and the same bits as zarr-python.
* dask.array (`from_zarr`): the same bits, and the NaN-mean image over (view, light)
  computed in float64 equals gonio's mean image (`export --mean-image`) bit for bit
  (a float64 sum of float16 values is exact, so the summation order does not matter).

Exits 0 when everything matches, 1 with a message otherwise; exits 3 with a message
when a package is missing (run.sh turns that into a skip outside CI).
"""
import json
import os
import sys

try:
    import numpy as np
    import zarr
    import xarray as xr
    import dask
    import dask.array as da
    import OpenEXR
except ImportError as e:  # pragma: no cover - depends on the environment
    print(f"check_zarr: SKIPPED ({e}; tests/interop/setup_python.sh installs the pins)")
    sys.exit(3)


def fail(msg):
    print(f"check_zarr: FAIL: {msg}", file=sys.stderr)
    sys.exit(1)


def bits(a):
    """float16 → uint16 bit patterns (NaNs compared by their bits too)."""
    return np.ascontiguousarray(a).view(np.uint16)


def read_exr_rgb(path):
    with OpenEXR.File(path) as f:
        ch = f.channels()
        if "RGB" in ch:
            rgb = ch["RGB"].pixels
        else:
            rgb = np.stack([ch[c].pixels for c in ("R", "G", "B")], axis=-1)
    if rgb.dtype != np.float16:
        fail(f"{path}: expected half-float channels, got {rgb.dtype}")
    return rgb


def journal_records(ds):
    recs = {}
    with open(os.path.join(ds, "journal.jsonl")) as f:
        for line in f:
            line = line.strip()
            if not line:
                continue
            try:
                rec = json.loads(line)["rec"]
            except (ValueError, KeyError):
                continue  # a torn last line: gonio ignores it too
            recs.setdefault(rec["index"], rec)
    return recs


def main():
    if len(sys.argv) != 4:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
    store, ds, mean_path = sys.argv[1:]
    manifest = json.load(open(os.path.join(ds, "manifest.json")))
    views = manifest["sweep"]["views_deg"]
    lights = manifest["sweep"]["lights_deg"]
    nv, nl = len(views), len(lights)
    h, w = manifest["image_height"], manifest["image_width"]

    # ---- zarr-python ---------------------------------------------------------------
    g = zarr.open_group(store, mode="r", zarr_format=3)
    arr = g["btf"]
    if arr.shape != (nv, nl, h, w, 3) or arr.dtype != np.float16:
        fail(f"btf is {arr.shape} {arr.dtype}, expected {(nv, nl, h, w, 3)} float16")
    if tuple(arr.metadata.dimension_names) != ("view", "light", "y", "x", "channel"):
        fail(f"dimension_names {arr.metadata.dimension_names}")
    if arr.shards != (1, nl, h, w, 3) or arr.chunks != (1, 1, h, w, 3):
        fail(f"shards {arr.shards} / chunks {arr.chunks}: expected one view per shard, one image per chunk")
    if not np.isnan(arr.fill_value):
        fail(f"fill value {arr.fill_value}, expected NaN")
    data = arr[...]
    status = g["status"][...]
    attrs = dict(g.attrs)["gonio"]
    if attrs["values"] != manifest["values"]:
        fail("group attribute gonio.values differs from the manifest's values")

    # ---- reference: the dataset's EXRs ---------------------------------------------
    recs = journal_records(ds)
    checked = 0
    for v in range(nv):
        for li in range(nl):
            idx = v * nl + li
            rec = recs.get(idx)
            kind = rec["status"]["kind"] if rec else "absent"
            st = int(status[v, li])
            if kind in ("measured", "substituted"):
                if st not in (1, 2, 3) or (st == 2) != (kind == "substituted"):
                    fail(f"pair {idx} ({kind}) has status {st}")
                if st == 3:
                    continue
                ref = read_exr_rgb(os.path.join(ds, rec["image"]))
                if not np.array_equal(bits(data[v, li]), bits(ref)):
                    n = int((bits(data[v, li]) != bits(ref)).sum())
                    fail(f"pair {idx} (view {v}, light {li}): {n} values differ from {rec['image']}")
                checked += 1
            elif st == 3:
                continue  # an isotropic equivalent: checked by gonio's own tests
            else:
                if st != 0:
                    fail(f"pair {idx} is {kind} in the dataset but has status {st}")
                if not np.isnan(data[v, li]).all():
                    fail(f"missing pair {idx} (view {v}, light {li}) is not all NaN")
    if checked == 0:
        fail("no measured pair to compare")
    missing = int((status == 0).sum())

    # ---- xarray --------------------------------------------------------------------
    xds = xr.open_zarr(store, consolidated=False, zarr_format=3)
    btf = xds["btf"]
    if btf.dims != ("view", "light", "y", "x", "channel"):
        fail(f"xarray dims {btf.dims}")
    for c, dim, ref in (("view_theta", "view", [d[0] for d in views]), ("view_phi", "view", [d[1] for d in views]),
                        ("light_theta", "light", [d[0] for d in lights]), ("light_phi", "light", [d[1] for d in lights])):
        if c not in btf.coords or btf.coords[c].dims != (dim,):
            fail(f"xarray: {c} is not a coordinate along {dim} ({list(btf.coords)})")
        if not np.array_equal(btf.coords[c].values, np.asarray(ref, dtype=np.float64)):
            fail(f"xarray: {c} differs from the manifest's sweep")
    if btf.dtype != np.float16 or not np.array_equal(bits(btf.values), bits(data)):
        fail(f"xarray values ({btf.dtype}) differ from zarr-python's")
    if "units" not in btf.attrs:
        fail("xarray: btf has no units attribute")

    # ---- dask.array ----------------------------------------------------------------
    darr = da.from_zarr(store, component="btf")
    if not np.array_equal(bits(darr.compute()), bits(data)):
        fail("dask.array values differ from zarr-python's")
    with np.errstate(invalid="ignore"):
        mean = da.nanmean(darr.astype(np.float64), axis=(0, 1)).compute()
    ref_mean = np.load(mean_path)
    if ref_mean.shape != mean.shape or ref_mean.dtype != np.float64:
        fail(f"gonio's mean image is {ref_mean.shape} {ref_mean.dtype}, dask's {mean.shape}")
    if not np.array_equal(ref_mean.view(np.uint64), mean.view(np.uint64)):
        n = int((ref_mean.view(np.uint64) != mean.view(np.uint64)).sum())
        fail(f"dask.array's mean image differs from gonio's in {n} of {mean.size} values "
             f"(max |Δ| {np.nanmax(np.abs(ref_mean - mean))})")

    print(f"check_zarr: {store}: [{nv}, {nl}, {h}, {w}, 3] f16; {checked} images bit-exact vs the EXRs, "
          f"{missing} missing pairs all NaN; zarr {zarr.__version__}, xarray {xr.__version__}, "
          f"dask {dask.__version__}: same bits; "
          f"dask nanmean = gonio mean image bit for bit")


if __name__ == "__main__":
    main()
