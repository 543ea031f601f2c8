#!/usr/bin/env bash
# The gphoto2 camera backend (feature `gphoto2`) against libgphoto2's `vusb` virtual
# camera: a PTP camera emulated inside libgphoto2 (the `vusb` io library of 2.5.34) that
# appears as a Nikon on usb:001,001 and serves the JPEGs of $VCAMERADIR as its captures.
#
# Debian's libgphoto2 (2.5.30) is built without vusb; the `gphoto2` Python wheel bundles a
# libgphoto2 2.5.34 that has it. So:
#  1. builds and lints gonio-devices with --features gphoto2 against the system
#     libgphoto2-dev (the headers and the link). With GONIO_LAB_FEATURES (tests/run.sh sets
#     `v4l2,genicam,gphoto2`) every cargo command here uses those features instead, as
#     tests/genicam/run.sh does, so the two share one lab build of gonio, one lint and one
#     test build of gonio-devices;
#  2. `pip download gphoto2==2.6.4 --no-deps` into a temporary folder and unpacks it
#     (GONIO_GPHOTO2_WHEEL=path/to.whl uses a wheel already downloaded, for offline runs);
#  3. a shim folder with libgphoto2.so.6 and libgphoto2_port.so.12 linked to the wheel's
#     hash-named libraries (found by glob), so the test binary loads them instead of
#     Debian's; IOLIBS/CAMLIBS point at the wheel's vusb io library and camera drivers;
#  4. an empty VCAMERADIR, into which devices/tests/gphoto2_vusb.rs writes its reference
#     JPEG (a drawn pattern); it then checks: camera found, shutter speed the nearest
#     choice and read back, aperture set from the choices, refusals (aperture not offered,
#     ISO, gain, wrong size), capture, download, decoded image equal to the reference,
#     file deleted from the card;
#  5. `gonio devices list --json` (libgphoto2's auto-detection) lists the vusb camera with
#     the rig-file options that open it, and lists none with Debian's libgphoto2;
#  6. end to end: `gonio acquire --rig devices/rigs/gphoto2-vusb.toml --sweep fibonacci:4`
#     (the lab build with --features gphoto2; simulated axes and light, the vusb camera
#     serving the same reference JPEG): complete, `gonio verify` clean, every stored raw
#     frame 96 × 64 16-bit RGB with the read-back exposure 0.1 s.
#
# Needs libgphoto2-dev, libclang (bindgen of libgphoto2_sys), pkg-config, python3 with pip
# and network access for the wheel (or GONIO_GPHOTO2_WHEEL). Without them it prints why it
# is skipped; under CI ($CI set) that is a failure.
# Usage: bash tests/gphoto2/run.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
log() { echo "gphoto2: $*"; }
die() { echo "gphoto2: FAILED: $*" >&2; exit 1; }
skip() {
  [ -n "${CI:-}" ] && die "$1 (mandatory under CI)"
  log "skipped: $1"
  exit 0
}

pkg-config --exists libgphoto2 2>/dev/null || skip "needs libgphoto2-dev (apt-get install libgphoto2-dev libclang-dev pkg-config)"
command -v python3 >/dev/null || skip "needs python3 (to fetch and unpack the gphoto2 wheel)"
# pip for the download: the project venv's (tests/run.sh exports GONIO_PYTHON) when it has
# one, else the system python3's.
PIP_PY=python3
if [ -n "${GONIO_PYTHON:-}" ] && "$GONIO_PYTHON" -m pip --version >/dev/null 2>&1; then
  PIP_PY=$GONIO_PYTHON
fi

# The features of every cargo command below (the lab build shared with tests/genicam/run.sh).
FEATURES=${GONIO_LAB_FEATURES:-gphoto2}
case ",$FEATURES," in *,gphoto2,*) ;; *) FEATURES="$FEATURES,gphoto2" ;; esac
# As tests/genicam/run.sh: target/lab locally (the same dir, so the lab build is shared),
# target/ under CI; GONIO_GPHOTO2_TARGET_DIR overrides.
if [ -n "${GONIO_GPHOTO2_TARGET_DIR:-}" ]; then
  export CARGO_TARGET_DIR=$GONIO_GPHOTO2_TARGET_DIR
elif [ -n "${CI:-}" ]; then
  export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-$ROOT/target}
else
  export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-$ROOT/target/lab}
fi
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT

log "building and linting gonio-devices with --features $FEATURES (target dir $CARGO_TARGET_DIR)"
cargo clippy -q -p gonio-devices --features "$FEATURES" --all-targets -- -D warnings ||
  die "cargo clippy -p gonio-devices --features $FEATURES (needs libgphoto2-dev and libclang)"
out=$(cargo test -q -p gonio-devices --features "$FEATURES" --lib gphoto2:: 2>&1) || {
  echo "$out" | tail -40 >&2
  die "unit tests of the gphoto2 backend"
}
echo "$out" | grep 'test result' || true
TEST_BIN=$(cargo test -q -p gonio-devices --features "$FEATURES" --test gphoto2_vusb --no-run --message-format=json 2>/dev/null |
  python3 -c 'import json,sys
for l in sys.stdin:
    m = json.loads(l)
    if m.get("reason") == "compiler-artifact" and m.get("executable") and m["target"]["name"] == "gphoto2_vusb":
        print(m["executable"])')
[ -x "$TEST_BIN" ] || die "no test binary for devices/tests/gphoto2_vusb.rs"

if [ -n "${GONIO_GPHOTO2_WHEEL:-}" ]; then
  WHEEL=$GONIO_GPHOTO2_WHEEL
  log "using the wheel $WHEEL"
else
  log "pip download gphoto2==2.6.4 --no-deps (the libgphoto2 2.5.34 with vusb)"
  "$PIP_PY" -m pip download -q gphoto2==2.6.4 --no-deps --only-binary=:all: -d "$WORK/wheel" >"$WORK/pip.log" 2>&1 || {
    tail -5 "$WORK/pip.log" >&2
    skip "pip download gphoto2==2.6.4 failed (no network? set GONIO_GPHOTO2_WHEEL to a downloaded wheel)"
  }
  WHEEL=$(ls "$WORK"/wheel/gphoto2-2.6.4-*.whl | head -1)
fi
[ -f "$WHEEL" ] || die "no wheel at $WHEEL"
python3 -m zipfile -e "$WHEEL" "$WORK/wh" || die "cannot unpack $WHEEL"
LIBS=$WORK/wh/gphoto2.libs
lib=$(ls "$LIBS"/libgphoto2-*.so.6* 2>/dev/null | head -1)
port=$(ls "$LIBS"/libgphoto2_port-*.so.12* 2>/dev/null | head -1)
[ -n "$lib" ] && [ -n "$port" ] || die "the wheel has no libgphoto2-*.so.6 / libgphoto2_port-*.so.12 in gphoto2.libs"
VUSB=$WORK/wh/gphoto2/libgphoto2/vusb
[ -e "$VUSB/vusb.so" ] || die "the wheel has no vusb io library ($VUSB/vusb.so)"
mkdir -p "$WORK/shim" "$WORK/vcam"
ln -s "$lib" "$WORK/shim/libgphoto2.so.6"
ln -s "$port" "$WORK/shim/libgphoto2_port.so.12"
log "libgphoto2 from the wheel: $(basename "$lib"), io library $VUSB/vusb.so"

log "devices/tests/gphoto2_vusb.rs against the vusb camera (VCAMERADIR=$WORK/vcam)"
out=$(VCAMERADIR=$WORK/vcam IOLIBS=$VUSB CAMLIBS=$WORK/wh/gphoto2/libgphoto2/camlibs \
  LD_LIBRARY_PATH=$WORK/shim:$LIBS "$TEST_BIN" --nocapture --test-threads=1 2>&1) || {
  echo "$out" | tail -40 >&2
  die "devices/tests/gphoto2_vusb.rs"
}
echo "$out" | grep -oE 'gphoto2_vusb: .*' || true
for want in 'found Nikon' 'applied 0.1 s, read back' 'captured ' 'equals the reference JPEG pixel for pixel' 'deleted from the card' 'gphoto2_vusb: passed'; do
  echo "$out" | grep -q "$want" || die "the test did not report \"$want\" (was it skipped?)"
done
echo "$out" | grep -q SKIPPED && die "the vusb test was skipped"

log "end to end: gonio acquire --rig devices/rigs/gphoto2-vusb.toml --sweep fibonacci:4 (vusb camera, simulated axes)"
cargo build -q -p gonio --no-default-features --features "$FEATURES" --bin gonio ||
  die "cargo build -p gonio --no-default-features --features $FEATURES"
GONIO=$CARGO_TARGET_DIR/debug/gonio

listed() { # listed JSON: the gphoto2 cameras, one line each
  python3 - "$1" <<'PY'
import json, sys
l = json.load(open(sys.argv[1]))
rows = [b for b in l["cameras"] if b["backend"] == "gphoto2"]
assert len(rows) == 1 and rows[0]["built"] and not rows[0]["error"], rows
for c in rows[0]["cameras"]:
    print(f'{c["model"]} at {c["address"]} ({c["rig_options"]})')
PY
}
log "gonio devices list --json with the vusb camera"
VCAMERADIR=$WORK/vcam IOLIBS=$VUSB CAMLIBS=$WORK/wh/gphoto2/libgphoto2/camlibs LD_LIBRARY_PATH=$WORK/shim:$LIBS \
  "$GONIO" devices list --json >"$WORK/list.json" || die "gonio devices list --json failed"
found=$(listed "$WORK/list.json") || die "gonio devices list --json: no gphoto2 entry: $(cat "$WORK/list.json")"
echo "$found" | grep -q 'Nikon DSC D750 at usb:001,001 (port = "usb:001,001", model = "Nikon DSC D750")' ||
  die "gonio devices list does not list the vusb camera: $(cat "$WORK/list.json")"
log "devices list: $found"
"$GONIO" devices list --json >"$WORK/list-none.json" || die "gonio devices list --json failed"
[ -z "$(listed "$WORK/list-none.json")" ] || die "Debian's libgphoto2 (no vusb) lists a camera: $(cat "$WORK/list-none.json")"
log "devices list with Debian's libgphoto2: no camera"
VCAMERADIR=$WORK/vcam IOLIBS=$VUSB CAMLIBS=$WORK/wh/gphoto2/libgphoto2/camlibs LD_LIBRARY_PATH=$WORK/shim:$LIBS \
  "$GONIO" acquire --rig devices/rigs/gphoto2-vusb.toml --sample white-standard --sweep fibonacci:4 --plan-time 0 \
  --no-truth --raw --out "$WORK/ds" --json -q >"$WORK/acquire.json" 2>"$WORK/acquire.err" || {
  tail -30 "$WORK/acquire.err" >&2
  die "gonio acquire with the vusb camera failed"
}
grep -q '"complete": true' "$WORK/acquire.json" || die "the acquisition did not complete: $(cat "$WORK/acquire.json")"
"$GONIO" verify "$WORK/ds" || die "gonio verify of the acquired dataset"
python3 - "$WORK/ds" <<'PY' || die "stored frames are not the camera's"
import json, struct, sys, os
ds = sys.argv[1]
recs = [json.loads(l)["rec"] for l in open(os.path.join(ds, "journal.jsonl")) if l.strip()]
measured = [r for r in recs if r.get("raw")]
assert measured, "no frame stored"
for r in measured:
    assert r["exposure_s"] == 0.1, f"exposure {r['exposure_s']} is not the read-back 0.1000s choice"
    with open(os.path.join(ds, r["raw"]), "rb") as f:
        head = f.read(29)
    w, h, depth, colour = struct.unpack(">IIBB", head[16:26])
    assert head[:8] == b"\x89PNG\r\n\x1a\n" and (w, h, depth, colour) == (96, 64, 16, 2), (r["raw"], w, h, depth, colour)
print(f"gphoto2: {len(measured)} raw frames stored, 96 x 64 16-bit RGB, exposure 0.1 s as read back")
PY
log "passed"
