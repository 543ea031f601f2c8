#!/usr/bin/env bash
# Benchmark of the main job: wall time and peak memory of the full default acquisition
# (81 × 81 Bonn sweep, simulated rig, default sample), against a baseline run of the first
# N measurements in the same script. Memory must not grow with the number of measurements
# (the engine streams), so the peak-RSS ratio full/baseline should stay near 1.
#
# Usage: bench/acquire.sh [BASELINE_N]   (default 500)
set -euo pipefail
cd "$(dirname "$0")/.."
n=${1:-500}
cargo build --release --quiet --bin gonio
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
run() {  # $1 = label, rest = extra args
  local label=$1; shift
  ./target/release/gonio acquire --quiet --json --out "$work/$label" "$@" > "$work/$label.json" || true
}
run baseline --limit "$n"
run full
python3 - "$work/baseline.json" "$work/full.json" <<'PY'
import json, sys
b, f = (json.load(open(p)) for p in sys.argv[1:3])
def line(name, s):
    e = s.get("truth_error") or {}
    print(f"{name:<9} {s['stored_this_run']:>5} stored  wall {s['wall_time_s']:7.1f} s  "
          f"{s['images_per_s']:6.1f} img/s  peak RSS {s['peak_rss_mib']:7.1f} MiB  "
          f"rig clock {s['sweep_duration_s']/3600:5.2f} h  truth RMSE {e.get('rmse', float('nan')):.5f}  "
          f"PSNR {e.get('psnr_db', float('nan')):.2f} dB")
line("baseline", b)
line("full", f)
print(f"ratios full/baseline: measurements {f['stored_this_run']/b['stored_this_run']:.1f}x, "
      f"wall {f['wall_time_s']/b['wall_time_s']:.1f}x, peak RSS {f['peak_rss_mib']/b['peak_rss_mib']:.2f}x")
print("stage seconds (full):", json.dumps(f["stage_seconds"]))
print(f"targets: wall <= 300 s: {'met' if f['wall_time_s'] <= 300 else 'NOT met'}; "
      f"peak RSS <= 1024 MiB: {'met' if f['peak_rss_mib'] <= 1024 else 'NOT met'}")
PY
