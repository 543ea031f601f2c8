#!/usr/bin/env python3
"""Independent oracle for `gonio calibrate` (intrinsics): OpenCV's cv2.calibrateCamera on
the very corners gonio detected (DIR/corners.json) must give the same camera as gonio's own
Zhang + Levenberg-Marquardt fit (DIR/calibration.json).

Pixel conventions differ by half a pixel: gonio puts pixel centres at (i + 0.5, j + 0.5),
OpenCV at integers, so the corners are shifted by -0.5 on the way in and OpenCV's cx, cy by
+0.5 on the way out. The distortion model is matched to the recipe's (`opencv4` =
CALIB_FIX_K3, `radial` = also CALIB_ZERO_TANGENT_DIST, `none` = all fixed), and a fixed
`aspect_ratio` to CALIB_FIX_ASPECT_RATIO.

Tolerances (stated, checked): fx, fy, cx, cy agree within 0.05 % of the focal length;
distortion coefficients within 5 % of OpenCV's magnitude plus an absolute 1e-3 (k1, p1,
p2) / 5e-2 (k2, which the small field of view leaves weakly determined); reprojection RMS
within 1e-3 px.

Usage: opencv_intrinsics.py DIR
"""
import json
import sys

import cv2
import numpy as np


def main() -> int:
    d = sys.argv[1]
    corners = json.load(open(f"{d}/corners.json"))
    result = json.load(open(f"{d}/calibration.json"))
    g = result["intrinsics"]
    model = result["recipe"]["estimate"]["distortion"]
    w, h = corners["image_size"]
    obj, img = [], []
    for v in corners["views"]:
        o = np.array(v["object"], dtype=np.float64)
        obj.append(np.hstack([o, np.zeros((len(o), 1))]).astype(np.float32))
        img.append((np.array(v["image"], dtype=np.float64) - 0.5).astype(np.float32).reshape(-1, 1, 2))
    cam = g["camera"]
    k0 = np.array([[cam["fx"], 0, cam["cx"] - 0.5], [0, cam["fy"], cam["cy"] - 0.5], [0, 0, 1]], dtype=np.float64)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS
    if model == "opencv4":
        flags |= cv2.CALIB_FIX_K3
    elif model == "radial":
        flags |= cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    elif model == "none":
        flags |= cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    if result["recipe"]["estimate"].get("aspect_ratio") is not None:
        # fy / fx held fixed: OpenCV keeps the ratio of the initial camera matrix
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    # Start OpenCV from its own initialisation too: the oracle must not merely confirm the
    # starting point it was given.
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    results = {}
    # (OpenCV's own init with a fixed aspect ratio reads only the ratio of the matrix given)
    own = np.eye(3) if flags & cv2.CALIB_FIX_ASPECT_RATIO else None
    for name, f, guess in [("from gonio's estimate", flags, k0.copy()),
                           ("from OpenCV's own init", flags & ~cv2.CALIB_USE_INTRINSIC_GUESS, own)]:
        rms, k, dist, _, _ = cv2.calibrateCamera(obj, img, (w, h), guess, None, flags=f, criteria=crit)
        results[name] = (rms, k, dist.ravel())
    ok = True
    f_ref = min(cam["fx"], cam["fy"])
    for name, (rms, k, dist) in results.items():
        ocv = {"fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2] + 0.5, "cy": k[1, 2] + 0.5}
        diffs = {p: (cam[p] - ocv[p]) / f_ref * 100 for p in ocv}
        gd = cam["distortion"]
        dd = [abs(gd[i] - dist[i]) for i in range(4)]
        dist_tol = [1e-3 + 0.05 * abs(dist[0]), 5e-2 + 0.05 * abs(dist[1]), 1e-3, 1e-3]
        print(f"opencv {cv2.__version__} ({name}): rms {rms:.5f} px (gonio {g['rms_px']:.5f}); "
              + ", ".join(f"{p} {ocv[p]:.3f} (gonio {cam[p]:.3f}, {diffs[p]:+.4f} % of f)" for p in ocv))
        print(f"    distortion opencv {np.round(dist[:4], 6).tolist()} gonio {np.round(gd[:4], 6).tolist()}")
        if any(abs(x) > 0.05 for x in diffs.values()):
            print("    FAIL: intrinsics differ by more than 0.05 % of the focal length", file=sys.stderr)
            ok = False
        if any(a > t for a, t in zip(dd, dist_tol)):
            print(f"    FAIL: distortion differs: {dd} > {dist_tol}", file=sys.stderr)
            ok = False
        if abs(rms - g["rms_px"]) > 1e-3:
            print("    FAIL: reprojection RMS differs by more than 1e-3 px", file=sys.stderr)
            ok = False
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
