#!/usr/bin/env bash
# The GenICam camera backend (feature `genicam`) against a real GigE Vision device on the
# wire: Debian's arv-fake-gv-camera-0.8 (aravis-tools) on the loopback interface.
#
#  1. builds gonio (the lab build) with `--features genicam` once and lints the backend
#     with the feature on (the workspace lint of tests/run.sh has it off). With
#     GONIO_LAB_FEATURES (tests/run.sh sets `v4l2,genicam,gphoto2`) every cargo command here
#     uses those features instead, as tests/gphoto2/run.sh does: whichever script runs
#     second finds the lab build, the lint and the test build fresh;
#  2. the backend's unit tests and devices/tests/genicam_fake.rs (exposure read-back, the
#     fake's pattern in Mono8/Mono16/Bayer, a camera changed mid-run, timeout and re-arm,
#     the fake killed mid-run);
#  3. end to end: `gonio acquire --rig devices/rigs/genicam-fake-zaber.toml --sweep
#     fibonacci:8` with the stages on gonio's Zaber emulator, every stored raw frame
#     checked pixel for pixel against the fake's pattern (tests/genicam/check_pattern.py);
#  4. `--hdr 2`: the bracket's exposures are recorded as the camera read them back;
#  5. the fake killed mid-acquisition: the run fails with the camera named as disconnected,
#     and every frame stored before that still matches the pattern (none with wrong metadata);
#  6. `gonio devices list --json` finds the fake through Aravis' discovery (with the
#     `device` option that opens it), and no longer once it is killed.
#
# Needs libaravis-dev, libusb-1.0-0-dev and aravis-tools (.ci/run installs them). Without
# them it prints why it is skipped; under CI ($CI set) that is a failure.
# Usage: bash tests/genicam/run.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
log() { echo "genicam: $*"; }
die() { echo "genicam: FAILED: $*" >&2; exit 1; }

FAKE=arv-fake-gv-camera-0.8
if ! command -v "$FAKE" >/dev/null || ! pkg-config --exists aravis-0.8 2>/dev/null; then
  msg="needs $FAKE (apt-get install aravis-tools) and libaravis (apt-get install libaravis-dev libusb-1.0-0-dev)"
  [ -n "${CI:-}" ] && die "$msg (mandatory under CI; .ci/run installs them)"
  log "skipped: $msg"
  exit 0
fi
if pgrep -f "$FAKE" >/dev/null; then
  # One fake per host: it binds the GigE Vision control port.
  die "another $FAKE is already running on this host; stop it first"
fi

# The features of every cargo command below (the lab build shared with tests/gphoto2/run.sh).
FEATURES=${GONIO_LAB_FEATURES:-genicam}
case ",$FEATURES," in *,genicam,*) ;; *) FEATURES="$FEATURES,genicam" ;; esac
# Locally a separate target dir keeps target/debug/gonio the default build (target/lab, the
# same as tests/gphoto2/run.sh's). Under CI this shares target/: the dependencies
# tests/run.sh already built are not built again. GONIO_GENICAM_TARGET_DIR overrides.
if [ -n "${GONIO_GENICAM_TARGET_DIR:-}" ]; then
  export CARGO_TARGET_DIR=$GONIO_GENICAM_TARGET_DIR
elif [ -n "${CI:-}" ]; then
  export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-$ROOT/target}
else
  export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-$ROOT/target/lab}
fi
TARGET=$CARGO_TARGET_DIR
WORK=$(mktemp -d)
PIDS=()
cleanup() {
  for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done
  rm -rf "$WORK"
}
trap cleanup EXIT

# The lab build (acquisition only: no faer, zarrs, axum) plus the feature: the least that
# acquires, so CI compiles the feature's dependants once and nothing it does not run.
log "building gonio (lab build) with --features $FEATURES (target dir $TARGET)"
cargo build -q -p gonio --no-default-features --features "$FEATURES" --bin gonio ||
  die "cargo build -p gonio --no-default-features --features $FEATURES (needs libaravis-dev)"
cargo clippy -q -p gonio-devices --features "$FEATURES" --all-targets -- -D warnings ||
  die "cargo clippy -p gonio-devices --features $FEATURES"
GONIO=$TARGET/debug/gonio

log "unit tests and the fake-camera tests (devices/tests/genicam_fake.rs)"
out=$(cargo test -q -p gonio-devices --features "$FEATURES" --lib --test genicam_fake -- genicam:: fake:: --test-threads=1 --nocapture 2>&1) || {
  echo "$out" | tail -60 >&2
  die "cargo test -p gonio-devices --features $FEATURES"
}
echo "$out" | grep -oE 'genicam_fake: .*|test result.*' || true

start_fake() {
  "$FAKE" -i 127.0.0.1 >"$WORK/fake.log" 2>&1 &
  FAKE_PID=$!
  PIDS+=("$FAKE_PID")
  for _ in $(seq 50); do
    arv-tool-0.8 -a 127.0.0.1 >/dev/null 2>&1 && return 0
    sleep 0.1
  done
  die "$FAKE did not answer on 127.0.0.1"
}

start_stages() {
  "$GONIO" sim serve-stage --protocol zaber --axes 4 --range -200,200 --link "$WORK/zaber" >"$WORK/zaber.log" 2>&1 &
  PIDS+=("$!")
  for _ in $(seq 100); do
    [ -e "$WORK/zaber" ] && return 0
    sleep 0.1
  done
  die "the Zaber emulator did not create $WORK/zaber"
}

acquire() { # acquire OUT SWEEP
  GONIO_ZABER_PORT=$WORK/zaber "$GONIO" acquire --rig devices/rigs/genicam-fake-zaber.toml --sample white-standard \
    --sweep "$2" --plan-time 0 --no-truth --raw --out "$1" --json -q
}

log "end to end: gonio acquire --sweep fibonacci:8 with the fake camera and emulated Zaber stages"
start_fake
start_stages

# `gonio devices list`: the fake found by Aravis' discovery, listed with what a rig file writes.
listed() { # listed JSON: the genicam cameras at 127.0.0.1, one line each
  python3 - "$1" <<'PY'
import json, sys
l = json.load(open(sys.argv[1]))
rows = [b for b in l["cameras"] if b["backend"] == "genicam"]
assert len(rows) == 1 and rows[0]["built"] and not rows[0]["error"], rows
for c in rows[0]["cameras"]:
    if "127.0.0.1" in c["address"]:
        print(f'{c["model"]} at {c["address"]} ({c["rig_options"]})')
PY
}
"$GONIO" devices list --json >"$WORK/list.json" || die "gonio devices list --json failed"
found=$(listed "$WORK/list.json") || die "gonio devices list --json: no genicam entry: $(cat "$WORK/list.json")"
[ -n "$found" ] || die "gonio devices list does not list the fake camera: $(cat "$WORK/list.json")"
echo "$found" | grep -q 'device = "Aravis-Fake-' || die "the listed fake has no device option: $found"
log "devices list: $found"
acquire "$WORK/ds" fibonacci:8 >"$WORK/acquire.json" 2>"$WORK/acquire.err" || {
  tail -30 "$WORK/acquire.err" >&2
  die "gonio acquire with the fake camera failed"
}
grep -q '"complete": true' "$WORK/acquire.json" || die "the acquisition did not complete: $(cat "$WORK/acquire.json")"
"$GONIO" verify "$WORK/ds" >/dev/null || die "gonio verify of the acquired dataset"
n=$(grep -c '"raw":"raw/' "$WORK/ds/journal.jsonl" || true)
python3 tests/genicam/check_pattern.py "$WORK/ds" --min-frames "$n" | tail -4 || die "stored frames do not match the fake's pattern"
log "exposure recorded with the frames: $(grep '"raw":"raw/' "$WORK/ds/journal.jsonl" | grep -o '"exposure_s":[0-9.e-]*' | sort -u | tr '\n' ' ')(asked 0.0123456 s)"

# HDR brackets check the exposure the camera read back (docs/guide/hdr.md): the fake keeps
# whole microseconds, so every bracket exposure must be recorded as whole microseconds
# (what the sensor used, not the 1/8 of the base that was asked), and the stored base
# frames still match the pattern.
log "HDR: gonio acquire --hdr 2 --sweep fibonacci:3"
GONIO_ZABER_PORT=$WORK/zaber "$GONIO" acquire --rig devices/rigs/genicam-fake-zaber.toml --sample white-standard \
  --sweep fibonacci:3 --plan-time 0 --no-truth --raw --hdr 2 --out "$WORK/ds-hdr" --json -q >"$WORK/hdr.json" 2>"$WORK/hdr.err" || {
  tail -20 "$WORK/hdr.err" >&2
  die "gonio acquire --hdr 2 with the fake camera failed"
}
python3 - "$WORK/ds-hdr/journal.jsonl" <<'PY' || die "HDR bracket exposures are not the camera's read-back"
import json, sys
recs = [json.loads(l)["rec"] for l in open(sys.argv[1]) if l.strip()]
brackets = [r["extra"]["hdr"]["exposures_s"] for r in recs if r.get("raw") and (r.get("extra") or {}).get("hdr")]
assert brackets, "no HDR measurement stored"
for b in brackets:
    assert len(b) >= 2, b
    for e in b:
        assert abs(e * 1e6 - round(e * 1e6)) < 1e-6, f"exposure {e} s is not the fake's whole-microsecond read-back"
print(f"genicam: HDR: {len(brackets)} brackets, exposures as read back: {sorted({e for b in brackets for e in b})}")
PY
python3 tests/genicam/check_pattern.py "$WORK/ds-hdr" | tail -1 || die "an HDR base frame does not match the pattern"

log "fault: the fake killed mid-acquisition"
acquire "$WORK/ds-kill" fibonacci:12 >"$WORK/kill.json" 2>"$WORK/kill.err" &
ACQ=$!
PIDS+=("$ACQ")
# Stored frames so far (skipped pairs are journalled up front, without a frame).
frames() { local n; n=$(grep -c '"raw":"raw/' "$1" 2>/dev/null) || true; echo "${n:-0}"; }
for _ in $(seq 600); do
  [ "$(frames "$WORK/ds-kill/journal.jsonl")" -ge 5 ] && break
  sleep 0.1
done
[ "$(frames "$WORK/ds-kill/journal.jsonl")" -ge 5 ] || die "the second acquisition stored no frames in 60 s"
kill "$FAKE_PID"
rc=0
wait "$ACQ" || rc=$?
[ "$rc" -ne 0 ] || die "gonio acquire went on after the camera was killed"
grep -qi "disconnected\|timed out" "$WORK/kill.err" || {
  tail -20 "$WORK/kill.err" >&2
  die "the failed run does not say the camera was lost"
}
log "run ended with rc=$rc: $(grep -iE 'disconnected|timed out' "$WORK/kill.err" | tail -1)"
"$GONIO" devices list --json >"$WORK/list-killed.json" || die "gonio devices list --json failed"
[ -z "$(listed "$WORK/list-killed.json")" ] || die "gonio devices list still lists the killed fake camera"
log "devices list after the kill: the fake is no longer listed"
python3 tests/genicam/check_pattern.py "$WORK/ds-kill" --min-frames 5 | tail -1 ||
  die "a frame stored before the camera was lost does not match the pattern"
log "passed"
