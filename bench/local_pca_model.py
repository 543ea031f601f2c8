#!/usr/bin/env python3
"""Per-pass model of a sharded local PCA, fitted to and checked against
bench/local_pca_shards.sh's output (docs/guide/scale.md, "Local PCA").

Per pass, a shard's time is t = a + b·v (v views of the shard): a and b are fitted by
least squares on the 2- and 4-shard runs, the model predicts the 1-shard run, and the
prediction is compared with the measurement. A merge's time is fitted as
m = m0 + m1 · (bytes of its parts) over the 1-, 2- and 4-shard merges of that pass.

Carried to UBO2014 size (151 views × 151 lights × 400² texels): a pass's per-view cost
grows with lights × texels (every view multiplies lights · 3 columns of all texels). A sum
pass's part holds one row per texel, so it grows with the texels, and its merge costs
m0 + m1 · N · part; the merges after round 3 (k-means in the subspace, texels × d) and
round 8 (every texel's best cluster) also do work per texel, so their m0 grows with the
texels. A projection pass (rounds 2 and 7) joins one column per measurement: its parts
together hold the same bytes at any N, and its merge (SVDs of measurements × sketch
matrices) grows with the measurements. A two-level tree merge (64 nodes, groups of 8) reads
8 parts per merge on each level.

Usage: bench/local_pca_model.py LPCA.jsonl   (prints a JSON report)
"""
import json
import sys

rows = [json.loads(l) for l in open(sys.argv[1]) if l.strip()]
runs = [r for r in rows if "task" in r]
r0 = runs[0]
V, L, T = r0["views"], r0["lights"], r0["texels"]
passes = sorted({r["pass"] for r in runs if r["task"] == "lpca_pass"})


def lsq(pts):
    n = len(pts)
    mx = sum(x for x, _ in pts) / n
    my = sum(y for _, y in pts) / n
    sxx = sum((x - mx) ** 2 for x, _ in pts)
    b = sum((x - mx) * (y - my) for x, y in pts) / sxx if sxx > 0 else 0.0
    return my - b * mx, b


report = {"inputs": {"views": V, "lights": L, "texels": T, "k": r0["k"], "c": r0["c"], "d": r0["d"]}, "passes": {}}
single = next(r["seconds"] for r in runs if r["task"] == "lpca" and r["shards"] == 0)
pred_total = meas_total = 0.0
model = {}
for p in passes:
    pts = [(V / r["shards"], r["seconds"]) for r in runs
           if r["task"] == "lpca_pass" and r["pass"] == p and r["shards"] in (2, 4)]
    a, b = lsq(pts)
    meas = sum(r["seconds"] for r in runs if r["task"] == "lpca_pass" and r["pass"] == p and r["shards"] == 1)
    merges = [(r["shards"], r["seconds"]) for r in runs if r["task"] == "merge_pass" and r["pass"] == p]
    part = {r["shards"]: r["bytes"] for r in runs if r["task"] == "lpca_pass" and r["pass"] == p and r["shard"] == 1}
    mpts = [(n * part[n], s) for n, s in merges]
    m0, m1 = lsq(mpts)
    out_bytes = next((r["bytes"] for r in runs if r["task"] == "merge_pass" and r["pass"] == p and r["shards"] == 1), 0)
    model[p] = (a, b, m0, m1, part[1])
    pred = a + b * V
    pred_total += pred
    meas_total += meas
    report["passes"][p] = {
        "startup_s": round(a, 3),
        "per_view_s": round(b, 5),
        "predicted_1_shard_s": round(pred, 3),
        "measured_1_shard_s": round(meas, 3),
        "predicted_over_measured": round(pred / meas, 3) if meas else None,
        "part_bytes_1_shard": part[1],
        "part_bytes_per_shard": {n: part[n] for n in sorted(part)},
        "merge_s": {n: round(s, 3) for n, s in merges},
        "merged_bytes": out_bytes,
    }
report["all_passes_1_shard"] = {
    "predicted_s": round(pred_total, 2),
    "measured_s": round(meas_total, 2),
    "predicted_over_measured": round(pred_total / meas_total, 3),
}
report["single_process_s"] = round(single, 3)
fused = next((r["seconds"] for r in runs if r["task"] == "lpca_fused"), None)
if fused:
    report["single_process_fused_s"] = round(fused, 3)
report["sharded_1_over_single"] = round(
    (meas_total + sum(s for r in runs if r["task"] == "merge_pass" and r["shards"] == 1 for s in [r["seconds"]])) / single, 3)
report["checks"] = [r for r in rows if "check" in r]

# --- carried to UBO2014 size -------------------------------------------------------------
UV, UL, UT = 151, 151, 400 * 400
view_scale = (UL * UT) / (L * T)
texel_scale = UT / T
meas_scale = (UL * UV) / (L * V)
pred = {}
# (nodes, fanout): a flat merge, or a two-level tree (groups of `fanout` parts merged in
# parallel, then the nodes / fanout group parts; `gonio batch slurm --merge-fanout`).
for nodes, fanout in ((1, None), (8, None), (64, None), (64, 8)):
    vpn = -(-UV // nodes)
    wall = 0.0
    parts = {}
    for p, (a, b, m0, m1, part1) in model.items():
        compute = a + vpn * b * view_scale
        if p in (2, 7):
            merge = report["passes"][p]["merge_s"][1] * meas_scale
        else:
            start = max(m0, 0.0) * (texel_scale if p in (3, 8) else 1.0)
            per_part = max(m1, 0.0) * part1 * texel_scale
            if fanout:
                # Both levels read `fanout` parts; only the last does the round's own step.
                merge = start + 2 * fanout * per_part + max(m0, 0.0)
            else:
                merge = start + nodes * per_part
        parts[p] = {"compute_s": round(compute, 1), "merge_s": round(merge, 1)}
        wall += compute + merge
    key = f"{nodes}_nodes" + (f"_tree{fanout}" if fanout else "")
    pred[f"{key}_s"] = round(wall, 1)
    pred[f"{key}_per_round"] = parts
part8 = UT * (r0["k"] * (r0["c"] + 1) + 1) * 32
pred["pass8_part_GiB"] = round(part8 / 2**30, 2)
pred["pass8_merge_reads_GiB_64_nodes"] = round(64 * part8 / 2**30, 1)
pred["note"] = ("per node as this machine (2 cores); Slurm's start latency per dependent job (18 jobs flat, 27 as trees) and the "
                "shared filesystem come on top")
report["ubo2014_prediction"] = pred
print(json.dumps(report, indent=1))
