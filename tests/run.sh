#!/usr/bin/env bash
# The test command (README): formatting, lints, every Rust test, the reliability campaigns
# with their figures, then the interop checks against public readers and oracles (they
# need the venv that .ci/run installs; without it they are skipped with a notice, and
# under CI they fail).
set -euo pipefail
cd "$(dirname "$0")/.."
export GONIO_VENV="${GONIO_VENV:-$PWD/target/venv}"
if [ -x "$GONIO_VENV/bin/python" ]; then
  export GONIO_PYTHON="$GONIO_VENV/bin/python"
fi

# Wall time per stage, printed as each stage starts and at the end: CI's budget is
# about 50 minutes in all (installs included), so every stage's share is visible in the log.
t_start=$(date +%s)
t_prev=$t_start
stage() {
  local now
  now=$(date +%s)
  echo "== $* (previous stage $((now - t_prev)) s, total $((now - t_start)) s)"
  t_prev=$now
}

# Disk use, printed between stages: a full disk is a CI failure of its own.
disk() { echo "disk: target $(du -sh target 2>/dev/null | cut -f1), free $(df -h --output=avail . | tail -1 | tr -d ' ')"; }

stage "cargo fmt --check"
cargo fmt --all -- --check
stage "cargo clippy (warnings denied)"
cargo clippy --workspace --all-targets -- -D warnings
# A build that leaves out the default features (Zarr export) must still build and lint:
# "no dependency is paid for by a build that does not use it" holds only if it compiles.
# Library and binary only: the tests assume the default features.
stage "cargo clippy -p gonio --no-default-features (lib, bins): the lab build"
cargo clippy -p gonio --no-default-features --lib --bins -- -D warnings
# The lab build (acquisition only) links no faer, no zarrs and no axum: the crate cut and
# the features hold that, this checks it (ARCHITECTURE.md, "Crates").
lab_heavy=$(cargo tree -p gonio --no-default-features -e normal --prefix none | grep -E '^(faer|zarrs|axum) ' | sort -u || true)
if [ -n "$lab_heavy" ]; then
  echo "the lab build (--no-default-features) links: $lab_heavy" >&2
  exit 1
fi
echo "lab build: $(cargo tree -p gonio --no-default-features -e normal --prefix none | sort -u | wc -l) crates, no faer/zarrs/axum"
# The campaign modules of tests/it run once, in the figures stage below (one thread, their
# table rows printed): the workspace run skips them instead of running them twice.
campaigns=(campaign_kill9:: campaign_faults:: serial_drivers:: campaign_camera_faults:: calibration_faults::)
skips=()
for c in "${campaigns[@]}"; do skips+=(--skip "$c"); done
stage "cargo test"
cargo test --workspace -- "${skips[@]}"
# The stages below run the gonio binary this test build just linked (target/debug/gonio),
# copied aside so that no later cargo call relinks it: a plain `cargo build` has other
# features (the tests' dev-dependencies) and would compile gonio's crates a second time.
# gonio-bench goes beside it: `$GONIO_BIN bench …` runs the gonio-bench next to gonio.
mkdir -p target/ci-bin
cp target/debug/gonio target/debug/gonio-bench target/ci-bin/
export GONIO_BIN=$PWD/target/ci-bin/gonio
disk
stage "campaign figures (kill -9, storage, serial and camera faults)"
# One test thread: the rows of a table must not interleave. -q prints progress dots in
# front of a row, hence grep -o. A failing campaign test fails the run, with its output.
campaign_log=$(mktemp)
if ! cargo test -q -p gonio --test it -- "${campaigns[@]}" --nocapture --test-threads=1 >"$campaign_log" 2>&1; then
  cat "$campaign_log" >&2
  echo "campaign tests failed (output above)" >&2
  exit 1
fi
grep -oE "(kill9|faults): .*" "$campaign_log" || true
rm -f "$campaign_log"
stage "soak (emulated Zaber chain over a pty, real-time pacing)"
bash tests/campaigns/soak.sh
stage "interop"
bash tests/interop/run.sh
stage "slurm (sharded sim btf and PVMF through a one-node Slurm)"
if command -v sbatch >/dev/null && command -v slurmctld >/dev/null && [ "$(id -u)" = 0 ]; then
  bash tests/slurm/run.sh
elif [ -n "${CI:-}" ]; then
  echo "slurm: sbatch/slurmctld missing or not root under CI (.ci/run installs slurmctld slurmd slurm-client munge)" >&2
  exit 1
else
  echo "slurm: skipped (needs root and apt-get install slurmctld slurmd slurm-client munge; run .ci/run)"
fi
stage "browser (gonio view in headless chromium)"
bash tests/browser/run.sh

# --- Lab cameras: the GenICam backend (feature `genicam`) against Debian's fake GigE Vision
# camera on loopback (tests/genicam/: the backend's tests, an end-to-end acquisition with
# emulated Zaber stages checked against the fake's pattern, the fake killed mid-run) and the
# gphoto2 backend (feature `gphoto2`) against libgphoto2's vusb virtual camera
# (tests/gphoto2/: the backend's tests, capture/download/delete/decode, an acquisition).
# One build for all three camera backends: the scripts build with the same features
# (GONIO_LAB_FEATURES), so the lab build of gonio, the backends' lint and gonio-devices'
# test build are compiled once, by the first script, and the others (gphoto2, then the
# V4L2 stage below) find them fresh. The V4L2 stage once built gonio a second time with
# the default features plus `v4l2`, for nothing its VM runs needs. Mandatory under CI;
# elsewhere a script whose prerequisites are missing is skipped with a notice (and its
# feature is left out of the shared build).
disk
stage "lab cameras (genicam, gphoto2): one lab build with every camera feature"
# The V4L2 stage's prerequisites (below): apt-get for its VM's packages, libclang for the
# `v4l2` feature's bindgen.
vivid_ready() {
  command -v apt-get >/dev/null && { [ -n "$(ls /usr/lib/llvm-*/lib/libclang-[0-9]*.so* 2>/dev/null)" ] || [ -n "${LIBCLANG_PATH:-}" ]; }
}
lab_features=()
if vivid_ready; then
  lab_features+=(v4l2)
fi
if [ -n "${CI:-}" ] || { command -v arv-fake-gv-camera-0.8 >/dev/null && pkg-config --exists aravis-0.8 2>/dev/null; }; then
  lab_features+=(genicam)
fi
if [ -n "${CI:-}" ] || pkg-config --exists libgphoto2 2>/dev/null; then
  lab_features+=(gphoto2)
fi
GONIO_LAB_FEATURES=$(IFS=,; echo "${lab_features[*]}")
export GONIO_LAB_FEATURES
lab_start=$(date +%s)
bash tests/genicam/run.sh
bash tests/gphoto2/run.sh
echo "lab cameras: $(($(date +%s) - lab_start)) s wall (features: ${GONIO_LAB_FEATURES:-none})"

# --- V4L2 camera backend against the kernel's vivid driver in a QEMU VM (tests/vivid/).
# Needs apt-get (to download the Debian kernel/busybox/QEMU packages, never installed) and
# libclang (the `v4l2` feature's bindgen). Mandatory under CI; elsewhere skipped with a
# notice when those are missing.
disk
stage "vivid (V4L2 backend in a VM)"
if vivid_ready; then
  bash tests/vivid/run.sh
elif [ -n "${CI:-}" ]; then
  echo "vivid: apt-get or libclang missing under CI (.ci/run installs libclang-dev)" >&2
  exit 1
else
  echo "vivid: skipped (needs apt-get and libclang-dev; run .ci/run)"
fi
disk
stage "done"
