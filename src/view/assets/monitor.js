// The monitor page: progress of a dataset being written, from its journal, live over
// server-sent events. Read-only.
"use strict";
const $ = (id) => document.getElementById(id);

function update(s) {
  G.snapshot = s;
  const pct = s.total ? (100 * s.done) / s.total : 0;
  $("bar").style.width = pct.toFixed(1) + "%";
  $("progress").textContent = s.done + " / " + s.total + " pairs (" + pct.toFixed(1) + " %): " + s.measured +
    " measured, " + s.substituted + " substituted, " + s.skipped + " skipped" + (s.complete ? " · complete" : "");
  $("eta").textContent = s.complete ? "finished" : s.eta_s != null
    ? "ETA " + Math.round(s.eta_s) + " s at " + s.rate_per_s.toFixed(2) + " measurements/s" : "ETA: not enough measurements yet";
  const tl = $("timeline"), g = tl.getContext("2d");
  g.fillStyle = "#444"; g.fillRect(0, 0, tl.width, tl.height);
  const colors = ["#4a8", "#48c", "#d44"];
  const n = Math.max(s.total, 1);
  for (const [order, , kind] of s.timeline) {
    g.fillStyle = colors[kind];
    g.fillRect(Math.floor((order / n) * tl.width), 0, Math.max(1, Math.ceil(tl.width / n)), tl.height);
  }
  $("skipped").textContent = Object.entries(s.skipped_reasons).map(([r, k]) => "skipped ×" + k + ": " + r).join("\n");
  $("rounds").textContent = s.rounds.map((r) => "round " + r.round + ": " + r.done + " / " + r.pairs +
    " pairs · predicted PSNR " + (r.predicted_psnr_before_db == null ? "(prior) " : r.predicted_psnr_before_db.toFixed(2) + " → ") + r.predicted_psnr_after_db.toFixed(2) +
    " dB" + (r.outside_prior ? " · outside the prior" : "")).join("\n") +
    (s.adaptive_finished ? "\nfinished: " + s.adaptive_finished : (s.rounds.length ? "\n(more rounds may follow)" : ""));
  drawReferences(s);
  const tc = $("truth"), h = tc.getContext("2d");
  h.fillStyle = "#101215"; h.fillRect(0, 0, tc.width, tc.height);
  if (s.truth_rmse.length) {
    const max = Math.max(...s.truth_rmse.map((x) => x[1]), 1e-12);
    h.fillStyle = "#fd4";
    for (const [o, e] of s.truth_rmse) h.fillRect((o / n) * tc.width, tc.height - 2 - (e / max) * (tc.height - 4), 2, 2);
    h.fillStyle = "#aaa"; h.fillText("max " + max.toExponential(2), 4, 12);
  }
  if (s.stage_seconds) $("stages").textContent = Object.entries(s.stage_seconds)
    .map(([k, v]) => k + ": " + (typeof v === "number" ? v.toFixed(2) : JSON.stringify(v))).join("\n");
  if (s.last) {
    $("last").textContent = "#" + s.last.index + " (order " + s.last.order + ") light " + fmt(s.last.light_deg) + "° view " + fmt(s.last.view_deg) + "°";
    if (s.last.has_image) $("frame").src = "/api/frame?index=" + s.last.index;
    $("axes").textContent = "axes: " + s.last.axes_deg.map((a) => a.toFixed(2) + "°").join(", ") + " · rig time " + s.last.rig_time_s.toFixed(1) + " s";
    drawPose(s.last);
  }
  G.frames++;
  document.body.dataset.frame = String(G.frames);
  document.body.dataset.done = String(s.done);
}

// The drift references: one row each (run, rig time, ratio per channel against the first,
// largest drift), the newest last, at most the last 20 rows; built from text nodes only.
function drawReferences(s) {
  const refs = s.references || [];
  if (s.references_error) $("references").textContent = "references.jsonl: " + s.references_error;
  else if (refs.length) {
    const largest = Math.max(...refs.map((r) => r.drift));
    $("references").textContent = refs.length + " references, largest drift " + (100 * largest).toFixed(2) + " %" +
      (refs.length > 20 ? " (the last 20 below)" : "");
  }
  const t = $("reftable");
  t.replaceChildren();
  if (!refs.length) return;
  const row = (cells, tag) => {
    const tr = document.createElement("tr");
    for (const c of cells) { const td = document.createElement(tag); td.textContent = c; tr.appendChild(td); }
    t.appendChild(tr);
  };
  row(["#", "run", "rig time (s)", "after", "R", "G", "B", "drift"], "th");
  for (const r of refs.slice(-20)) row([r.number, r.run, r.rig_time_s.toFixed(1), r.after_index == null ? "-" : r.after_index,
    r.ratio[0].toFixed(4), r.ratio[1].toFixed(4), r.ratio[2].toFixed(4), (100 * r.drift).toFixed(2) + " %"], "td");
}

// The hemisphere seen from above with the light and the camera directions, and one dial
// per rig axis.
function drawPose(last) {
  const c = $("pose"), g = c.getContext("2d"), R = 80, cx = 128, cy = 100;
  g.clearRect(0, 0, c.width, c.height);
  g.strokeStyle = "#555"; g.beginPath(); g.arc(cx, cy, R, 0, 2 * Math.PI); g.stroke();
  const dot = (d, col, label) => {
    const r = (R * d[0]) / 90, p = (d[1] * Math.PI) / 180, x = cx + r * Math.cos(p), y = cy - r * Math.sin(p);
    g.strokeStyle = col; g.beginPath(); g.moveTo(cx, cy); g.lineTo(x, y); g.stroke();
    g.fillStyle = col; g.beginPath(); g.arc(x, y, 5, 0, 2 * Math.PI); g.fill(); g.fillText(label, x + 7, y);
  };
  dot(last.light_deg, "#fd4", "light"); dot(last.view_deg, "#9cf", "camera");
  last.axes_deg.forEach((a, i) => {
    const x = 24 + i * 52, y = 222, r = 18, t = (a * Math.PI) / 180;
    g.strokeStyle = "#777"; g.beginPath(); g.arc(x, y, r, 0, 2 * Math.PI); g.stroke();
    g.strokeStyle = "#fff"; g.beginPath(); g.moveTo(x, y); g.lineTo(x + r * Math.cos(t), y - r * Math.sin(t)); g.stroke();
    g.fillStyle = "#aaa"; g.fillText("axis " + i, x - 14, y + 32);
  });
}

async function main() {
  update(await api("/api/monitor", "json"));
  const es = new EventSource("/api/events");
  es.addEventListener("snapshot", (e) => { try { update(JSON.parse(e.data)); } catch (err) { showError(err.message); } });
  G.ready = true;
}
main().catch((e) => showError(e.message || e));
