#!/usr/bin/env python3
"""How good are the detected corners, and what do their errors do to the intrinsics?

Reads DIR/corners.json and DIR/calibration.json of a `gonio calibrate` intrinsics run on a
simulated rig (which writes `truth_image`: the exact projection of every detected corner)
and prints

1. per view: RMS and mean of the detection error (detected − exact), and the RMS left after
   removing its best affine part (what a pose change could absorb);
2. OpenCV's cv2.calibrateCamera, with the recipe's distortion model and aspect-ratio flag,
   on (a) the exact projections, (b) the detected corners, (c) the exact projections plus
   independent Gaussian noise of the detected corners' RMS, for a few seeds.

(a) checks the fitting chain (it must return the simulator's camera); (b) − (c) separates
the corners' *correlated* errors from noise of the same size: if (b) is far off while (c)
scatters little, the errors are systematic, not random.

Usage: corner_errors.py DIR [SEEDS]     (needs numpy and opencv-python-headless)
"""
import json
import sys

import cv2
import numpy as np


def main() -> int:
    d = sys.argv[1]
    seeds = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    c = json.load(open(f"{d}/corners.json"))
    r = json.load(open(f"{d}/calibration.json"))
    if not c.get("truth_image"):
        print("corners.json has no truth_image (not a simulated rig)", file=sys.stderr)
        return 2
    w, h = c["image_size"]
    errs = []
    print("view                          rms_px   mean_u   mean_v  rms_after_affine")
    for v, t in zip(c["views"], c["truth_image"]):
        im, tr = np.array(v["image"]), np.array(t)
        e = im - tr
        errs.append(e)
        x = np.c_[tr - tr.mean(0), np.ones(len(tr))]
        coef, *_ = np.linalg.lstsq(x, e, rcond=None)
        res = e - x @ coef
        print(f"{v['label']:28s} {np.sqrt((e**2).sum(1).mean()):7.4f} {e[:, 0].mean():+8.4f} {e[:, 1].mean():+8.4f}"
              f" {np.sqrt((res**2).sum(1).mean()):9.4f}")
    rms_all = float(np.sqrt(np.concatenate([(e**2).sum(1) for e in errs]).mean() / 2))
    est = r["recipe"]["estimate"]
    model = est["distortion"]
    flags = cv2.CALIB_USE_INTRINSIC_GUESS
    flags |= {"opencv4": cv2.CALIB_FIX_K3,
              "radial": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
              "none": cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
              "opencv5": 0}[model]
    if est.get("aspect_ratio") is not None:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    t = r["truth"]
    k0 = np.array([[t["fx"], 0, t["cx"] - 0.5], [0, t["fy"], t["cy"] - 0.5], [0, 0, 1.0]])
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-15)

    def fit(points):
        obj = [np.hstack([np.array(v["object"]), np.zeros((len(v["object"]), 1))]).astype(np.float32)
               for v in c["views"]]
        img = [(p - 0.5).astype(np.float32).reshape(-1, 1, 2) for p in points]
        rms, k, _, _, _ = cv2.calibrateCamera(obj, img, (w, h), k0.copy(), None, flags=flags, criteria=crit)
        return rms, k[0, 0], k[1, 1], k[0, 2] + 0.5, k[1, 2] + 0.5

    def show(name, f):
        rms, fx, fy, cx, cy = f
        print(f"{name:34s} rms {rms:.4f}  fx {100 * (fx - t['fx']) / t['fx']:+.4f} %  "
              f"cx {cx - t['cx']:+.3f} px ({100 * (cx - t['cx']) / t['cx']:+.4f} %)  "
              f"cy {cy - t['cy']:+.3f} px ({100 * (cy - t['cy']) / t['cy']:+.4f} %)")

    truth = [np.array(x) for x in c["truth_image"]]
    print(f"\nOpenCV {cv2.__version__}, model {model}, aspect ratio {est.get('aspect_ratio')}: errors against the truth")
    show("(a) exact projections", fit(truth))
    show("(b) detected corners", fit([np.array(v["image"]) for v in c["views"]]))
    for s in range(seeds):
        rng = np.random.default_rng(s + 1)
        show(f"(c) exact + noise {rms_all:.4f} px, seed {s + 1}",
             fit([p + rng.normal(0.0, rms_all, p.shape) for p in truth]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
