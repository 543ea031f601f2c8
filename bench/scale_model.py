#!/usr/bin/env python3
"""The scale model of docs/guide/scale.md, fitted to and checked against bench/scale.sh's output.

Runs with "shards": 0 are one process without --shard (the references); "shards": N ≥ 1
are the N parts of a sharded run, one after the other.

Per task, a shard's time is t = a + b·v (v views of the shard: a start-up, b per view).
a and b are fitted by least squares on the 2- and 4-shard runs only; the model then
predicts the 1-shard run (the whole job in one process, v = V) and the prediction is
compared with the measurement. Per-view costs scale with lights × texels (every view
renders, reads or multiplies lights images of texels pixels), which is how the model is
carried to a UBO2014-size job (151 × 151 directions, 400² texels).

With a second output at another texel count (bench/scale.sh V SIZE2), the per-image cost
of every task is fitted as c0 + c1 · texels across the two sizes (rendering and storing an
image has a part that does not grow with its texels), the UBO2014 figures use that fit,
and the first size's proportional model is checked against the second size.

Usage: bench/scale_model.py SCALE.jsonl [SCALE2.jsonl]   (prints a JSON report)
"""
import json
import sys

rows = [json.loads(l) for l in open(sys.argv[-1]) if l.strip()]
runs = [r for r in rows if "task" in r]
V = runs[0]["views"]
L = runs[0]["lights"]
T = runs[0]["texels"]


def fit(task, p=None):
    pts = [
        (V / r["shards"], r["seconds"])
        for r in runs
        if r["task"] == task and r["shards"] in (2, 4) and (p is None or r["pass"] == p)
    ]
    n = len(pts)
    mx = sum(x for x, _ in pts) / n
    my = sum(y for _, y in pts) / n
    sxx = sum((x - mx) ** 2 for x, _ in pts)
    b = sum((x - mx) * (y - my) for x, y in pts) / sxx
    return my - b * mx, b


def measured(task, shards, p=None):
    return sum(r["seconds"] for r in runs if r["task"] == task and r["shards"] == shards and r["shard"] > 0
               and (p is None or r["pass"] == p))


report = {"inputs": {"views": V, "lights": L, "texels": T}, "tasks": {}}
passes = sorted({r["pass"] for r in runs if r["task"] == "pca_pass"})
models = {"sim_btf": fit("sim_btf"), "pvmf": fit("pvmf")}
for p in passes:
    models[f"pca_pass{p}"] = fit("pca_pass", p)
for name, (a, b) in models.items():
    task, p = ("pca_pass", int(name[8:])) if name.startswith("pca_pass") else (name, None)
    pred = a + b * V
    meas = measured(task, 1, p)
    report["tasks"][name] = {
        "startup_s": round(a, 3),
        "per_view_s": round(b, 4),
        "per_image_ms": round(1000 * b / L, 3),
        "predicted_1_shard_s": round(pred, 3),
        "measured_1_shard_s": round(meas, 3),
        "predicted_over_measured": round(pred / meas, 3) if meas else None,
    }
merges = {r["task"] + f"_{r['shards']}" + (f"_p{r['pass']}" if r["task"] == "merge_pass" else ""): r["seconds"]
          for r in runs if r["task"].startswith("merge")}
report["merges_s"] = {k: round(v, 3) for k, v in merges.items()}
single = {r["task"]: r["seconds"] for r in runs if r["shards"] == 0}
report["single_process_s"] = {k: round(v, 3) for k, v in single.items()}
bytes_row = next((r["bytes"] for r in rows if "bytes" in r), {})
report["bytes"] = bytes_row

# --- carried to UBO2014 size: 151 views × 151 lights × 400² texels ------------------------
UV, UL, UT = 151, 151, 400 * 400
scale = (UL * UT) / (L * T)  # per-view cost ratio
k = 18  # PCA c = 8 + 10 oversampling: sketch columns
sum_part_bytes = UT * k * 32  # an exact-sum part
# The merge of a sum pass reads N parts and adds them: t = a + b · (N · part bytes),
# fitted on the 1-, 2- and 4-part merges of the sum passes.
part_bytes_here = bytes_row.get("pca_sum_part", T * k * 32)
mp = [(r["shards"] * part_bytes_here, r["seconds"]) for r in runs
      if r["task"] == "merge_pass" and r["pass"] < max(r2["pass"] for r2 in runs if r2["task"] == "merge_pass")]
mx = sum(x for x, _ in mp) / len(mp)
my = sum(y for _, y in mp) / len(mp)
merge_s_per_byte = sum((x - mx) * (y - my) for x, y in mp) / max(sum((x - mx) ** 2 for x, _ in mp), 1e-30)
merge_start_s = my - merge_s_per_byte * mx
report["merge_pass_model"] = {"startup_s": round(merge_start_s, 4), "MB_per_s": round(1e-6 / merge_s_per_byte, 1) if merge_s_per_byte > 0 else None}


def per_view(name):
    return models[name][1] * scale


def fit_file(path):
    """Per-task (start-up, per-view) of another bench/scale.sh output, and its shape."""
    global runs, V, L, T
    saved = (runs, V, L, T)
    rs = [json.loads(l) for l in open(path) if l.strip()]
    runs = [r for r in rs if "task" in r]
    V, L, T = runs[0]["views"], runs[0]["lights"], runs[0]["texels"]
    out = {"sim_btf": fit("sim_btf"), "pvmf": fit("pvmf")}
    for p in passes:
        out[f"pca_pass{p}"] = fit("pca_pass", p)
    shape = (L, T)
    runs, V, L, T = saved
    return out, shape


if len(sys.argv) > 2:
    # Two sizes: per-image cost c0 + c1 · texels, from the small (argv[1]) and the large
    # (argv[2], the main file) run.
    small, (Ls, Ts) = fit_file(sys.argv[1])
    check = {}
    per_image = {}
    for name in models:
        ps, pl = small[name][1] / Ls, models[name][1] / L
        c1 = (pl - ps) / (T - Ts)
        c0 = ps - c1 * Ts
        per_image[name] = (c0, c1)
        # The small size's proportional model carried to the large size, against the fit there.
        check[name] = round(small[name][1] * (L * T) / (Ls * Ts) / models[name][1], 3)
    pca_small = sum(small[f"pca_pass{p}"][1] for p in passes) * (L * T) / (Ls * Ts)
    check["pca_all_passes"] = round(pca_small / sum(models[f"pca_pass{p}"][1] for p in passes), 3)
    report["size_check_proportional_over_fitted"] = check
    report["per_image_ms_model"] = {k: {"c0_ms": round(1000 * c0, 3), "c1_ms_per_texel": c1 * 1000}
                                    for k, (c0, c1) in per_image.items()}

    def per_view(name):  # noqa: F811 (the two-size model replaces the proportional one)
        c0, c1 = per_image[name]
        return UL * max(c0 + c1 * UT, 0.0)


pca_view = sum(per_view(f"pca_pass{p}") for p in passes)
render_view = per_view("sim_btf")
a_pca = sum(models[f"pca_pass{p}"][0] for p in passes)
pred = {"per_view_render_s": round(render_view, 2), "per_view_pca_all_passes_s": round(pca_view, 2)}
for nodes in (1, 8, 64):
    views_per_node = -(-UV // nodes)
    # Every pass: the slowest node's views, then the merge of the nodes' parts (the sum
    # passes: N exact-sum parts; the projection's parts are small).
    pca_wall = a_pca + views_per_node * pca_view + (len(passes) - 1) * (
        merge_start_s + nodes * sum_part_bytes * max(merge_s_per_byte, 0.0))
    pred[f"global_pca_{nodes}_nodes_h"] = round(pca_wall / 3600, 3)
    pred[f"global_pca_{nodes}_nodes_s"] = round(pca_wall, 1)
    gen = 1000 * (models["sim_btf"][0] + UV * render_view) / nodes
    pred[f"generate_1000_materials_{nodes}_nodes_h"] = round(gen / 3600, 1)
pred["sum_part_MiB"] = round(sum_part_bytes / 2**20, 1)
if bytes_row.get("dataset"):
    per_texel_image = bytes_row["dataset"] / (V * L * T)
    pred["dataset_GB_per_material"] = round(per_texel_image * UV * UL * UT / 1e9, 1)
    pred["dataset_bytes_per_texel_image"] = round(per_texel_image, 2)
pred["note"] = ("per node as this machine (2 cores); Slurm's own start latency per dependent job and the "
                "shared filesystem's bandwidth (22 GB read per PCA pass, split over the nodes) come on top")
report["ubo2014_prediction"] = pred
print(json.dumps(report, indent=1))
