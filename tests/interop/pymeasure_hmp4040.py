#!/usr/bin/env python3
"""Drive gonio's HMP4040 emulator with PyMeasure's HMP4040 class over pyvisa-py.

Usage: pymeasure_hmp4040.py PTY

Started by tests/interop/run.sh against `gonio sim serve-light` (4 channels, a 12 V / 100 W
halogen lamp on each). Reads the identity, selects a channel, sets voltage and current,
switches the output on, measures voltage and current and checks them against the lamp
model the emulator documents (simulator/src/emulate/hmp.rs), switches off and checks the
SCPI error queue; prints a transcript and exits non-zero naming the failed step.
"""
import math
import sys

from pymeasure.instruments.rohdeschwarz import HMP4040

if len(sys.argv) != 2:
    sys.exit("usage: pymeasure_hmp4040.py PTY")
resource = f"ASRL{sys.argv[1]}::INSTR"

# The emulator's lamp (defaults of `gonio sim serve-light`):
# R(V) = R_cold + (R_hot - R_cold) * sqrt(V / V_rated), R_hot = V_rated^2 / P_rated.
V_RATED, P_RATED, R_COLD = 12.0, 100.0, 0.12
R_HOT = V_RATED**2 / P_RATED


def lamp_current(v):
    return v / (R_COLD + (R_HOT - R_COLD) * math.sqrt(v / V_RATED)) if v > 0 else 0.0


def step(what, value=None):
    print(f"pymeasure    | {what}" + ("" if value is None else f" -> {value}"), flush=True)


def check(cond, msg):
    if not cond:
        print(f"pymeasure    | FAILED: {msg}", file=sys.stderr, flush=True)
        sys.exit(1)


hmp = HMP4040(resource, visa_library="@py", baud_rate=9600,
              read_termination="\n", write_termination="\n", timeout=3000)
step(f"HMP4040({resource!r}, visa_library='@py')", "ok")
idn = hmp.id
step("id", idn)
check(idn.split(",")[1] == "HMP4040", "*IDN? names the model")
hmp.clear()
step("clear() (*CLS)", "ok")
step("version", hmp.version)

hmp.selected_channel = 2
step("selected_channel = 2; selected_channel", hmp.selected_channel)
check(hmp.selected_channel == 2, "INST:NSEL")

hmp.voltage = 12
hmp.current = 9.5
step("voltage = 12; current = 9.5; voltage, current", (hmp.voltage, hmp.current))
check(abs(float(hmp.voltage) - 12) < 1e-9 and abs(float(hmp.current) - 9.5) < 1e-9, "VOLT/CURR read back")
step("max_voltage, max_current", (hmp.max_voltage, hmp.max_current))

hmp.selected_channel_active = True
hmp.output_enabled = True
step("selected_channel_active = True; output_enabled = True", (hmp.selected_channel_active, hmp.output_enabled))
check(hmp.selected_channel_active and hmp.output_enabled, "OUTP:SEL? and OUTP:GEN?")

v, i = float(hmp.measured_voltage), float(hmp.measured_current)
step("measured_voltage, measured_current", (v, i))
check(abs(v - 12) < 1e-3, "constant voltage at the set 12 V")
check(abs(i - lamp_current(12)) < 2e-4, f"current {i} A vs the lamp model's {lamp_current(12):.4f} A")
check(abs(v * i - P_RATED) < 0.01, "the rated 100 W at the rated voltage")

hmp.voltage_and_current = (6, 9.5)
v, i = float(hmp.measured_voltage), float(hmp.measured_current)
step("voltage_and_current = (6, 9.5); measured", (v, i))
check(abs(v - 6) < 1e-3 and abs(i - lamp_current(6)) < 2e-4,
      f"half voltage: {i} A vs the lamp model's {lamp_current(6):.4f} A (a lamp is not a resistor)")
check(i > 12 / R_HOT / 2, "a colder filament draws more than half the current")

hmp.voltage_and_current = (12, 5)
v, i = float(hmp.measured_voltage), float(hmp.measured_current)
step("voltage_and_current = (12, 5); measured (current limited)", (v, i))
check(abs(i - 5) < 2e-4 and v < 12, "constant current at the 5 A limit")
check(abs(i - lamp_current(v)) < 2e-3, "the lamp's operating point")

hmp.selected_channel_active = False
v, i = float(hmp.measured_voltage), float(hmp.measured_current)
step("selected_channel_active = False; measured", (v, i))
check(v == 0 and i == 0, "output off")
hmp.output_enabled = False

check(hmp.check_errors() == [], "no error after a clean session")
hmp.write("VOLT:FOO 1")
errs = hmp.check_errors()
step("write('VOLT:FOO 1'); check_errors()", errs)
check(len(errs) == 1 and int(errs[0][0]) == -113 and "Undefined header" in str(errs[0][1]), "-113 Undefined header")
hmp.write("VOLT 40")
errs = hmp.check_errors()
step("write('VOLT 40'); check_errors()", errs)
check(len(errs) == 1 and int(errs[0][0]) == -222, "-222 Data out of range")
step("next_error when clean", hmp.next_error)
hmp.adapter.close()
print("pymeasure    | session OK", flush=True)
