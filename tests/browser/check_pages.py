"""Real-browser checks of `gonio view` (Debian chromium, headless, WebGL2 via SwiftShader,
driven by Playwright's Python package with executable_path: no browser download).

Usage: check_pages.py GONIO DATASET GBTF SCRATCH SCREENSHOT_DIR [MORE_FILES…]
(more .gbtf and UBO2014 .btf files get the same canvas checks as GBTF: every method served
here has a GPU decoder, and the page must use it rather than the server's picture)

* every page loads with no console error (relight, inspect, monitor);
* the relight canvas matches `gonio render` for the same URL state (>= 99 % of pixel
  values within 2/255, mean <= 0.5/255) on plane, sphere, cylinder and grazing-light states,
  for a PVMF .gbtf, the raw dataset and every further file (PCA, local PCA, DFMF .btf and
  CIELab .gbtf, median cut, homomorphic);
* moving the light changes the picture, and the change matches the reference's;
* the monitor's progress advances while a simulated acquisition writes a dataset;
* a screenshot is written.
"""
import io
import json
import os
import subprocess
import sys
import time
import base64

import numpy as np
from PIL import Image
from playwright.sync_api import sync_playwright

GONIO, DATASET, GBTF, SCRATCH, SHOTS = sys.argv[1:6]
MORE = sys.argv[6:]
FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--enable-unsafe-swiftshader",
]
SIZE = "64x64"
STATES = [
    ("plane", "light=30,20&view=0,0&shape=plane"),
    ("plane-oblique", "light=45,100&view=30,250&shape=plane"),
    ("sphere", "light=40,60&view=20,200&shape=sphere"),
    ("cylinder", "light=35,300&view=25,30&shape=cylinder"),
    ("grazing", "light=80,120&view=30,10&shape=plane"),
]
failures = []
passed = 0


def check(cond, what):
    global passed
    if cond:
        passed += 1
        print("  ok  ", what, flush=True)
    else:
        failures.append(what)
        print("  FAIL", what, flush=True)


class Server:
    def __init__(self, path, extra=()):
        self.p = subprocess.Popen([GONIO, "view", path, "--port", "0", *extra], stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True)
        line = self.p.stdout.readline().strip()
        if not line.startswith("http://127.0.0.1:"):
            raise SystemExit(f"gonio view {path}: first line {line!r}; stderr: {self.p.stderr.read()}")
        self.url = line
        self.base = line.split("/?token=")[0]

    def close(self):
        self.p.terminate()
        self.p.wait(timeout=10)


def reference(path, query):
    q = dict(kv.split("=") for kv in query.split("&"))
    out = os.path.join(SCRATCH, "ref.png")
    subprocess.run([GONIO, "render", path, "--light", q["light"], "--view", q["view"], "--shape", q["shape"],
                    "--size", SIZE, "--out", out, "--exposure", q.get("exposure", "1")], check=True,
                   stdout=subprocess.DEVNULL)
    return np.asarray(Image.open(out).convert("RGB"), dtype=np.int16)


def canvas(page):
    url = page.evaluate("window.gonio.snapshot()")
    png = base64.b64decode(url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def open_page(page, url, errors):
    errors.clear()
    page.goto(url)
    # Polled from Python: the page's CSP forbids the eval that wait_for_function needs.
    deadline = time.time() + 120
    # A streamed raw dataset: wait until every image is on the GPU and drawn (idle).
    cond = ("window.gonio && ((window.gonio.ready === true && window.gonio.frames > 0 && "
            "(!window.gonio.streaming || window.gonio.idle === true)) || window.gonio.errors.length > 0)")
    while not page.evaluate(cond):
        if time.time() > deadline:
            raise SystemExit(f"{url}: the page did not finish loading in 120 s")
        time.sleep(0.1)
    errs = page.evaluate("window.gonio.errors")
    return errs + errors


def main():
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=FLAGS,
                                    headless=True)
        page = browser.new_page(viewport={"width": 1100, "height": 760})
        errors = []
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: errors.append(str(e)))

        sources = [(os.path.basename(GBTF), GBTF), ("raw dataset", DATASET)]
        sources += [(os.path.basename(f), f) for f in MORE if f.endswith(".gbtf") or f.endswith(".btf")]
        for label, path in sources:
            srv = Server(path)
            try:
                print(f"{label}: {path}", flush=True)
                errs = open_page(page, srv.url + "&" + STATES[0][1] + "&size=" + SIZE, errors)
                check(not errs, f"{label}: relight page loads without console error {errs}")
                check(page.evaluate("window.gonio.errors.length") == 0, f"{label}: no page error")
                gpu = page.evaluate("document.getElementById('fallback').hidden && window.gonio.gpu")
                check(bool(gpu), f"{label}: decoded on the GPU ({gpu}), not the server's picture")
                pics = {}
                for name, q in STATES:
                    errs = open_page(page, srv.base + "/?" + q + "&size=" + SIZE, errors)
                    got = canvas(page)
                    want = reference(path, q)
                    d = np.abs(got - want)
                    frac = float((d <= 2).mean())
                    mean = float(d.mean())
                    print(f"    {name}: {frac * 100:.2f} % of values within 2/255, mean {mean:.3f}/255, max {int(d.max())}")
                    check(not errs and frac >= 0.99 and mean <= 0.5,
                          f"{label}: canvas matches gonio render ({name}: {frac*100:.2f} %, mean {mean:.3f})")
                    pics[name] = (got, want)
                # Moving the light: same view and shape, light from 30,20 to 45,100.
                a_got, a_want = pics["plane"]
                q2 = "light=60,200&view=0,0&shape=plane"
                open_page(page, srv.base + "/?" + q2 + "&size=" + SIZE, errors)
                b_got, b_want = canvas(page), reference(path, q2)
                dg, dw = b_got - a_got, b_want - a_want
                change = float(np.abs(dw).mean())
                agree = float((np.abs(dg - dw) <= 3).mean())
                print(f"    moving the light: reference changes by {change:.2f}/255 on average; "
                      f"{agree*100:.2f} % of the page's changes agree within 3/255")
                check(change > 2.0 and agree >= 0.99, f"{label}: moving the light changes the picture as the reference predicts")
                for pg in ("/inspect", "/monitor") if path == DATASET else ("/inspect",):
                    errs = open_page(page, srv.base + pg, errors)
                    check(not errs, f"{label}: {pg} loads without console error {errs}")
                if path == DATASET:
                    open_page(page, srv.base + "/?light=40,60&view=20,200&shape=sphere&size=256x256", errors)
                    os.makedirs(SHOTS, exist_ok=True)
                    shot = os.path.join(SHOTS, "viewer-relight.png")
                    page.screenshot(path=shot)
                    check(os.path.getsize(shot) > 1000, f"screenshot written: {shot}")
            finally:
                srv.close()

        # Streaming a raw dataset through a GPU pool smaller than the dataset (pool=12 of
        # 144 images): the images of the current picture come first and evict others, so
        # each state's picture is still exactly the reference's.
        srv = Server(DATASET)
        try:
            for name, q in [("plane", "light=30,20&view=0,0&shape=plane"), ("light moved", "light=60,200&view=0,0&shape=plane"),
                            ("oblique", "light=45,100&view=30,250&shape=plane")]:
                errs = open_page(page, srv.url + "&" + q + "&size=" + SIZE + "&pool=12", errors)
                got, want = canvas(page), reference(DATASET, q)
                d = np.abs(got - want)
                st = page.evaluate("window.gonio.streaming")
                print(f"    pool of {st['slots']}: {name}: {st['needed']} images needed, {st['loaded']} on the GPU; "
                      f"{(d <= 2).mean() * 100:.2f} % within 2/255, max {int(d.max())}")
                check(not errs and st["slots"] == 12 and st["loaded"] <= 12 and (d <= 2).mean() >= 0.99 and d.mean() <= 0.5,
                      f"raw streaming through 12 GPU slots: {name} matches gonio render")
            # In place: move the light on the open page; the needed images replace others.
            page.evaluate("window.gonio.setState({light: [75, 10]})")
            deadline = time.time() + 60
            while time.time() < deadline and not page.evaluate("window.gonio.idle === true && window.gonio.complete === true"):
                time.sleep(0.1)
            time.sleep(0.3)
            page.evaluate("window.gonio.setState({})")
            got = canvas(page)
            want = reference(DATASET, "light=75,10&view=30,250&shape=plane")
            d = np.abs(got - want)
            print(f"    pool of 12, light moved in place: {(d <= 2).mean() * 100:.2f} % within 2/255, max {int(d.max())}")
            check((d <= 2).mean() >= 0.99 and d.mean() <= 0.5, "raw streaming: moving the light in place streams the new images")
        finally:
            srv.close()

        # Inspect with --model: the dataset's measurement and truth next to a compressed
        # file's reconstruction, with error maps and PSNR.
        srv = Server(DATASET, ["--model", GBTF])
        try:
            errs = open_page(page, srv.url.replace("/?", "/inspect?"), errors)
            check(not errs, f"inspect --model loads without console error {errs}")
            deadline = time.time() + 30
            js = ("Array.from(document.querySelectorAll('#pairs img')).map(i => [i.alt, i.complete && i.naturalWidth > 0])")
            imgs = page.evaluate(js)
            while time.time() < deadline and not all(ok for _, ok in imgs):
                time.sleep(0.2)
                imgs = page.evaluate(js)
            names = [a for a, _ in imgs]
            print(f"    inspect --model shows: {names}")
            want = ["measured", "model", "truth", "|measured − truth|", "|model − truth|", "|model − measured|"]
            check(names == want and all(ok for _, ok in imgs), "inspect --model: measured, model and truth side by side with three heat maps")
            text = page.evaluate("document.getElementById('errors').textContent")
            print("    " + text.replace("\n", "\n    "))
            import re
            psnr = {m[0]: float(m[1]) for m in re.findall(r"(\w+ vs \w+): PSNR ([0-9.]+) dB", text)}
            check(set(psnr) == {"measured vs truth", "model vs truth", "model vs measured"}
                  and all(10 < v < 200 for v in psnr.values()), f"inspect --model: three finite PSNRs {psnr}")
        finally:
            srv.close()
        for bad_model, why in [m.split("=", 1) for m in os.environ.get("GONIO_MISMATCHED_MODELS", "").split(",") if m]:
            r = subprocess.run([GONIO, "view", DATASET, "--port", "0", "--model", bad_model], capture_output=True,
                               text=True, timeout=60)
            print(f"    --model {os.path.basename(bad_model)}: exit {r.returncode}: {r.stderr.strip().splitlines()[-1:]}")
            check(r.returncode != 0 and why in r.stderr and not r.stdout.startswith("http"),
                  f"a --model whose {why} differ is refused, naming it")

        # Monitor on a dataset being written.
        live = os.path.join(SCRATCH, "live")
        acq = subprocess.Popen([GONIO, "acquire", "--size", "32x32", "--sweep", "fibonacci:12", "--realtime",
                                "--no-truth", "--out", live], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            deadline = time.time() + 60
            while not os.path.exists(os.path.join(live, "manifest.json")) and time.time() < deadline:
                time.sleep(0.2)
            srv = Server(live)
            try:
                errs = open_page(page, srv.url.replace("/?", "/monitor?"), errors)
                check(not errs, f"monitor on a live acquisition loads without console error {errs}")
                seen = []
                deadline = time.time() + 90
                while time.time() < deadline and (len(set(seen)) < 3):
                    seen.append(int(page.evaluate("document.body.dataset.done || '0'")))
                    time.sleep(0.5)
                    if acq.poll() is not None and len(seen) > 4:
                        break
                distinct = sorted(set(seen))
                print(f"    monitor 'done' values seen: {distinct[:10]}{' …' if len(distinct) > 10 else ''}")
                check(len(distinct) >= 3 and seen == sorted(seen), "monitor progress advances while the acquisition runs")
                page.screenshot(path=os.path.join(SHOTS, "viewer-monitor.png"))
            finally:
                srv.close()
        finally:
            acq.terminate()
            acq.wait(timeout=30)
        browser.close()
    print(f"browser: {passed} passed, {len(failures)} failed")
    for f in failures:
        print("  failed:", f)
    sys.exit(1 if failures else 0)


main()
