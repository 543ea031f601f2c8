#!/usr/bin/env bash
# gonio's V4L2 camera backend against the Linux kernel's own virtual video driver, vivid.
#
# Nothing is installed on the host: a Debian kernel, busybox and QEMU are fetched from
# Debian's package registry with `apt-get download` and unpacked with `dpkg -x` under
# target/vivid/ (installing qemu-system-x86 here would replace the machine's newer
# qemu-utils). An initramfs holds busybox, the vivid module and its dependencies, and
# gonio's check program (devices/examples/v4l2_check.rs, built with the `v4l2` feature in
# its own target dir so the feature flip does not invalidate other builds) and gonio
# itself. QEMU boots it under software emulation, /init loads vivid, runs two end-to-end
# `gonio acquire`s with the vivid camera (rigs v4l2-vivid: simulated axes, and
# v4l2-vivid-zaber: axes on gonio's Zaber emulator over a pty) and one with `--hdr 2`
# (vivid has no exposure control: every measurement must record the exposure it did not
# apply), then the check, whose
# PASS/FAIL table is read back from the serial console.
#
# Usage: tests/vivid/run.sh            exit 0 = every check passed
#        VIVID_KVM=1 ...               use KVM instead of software emulation
#        VIVID_ACQUIRE=0 ...           skip the end-to-end `gonio acquire` with a vivid rig
#        VIVID_TIMEOUT=300 ...         seconds before the VM is killed (default 240)
# The serial console is kept in target/vivid/serial.log.
# Downloads and the unpacked tree are cached in target/vivid/; reruns only rebuild the
# initramfs and boot.
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
W=$ROOT/target/vivid
DEBS=$W/debs
TREE=$W/root
mkdir -p "$DEBS" "$TREE"
t_start=$(date +%s.%N)
log() { echo "vivid: $*" >&2; }
die() { echo "vivid: FAIL: $*" >&2; exit 1; }

command -v apt-get >/dev/null || die "apt-get not found (needs a Debian/Ubuntu host)"
command -v dpkg >/dev/null || die "dpkg not found"

# --- 1. packages -----------------------------------------------------------------------
have_lists() { # (no `grep -q` on a pipe: with pipefail its early exit fails apt-cache)
  local out
  out=$(apt-cache policy busybox-static 2>/dev/null || true)
  case "$out" in *"Candidate: (none)"* | "") return 1 ;; *Candidate:*) return 0 ;; *) return 1 ;; esac
}
PKG_STAMP=$W/.packages-ok # written once qemu runs from the unpacked tree
if [ ! -f "$PKG_STAMP" ] && ! have_lists; then
  log "apt lists empty; running apt-get update"
  apt-get update -qq >/dev/null || die "apt-get update failed"
fi

# The kernel: whatever linux-image-amd64 currently points at (a versioned package).
KPKG=$(cat "$W/kernel-package" 2>/dev/null || true)
if [ -z "$KPKG" ] || ! ls "$DEBS/${KPKG}"_*.deb >/dev/null 2>&1; then
  KPKG=$(apt-cache depends linux-image-amd64 2>/dev/null | awk '/Depends: linux-image-[0-9]/{print $2; exit}')
  [ -n "$KPKG" ] || die "cannot resolve linux-image-amd64 to a versioned kernel package"
  echo "$KPKG" >"$W/kernel-package"
fi

download() { # download packages not yet in $DEBS
  local need=()
  for p in "$@"; do
    ls "$DEBS/${p}"_*.deb >/dev/null 2>&1 || need+=("$p")
  done
  if [ ${#need[@]} -gt 0 ]; then
    log "apt-get download ${need[*]}"
    (cd "$DEBS" && apt-get download -q "${need[@]}" >/dev/null 2>"$W/apt-download.err") \
      || { cat "$W/apt-download.err" >&2; die "apt-get download ${need[*]} failed"; }
  fi
}
installed_on_host() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q 'install ok installed'; }
# First alternative of each Depends of a package.
depends_of() { apt-cache depends "$1" 2>/dev/null | awk '/^  Depends: [^<]/{print $2}' | sort -u; }

export LD_LIBRARY_PATH="$TREE/usr/lib/x86_64-linux-gnu:$TREE/lib/x86_64-linux-gnu${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
QEMU=$TREE/usr/bin/qemu-system-x86_64
FW=$W/firmware
if [ ! -f "$PKG_STAMP" ]; then
  download "$KPKG" busybox-static qemu-system-x86 qemu-system-common qemu-system-data seabios ipxe-qemu
  # Shared libraries qemu-system-x86_64 needs that the host lacks, and theirs, recursively.
  queue=$(depends_of qemu-system-x86 | grep '^lib' || true)
  seen=" "
  while [ -n "$queue" ]; do
    next=""
    for p in $queue; do
      case "$seen" in *" $p "*) continue ;; esac
      seen="$seen$p "
      installed_on_host "$p" && continue
      download "$p"
      next="$next $(depends_of "$p" | grep '^lib' || true)"
    done
    queue=$next
  done

  stamp=$TREE/.unpacked
  if [ ! -f "$stamp" ] || [ -n "$(find "$DEBS" -name '*.deb' -newer "$stamp" 2>/dev/null)" ]; then
    log "unpacking $(ls "$DEBS"/*.deb | wc -l) packages"
    for d in "$DEBS"/*.deb; do dpkg -x "$d" "$TREE"; done
    touch "$stamp"
  fi

  [ -x "$QEMU" ] || die "qemu-system-x86_64 missing after unpacking"
  missing=$(ldd "$QEMU" | awk '/not found/{print $1}')
  [ -z "$missing" ] || die "qemu-system-x86_64 still misses: $missing"
  # Firmware: Debian spreads it over qemu, seabios and ipxe dirs (with absolute symlinks).
  if [ ! -f "$FW/bios-256k.bin" ]; then
    mkdir -p "$FW"
    for d in usr/share/qemu usr/share/seabios usr/lib/ipxe/qemu; do
      [ -d "$TREE/$d" ] || continue
      for f in "$TREE/$d"/*; do
        [ -f "$f" ] && ! [ -L "$f" ] && cp -f "$f" "$FW/"
      done
    done
    [ -f "$FW/bios-256k.bin" ] || die "no SeaBIOS image after unpacking"
  fi
  touch "$PKG_STAMP"
fi

KVER=$(basename "$(ls -d "$TREE"/lib/modules/*/ | head -1)")
KERNEL=$TREE/boot/vmlinuz-$KVER
[ -f "$KERNEL" ] || die "kernel image $KERNEL missing"
MODDIR=$TREE/lib/modules/$KVER

# --- 2. gonio's check program ------------------------------------------------------------
# Features: GONIO_LAB_FEATURES when it has `v4l2` (tests/run.sh: the lab build of the
# camera stage before this one, in the same target dir, so every build below is fresh but
# the check program); else `v4l2` alone, with gonio's default features.
LAB=""
case ",${GONIO_LAB_FEATURES:-}," in
  *,v4l2,*) LAB=1 ;;
esac
if [ -n "$LAB" ]; then
  FEATURES=$GONIO_LAB_FEATURES
  GONIO_BUILD=(-p gonio --no-default-features --features "$FEATURES")
else
  FEATURES=v4l2
  GONIO_BUILD=(-p gonio --features v4l2)
fi
# Locally a separate target dir keeps target/debug/gonio the default build. Under CI this is
# the last step, so it shares target/: the dependencies tests/run.sh already built are not
# built a second time (that took over 10 minutes of a CI run). GONIO_VIVID_TARGET_DIR overrides.
if [ -n "${GONIO_VIVID_TARGET_DIR:-}" ]; then
  export CARGO_TARGET_DIR=$GONIO_VIVID_TARGET_DIR
elif [ -n "${CI:-}" ]; then
  export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-$ROOT/target}
elif [ -n "$LAB" ]; then
  export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-$ROOT/target/lab}
else
  export CARGO_TARGET_DIR=$ROOT/target/v4l2
fi
log "building v4l2_check (features $FEATURES, target dir $CARGO_TARGET_DIR)"
cargo build -q -p gonio-devices --features "$FEATURES" --example v4l2_check || die "cargo build of v4l2_check failed (needs libclang-dev)"
# The backend's host-side unit tests (conversions, MJPEG, freshness rule, error mapping).
unit=$(cargo test -q -p gonio-devices --features "$FEATURES" --lib v4l2:: 2>&1) || {
  echo "$unit" | tail -40 >&2
  die "v4l2 unit tests failed"
}
echo "vivid: host unit tests: $(echo "$unit" | grep '^test result' | tail -1)"
CHECK=$CARGO_TARGET_DIR/debug/examples/v4l2_check
[ -x "$CHECK" ] || die "$CHECK missing"

# The end-to-end acquisitions (devices/rigs/v4l2-vivid*.toml) need gonio itself with the
# feature; VIVID_ACQUIRE=0 skips them.
GONIO_BIN=""
if [ "${VIVID_ACQUIRE:-1}" != 0 ]; then
  log "building ${GONIO_BUILD[*]} (target dir $CARGO_TARGET_DIR)"
  cargo build -q "${GONIO_BUILD[@]}" --bin gonio || die "cargo build ${GONIO_BUILD[*]} --bin gonio failed"
  GONIO_BIN=$CARGO_TARGET_DIR/debug/gonio
fi

# --- 3. initramfs ------------------------------------------------------------------------
IR=$W/initramfs
rm -rf "$IR"
mkdir -p "$IR"/{bin,sbin,dev,proc,sys,tmp,lib/modules}
cp "$TREE/bin/busybox" "$IR/bin/busybox"
for a in sh mount insmod poweroff sleep cat ls echo; do ln -s busybox "$IR/bin/$a"; done
for a in grep find wc rmmod mkdir kill; do ln -s busybox "$IR/bin/$a"; done
cp "$CHECK" "$IR/bin/v4l2_check"
bins=("$CHECK")
if [ -n "$GONIO_BIN" ]; then
  # Debug info is most of a debug binary's size; the VM does not need it.
  strip -o "$IR/bin/gonio" "$GONIO_BIN" 2>/dev/null || cp "$GONIO_BIN" "$IR/bin/gonio"
  mkdir -p "$IR/rigs"
  cp devices/rigs/v4l2-vivid.toml devices/rigs/v4l2-vivid-zaber.toml "$IR/rigs/"
  bins+=("$GONIO_BIN")
fi
# Shared libraries of the programs, at the paths the loader expects.
for lib in $(for b in "${bins[@]}"; do ldd "$b"; done | awk '/=> \//{print $3} /^\t\/lib/{print $1}' | sort -u); do
  mkdir -p "$IR$(dirname "$lib")"
  cp -L "$lib" "$IR$lib"
done

# vivid and its module dependencies (from each module's `depends=` modinfo field), in
# load order (dependencies first).
find_mod() { find "$MODDIR/kernel" -name "$1.ko" -o -name "$(echo "$1" | tr _ -).ko" | head -1; }
mod_deps() { strings -a "$1" | sed -n 's/^depends=//p' | head -1 | tr ',' ' '; }
ORDER=()
visit() {
  local name=$1 path dep
  case " ${ORDER[*]:-} " in *" $name "*) return ;; esac
  path=$(find_mod "$name")
  [ -n "$path" ] || die "kernel module $name not found in $MODDIR"
  for dep in $(mod_deps "$path"); do visit "$dep"; done
  ORDER+=("$name")
  cp "$path" "$IR/lib/modules/$name.ko"
}
visit vivid
log "modules: ${ORDER[*]}"

cat >"$IR/init" <<EOF
#!/bin/sh
mount -t proc proc /proc
mount -t sysfs sys /sys
mount -t devtmpfs dev /dev
echo 1 > /proc/sys/kernel/printk
for m in ${ORDER[*]}; do
  if [ "\$m" = vivid ]; then
    # One instance with only a video-capture node (webcam input 0), error injection on.
    insmod /lib/modules/\$m.ko n_devs=1 node_types=0x1 || echo "VIVID_INSMOD_FAILED \$m"
  else
    insmod /lib/modules/\$m.ko || echo "VIVID_INSMOD_FAILED \$m"
  fi
done
i=0
while [ ! -e /dev/video0 ] && [ \$i -lt 50 ]; do sleep 0.1; i=\$((i+1)); done
if [ -x /bin/gonio ]; then
  # End to end: plan, drive, capture from vivid, rectify, store. First with simulated
  # axes, then with the axes on gonio's Zaber emulator over a pty.
  mkdir -p /dev/pts && mount -t devpts devpts /dev/pts
  for rig in v4l2-vivid v4l2-vivid-zaber; do
    emu=""
    if [ "\$rig" = v4l2-vivid-zaber ]; then
      /bin/gonio sim serve-stage --protocol zaber --axes 4 --range -200,200 --link /tmp/zaber >/tmp/zaber.out 2>&1 &
      emu=\$!
      i=0
      while [ ! -e /tmp/zaber ] && [ \$i -lt 100 ]; do sleep 0.1; i=\$((i+1)); done
    fi
    echo
    echo "VIVID_ACQUIRE_BEGIN rig=\$rig"
    GONIO_ZABER_PORT=/tmp/zaber /bin/gonio acquire --rig /rigs/\$rig.toml --sample white-standard \\
      --sweep fibonacci:3 --plan-time 0 --no-truth --size 64x64 --raw --out /tmp/ds-\$rig --json -q
    rc=\$?
    echo
    echo "VIVID_ACQUIRE rig=\$rig rc=\$rc exr=\$(find /tmp/ds-\$rig -name '*.exr' | wc -l) png=\$(find /tmp/ds-\$rig -name '*.png' | wc -l) journal=\$(grep -c . /tmp/ds-\$rig/journal.jsonl)"
    [ -n "\$emu" ] && kill \$emu
  done
  # HDR bracketing against a camera that cannot apply the exposure it is asked for: vivid
  # has no exposure control, so the bracket's shorter exposure is not applied and every
  # measurement must record why (docs/guide/hdr.md), never clip silently.
  echo
  echo "VIVID_HDR_BEGIN"
  /bin/gonio acquire --rig /rigs/v4l2-vivid.toml --sample white-standard --sweep fibonacci:3 \\
    --plan-time 0 --no-truth --size 64x64 --hdr 2 --out /tmp/ds-hdr --json -q
  rc=\$?
  echo
  echo "VIVID_HDR rc=\$rc images=\$(grep -c '"image":"images/' /tmp/ds-hdr/journal.jsonl) not_applied=\$(grep -c 'camera applied [^"]* for the requested' /tmp/ds-hdr/journal.jsonl)"
fi
/bin/v4l2_check /dev/video0
echo "VIVID_DONE rc=\$?"
poweroff -f
EOF
chmod +x "$IR/init"
(cd "$IR" && find . | "$TREE/bin/busybox" cpio -o -H newc -R 0:0 2>/dev/null | gzip -1 >"$W/initramfs.cpio.gz")

# --- 4. boot -----------------------------------------------------------------------------
# Software emulation (TCG) by default: a boot, module load and the whole check take
# ~15 s. KVM only on request (VIVID_KVM=1): on this machine /dev/kvm opens but a nested
# guest hangs after the BIOS, so "the device exists" is not "KVM works".
ACCEL=(-accel tcg)
if [ "${VIVID_KVM:-0}" = 1 ]; then
  [ -r /dev/kvm ] && [ -w /dev/kvm ] || die "VIVID_KVM=1 but /dev/kvm is not usable"
  ACCEL=(-accel kvm)
fi
SERIAL=$W/serial.log
log "booting $KPKG under qemu (${ACCEL[1]})"
t_boot=$(date +%s.%N)
set +e
timeout "${VIVID_TIMEOUT:-240}" "$QEMU" -L "$FW" "${ACCEL[@]}" -m 512 -smp 1 -nographic -no-reboot \
  -vga none -nic none -kernel "$KERNEL" -initrd "$W/initramfs.cpio.gz" \
  -append "console=ttyS0 panic=-1 quiet loglevel=1" >"$SERIAL" 2>&1 </dev/null
qrc=$?
set -e
t_end=$(date +%s.%N)
# The table, without the BIOS's terminal escapes that share its first line.
tr -d '\r' <"$SERIAL" | sed -n '/v4l2_check on/,/^V4L2_CHECK/p' | sed 's/^.*\(v4l2_check on\)/\1/' \
  | grep -av '^faults: ' || true
# The camera rows of the fault campaign table, forwarded as printed in the VM (tests/run.sh
# shows them with the storage, serial and simulated-camera rows).
echo "-- camera faults in the VM (vivid) --"
tr -d '\r' <"$SERIAL" | grep -aoE 'faults: .*' || echo "vivid: no faults rows in the serial log"
grep -a "VIVID_INSMOD_FAILED" "$SERIAL" && die "module load failed (see $SERIAL)"
boot_s=$(echo "$t_end - $t_boot" | bc 2>/dev/null || python3 -c "print(round($t_end-$t_boot,1))")
total_s=$(echo "$t_end - $t_start" | bc 2>/dev/null || python3 -c "print(round($t_end-$t_start,1))")
log "qemu exit $qrc; VM ${boot_s}s, whole script ${total_s}s; serial log $SERIAL"
if [ -n "$GONIO_BIN" ]; then
  for rig in v4l2-vivid v4l2-vivid-zaber; do
    echo "-- gonio acquire in the VM, rig $rig --"
    summary=$(tr -d '\r' <"$SERIAL" | sed -n "/VIVID_ACQUIRE_BEGIN rig=$rig\$/,/VIVID_ACQUIRE rig=$rig rc/p" \
      | grep -E '"(measured|stored_this_run|complete|homography_from_pose|wall_time_s|motion|capture)"|VIVID_ACQUIRE rig' || true)
    echo "$summary"
    echo "$summary" | grep -q "VIVID_ACQUIRE rig=$rig rc=0 exr=[1-9]" || {
      tail -n 40 "$SERIAL" >&2
      die "gonio acquire with rig $rig failed in the VM"
    }
    echo "$summary" | grep -q '"complete": true' || die "acquisition with rig $rig did not complete"
  done
fi
if [ -n "$GONIO_BIN" ]; then
  # Every stored measurement of the --hdr 2 run names the exposure vivid did not apply.
  echo "-- gonio acquire --hdr 2 in the VM (vivid: no exposure control) --"
  hdr=$(tr -d '\r' <"$SERIAL" | grep -aoE 'VIVID_HDR rc=[0-9]+ images=[0-9]+ not_applied=[0-9]+' || true)
  echo "${hdr:-no VIVID_HDR line in the serial log}"
  if [[ $hdr =~ rc=0\ images=([1-9][0-9]*)\ not_applied=([0-9]+) ]] && [ "${BASH_REMATCH[1]}" = "${BASH_REMATCH[2]}" ]; then
    echo "vivid: every HDR measurement records the exposure the camera did not apply"
  else
    tail -n 40 "$SERIAL" >&2
    die "gonio acquire --hdr 2 with vivid: expected rc=0 and a not-applied reason on every stored measurement"
  fi
fi
grep -aq "VIVID_DONE rc=0" "$SERIAL" || {
  tail -n 30 "$SERIAL" >&2
  die "v4l2_check did not pass inside the VM"
}
grep -aqE "V4L2_CHECK pass=[1-9][0-9]* fail=0" "$SERIAL" || die "no passing summary line"
echo "vivid: PASS"
