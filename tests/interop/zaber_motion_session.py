#!/usr/bin/env python3
"""Drive gonio's Zaber ASCII emulator with Zaber's own client library, zaber-motion.

Usage: zaber_motion_session.py PTY [--units-per-deg 1000]

Started by tests/interop/run.sh against `gonio sim serve-stage --protocol zaber`. Prints a
transcript of the session (each step and what the library returned); exits non-zero with a
message naming the step when anything differs from what a real device would do.
Needs no internet: identify_devices=False skips the device-database lookup, so positions are
in native units (the emulator's default is 1000 units per degree, range ±180°).
"""
import argparse
import sys
import time

from zaber_motion import Library, LogOutputMode
from zaber_motion.ascii import Connection
from zaber_motion.exceptions import CommandFailedException, MotionLibException

p = argparse.ArgumentParser()
p.add_argument("pty")
p.add_argument("--units-per-deg", type=float, default=1000.0)
args = p.parse_args()
upd = args.units_per_deg


def step(what, value=None):
    print(f"zaber-motion | {what}" + ("" if value is None else f" -> {value}"), flush=True)


def check(cond, msg):
    if not cond:
        print(f"zaber-motion | FAILED: {msg}", file=sys.stderr, flush=True)
        sys.exit(1)


Library.set_log_output(LogOutputMode.OFF)
step("zaber_motion version", __import__("importlib.metadata").metadata.version("zaber-motion"))
with Connection.open_serial_port(args.pty, direct=True) as conn:
    step(f"open_serial_port({args.pty!r}, direct=True)", "ok")
    devices = conn.detect_devices(identify_devices=False)
    step("detect_devices(identify_devices=False)", f"{len(devices)} device(s)")
    check(len(devices) == 1, f"expected 1 device, found {len(devices)}")
    dev = devices[0]
    step("device address", dev.device_address)
    serial = dev.settings.get("system.serial")
    step("settings.get('system.serial')", int(serial))
    step("settings.get('device.id')", int(dev.settings.get("device.id")))
    step("axis count (system.axiscount)", int(dev.settings.get("system.axiscount")))
    axis = dev.get_axis(1)
    lim_min = axis.settings.get("limit.min")
    lim_max = axis.settings.get("limit.max")
    step("axis 1 limit.min / limit.max (native)", f"{lim_min:.0f} / {lim_max:.0f}")
    check(lim_min == -180 * upd and lim_max == 180 * upd, "limits are the emulator's ±180°")
    flags = axis.warnings.get_flags()
    step("warnings before homing", sorted(flags))
    check("WR" in flags, "an unhomed axis reports WR (no reference position)")

    axis.home()
    pos = axis.get_position()
    step("home()", f"position {pos:.0f}")
    check(pos == 0, "home is position 0")
    check("WR" not in axis.warnings.get_flags(), "WR cleared by homing")

    target = round(30 * upd)
    axis.move_absolute(target, wait_until_idle=False)
    busy = axis.is_busy()
    step(f"move_absolute({target}, wait_until_idle=False); is_busy()", busy)
    check(busy, "the axis is BUSY right after a 30° move starts")
    axis.wait_until_idle()
    pos = axis.get_position()
    step("wait_until_idle(); get_position()", f"{pos:.0f}")
    check(pos == target and not axis.is_busy(), "absolute move reached its target and is IDLE")

    rel = round(-12.5 * upd)
    axis.move_relative(rel)
    pos = axis.get_position()
    step(f"move_relative({rel})", f"position {pos:.0f}")
    check(pos == target + rel, "relative move")

    out_of_range = round(400 * upd)
    try:
        axis.move_absolute(out_of_range)
    except CommandFailedException as e:
        step(f"move_absolute({out_of_range}) (400°, out of range)", f"rejected: {type(e).__name__}: {e.details.response_data if e.details else e}")
    except MotionLibException as e:
        step(f"move_absolute({out_of_range}) (400°, out of range)", f"rejected: {type(e).__name__}: {e}")
    else:
        check(False, "an out-of-range move must be rejected")
    pos = axis.get_position()
    step("get_position() after the rejection", f"{pos:.0f}")
    check(pos == target + rel, "a rejected move does not move")

    axis.move_absolute(0)
    step("move_absolute(0); get_position()", f"{axis.get_position():.0f}")
    resp = conn.generic_command("get pos", device=1, axis=1)
    step("generic_command('get pos', device=1, axis=1)", f"{resp.reply_flag} {resp.status} {resp.warning_flag} {resp.data}")
    check(resp.reply_flag == "OK" and resp.status == "IDLE", "generic reply")

    # Serial-layer overhead as a client sees it (printed, not asserted: timing depends on load).
    n = 200
    t0 = time.perf_counter()
    for _ in range(n):
        axis.get_position()
    dt = time.perf_counter() - t0
    step(f"{n} x get_position() round trips", f"{n / dt:.0f} commands/s ({dt / n * 1e3:.2f} ms each)")
print("zaber-motion | session OK", flush=True)
