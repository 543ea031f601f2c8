// Shared helpers of the viewer's pages (no dependencies, no network but this server).
"use strict";
const G = (window.gonio = window.gonio || { errors: [], frames: 0, bytes: 0 });

// The token arrives once in the URL; the server has set an HttpOnly cookie by now, so drop
// it from the address bar (and from anything copied from it).
(function dropToken() {
  const u = new URL(location.href);
  if (u.searchParams.has("token")) {
    u.searchParams.delete("token");
    history.replaceState(null, "", u.pathname + (u.search ? u.search : "") + u.hash);
  }
})();

function showError(msg) {
  G.errors.push(String(msg));
  const e = document.getElementById("error");
  if (e) e.textContent = String(msg);
}

async function api(url, kind) {
  const r = await fetch(url, { credentials: "same-origin" });
  if (!r.ok) throw new Error(url + ": " + r.status + " " + (await r.text()));
  if (kind === "json") return r.json();
  const b = await r.arrayBuffer();
  G.bytes += b.byteLength;
  return b;
}

// θ,φ in degrees → unit vector (conventions.md).
function unitDeg(d) {
  const t = (d[0] * Math.PI) / 180, p = (d[1] * Math.PI) / 180;
  return [Math.sin(t) * Math.cos(p), Math.sin(t) * Math.sin(p), Math.cos(t)];
}

function parseDir(s, dflt) {
  if (!s) return dflt;
  const p = s.split(",").map(Number);
  if (p.length !== 2 || !p.every(Number.isFinite) || p[0] < 0 || p[0] >= 90) return dflt;
  return [p[0], ((p[1] % 360) + 360) % 360];
}

// The URL state shared by the relight page, `gonio render` and the tests.
function readState() {
  const q = new URLSearchParams(location.search);
  const size = (q.get("size") || "").match(/^(\d+)x(\d+)$/);
  const e = Number(q.get("exposure"));
  return {
    light: parseDir(q.get("light"), [30, 0]),
    view: parseDir(q.get("view"), [0, 0]),
    shape: ["plane", "sphere", "cylinder"].includes(q.get("shape")) ? q.get("shape") : "plane",
    exposure: Number.isFinite(e) && e > 0 ? e : 1,
    size: size ? [Math.min(2048, Math.max(1, +size[1])), Math.min(2048, Math.max(1, +size[2]))] : [256, 256],
  };
}

function fmt(d) {
  return d[0].toFixed(1) + "," + d[1].toFixed(1);
}

// A hemisphere widget: centre θ = 0, rim θ = 90°, φ counter-clockwise from the right.
class Hemi {
  constructor(canvas, dirs, onChange) {
    this.c = canvas;
    this.dirs = dirs || [];
    this.value = [0, 0];
    this.onChange = onChange;
    let down = false;
    const pick = (ev) => {
      const r = canvas.getBoundingClientRect();
      const R = canvas.width / 2 - 4;
      const x = (ev.clientX - r.left) * (canvas.width / r.width) - canvas.width / 2;
      const y = -((ev.clientY - r.top) * (canvas.height / r.height) - canvas.height / 2);
      const th = Math.min(89, (Math.hypot(x, y) / R) * 90);
      let ph = (Math.atan2(y, x) * 180) / Math.PI;
      if (ph < 0) ph += 360;
      this.set([Math.round(th * 10) / 10, th === 0 ? 0 : Math.round(ph * 10) / 10], true);
    };
    canvas.addEventListener("pointerdown", (e) => { down = true; canvas.setPointerCapture(e.pointerId); pick(e); });
    canvas.addEventListener("pointermove", (e) => { if (down) pick(e); });
    canvas.addEventListener("pointerup", () => { down = false; });
  }
  set(v, fromUser) {
    this.value = v;
    this.draw();
    if (fromUser && this.onChange) this.onChange(v);
  }
  draw() {
    const g = this.c.getContext("2d"), w = this.c.width, R = w / 2 - 4, c = w / 2;
    g.clearRect(0, 0, w, w);
    g.strokeStyle = "#444";
    for (const t of [30, 60, 90]) { g.beginPath(); g.arc(c, c, (R * t) / 90, 0, 2 * Math.PI); g.stroke(); }
    g.fillStyle = "#678";
    for (const d of this.dirs) {
      const r = (R * d[0]) / 90, p = (d[1] * Math.PI) / 180;
      g.fillRect(c + r * Math.cos(p) - 1, c - r * Math.sin(p) - 1, 2, 2);
    }
    const r = (R * this.value[0]) / 90, p = (this.value[1] * Math.PI) / 180;
    g.fillStyle = "#fd4";
    g.beginPath(); g.arc(c + r * Math.cos(p), c - r * Math.sin(p), 5, 0, 2 * Math.PI); g.fill();
  }
}

window.addEventListener("error", (e) => showError(e.message));
window.addEventListener("unhandledrejection", (e) => showError(e.reason && e.reason.message ? e.reason.message : e.reason));
