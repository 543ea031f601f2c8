// The inspect page: one grid pair's images side by side (measured / model / truth where
// they exist), the error heat map and PSNR, and the ABRDF of a clicked texel.
"use strict";
let info;
const $ = (id) => document.getElementById(id);

async function showPair() {
  const l = $("l").value, v = $("v").value, e = Number($("exposure").value) > 0 ? $("exposure").value : "1";
  const cmp = await api("/api/compare?l=" + l + "&v=" + v, "json");
  const box = $("pairs");
  box.textContent = "";
  const add = (title, src) => {
    const d = document.createElement("div");
    d.textContent = title;
    const img = document.createElement("img");
    img.className = "pair"; img.alt = title; img.src = src;
    img.addEventListener("click", (ev) => {
      const r = img.getBoundingClientRect();
      const x = Math.floor(((ev.clientX - r.left) / r.width) * info.width);
      const y = Math.floor(((ev.clientY - r.top) / r.height) * info.height);
      showAbrdf(x, y).catch((err) => showError(err.message));
    });
    d.appendChild(document.createElement("br")); d.appendChild(img); box.appendChild(d);
    return img;
  };
  if (cmp.sources.length === 0) add("not measured (yet)", "");
  for (const s of cmp.sources) add(s, "/api/pair?l=" + l + "&v=" + v + "&source=" + s + "&exposure=" + e);
  for (const r of cmp.errors)
    add("|" + r.source + " − " + r.reference + "|", "/api/heat?l=" + l + "&v=" + v + "&a=" + r.source + "&b=" + r.reference);
  $("errors").textContent = cmp.errors.length
    ? cmp.errors.map((r) => r.source + " vs " + r.reference + ": PSNR " + (typeof r.psnr_db === "number" ? r.psnr_db.toFixed(2) : r.psnr_db) +
      " dB, RMSE " + r.rmse.toExponential(3) + " (linear; peak = reference maximum)").join("\n")
    : "no second image to compare with for this pair (" + (cmp.sources.join(", ") || "none") + ")";
  G.frames++;
  document.body.dataset.frame = String(G.frames);
}

// The latest texel asked for: a poll of an earlier click stops when another texel is clicked.
let abrdfAsked = 0;

async function showAbrdf(x, y) {
  const asked = ++abrdfAsked;
  let a = await api("/api/abrdf?x=" + x + "&y=" + y, "json");
  // A large raw dataset answers 202 with {building, message} while its texel-major cache
  // is built in the background: show the progress and poll until the values come.
  while (a.building && !a.values) {
    if (asked !== abrdfAsked) return;
    $("texel").textContent = x + ", " + y;
    $("abrdfnote").textContent = a.message;
    await new Promise((r) => setTimeout(r, 1000));
    if (asked !== abrdfAsked) return;
    a = await api("/api/abrdf?x=" + x + "&y=" + y, "json");
  }
  if (asked !== abrdfAsked) return;
  $("texel").textContent = x + ", " + y;
  $("abrdfnote").textContent = a.cache && a.cache.note ? a.cache.note : "";
  const c = $("abrdf");
  c.width = a.lights; c.height = a.views;
  const g = c.getContext("2d"), im = g.createImageData(a.lights, a.views);
  const e = Number($("exposure").value) > 0 ? Number($("exposure").value) : 1;
  const srgb = (x) => { x = Math.min(1, Math.max(0, x * e)); return 255 * (x <= 0.0031308 ? 12.92 * x : 1.055 * Math.pow(x, 1 / 2.4) - 0.055); };
  a.values.forEach((rgb, i) => { im.data.set([srgb(rgb[0]), srgb(rgb[1]), srgb(rgb[2]), 255], i * 4); });
  g.putImageData(im, 0, 0);
  G.abrdf = a;
}

async function main() {
  info = await api("/api/info", "json");
  $("what").textContent = info.kind + " · " + info.method + " · " + info.width + "×" + info.height +
    (info.model ? " · model: " + info.model + " (--model)" : "");
  const fill = (sel, dirs) => dirs.forEach((d, i) => {
    const o = document.createElement("option"); o.value = String(i); o.textContent = i + ": " + fmt(d); sel.appendChild(o);
  });
  fill($("l"), info.lights_deg); fill($("v"), info.views_deg);
  if (info.measured_pairs && info.measured_pairs.length) {
    $("l").value = String(info.measured_pairs[0][0]); $("v").value = String(info.measured_pairs[0][1]);
  }
  for (const id of ["l", "v", "exposure"]) $(id).onchange = () => showPair().catch((e) => showError(e.message));
  await showPair();
  await showAbrdf(Math.floor(info.width / 2), Math.floor(info.height / 2));
  G.ready = true;
}
main().catch((e) => showError(e.message || e));
