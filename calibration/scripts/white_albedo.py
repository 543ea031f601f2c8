#!/usr/bin/env python3
"""π · BRDF / albedo − 1 of a calibrated acquisition of a white standard, pair by pair.

Reads DATASET/manifest.json (its records: directions and image paths) and every stored
image (linear EXR; with `value_unit = brdf_per_sr` the values are BRDF in 1/sr) and
prints, for the pairs with θ_l, θ_v ≤ THETA (default 60°) and for the others separately:
the number of pairs, the worst |π·mean/albedo − 1| over pairs and channels (with the pair),
its mean, and the RMS over all texels.

Usage: white_albedo.py DATASET [ALBEDO=0.9] [THETA=60]     (needs numpy and OpenEXR)
"""
import json
import math
import sys

import Imath
import numpy as np
import OpenEXR


def read_exr(path):
    f = OpenEXR.InputFile(path)
    dw = f.header()["dataWindow"]
    w, h = dw.max.x - dw.min.x + 1, dw.max.y - dw.min.y + 1
    pt = Imath.PixelType(Imath.PixelType.FLOAT)
    return np.stack([np.frombuffer(f.channel(c, pt), dtype=np.float32).reshape(h, w) for c in "RGB"], -1)


def main() -> int:
    d = sys.argv[1]
    albedo = float(sys.argv[2]) if len(sys.argv) > 2 else 0.9
    theta = float(sys.argv[3]) if len(sys.argv) > 3 else 60.0
    m = json.load(open(f"{d}/manifest.json"))
    unit = m.get("extra", {}).get("value_unit")
    if unit != "brdf_per_sr":
        print(f"{d}: value_unit is {unit!r}, not brdf_per_sr: acquire with --calibration", file=sys.stderr)
        return 2
    groups = {"in": [], "out": []}
    for r in m["records"]:
        if not r.get("image"):
            continue
        img = read_exr(f"{d}/{r['image']}").astype(np.float64)
        rel = math.pi * img / albedo - 1.0
        mean = rel.reshape(-1, 3).mean(0)
        key = "in" if r["light_deg"][0] <= theta + 1e-9 and r["view_deg"][0] <= theta + 1e-9 else "out"
        groups[key].append((np.abs(mean).max(), r["light_deg"], r["view_deg"], float((rel**2).mean())))
    for key, name in [("in", f"theta <= {theta:g}"), ("out", f"theta > {theta:g}")]:
        g = groups[key]
        if not g:
            continue
        worst = max(g, key=lambda x: x[0])
        print(f"{name}: {len(g)} pairs, worst |pi*mean/albedo - 1| {100 * worst[0]:.4f} % "
              f"(light {worst[1]}, view {worst[2]}), mean {100 * np.mean([x[0] for x in g]):.4f} %, "
              f"texel RMS {100 * math.sqrt(np.mean([x[3] for x in g])):.4f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
