#!/usr/bin/env python3
"""Check a gonio UBO2003 export with the public `btf-extractor` 1.7.0 reader.

Usage: check_ubo2003.py ZIP NPY [--mean-tol X] [--max-tol Y]

ZIP is written by `gonio::store::export_ubo2003`, NPY (with its sidecar NPY.json) by
`gonio::store::export_npy` from the same dataset. NPY holds, as float32 [N, H, W, 3] in
RGB order, exactly the 8-bit sRGB values gonio gave its JPEG encoder; NPY.json lists
per image the ZIP entry name and its integer angles (tl, pl, tv, pv).

Checks:
  * the archive holds exactly the listed .jpg entries, and the reader's `angles_set`
    is exactly the set of listed angle tuples (so skipped measurements are absent and
    the reader's fixed-offset name parsing recovers every tuple);
  * every image the reader returns has the reference's shape and equals the reference
    within JPEG tolerance: per image mean |error| <= 2.5/255 and max |error| <= 32/255
    by default (see MEAN_TOL below for the measurements behind these);
  * channel order: `Ubo2003.angles_to_image` returns BGR (it decodes with simplejpeg,
    colorspace="BGR", for OpenCV compatibility). The script converts to RGB and also
    confirms the order from the data: the RGB interpretation must fit the reference
    better than the raw BGR array does.

Prints `ubo2003 interop: N images, max mean-abs err X/255` and exits non-zero on any
failure.
"""
import argparse
import json
import sys
import zipfile

import numpy as np
from btf_extractor import Ubo2003

# JPEG tolerance, in 8-bit units (/255). gonio writes quality 95 without chroma
# subsampling (4:4:4); the reader decodes with libjpeg-turbo (simplejpeg). Measured
# mean / max abs error per 256 x 256 image at q95 4:4:4:
#   noise-free gradients and hard edges            0.45 / 4
#   12-bit shot noise (sigma = sqrt(DN)/4095)      1.5-1.8 / 10-12
#   10-bit shot noise, or uniform +-0.02 linear    2.7-3.2 / 18-23
# gonio's synthetic interop dataset (12-bit shot noise, hard-edged checker, a clipped
# over-exposed texel) gives 1.75 / 19. The defaults leave headroom for other decoders'
# rounding while a wrong channel order, a flipped image, a missing sRGB encoding or a
# mismatched entry gives mean errors of tens. Noisier data need --mean-tol/--max-tol.
MEAN_TOL = 2.5
MAX_TOL = 32.0


def main(argv):
    ap = argparse.ArgumentParser(description="Check a gonio UBO2003 export with btf-extractor 1.7.0.")
    ap.add_argument("zip", help="archive written by export_ubo2003")
    ap.add_argument("npy", help="reference written by export_npy (with NPY.json beside it)")
    ap.add_argument("--mean-tol", type=float, default=MEAN_TOL, help="per-image mean abs error limit, /255")
    ap.add_argument("--max-tol", type=float, default=MAX_TOL, help="per-image max abs error limit, /255")
    args = ap.parse_args(argv[1:])
    zip_path, npy_path = args.zip, args.npy
    mean_tol, max_tol = args.mean_tol, args.max_tol
    failures = []

    ref = np.load(npy_path)
    with open(npy_path + ".json", encoding="utf-8") as f:
        side = json.load(f)
    entries = side["entries"]
    if ref.dtype != np.float32 or ref.ndim != 4 or ref.shape[3] != 3:
        failures.append(f"reference array has dtype {ref.dtype} shape {ref.shape}")
    if ref.shape[0] != len(entries):
        failures.append(f"reference holds {ref.shape[0]} images, sidecar lists {len(entries)}")

    with zipfile.ZipFile(zip_path) as z:
        jpgs = sorted(n for n in z.namelist() if n.endswith(".jpg"))
    listed = sorted(e["entry"] for e in entries)
    if jpgs != listed:
        failures.append(
            f"archive entries differ from the sidecar: only in zip {sorted(set(jpgs) - set(listed))[:5]}, "
            f"only in sidecar {sorted(set(listed) - set(jpgs))[:5]}"
        )

    btf = Ubo2003(zip_path)
    expected = {(e["tl"], e["pl"], e["tv"], e["pv"]) for e in entries}
    if len(expected) != len(entries):
        failures.append("the sidecar lists an angle tuple twice")
    missing = expected - set(btf.angles_set)
    extra = set(btf.angles_set) - expected
    if missing:
        failures.append(f"{len(missing)} exported angle tuples not in angles_set, e.g. {sorted(missing)[:3]}")
    if extra:
        failures.append(f"{len(extra)} unexpected angle tuples in angles_set, e.g. {sorted(extra)[:3]}")

    worst_mean = 0.0
    worst_max = 0.0
    sum_rgb = 0.0
    sum_bgr = 0.0
    for i, e in enumerate(entries):
        key = (e["tl"], e["pl"], e["tv"], e["pv"])
        parsed = Ubo2003._filename_to_angles(e["entry"])
        if parsed != key:
            failures.append(f"{e['entry']!r}: the reader parses {parsed}, expected {key}")
            continue
        if key in missing or i >= ref.shape[0]:
            continue
        bgr = btf.angles_to_image(*key)
        want = ref[i]
        if bgr.shape != want.shape or bgr.dtype != np.uint8:
            failures.append(f"{e['entry']!r}: reader returned {bgr.dtype} {bgr.shape}, expected uint8 {want.shape}")
            continue
        rgb = bgr[..., ::-1].astype(np.float32)
        err = np.abs(rgb - want)
        mean, mx = float(err.mean()), float(err.max())
        sum_rgb += mean
        sum_bgr += float(np.abs(bgr.astype(np.float32) - want).mean())
        worst_mean = max(worst_mean, mean)
        worst_max = max(worst_max, mx)
        if mean > mean_tol or mx > max_tol:
            failures.append(
                f"{e['entry']!r}: mean abs err {mean:.2f}/255 (limit {mean_tol}), max {mx:.0f}/255 (limit {max_tol})"
            )
    if entries and not sum_rgb < sum_bgr:
        failures.append(
            f"channel order: reading the reader's output as RGB (mean err {sum_rgb:.2f}) does not fit "
            f"better than as BGR ({sum_bgr:.2f}); test images need colour to tell"
        )

    print(
        f"ubo2003 interop: {len(entries)} images, max mean-abs err {worst_mean:.2f}/255 "
        f"(max abs err {worst_max:.0f}/255; reader returns BGR, compared as RGB)"
    )
    for f in failures:
        print(f"FAIL: {f}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
