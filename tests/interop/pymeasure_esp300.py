#!/usr/bin/env python3
"""Drive gonio's Newport ESP300 emulator with PyMeasure's ESP300 driver over pyvisa-py.

Usage: pymeasure_esp300.py PTY

Started by tests/interop/run.sh against `gonio sim serve-stage --protocol esp300 --axes 3`
(PyMeasure's ESP300 class has three axes: x, y, phi). Enables, homes, moves, reads positions
and queries errors; prints a transcript and exits non-zero naming the failed step.
"""
import sys
import warnings

from pymeasure.instruments.newport import ESP300
from pymeasure.instruments.newport.esp300 import AxisError, GeneralError

if len(sys.argv) != 2:
    sys.exit("usage: pymeasure_esp300.py PTY")
# PyMeasure warns (once, at close) that it does not know whether the ESP300 speaks SCPI.
warnings.filterwarnings("ignore", message="It is not known whether this device support SCPI")
resource = f"ASRL{sys.argv[1]}::INSTR"


def step(what, value=None):
    print(f"pymeasure    | {what}" + ("" if value is None else f" -> {value}"), flush=True)


def check(cond, msg):
    if not cond:
        print(f"pymeasure    | FAILED: {msg}", file=sys.stderr, flush=True)
        sys.exit(1)


esp = ESP300(resource, visa_library="@py", baud_rate=19200,
             read_termination="\r\n", write_termination="\r", timeout=3000)
step(f"ESP300({resource!r}, visa_library='@py')", "ok")
version = esp.ask("VE?").strip()
step("ask('VE?')", version)
check(version.startswith("ESP300"), "firmware string")
esp.clear_errors()
step("clear_errors()", "ok")

esp.x.position = 5
errs = esp.errors
step("x.position = 5 before enabling; errors", [str(e) for e in errs])
check(len(errs) == 1 and isinstance(errs[0], AxisError) and errs[0].error == "13", "motor not enabled")

# Axis by axis, not ESP300.enable(): that one finds its axes by reading every attribute of
# the instrument, including the SCPI ones (*OPC?, *IDN?, ...) that the ESP300 command set does
# not have, so against a real ESP300 (and this emulator) it waits for replies that never come.
axes = (esp.x, esp.y, esp.phi)
for a in axes:
    a.enable()
step("x/y/phi.enable(); enabled", [a.enabled for a in axes])
check(esp.x.enabled and esp.phi.enabled, "MO? reports enabled")

esp.x.home()
esp.x.wait_for_stop()
step("x.home(); x.wait_for_stop(); x.position", esp.x.position)
check(abs(esp.x.position) < 1e-9, "home is 0")

esp.x.position = 12.5
step("x.position = 12.5; motion_done right after", esp.x.motion_done)
esp.x.wait_for_stop()
pos = esp.x.position
step("x.wait_for_stop(); x.position", pos)
check(abs(pos - 12.5) < 1e-6, "absolute move")

esp.y.position = -30
esp.y.wait_for_stop()
step("y.position = -30; y.position", esp.y.position)
check(abs(esp.y.position + 30) < 1e-6, "second axis")

esp.x.position = 500
errs = esp.errors
step("x.position = 500 (beyond the right limit); errors", [str(e) for e in errs])
check(len(errs) == 1 and isinstance(errs[0], AxisError) and errs[0].error == "06", "software limit error")
check(abs(esp.x.position - 12.5) < 1e-6, "rejected move did not move")

esp.write("XX")
errs = esp.errors
step("write('XX'); errors", [str(e) for e in errs])
check(len(errs) == 1 and isinstance(errs[0], GeneralError) and errs[0].error == "6", "command does not exist")
step("error (TE?) when clean", esp.error)
check(esp.error == 0, "no error left")
tb = esp.ask("TB?").strip()
step("ask('TB?')", tb)
for a in axes:
    a.disable()
step("x/y/phi.disable(); x.enabled", esp.x.enabled)
check(not esp.x.enabled, "MF turns the motor off")
esp.adapter.close()
print("pymeasure    | session OK", flush=True)
