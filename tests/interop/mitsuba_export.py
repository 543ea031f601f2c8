"""Mitsuba 3 renders the scene `gonio export --format mitsuba` wrote; the picture must match
`gonio render --material` of the same fitted glTF model in the same scene: a directional
light of unit irradiance from a grid direction, an orthographic camera along a grid view
direction looking at the sample's plane, 8-bit sRGB after clamping at 1.

Usage: mitsuba_export.py GONIO FIT.gbtf EXPORT_DIR WORK_DIR [--max-mean 2] [--json OUT]

The mean absolute difference per channel (of 255) over the pixels inside one texel must be
≤ --max-mean for every scene: a pixel whose gonio value equals its 8 neighbours' lies within
one texel, where Mitsuba's average over the pixel's area and gonio's sample at its centre
see the same texel; pixels across texel edges differ by the sampling, not the BSDF, and
are reported apart (all pixels). Mitsuba's `principled` is not glTF's model term for term (Burley
diffuse, exact dielectric Fresnel): the difference printed here is what that costs.
"""
import argparse
import json
import math
import os
import subprocess
import sys

import numpy as np
from PIL import Image
import mitsuba as mi

mi.set_variant("scalar_rgb")

SCENES = [((45, 0), (0, 0)), ((30, 60), (30, 240)), ((60, 18), (15, 180)), ((0, 0), (45, 340)), ((45, 100), (60, 0))]
SIZE = 128


def unit(d):
    t, p = math.radians(d[0]), math.radians(d[1])
    return np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])


def srgb8(x):
    x = np.clip(x, 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.clip(np.floor(s * 255.0 + 0.5), 0, 255)


def mitsuba_render(scene_xml, folder, light, view, half):
    assert f'<scale x="{half}" y="{half}" z="1"/>' in scene_xml
    w = unit(view)
    r = np.array([w[2], 0.0, -w[0]])
    r /= np.linalg.norm(r)
    u = np.cross(w, r)
    l = unit(light)
    # gonio's plane spans [-1, 1] on the picture's side; the exported rectangle spans
    # [-half, half] mm, so the orthographic camera covers the same square.
    extra = f"""
    <emitter type="directional">
        <vector name="direction" x="{-l[0]}" y="{-l[1]}" z="{-l[2]}"/>
        <rgb name="irradiance" value="1, 1, 1"/>
    </emitter>
    <sensor type="orthographic">
        <transform name="to_world">
            <lookat origin="{4 * w[0]}, {4 * w[1]}, {4 * w[2]}" target="0, 0, 0" up="{u[0]}, {u[1]}, {u[2]}"/>
        </transform>
        <sampler type="independent"><integer name="sample_count" value="64"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="{SIZE}"/>
            <integer name="height" value="{SIZE}"/>
            <string name="pixel_format" value="rgb"/>
            <rfilter type="box"/>
        </film>
    </sensor>
    <integrator type="direct">
        <integer name="emitter_samples" value="1"/>
        <integer name="bsdf_samples" value="0"/>
    </integrator>
</scene>"""
    # The exported rectangle spans [-half, half] mm; Mitsuba's orthographic camera images
    # [-1, 1]² of its own frame whatever the to_world's scale, so the sample is brought to
    # gonio's unit square here (a test-only change of units, not of the material).
    text = scene_xml.replace(f'<scale x="{half}" y="{half}" z="1"/>', '<scale x="1" y="1" z="1"/>')
    text = text.replace("</scene>", extra)
    mi.file_resolver().prepend(folder)
    scene = mi.load_string(text)
    img = np.array(mi.render(scene, spp=64))
    return img[:, :, :3]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("gonio")
    ap.add_argument("fit")
    ap.add_argument("export_dir")
    ap.add_argument("work")
    ap.add_argument("--max-mean", type=float, default=2.0)
    ap.add_argument("--json")
    a = ap.parse_args()
    folder = os.path.abspath(a.export_dir)
    scene_xml = open(os.path.join(folder, "scene.xml")).read()
    half = scene_xml.split('<shape type="rectangle"', 1)[1].split('<scale x="', 1)[1].split('"')[0]
    rows = []
    ok = True
    for light, view in SCENES:
        name = f"l{light[0]}_{light[1]}_v{view[0]}_{view[1]}"
        ref = os.path.join(a.work, f"gonio_{name}.png")
        subprocess.run(
            [a.gonio, "render", a.fit, "--material", "--light", f"{light[0]},{light[1]}", "--view",
             f"{view[0]},{view[1]}", "--size", f"{SIZE}x{SIZE}", "--out", ref],
            check=True, stdout=subprocess.DEVNULL)
        g = np.asarray(Image.open(ref).convert("RGB"), dtype=np.float64)
        m = srgb8(mitsuba_render(scene_xml, folder, light, view, half))
        Image.fromarray(m.astype(np.uint8)).save(os.path.join(a.work, f"mitsuba_{name}.png"))
        d = np.abs(m - g)
        same = np.ones(g.shape[:2], dtype=bool)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                same &= np.all(g == np.roll(np.roll(g, dy, axis=0), dx, axis=1), axis=2)
        same[[0, -1], :] = False
        same[:, [0, -1]] = False
        inner = d[same]
        row = {"light": light, "view": view, "mean_abs_8bit": float(inner.mean()), "max_abs_8bit": float(inner.max()),
               "inner_pixels": int(same.sum()), "mean_abs_all_pixels_8bit": float(d.mean()),
               "mean_gonio_8bit": float(g.mean())}
        rows.append(row)
        good = row["mean_abs_8bit"] <= a.max_mean
        ok &= good
        print(f"mitsuba export: light {light} view {view}: mean |Mitsuba - gonio| {row['mean_abs_8bit']:.3f}/255, "
              f"max {row['max_abs_8bit']:.0f}/255 over {row['inner_pixels']} pixels inside a texel; "
              f"{row['mean_abs_all_pixels_8bit']:.3f}/255 over all (gonio mean {row['mean_gonio_8bit']:.1f}/255)"
              f"{'' if good else '  FAIL'}")
    if a.json:
        json.dump(rows, open(a.json, "w"), indent=2)
    if not ok:
        print(f"mitsuba export: a scene's mean difference exceeds {a.max_mean}/255", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
