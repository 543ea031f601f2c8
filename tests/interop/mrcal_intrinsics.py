#!/usr/bin/env python3
"""mrcal as a peer for `gonio calibrate` (intrinsics): the very corners gonio detected
(DIR/corners.json) are handed to mrcal's own tool, `mrcal-calibrate-cameras`, through its
corners-cache file, with the same lens model (gonio `opencv5` = LENSMODEL_OPENCV5,
`opencv4` = LENSMODEL_OPENCV4) and the same plain least-squares problem (no board-warp
solve, no regularization, no outlier rejection: gonio does none of them). Then both
cameras and both projection-uncertainty maps are compared on gonio's grid
(calibration.json's `projection_uncertainty`), and on the simulator both against the true
camera (calibration.json's `truth`).

Pixel conventions: gonio puts pixel centres at (i + 0.5, j + 0.5), mrcal (like OpenCV) at
integers, so corners go in shifted by -0.5 and mrcal's cx, cy come out shifted by +0.5.

Checks (stated, asserted):
- agreement within the uncertainties: at every grid node the two cameras project the same
  ray less than 3 sigma apart, sigma = gonio's one-sigma projection uncertainty there;
- gonio's whole-image error against the truth is no worse than mrcal's (max over the grid,
  within 2 % + 0.01 px: the two solve the same problem to the same optimum);
- mrcal's uncertainty map (worst-direction stdev, points at infinity) and gonio's are
  printed side by side (centre, sample region, image corners); gonio's is not smaller
  than mrcal's anywhere by more than a factor 2 (gonio holds the ray fixed in the camera
  frame and so includes the principal point's full uncertainty; mrcal's is the smaller).

- with `--max-truth-error PX` (a recipe that covers the imager): gonio's whole-image error
  against the truth is below PX, and its result carries no uncertainty warning.

Usage: mrcal_intrinsics.py DIR [--max-truth-error PX]   (needs Debian's python3-mrcal and mrcal)
"""
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

try:
    import mrcal
except ImportError:
    print("mrcal interop: SKIPPED (python3-mrcal is not installed: apt-get install mrcal python3-mrcal)")
    sys.exit(0)


def opencv_project(cam, x, y):
    """gonio's CameraModel.project for normalized (x, y)."""
    k1, k2, p1, p2, k3 = cam["distortion"]
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return cam["fx"] * xd + cam["cx"], cam["fy"] * yd + cam["cy"]


def opencv_unproject(cam, u, v):
    xd, yd = (u - cam["cx"]) / cam["fx"], (v - cam["cy"]) / cam["fy"]
    x, y = xd.copy(), yd.copy()
    for _ in range(100):
        pu, pv = opencv_project(cam, x, y)
        x -= (pu - u) / cam["fx"]
        y -= (pv - v) / cam["fy"]
    return x, y


def main() -> int:
    d = sys.argv[1]
    max_truth_error = None
    if len(sys.argv) == 4 and sys.argv[2] == "--max-truth-error":
        max_truth_error = float(sys.argv[3])
    elif len(sys.argv) != 2:
        print("usage: mrcal_intrinsics.py DIR [--max-truth-error PX]", file=sys.stderr)
        return 2
    corners = json.load(open(f"{d}/corners.json"))
    result = json.load(open(f"{d}/calibration.json"))
    g = result["intrinsics"]["camera"]
    model = result["recipe"]["estimate"]["distortion"]
    lensmodel = {"opencv5": "LENSMODEL_OPENCV5", "opencv4": "LENSMODEL_OPENCV4"}.get(model)
    if lensmodel is None:
        print(f"mrcal interop: distortion model {model!r} has no mrcal counterpart used here", file=sys.stderr)
        return 1
    board = result["recipe"].get("checkerboard")
    if board is not None:
        nw, nh, pitch = board["cols"], board["rows"], board["pitch_mm"]
    else:
        cb = result["recipe"]["coded_board"]
        nw, nh, pitch = cb["squares_x"] - 1, cb["squares_y"] - 1, cb["pitch_mm"]
    w, h = corners["image_size"]
    work = tempfile.mkdtemp(prefix="gonio-mrcal-")
    # mrcal's board: point (row r, col c) at (c, r) * spacing; gonio's object points are
    # centred on the board, so the grid index is the offset from the centre.
    lines = ["# filename x y level"]
    for k, v in enumerate(corners["views"]):
        grid = {}
        for o, p in zip(v["object"], v["image"]):
            c = int(round(o[0] / pitch + (nw - 1) / 2))
            r = int(round(o[1] / pitch + (nh - 1) / 2))
            grid[(r, c)] = (p[0] - 0.5, p[1] - 0.5)
        name = f"frame{k:03d}.png"
        for r in range(nh):
            for c in range(nw):
                if (r, c) in grid:
                    x, y = grid[(r, c)]
                    lines.append(f"{name} {x:.6f} {y:.6f} 0")
                else:
                    lines.append(f"{name} - - -")
    cache = os.path.join(work, "corners.vnl")
    open(cache, "w").write("\n".join(lines) + "\n")
    cmd = [
        "mrcal-calibrate-cameras",
        "--corners-cache", cache,
        "--lensmodel", lensmodel,
        "--focal", f"{g['fx']:.1f}",
        "--imagersize", str(w), str(h),
        "--object-spacing", str(pitch),
        "--object-width-n", str(nw),
        "--object-height-n", str(nh),
        "--skip-calobject-warp-solve",
        "--skip-regularization",
        "--skip-outlier-rejection",
        "--outdir", work,
        "frame*.png",
    ]
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=work)
    if run.returncode != 0:
        print(run.stdout[-3000:], run.stderr[-3000:], sep="\n", file=sys.stderr)
        print("mrcal interop: mrcal-calibrate-cameras failed", file=sys.stderr)
        return 1
    m = mrcal.cameramodel(os.path.join(work, "camera-0.cameramodel"))
    lm, p = m.intrinsics()
    dist = list(p[4:9]) if len(p) >= 9 else list(p[4:8]) + [0.0]
    mc = {"fx": p[0], "fy": p[1], "cx": p[2] + 0.5, "cy": p[3] + 0.5, "distortion": dist}
    print(f"mrcal {lm}: fx {mc['fx']:.3f} fy {mc['fy']:.3f} cx {mc['cx']:.3f} cy {mc['cy']:.3f} dist {np.round(dist, 5).tolist()}")
    print(f"gonio {model}: fx {g['fx']:.3f} fy {g['fy']:.3f} cx {g['cx']:.3f} cy {g['cy']:.3f} dist {np.round(g['distortion'], 5).tolist()}")

    u = result["projection_uncertainty"]
    gx, gy = np.array(u["grid_x"]), np.array(u["grid_y"])
    U, V = np.meshgrid(gx, gy)
    # null = gonio's estimate defines no ray there (its distortion folds over)
    sig_g = np.array([np.nan if s is None else s for s in u["sigma_px"]], dtype=float).reshape(U.shape)
    # the two cameras on the same rays (through gonio's estimate)
    with np.errstate(all="ignore"):
        x, y = opencv_unproject(g, U, V)
    with np.errstate(all="ignore"):
        mu, mv = opencv_project(mc, x, y)
    diff = np.hypot(mu - U, mv - V)
    ratio = diff / sig_g
    # mrcal's own uncertainty map at the same pixels (its convention: centres at integers)
    q = np.stack([U - 0.5, V - 0.5], axis=-1)
    vcam = mrcal.unproject(q, *m.intrinsics())
    sig_m = mrcal.projection_uncertainty(vcam, model=m, atinfinity=True, what="worstdirection-stdev")
    ok = True
    both = np.isfinite(sig_g) & np.isfinite(sig_m)
    print(f"grid {U.shape[1]} x {U.shape[0]}: gonio defines a ray at {np.isfinite(sig_g).mean():.1%} of the nodes, "
          f"mrcal at {np.isfinite(sig_m).mean():.1%}; compared where both do")
    if both.mean() < 0.5:
        print("FAIL: fewer than half the nodes have a ray in both models", file=sys.stderr)
        ok = False
    diff, ratio, sig_g, sig_m = (np.where(both, a, np.nan) for a in (diff, ratio, sig_g, sig_m))
    print(f"gonio vs mrcal projection: max difference {np.nanmax(diff):.4f} px, "
          f"max difference / gonio sigma {np.nanmax(ratio):.2f}")
    if not np.nanmax(ratio) < 3.0:
        print("FAIL: gonio and mrcal disagree by more than 3 sigma somewhere", file=sys.stderr)
        ok = False
    cy_i, cx_i = np.unravel_index(np.argmin(np.hypot(U - g["cx"], V - g["cy"])), U.shape)
    print("uncertainty (1 sigma, px)   gonio    mrcal")
    for label, (j, i) in [("centre", (cy_i, cx_i)), ("top-left", (0, 0)), ("top-right", (0, -1)),
                          ("bottom-left", (-1, 0)), ("bottom-right", (-1, -1))]:
        print(f"  {label:<24} {sig_g[j, i]:8.4f} {sig_m[j, i]:8.4f}")
    print(f"  {'whole image max':<24} {np.nanmax(sig_g):8.4f} {np.nanmax(sig_m):8.4f}")
    if not np.all((sig_g * 2.0 >= sig_m)[both]):
        print("FAIL: gonio's uncertainty is less than half mrcal's somewhere", file=sys.stderr)
        ok = False
    t = result.get("truth")
    if t is not None:
        with np.errstate(all="ignore"):
            eg = np.hypot(*(np.array(opencv_project(t, x, y)) - np.array([U, V])))
            xm, ym = opencv_unproject(mc, U, V)
            em = np.hypot(*(np.array(opencv_project(t, xm, ym)) - np.array([U, V])))
        eg, em = np.nanmax(np.where(both, eg, np.nan)), np.nanmax(np.where(both, em, np.nan))
        print(f"whole-image error against the truth (where both define a ray): gonio max {eg:.4f} px, mrcal max {em:.4f} px")
        if not eg <= em * 1.02 + 0.01:
            print("FAIL: gonio's whole-image error is worse than mrcal's", file=sys.stderr)
            ok = False
    if max_truth_error is not None:
        pt = result.get("projection_truth") or {}
        worst = pt.get("max_error_px")
        warning = (result.get("projection_uncertainty") or {}).get("warning")
        print(f"covering recipe: whole-image error {worst} px (bound {max_truth_error}), warning {warning!r}")
        if worst is None or not worst < max_truth_error or warning is not None:
            print("FAIL: the covering recipe does not hold over the whole image", file=sys.stderr)
            ok = False
    print("mrcal interop: " + ("OK" if ok else "FAILED"))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
