#!/usr/bin/env python3
"""A UBO2014 DFMF .btf written by `gonio compress --method dfmf --format btf`, read by the
public btf-extractor 1.7.0 reader (class Ubo2014), must decode to the same images as gonio's
own reconstruction of the same file (`gonio reconstruct FILE ... --out X.npy`).

usage: check_ubo2014.py GONIO FILE.btf DATASET_DIR WORK_DIR [--pairs N] [--atol A] [--rtol R]

The directions are taken from the dataset's manifest (gonio's degrees); the reader's own
direction list (rounded to 0.1° by the reader) must agree with them, which checks the
direction encoding (radians, θ/φ order) too. Pairs are spread over the whole grid,
including the first and last index. The reader returns BGR; it is compared as RGB.
Exits non-zero on any mismatch. A malformed file crashes the reader (LoadBTF returns NULL
and the Cython wrapper dereferences it), so a crash here is a failure as well.
"""
import argparse
import json
import subprocess
import sys

import numpy as np
from btf_extractor import Ubo2014


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("gonio")
    ap.add_argument("btf")
    ap.add_argument("dataset")
    ap.add_argument("work")
    ap.add_argument("--pairs", type=int, default=6)
    # f32 dot products in a different summation order (the reader uses 8-wide SIMD sums),
    # and exp() of two libms: a few ulp of the values; 1e-5 absolute covers them.
    ap.add_argument("--atol", type=float, default=1e-5)
    ap.add_argument("--rtol", type=float, default=1e-4)
    a = ap.parse_args()

    sweep = json.load(open(f"{a.dataset}/manifest.json"))
    sweep = sweep.get("header", sweep)["sweep"]
    lights, views = sweep["lights_deg"], sweep["views_deg"]
    btf = Ubo2014(a.btf)
    # The reader lists img_shape as (Width, Height, 3); its images are H × W × 3.
    w, h, _ = btf.img_shape
    nl, nv = len(lights), len(views)

    # The reader's directions (its dict maps angles -> (light, view) index).
    by_index = {idx: ang for ang, idx in btf.angles_vs_index_dict.items()}
    assert len(by_index) == nl * nv, (len(by_index), nl, nv)

    def close_dir(reader, ours):
        dt = abs(reader[0] - ours[0])
        dp = abs((reader[1] - ours[1] + 180.0) % 360.0 - 180.0)
        return dt <= 0.051 and (ours[0] < 0.1 or dp <= 0.051)

    for li in range(nl):
        ang = by_index[(li, 0)]
        assert close_dir(ang[0:2], lights[li]), ("light", li, ang[0:2], lights[li])
    for vi in range(nv):
        ang = by_index[(0, vi)]
        assert close_dir(ang[2:4], views[vi]), ("view", vi, ang[2:4], views[vi])

    n = nl * nv
    k = max(2, a.pairs)
    indices = sorted({round(i * (n - 1) / (k - 1)) for i in range(k)})
    worst = 0.0
    for idx in indices:
        vi, li = divmod(idx, nl)
        out = f"{a.work}/rec_{li}_{vi}.npy"
        lt, lp = lights[li]
        vt, vp = views[vi]
        subprocess.run(
            [a.gonio, "reconstruct", a.btf, "--light", f"{lt},{lp}", "--view", f"{vt},{vp}", "--out", out],
            check=True,
            stdout=subprocess.DEVNULL,
        )
        ours = np.load(out)
        theirs = btf._angleindex_to_image_unsafe(li, vi)[..., ::-1]
        assert ours.shape == theirs.shape == (h, w, 3), (ours.shape, theirs.shape)
        diff = np.abs(ours - theirs)
        lim = a.atol + a.rtol * np.abs(theirs)
        bad = diff > lim
        if bad.any():
            y, x, c = np.argwhere(bad)[0]
            print(
                f"FAIL light {li} {lights[li]}, view {vi} {views[vi]}: {bad.sum()} values differ, "
                f"first at y={y} x={x} c={c}: gonio {ours[y, x, c]!r}, btf-extractor {theirs[y, x, c]!r}",
                file=sys.stderr,
            )
            sys.exit(1)
        if not (theirs.max() > 0):
            print(f"FAIL light {li}, view {vi}: the reader decoded an all-zero image", file=sys.stderr)
            sys.exit(1)
        worst = max(worst, float(diff.max()))
    print(
        f"ubo2014: {a.btf}: {nl} lights x {nv} views, {w}x{h}; {len(indices)} pairs decoded by "
        f"btf-extractor equal gonio's reconstruction (max abs diff {worst:.2e})"
    )


if __name__ == "__main__":
    main()
