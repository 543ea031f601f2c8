"""Figures of `gonio view` (a benchmark, not a test; prints a table and a JSON line).

Usage: bench.py GONIO SCRATCH [SIDE] [COMPONENTS]

* Writes a PVMF .gbtf of the real shape of a full Bonn acquisition (81 lights × 81 views,
  SIDE² texels, COMPONENTS per view; defaults 256 and 8) with seeded random factors: the
  viewer's transfer and decoding cost depend on the shape of the factors, not on their
  values. (A real 81 × 81 × 256² acquisition and compression gives the same file size.)
* Serves it with `gonio view` and opens the relight page in headless chromium
  (SwiftShader): time to first picture (navigation start → first frame drawn, factors
  fetched and uploaded), bytes transferred (factor payload and all resources), then
  relight frames per second at 512² for the plane and the sphere (light moving every
  frame; each frame waits for the GPU with a 1-pixel readPixels).
* Times `gonio render` on the same scenes for comparison (the CPU reference).
"""
import json
import os
import struct
import subprocess
import sys
import time
import zlib

import numpy as np
from playwright.sync_api import sync_playwright

GONIO, SCRATCH = sys.argv[1], sys.argv[2]
SIDE = int(sys.argv[3]) if len(sys.argv) > 3 else 256
C = int(sys.argv[4]) if len(sys.argv) > 4 else 8
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--enable-unsafe-swiftshader"]


def bonn81():
    out = []
    for th, n in ((0, 1), (15, 6), (30, 12), (45, 18), (60, 20), (75, 24)):
        out += [[float(th), k * 360.0 / n] for k in range(n)]
    return out


def write_gbtf(path):
    rng = np.random.default_rng(1)
    dirs = bonn81()
    t = SIDE * SIDE
    blocks, infos = [], []
    for v in range(81):
        basis = (0.2 + 0.05 * rng.standard_normal((t, C))).astype("<f4")
        rows = (0.5 / C + 0.02 * rng.standard_normal((81 * 3, C))).astype("<f4")
        blocks += [basis, rows]
        infos += [{"name": f"us{v}", "rows": t, "cols": C}, {"name": f"v{v}", "rows": 81 * 3, "cols": C}]
    header = json.dumps({"method": "pvmf", "params": {"components": C, "note": "synthetic factors for benchmarks"},
                         "width": SIDE, "height": SIDE, "channels": 3, "dtype": "f32le",
                         "lights_deg": dirs, "views_deg": dirs, "filled": [], "source": {}, "blocks": infos}).encode()
    with open(path, "wb") as f:
        f.write(b"GBTF\0\r\n\x1a" + struct.pack("<IQ", 1, len(header)) + header + struct.pack("<I", zlib.crc32(header)))
        for b in blocks:
            raw = b.tobytes()
            f.write(struct.pack("<Q", len(raw)) + raw + struct.pack("<I", zlib.crc32(raw)))
    return os.path.getsize(path)


def main():
    os.makedirs(SCRATCH, exist_ok=True)
    path = os.path.join(SCRATCH, f"bench_pvmf_{SIDE}_c{C}.gbtf")
    size = write_gbtf(path)
    srv = subprocess.Popen([GONIO, "view", path, "--port", "0"], stdout=subprocess.PIPE, text=True)
    url = srv.stdout.readline().strip()
    base = url.split("/?token=")[0]
    res = {"file": path, "file_bytes": size, "side": SIDE, "components": C}
    try:
        with sync_playwright() as p:
            b = p.chromium.launch(executable_path="/usr/bin/chromium", args=FLAGS)
            page = b.new_page(viewport={"width": 1100, "height": 760})
            page.goto(url + "&light=30,20&view=0,0&shape=plane&size=512x512")
            while not page.evaluate("window.gonio && window.gonio.frames > 0 || (window.gonio && window.gonio.errors.length > 0)"):
                time.sleep(0.05)
            errs = page.evaluate("window.gonio.errors")
            if errs:
                raise SystemExit(f"page errors: {errs}")
            res["first_picture_s"] = page.evaluate("window.gonio.firstPictureMs") / 1000
            res["factor_bytes"] = page.evaluate("window.gonio.bytes")
            res["all_resource_bytes"] = page.evaluate(
                "performance.getEntriesByType('resource').reduce((s, e) => s + e.encodedBodySize, 0)"
                " + performance.getEntriesByType('navigation')[0].encodedBodySize")
            for shape, side in (("plane", 512), ("sphere", 512), ("sphere", 128)):
                page.goto(base + f"/?light=30,20&view=20,200&shape={shape}&size={side}x{side}")
                while not page.evaluate("window.gonio && window.gonio.frames > 0"):
                    time.sleep(0.05)
                page.evaluate("window.gonio.bench(1)")  # warm-up
                res[f"fps_{side}_{shape}"] = page.evaluate("window.gonio.bench(5)")
            b.close()
    finally:
        srv.terminate()
        srv.wait(timeout=10)
    for shape in ("plane", "sphere"):
        t0 = time.time()
        subprocess.run([GONIO, "render", path, "--light", "30,20", "--view", "20,200", "--shape", shape,
                        "--size", "512x512", "--out", os.path.join(SCRATCH, "bench.png")], check=True,
                       stdout=subprocess.DEVNULL)
        res[f"cpu_render_512_{shape}_s"] = time.time() - t0
    print(f"file            {res['file_bytes'] / 2**20:.1f} MiB ({SIDE}², 81 × 81, PVMF c = {C})")
    print(f"first picture   {res['first_picture_s']:.2f} s")
    print(f"transferred     {res['factor_bytes'] / 2**20:.1f} MiB factors, {res['all_resource_bytes'] / 2**20:.1f} MiB in all")
    print(f"relight 512²    plane {res['fps_512_plane']:.2f} fps, sphere {res['fps_512_sphere']:.2f} fps (SwiftShader)")
    print(f"relight 128²    sphere {res['fps_128_sphere']:.2f} fps (SwiftShader)")
    print(f"gonio render    plane {res['cpu_render_512_plane_s']:.2f} s, sphere {res['cpu_render_512_sphere_s']:.2f} s (512², incl. loading the file)")
    print(json.dumps(res))


main()
