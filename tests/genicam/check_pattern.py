#!/usr/bin/env python3
"""Check a dataset acquired from arv-fake-gv-camera-0.8 (Mono8) against the fake's pattern.

Usage: check_pattern.py DATASET_DIR [--min-frames N]

Every stored measurement of DATASET_DIR (journal.jsonl) must have a raw frame
(raw/NNNNN.png, 16-bit RGB, DN as the camera delivered them) equal, pixel for pixel, to
the fake camera's Mono8 diagonal ramp for that frame (libaravis src/arvfakecamera.c):

    value(x, y) = clamp(floor(((x + y + frame_id) mod 255) * s), 0, 255)
    s = 1 + GainRaw + log10(exposure_us / 10000)   (exposure_us: whole microseconds)

with frame_id the record's frame_sequence and exposure the record's exposure_s (GainRaw 0,
gonio's gain 1). A frame stored with the wrong exposure or sequence cannot match, so this
checks the metadata as well as the pixels. Prints per-frame statistics; exits 1 on the
first mismatch. Standard library only (the PNG reader below handles what gonio writes:
8-bit-per-sample RGB or 16-bit RGB, not interlaced).
"""

import json
import math
import struct
import sys
import zlib
from pathlib import Path


def read_png(path):
    data = Path(path).read_bytes()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path}: not a PNG")
    pos, idat, header = 8, b"", None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        pos += 12 + length
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        elif kind == b"IEND":
            break
    width, height, depth, colour, _, _, interlace = header
    if colour != 2 or interlace != 0 or depth not in (8, 16):
        raise ValueError(f"{path}: colour type {colour}, depth {depth}, interlace {interlace} not handled")
    bpp = 3 * depth // 8
    stride = width * bpp
    raw = zlib.decompress(idat)
    rows, prev = [], bytearray(stride)
    for y in range(height):
        f = raw[y * (stride + 1)]
        line = bytearray(raw[y * (stride + 1) + 1 : (y + 1) * (stride + 1)])
        for i in range(stride):
            a = line[i - bpp] if i >= bpp else 0
            b = prev[i]
            c = prev[i - bpp] if i >= bpp else 0
            if f == 1:
                line[i] = (line[i] + a) & 0xFF
            elif f == 2:
                line[i] = (line[i] + b) & 0xFF
            elif f == 3:
                line[i] = (line[i] + (a + b) // 2) & 0xFF
            elif f == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
                line[i] = (line[i] + pred) & 0xFF
        rows.append(line)
        prev = line
    if depth == 16:
        values = [[int.from_bytes(r[i : i + 2], "big") for i in range(0, stride, 2)] for r in rows]
    else:
        values = [list(r) for r in rows]
    return width, height, values


def main():
    args = sys.argv[1:]
    if not args:
        print(__doc__)
        return 2
    root = Path(args[0])
    min_frames = int(args[args.index("--min-frames") + 1]) if "--min-frames" in args else 1
    lines = [json.loads(l) for l in (root / "journal.jsonl").read_text().splitlines() if l.strip()]
    # Each journal line is {"crc": …, "rec": the measurement record}.
    records = [l.get("rec", l) for l in lines]
    checked = 0
    for r in records:
        raw = r.get("raw")
        if not raw:
            continue
        seq, exposure = r.get("frame_sequence"), r["exposure_s"]
        if seq is None:
            print(f"{raw}: no frame_sequence in the record", file=sys.stderr)
            return 1
        # The fake keeps whole microseconds (a 32-bit register), as does its pattern.
        scale = 1.0 + math.log10(round(exposure * 1e6) / 10000.0)
        w, h, rows = read_png(root / raw)
        bad, total = 0, 0.0
        for y in range(h):
            row = rows[y]
            for x in range(w):
                want = min(max(math.floor(((x + y + seq) % 255) * scale), 0), 255)
                px = row[3 * x : 3 * x + 3]
                total += px[0]
                if px != [want, want, want]:
                    if bad == 0:
                        print(f"{raw}: ({x}, {y}) is {px}, the pattern of frame {seq} at {exposure} s says {want}", file=sys.stderr)
                    bad += 1
        mean = total / (w * h)
        print(f"genicam e2e: {raw} frame {seq} exposure {exposure} s {w}x{h}: mean {mean:.3f} DN, {bad} pixels off the pattern")
        if bad:
            return 1
        checked += 1
    print(f"genicam e2e: {checked} stored frames match the fake camera's pattern exactly")
    if checked < min_frames:
        print(f"genicam e2e: expected at least {min_frames} frames", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
