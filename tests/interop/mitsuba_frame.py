"""Mitsuba 3 as an independent oracle for gonio's raw frames.

Usage: python mitsuba_frame.py GONIO_BIN WORKDIR

For a flat sample (point light, perspective camera), renders the camera's radiance image
with `GONIO_BIN sim render --kind radiance --scene-json` and the same scene with Mitsuba 3
(PyPI `mitsuba` 3.9.1, variant `scalar_rgb`): a `perspective` sensor at gonio's camera
pose and focal length, a `point` emitter of gonio's intensity at gonio's lamp position,
the sample as a `rectangle` with the matching BSDF (`diffuse` for the Lambertian white
standard, `roughconductor` GGX for tests/interop/flat-conductor.toml), the `direct`
integrator. Scene units are metres (gonio works in mm and converts the inverse-square
falloff to metres), so both radiances are W m⁻² sr⁻¹ and are compared without any scale
factor.

Compared: pixels whose centre ray meets the sample at least MARGIN_MM inside its edge
(gonio's holder frame and markers are not modelled in the Mitsuba scene). Both renderers
integrate over the pixel area (gonio: an 8×8 sheared grid; Mitsuba: SPP random samples
with a box filter); on a flat sample the radiance varies smoothly across a pixel, so the
two agree up to Mitsuba's sampling noise. Measures: the ratio of the mean radiances (scale,
i.e. units, falloff, normalization), and the per-pixel relative RMS difference (shape:
pose, projection, BSDF lobe). Tolerances are printed with the measured values; exits 1 if
a case exceeds them. A negative control (the conductor rendered with α = 0.25 in Mitsuba)
must fail the shape tolerance.
"""

import json
import math
import subprocess
import sys

import numpy as np
import mitsuba as mi

mi.set_variant("scalar_rgb")

MARGIN_MM = 1.0
SPP = 64
# Measured (4 cases): |ratio − 1| ≤ 1e-6, RMS ≤ 2.2e-4, max ≤ 6.7e-4; gonio's EXR is half
# float (relative step 4.9e-4), which bounds the per-pixel agreement.
TOL_SCALE = 5e-4  # |mean ratio − 1|
TOL_SHAPE = 1e-3  # per-pixel relative RMS difference

GOLD = {"eta": [0.1431, 0.3749, 1.4425], "k": [3.9831, 2.3857, 1.6032]}

CASES = [
    # (label, sample, gonio light θ,φ, view θ,φ, mitsuba bsdf)
    ("white standard, oblique", "white-standard", "45,30", "30,200",
     {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.9, 0.9, 0.9]}}),
    ("white standard, grazing light", "white-standard", "75,0", "15,90",
     {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.9, 0.9, 0.9]}}),
    ("rough gold, near mirror", "tests/interop/flat-conductor.toml", "30,0", "30,180", None),
    ("rough gold, off mirror", "tests/interop/flat-conductor.toml", "45,60", "30,200", None),
]


def conductor(alpha):
    return {
        "type": "roughconductor",
        "distribution": "ggx",
        "alpha": alpha,
        "eta": {"type": "rgb", "value": GOLD["eta"]},
        "k": {"type": "rgb", "value": GOLD["k"]},
    }


def gonio_render(gonio, work, label, sample, light, view):
    stem = f"{work}/{label.replace(' ', '_').replace(',', '')}"
    subprocess.run(
        [gonio, "--quiet", "sim", "render", "--sample", sample, "--light", light, "--view", view,
         "--kind", "radiance", "--supersample", "8", "--out", f"{stem}.exr",
         "--scene-json", f"{stem}.json"],
        check=True,
    )
    img = np.array(mi.Bitmap(f"{stem}.exr"), dtype=np.float64)[:, :, :3]
    scene = json.load(open(f"{stem}.json"))
    return img, scene


def mask_and_crop(scene):
    """Pixels whose centre ray meets the sample MARGIN_MM inside its edge, and their box."""
    c = scene["camera"]
    w, h = c["width"], c["height"]
    pos, right, down, fwd = (np.array(c[k]) for k in ("position", "right", "down", "forward"))
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d = (right[None, None, :] * ((u - c["cx"]) / c["fx"])[..., None]
         + down[None, None, :] * ((v - c["cy"]) / c["fy"])[..., None] + fwd[None, None, :])
    t = -pos[2] / d[..., 2]
    p = pos[None, None, :] + d * t[..., None]
    half = scene["sample"]["size_mm"] / 2 - MARGIN_MM
    m = (t > 0) & (np.abs(p[..., 0]) < half) & (np.abs(p[..., 1]) < half)
    ys, xs = np.nonzero(m)
    return m, (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)


def mitsuba_render(scene, bsdf, box):
    c, L = scene["camera"], scene["light"]
    if abs(c["cx"] - c["width"] / 2) > 1e-9 or abs(c["cy"] - c["height"] / 2) > 1e-9 or c["fx"] != c["fy"]:
        sys.exit("mitsuba_frame.py handles a centred principal point and square pixels only")
    s = 1e-3  # mm → m
    pos = np.array(c["position"]) * s
    target = pos + np.array(c["forward"])
    up = -np.array(c["down"])
    x0, y0, x1, y1 = box
    T = mi.ScalarTransform4f
    scene_dict = {
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        "sensor": {
            "type": "perspective",
            "fov_axis": "x",
            "fov": math.degrees(2 * math.atan(c["width"] / 2 / c["fx"])),
            "to_world": T().look_at(origin=pos.tolist(), target=target.tolist(), up=up.tolist()),
            "film": {
                "type": "hdrfilm", "width": c["width"], "height": c["height"],
                "crop_offset_x": int(x0), "crop_offset_y": int(y0),
                "crop_width": int(x1 - x0), "crop_height": int(y1 - y0),
                "rfilter": {"type": "box"}, "pixel_format": "rgb",
            },
            "sampler": {"type": "independent", "sample_count": SPP},
        },
        "light": {
            "type": "point",
            "position": (np.array(L["position"]) * s).tolist(),
            "intensity": {"type": "rgb", "value": [L["intensity_w_sr"]] * 3},
        },
        "sample": {
            "type": "rectangle",
            "to_world": T().scale([scene["sample"]["size_mm"] / 2 * s] * 2 + [1.0]),
            "bsdf": bsdf,
        },
    }
    img = mi.render(mi.load_dict(scene_dict), spp=SPP)
    return np.array(img, dtype=np.float64)[:, :, :3]


def compare(g, m, mask, box):
    x0, y0, x1, y1 = box
    gm = g[y0:y1, x0:x1][mask[y0:y1, x0:x1]]
    mm = m[mask[y0:y1, x0:x1]]
    scale = gm.mean() / mm.mean()
    floor = 1e-3 * mm.max()
    rel = (gm - mm) / np.maximum(mm, floor)
    return scale, float(np.sqrt(np.mean(rel ** 2))), float(np.abs(rel).max()), gm.size // 3


def main():
    gonio, work = sys.argv[1], sys.argv[2]
    bad = 0
    print(f"{'case':34} {'pixels':>7} {'mean ratio':>11} {'rel RMS':>9} {'rel max':>9}  (tol: |ratio−1| ≤ {TOL_SCALE:g}, RMS ≤ {TOL_SHAPE:g})")
    for label, sample, light, view, bsdf in CASES:
        g, scene = gonio_render(gonio, work, label, sample, light, view)
        mask, box = mask_and_crop(scene)
        m = mitsuba_render(scene, bsdf or conductor(0.3), box)
        scale, rms, mx, n = compare(g, m, mask, box)
        ok = abs(scale - 1) <= TOL_SCALE and rms <= TOL_SHAPE
        bad += not ok
        print(f"{label:34} {n:7d} {scale:11.6f} {rms:9.2e} {mx:9.2e}  {'ok' if ok else 'FAIL'}")
        if label == "rough gold, near mirror":
            m2 = mitsuba_render(scene, conductor(0.25), box)
            scale2, rms2, _, _ = compare(g, m2, mask, box)
            caught = abs(scale2 - 1) > TOL_SCALE or rms2 > TOL_SHAPE
            print(f"{'  negative control (α 0.25)':34} {'':7} {scale2:11.6f} {rms2:9.2e} {'':9}  "
                  f"{'caught' if caught else 'NOT CAUGHT'}")
            bad += not caught
    if bad:
        sys.exit(f"mitsuba_frame: {bad} case(s) outside tolerance")
    print("mitsuba_frame: gonio's raw radiance frames match Mitsuba 3")


if __name__ == "__main__":
    main()
