"""The averaged-BRDF exports read by other people's code (issue 33).

usage: check_average_export.py GONIO_BIN FIT.gbtf WORKDIR [--sizes 16,32,64] [--pairs N]
       [--rgl-mean-tol X] [--rgl-p99-tol X]

1. `gonio export FIT.gbtf --format rgl-bsdf --size N` for each size, loaded by Mitsuba 3's
   `measured` plugin (scalar_rgb). `bsdf.eval(ctx, si, wo) / cos θ_o` at seeded random
   (light, view) pairs (θ ≤ 85°, a third near the mirror direction) against gonio's
   isotropic fit: the averaged glTF fit's parameters (read from the file's `description`
   by a tensor-file reader written here) evaluated by `GONIO_BIN brdf eval --model gltf`
   at the pair rotated by 0°, 10°, …, 350° about the normal and averaged. Relative error
   per pair: the largest over R, G, B of |mitsuba − gonio| / gonio. Prints mean, 99th
   percentile and max and the file size per grid size, and the same with the light on the
   file's θ_i slices (0°, 4°, …: the grid's own error, without the interpolation between
   slices); fails when the largest size's mean or 99th percentile is above the tolerances
   (the max sits at grazing glossy pairs between slices; it is printed, not bounded).
2. `gonio export FIT.gbtf --format merl` read back by a reader written here after the
   layout of the MERL public reader (BRDFRead.cpp: i32 dims, then float64 per channel,
   φ_d fastest, scaled by 1/1500, 1.15/1500, 1.66/1500; half/diff → standard angles by
   its rotations), compared at random bins with the same gonio reference: must agree at
   float precision (≤ 1e-9 relative); the reader's lookup by directions must land on the
   bins it was written for.
"""

import json
import math
import os
import random
import struct
import subprocess
import sys

import numpy as np
import mitsuba as mi

mi.set_variant("scalar_rgb")

ROTATIONS = 36


def parse_args(argv):
    if len(argv) < 3:
        sys.exit(__doc__)
    opts = {"sizes": [16, 32, 64], "pairs": 600, "rgl_mean_tol": 0.02, "rgl_p99_tol": 0.25}
    gonio, fit, work = argv[:3]
    rest = argv[3:]
    while rest:
        k, v = rest[0], rest[1]
        rest = rest[2:]
        if k == "--sizes":
            opts["sizes"] = [int(x) for x in v.split(",")]
        elif k == "--pairs":
            opts["pairs"] = int(v)
        elif k == "--rgl-mean-tol":
            opts["rgl_mean_tol"] = float(v)
        elif k == "--rgl-p99-tol":
            opts["rgl_p99_tol"] = float(v)
        else:
            sys.exit(f"unknown option {k}\n{__doc__}")
    return gonio, fit, work, opts


def read_tensor_file(path):
    """Mitsuba's tensor-file container, read independently of Mitsuba: name → (dtype, shape, bytes)."""
    b = open(path, "rb").read()
    assert b[:12] == b"tensor_file\0", "bad magic"
    assert b[12:14] == bytes([1, 0]), "bad version"
    (n,) = struct.unpack_from("<I", b, 14)
    at, fields = 18, {}
    for _ in range(n):
        (ln,) = struct.unpack_from("<H", b, at)
        name = b[at + 2 : at + 2 + ln].decode()
        at += 2 + ln
        ndim, dtype, off = struct.unpack_from("<HBQ", b, at)
        at += 11
        shape = struct.unpack_from("<" + "Q" * ndim, b, at)
        at += 8 * ndim
        fields[name] = (dtype, shape, off)
    out = {}
    for name, (dtype, shape, off) in fields.items():
        np_type = {1: np.uint8, 10: np.float32}[dtype]
        count = int(np.prod(shape))
        out[name] = np.frombuffer(b, dtype=np_type, count=count, offset=off).reshape(shape)
    return out


def vec(t, p):
    t, p = math.radians(t), math.radians(p)
    return (math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t))


def angles(v):
    x, y, z = v
    t = math.degrees(math.acos(max(-1.0, min(1.0, z))))
    p = math.degrees(math.atan2(y, x)) % 360.0 if t > 0 else 0.0
    return t, p


def gonio_iso(gonio, params, pairs):
    """gonio's isotropic fit: the mean over 36 rotations of `gonio brdf eval --model gltf`."""
    lines = []
    for tl, pl, tv, pv in pairs:
        for k in range(ROTATIONS):
            r = 360.0 * k / ROTATIONS
            lines.append(
                json.dumps(
                    {
                        "theta_l": tl,
                        "phi_l": (pl + r) % 360.0 if tl > 0 else 0.0,
                        "theta_v": tv,
                        "phi_v": (pv + r) % 360.0 if tv > 0 else 0.0,
                    }
                )
            )
    p = subprocess.run(
        [gonio, "brdf", "eval", "--model", "gltf", "--params", json.dumps(params)],
        input="\n".join(lines) + "\n",
        capture_output=True,
        text=True,
    )
    if p.returncode != 0:
        sys.exit(f"gonio brdf eval failed ({p.returncode}): {p.stderr.strip()}")
    vals = [json.loads(l)["rgb"] for l in p.stdout.splitlines()]
    assert len(vals) == len(lines), (len(vals), len(lines))
    out = []
    for i in range(len(pairs)):
        s = [0.0, 0.0, 0.0]
        for k in range(ROTATIONS):
            for c in range(3):
                s[c] += vals[i * ROTATIONS + k][c]
        out.append([x / ROTATIONS for x in s])
    return out


def fit_params(desc):
    f = desc["fit"]
    return {"base_color": f["base_color"], "metallic": f["metallic"], "roughness": f["roughness"], "normal": f["normal"]}


def random_pairs(n, roughness):
    rng = random.Random(33)
    spread = max(2.0, math.degrees(2.0 * roughness * roughness))
    out = []
    for i in range(n):
        tl, pl = rng.uniform(0.0, 85.0), rng.uniform(0.0, 360.0)
        if i % 3 == 2:
            tv = min(85.0, max(0.0, tl + rng.gauss(0.0, spread)))
            pv = (pl + 180.0 + rng.gauss(0.0, spread)) % 360.0
        else:
            tv, pv = rng.uniform(0.0, 85.0), rng.uniform(0.0, 360.0)
        out.append((tl, pl, tv, pv))
    return out


def rel_errors(bsdf, pairs, ref):
    ctx = mi.BSDFContext()
    si = mi.SurfaceInteraction3f()
    rel = []
    for (tl, pl, tv, pv), g in zip(pairs, ref):
        si.wi = mi.Vector3f(*vec(tl, pl))
        wo = mi.Vector3f(*vec(tv, pv))
        f = bsdf.eval(ctx, si, wo)
        got = [float(f[c]) / float(wo[2]) for c in range(3)]
        if min(g) <= 0.0:
            continue
        rel.append(max(abs(got[c] - g[c]) / g[c] for c in range(3)))
    return np.array(rel)


def check_rgl(gonio, fit, work, opts):
    results = []
    for size in opts["sizes"]:
        path = os.path.join(work, f"average-{size}.bsdf")
        subprocess.run(
            [gonio, "export", fit, "--format", "rgl-bsdf", "--size", str(size), path, "--json"],
            check=True,
            capture_output=True,
        )
        t = read_tensor_file(path)
        m = len(t["theta_i"])
        assert t["rgb"].shape == (1, m, 3, size, size), t["rgb"].shape
        assert t["vndf"].shape == (1, m, size, size) and t["ndf"].shape == (size, size)
        assert int(t["jacobian"][0]) == 1
        desc = json.loads(bytes(t["description"]).decode())
        assert desc["generator"].startswith("gonio "), desc
        params = fit_params(desc)
        pairs = random_pairs(opts["pairs"], params["roughness"])
        ref = gonio_iso(gonio, params, pairs)
        bsdf = mi.load_dict({"type": "measured", "filename": path})
        rel = rel_errors(bsdf, pairs, ref)
        rng = random.Random(4)
        on = [(4.0 * rng.randrange(22), p[1], p[2], p[3]) for p in pairs]
        on_rel = rel_errors(bsdf, on, gonio_iso(gonio, params, on))
        mb = os.path.getsize(path) / 1e6
        p99 = float(np.percentile(rel, 99))
        results.append((size, float(rel.mean()), float(rel.max()), p99, mb))
        print(
            f"rgl-bsdf size {size}: Mitsuba 3 measured vs gonio isotropic fit over {len(rel)} pairs: "
            f"mean rel {rel.mean():.4f}, p99 {p99:.4f}, max {rel.max():.4f}; light on the slices: mean "
            f"{on_rel.mean():.4f}, max {on_rel.max():.4f}; {mb:.2f} MB"
        )
    size, mean, _, p99, _ = results[-1]
    if mean > opts["rgl_mean_tol"] or p99 > opts["rgl_p99_tol"]:
        sys.exit(
            f"rgl-bsdf size {size}: mean rel {mean:.4f} / p99 {p99:.4f} above {opts['rgl_mean_tol']} / {opts['rgl_p99_tol']}"
        )
    return results


# ---- MERL: a reader after the public BRDFRead.cpp's layout ---------------------------------
BRDF_SAMPLING_RES_THETA_H = 90
BRDF_SAMPLING_RES_THETA_D = 90
BRDF_SAMPLING_RES_PHI_D = 360
SCALES = (1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0)


def read_merl(path):
    b = open(path, "rb").read()
    dims = struct.unpack_from("<3i", b, 0)
    n = dims[0] * dims[1] * dims[2]
    assert n == BRDF_SAMPLING_RES_THETA_H * BRDF_SAMPLING_RES_THETA_D * BRDF_SAMPLING_RES_PHI_D // 2, dims
    assert len(b) == 12 + 3 * n * 8, (len(b), n)
    return np.frombuffer(b, dtype="<f8", count=3 * n, offset=12)


def rotate(v, axis, angle):
    """Rodrigues' rotation, as the public reader's rotate_vector."""
    c, s = math.cos(angle), math.sin(angle)
    dot = sum(a * b for a, b in zip(v, axis))
    cross = (axis[1] * v[2] - axis[2] * v[1], axis[2] * v[0] - axis[0] * v[2], axis[0] * v[1] - axis[1] * v[0])
    return tuple(v[i] * c + axis[i] * dot * (1 - c) + cross[i] * s for i in range(3))


def std_to_half_diff(ti, fi, to, fo):
    i = (math.sin(ti) * math.cos(fi), math.sin(ti) * math.sin(fi), math.cos(ti))
    o = (math.sin(to) * math.cos(fo), math.sin(to) * math.sin(fo), math.cos(to))
    h = tuple(a + b for a, b in zip(i, o))
    ln = math.sqrt(sum(x * x for x in h))
    h = tuple(x / ln for x in h)
    th, fh = math.acos(max(-1, min(1, h[2]))), math.atan2(h[1], h[0])
    tmp = rotate(i, (0, 0, 1), -fh)
    d = rotate(tmp, (0, 1, 0), -th)
    return th, fh, math.acos(max(-1, min(1, d[2]))), math.atan2(d[1], d[0])


def theta_half_index(th):
    if th <= 0.0:
        return 0
    idx = int(math.sqrt(th / (math.pi / 2.0)) * BRDF_SAMPLING_RES_THETA_H)
    return max(0, min(idx, BRDF_SAMPLING_RES_THETA_H - 1))


def theta_diff_index(td):
    idx = int(td / (math.pi * 0.5) * BRDF_SAMPLING_RES_THETA_D)
    return max(0, min(idx, BRDF_SAMPLING_RES_THETA_D - 1))


def phi_diff_index(fd):
    if fd < 0.0:
        fd += math.pi
    idx = int(fd / math.pi * BRDF_SAMPLING_RES_PHI_D / 2)
    return max(0, min(idx, BRDF_SAMPLING_RES_PHI_D // 2 - 1))


def lookup_index(ti, fi, to, fo):
    th, _, td, fd = std_to_half_diff(ti, fi, to, fo)
    return (
        phi_diff_index(fd)
        + theta_diff_index(td) * (BRDF_SAMPLING_RES_PHI_D // 2)
        + theta_half_index(th) * (BRDF_SAMPLING_RES_PHI_D // 2) * BRDF_SAMPLING_RES_THETA_D
    )


def bin_directions(i, j, k, frac=0.0):
    """The (light, view) pair of bin (i, j, k) at fraction `frac` into the bin (0: its angles)."""
    th = ((i + frac) / 90.0) ** 2 * (math.pi / 2)
    td = (j + frac) * (math.pi / 2) / 90.0
    fd = (k + frac) * math.pi / 180.0
    d = (math.sin(td) * math.cos(fd), math.sin(td) * math.sin(fd), math.cos(td))
    l = rotate(d, (0, 1, 0), th)
    h = (math.sin(th), 0.0, math.cos(th))
    dot = sum(a * b for a, b in zip(h, l))
    v = tuple(2 * dot * h[c] - l[c] for c in range(3))
    return l, v


def check_merl(gonio, fit, work):
    path = os.path.join(work, "average.binary")
    subprocess.run([gonio, "export", fit, "--format", "merl", path, "--json"], check=True, capture_output=True)
    side = json.load(open(path + ".json"))
    params = fit_params(side["provenance"])
    data = read_merl(path)
    n = data.size // 3
    rng = random.Random(1500)
    bins, pairs = [], []
    while len(bins) < 1500:
        i, j, k = rng.randrange(90), rng.randrange(90), rng.randrange(180)
        l, v = bin_directions(i, j, k)
        if l[2] <= 1e-6 or v[2] <= 1e-6:
            continue
        (tl, pl), (tv, pv) = angles(l), angles(v)
        if tl >= 89.99 or tv >= 89.99:
            continue
        bins.append((i, j, k))
        pairs.append((tl, pl, tv, pv))
    ref = gonio_iso(gonio, params, pairs)
    worst = 0.0
    for (i, j, k), g in zip(bins, ref):
        idx = k + 180 * (j + 90 * i)
        for c in range(3):
            got = data[c * n + idx] * SCALES[c]
            worst = max(worst, abs(got - g[c]) / max(abs(g[c]), 1e-300))
    # The lookup by directions (half a bin in) lands on the bin written for those angles.
    hits = 0
    for i, j, k in bins[:300]:
        l, v = bin_directions(i, j, k, 0.5)
        (tl, pl), (tv, pv) = angles(l), angles(v)
        got = lookup_index(math.radians(tl), math.radians(pl), math.radians(tv), math.radians(pv))
        hits += got == k + 180 * (j + 90 * i)
    mb = os.path.getsize(path) / 1e6
    print(
        f"merl: {len(bins)} random bins read back by the MERL-layout reader vs gonio isotropic fit: max rel "
        f"{worst:.2e}; direction lookup on the written bin {hits}/300; {mb:.2f} MB"
    )
    if worst > 1e-9:
        sys.exit(f"merl: max rel error {worst:.3e} above float precision (1e-9)")
    if hits < 300:
        sys.exit(f"merl: the reader's direction lookup landed on another bin for {300 - hits} of 300 bins")
    return worst, mb


def main():
    gonio, fit, work, opts = parse_args(sys.argv[1:])
    os.makedirs(work, exist_ok=True)
    check_rgl(gonio, fit, work, opts)
    check_merl(gonio, fit, work)


if __name__ == "__main__":
    main()
