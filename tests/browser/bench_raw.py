"""Progressive streaming of a large raw dataset in `gonio view` (a benchmark, not a test;
prints a table and a JSON line).

Usage: bench_raw.py GONIO DATASET [FILL_SECONDS]

Serves DATASET (e.g. `gonio sim btf --size 256 --out DIR`: 81 × 81 × 256², 1.3 GiB of EXR) and
opens the relight page in headless chromium (SwiftShader), once per state (plane seen from
above at 256², sphere at 128²), each in a fresh page (a state without a complete picture
within BENCH_WAIT_S seconds, default 240, is reported as such):

* first picture: navigation start → the first frame drawn with every image that picture
  uses on the GPU (the server lists them, most used first; they are streamed first);
* bytes transferred until then (image payload) and how many images that was;
* then it lets the stream fill the GPU pool for FILL_SECONDS (default 60) and reports the
  images and bytes transferred by then.
"""
import json
import os
import subprocess
import sys
import time

from playwright.sync_api import sync_playwright

GONIO, DATASET = sys.argv[1], sys.argv[2]
FILL = float(sys.argv[3]) if len(sys.argv) > 3 else 60.0
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--enable-unsafe-swiftshader"]
STATES = [("plane", "light=30,20&view=0,0&shape=plane&size=256x256"),
          ("sphere", "light=40,60&view=20,200&shape=sphere&size=128x128")]
WAIT = float(os.environ.get("BENCH_WAIT_S", "240"))


def du(path):
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(path) for f in fs)


def main():
    srv = subprocess.Popen([GONIO, "view", DATASET, "--port", "0"], stdout=subprocess.PIPE, text=True)
    url = srv.stdout.readline().strip()
    base = url.split("/?token=")[0]
    res = {"dataset": DATASET, "dataset_bytes": du(DATASET)}
    try:
        with sync_playwright() as p:
            b = p.chromium.launch(executable_path="/usr/bin/chromium", args=FLAGS)

            for name, q in STATES:
                page = b.new_page(viewport={"width": 1100, "height": 760})
                page.goto(url + "&" + q)  # a fresh page is a fresh context: the token again

                deadline = time.time() + WAIT
                while not page.evaluate("window.gonio && (window.gonio.ready === true && window.gonio.frames > 0"
                                        " && window.gonio.firstPictureMs !== undefined || window.gonio.errors.length > 0)"):
                    if time.time() > deadline:
                        s = page.evaluate("window.gonio.streaming")
                        print(f"{name}: no complete picture in {WAIT:.0f} s: {s}, {page.evaluate('window.gonio.bytes')} bytes",
                              flush=True)
                        break
                    time.sleep(0.05)
                if time.time() > deadline:
                    page.close()
                    continue
                errs = page.evaluate("window.gonio.errors")
                if errs:
                    raise SystemExit(f"page errors: {errs}")
                s = page.evaluate("window.gonio.streaming")
                res[name] = {
                    "first_picture_s": page.evaluate("window.gonio.firstPictureMs") / 1000,
                    "bytes_at_first_picture": page.evaluate("window.gonio.firstCompleteBytes"),
                    "images_needed": s["needed"],
                    "gpu_slots": s["slots"],
                    "pairs": s["pairs"],
                }
                t0 = time.time()
                while time.time() - t0 < FILL and not page.evaluate("window.gonio.idle === true"):
                    time.sleep(0.5)
                s = page.evaluate("window.gonio.streaming")
                res[name].update({"fill_s": time.time() - t0, "images_after_fill": s["loaded"],
                                  "bytes_after_fill": page.evaluate("window.gonio.bytes")})
                print(name, json.dumps(res[name]), flush=True)
                page.close()
            b.close()
    finally:
        srv.terminate()
        srv.wait(timeout=10)
    print(f"dataset           {res['dataset_bytes'] / 1e9:.2f} GB on disk ({DATASET})")
    for name, _ in STATES:
        if name not in res:
            continue
        r = res[name]
        print(f"{name:8s} first picture {r['first_picture_s']:.2f} s after {r['bytes_at_first_picture'] / 2**20:.1f} MiB "
              f"({r['images_needed']} images of {r['pairs']}); after {r['fill_s']:.0f} s more: "
              f"{r['images_after_fill']} images on the GPU ({r['gpu_slots']} slots), {r['bytes_after_fill'] / 2**20:.0f} MiB")
    print(json.dumps(res))


main()
