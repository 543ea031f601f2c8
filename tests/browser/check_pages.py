"""Real-browser checks of `gonio view` (Debian chromium, headless, WebGL2 via SwiftShader,
driven by Playwright's Python package with executable_path: no browser download).

Usage: check_pages.py GONIO DATASET GBTF SCRATCH SCREENSHOT_DIR [MORE_FILES…]
(more .gbtf files get the same canvas checks as GBTF; a UBO2014 .btf, which has no GPU
decoder, is checked for loading without error and showing the server's picture)

* every page loads with no console error (relight, inspect, monitor);
* the relight canvas matches `gonio render` for the same URL state (>= 99 % of pixel
  values within 2/255, mean <= 0.5/255) on plane, sphere, cylinder and grazing-light states,
  for a PVMF .gbtf and for the raw dataset;
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
BTF = next((f for f in MORE if f.endswith(".btf")), None)
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
    def __init__(self, path):
        self.p = subprocess.Popen([GONIO, "view", path, "--port", "0"], stdout=subprocess.PIPE,
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
    cond = "window.gonio && ((window.gonio.ready === true && window.gonio.frames > 0) || window.gonio.errors.length > 0)"
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
        sources += [(os.path.basename(f), f) for f in MORE if f.endswith(".gbtf")]
        for label, path in sources:
            srv = Server(path)
            try:
                print(f"{label}: {path}", flush=True)
                errs = open_page(page, srv.url + "&" + STATES[0][1] + "&size=" + SIZE, errors)
                check(not errs, f"{label}: relight page loads without console error {errs}")
                check(page.evaluate("window.gonio.errors.length") == 0, f"{label}: no page error")
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

        # A method without a GPU decoder (DFMF .btf): the page shows the server's CPU render.
        if BTF:
            srv = Server(BTF)
            try:
                q = "light=40,60&view=20,200&shape=sphere"
                errs = open_page(page, srv.url + "&" + q + "&size=" + SIZE, errors)
                check(not errs, f"DFMF .btf: relight page (server-rendered) loads without console error {errs}")
                shown = page.evaluate("!document.getElementById('fallback').hidden")
                check(shown, "DFMF .btf: the page shows the server's reference picture")
                errs = open_page(page, srv.base + "/inspect", errors)
                check(not errs, f"DFMF .btf: /inspect loads without console error {errs}")
            finally:
                srv.close()

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
