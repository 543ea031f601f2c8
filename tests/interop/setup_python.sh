#!/usr/bin/env bash
# Create (or re-use) a Python virtual environment with the public btf-extractor 1.7.0
# reader used by tests/interop/check_ubo2003.py and the Mitsuba 3 renderer (PyPI `mitsuba`
# 3.9.1 with `drjit` 1.5.0, binary wheels) used as an oracle by tests/interop/mitsuba_*.py,
# zarr-python, xarray and dask (tests/interop/check_zarr.py), MaterialX and usd-core
# (tests/interop/check_material_export.py), with every package pinned.
#
# Usage: tests/interop/setup_python.sh VENV_DIR
# Then:  GONIO_PYTHON=VENV_DIR/bin/python cargo test -p gonio --lib store
#
# Idempotent: an existing venv that already imports btf_extractor 1.7.0 with the pinned
# versions is left as it is. btf-extractor ships only an sdist whose Cython extension
# needs Cython < 0.30 and poetry-core at build time, hence the two-step install without
# build isolation.
set -euo pipefail

if [ $# -ne 1 ]; then
    echo "usage: $0 VENV_DIR" >&2
    exit 2
fi
# Absolute: the check below runs from / (see there).
venv=$(realpath -m "$1")
python=${PYTHON:-python3}

build_pins=(
    "Cython==0.29.37"
    "poetry-core==2.5.0"
    "numpy==1.26.4"
    "setuptools==65.5.0"
    "wheel==0.48.0"
)
runtime_pins=(
    "btf-extractor==1.7.0"
    "imageio==2.38.1"
    "nptyping==1.4.4"
    "typish==1.9.3"
    "pillow==13.0.0"
    "simplejpeg==1.9.0"
    "packaging==26.3"
    "mitsuba==3.9.1"
    "drjit==1.5.0"
    # OpenCV: oracle for camera calibration (tests/interop/opencv_intrinsics.py).
    # 4.10.0.84: the newest release that still accepts numpy 1.26 (5.x needs numpy >= 2).
    "opencv-python-headless==4.10.0.84"
    # Vendor clients for the motor-controller emulators (tests/interop/zaber_motion_session.py,
    # tests/interop/pymeasure_esp300.py) and their dependencies; pandas 2.2.3 because pandas 3
    # needs numpy >= 2 (btf-extractor needs numpy < 2).
    "zaber-motion==10.2.0"
    "reactivex==4.1.0"
    "pymeasure==0.16.0"
    "pyvisa==1.16.2"
    "pyvisa-py==0.8.1"
    "pyserial==3.5"
    "pandas==2.2.3"
    "python-dateutil==4.0.0"
    "pytz==2026.6"
    "tzdata==2026.6"
    "pint==0.25.3"
    "flexcache==0.3"
    "flexparser==0.4"
    "platformdirs==4.14.7"
    "typing_extensions==4.16.0"
    "pyqtgraph==0.14.0"
    "qtpy==2.4.3"
    "colorama==0.4.6"
    # Zarr v3 readers for `gonio export --format zarr` (tests/interop/check_zarr.py):
    # zarr-python 3.1.5 (the newest 3.x resolved with numpy 1.26 on Python 3.11),
    # xarray, dask.array, and OpenEXR's bindings to read the reference EXRs; with their
    # dependencies (google-crc32c: the crc32c codec of the shard index).
    "zarr==3.1.5"
    "numcodecs==0.16.6"
    "google-crc32c==1.9.0"
    "donfig==0.8.1.post1"
    "PyYAML==6.0.4"
    "xarray==2026.9.0"
    "dask==2026.8.0"
    "click==8.5.1"
    "cloudpickle==3.1.3"
    "fsspec==2026.9.0"
    "importlib_metadata==10.2.0"
    "lazy-importer==0.1.0"
    "zipp==4.1.2"
    "partd==1.4.2"
    "locket==1.0.0"
    "toolz==1.2.0"
    "OpenEXR==3.5.3"
    # Playwright's Python client drives Debian's /usr/bin/chromium in tests/browser/
    # (executable_path; its own browser download is never used).
    "playwright==1.65.2"
    "greenlet==3.5.6"
    # Readers of `gonio export --format materialx|usd` (tests/interop/check_material_export.py):
    # MaterialX's validate() and OpenUSD's stage (usd-core, no numpy needed).
    "MaterialX==1.39.5"
    "usd-core==26.11"
)

# Run from /, not from the checkout: `python -` puts the working directory first on
# sys.path, and a workspace folder named like a Python package (`sparse/`, the gonio-sparse
# crate) then shadows it: dask imports `sparse` when it exists and fails on the empty
# namespace package. On failure the reason is printed, not swallowed.
check() {
    (cd / && "$venv/bin/python" - "$@") <<'PY'
import sys
from importlib.metadata import version
from btf_extractor import Ubo2003  # noqa: F401
import mitsuba
mitsuba.set_variant("scalar_rgb")
import cv2  # noqa: F401
import zaber_motion.ascii  # noqa: F401
import pymeasure.instruments.newport  # noqa: F401
import pyvisa_py  # noqa: F401
import playwright.sync_api  # noqa: F401
import zarr, xarray, dask.array, OpenEXR  # noqa: F401,E401
import MaterialX  # noqa: F401
from pxr import Usd  # noqa: F401
pins = dict(p.split("==") for p in sys.argv[1:])
bad = {k: version(k) for k, v in pins.items() if version(k) != v}
if bad:
    print("venv check: installed versions differ from the pins:", bad, file=sys.stderr)
sys.exit(1 if bad else 0)
PY
}

if [ -x "$venv/bin/python" ] && check "${build_pins[@]}" "${runtime_pins[@]}" 2>/dev/null; then
    echo "$venv: btf-extractor 1.7.0, mitsuba 3.9.1, zarr 3.1.5 ready"
    exit 0
fi

"$python" -m venv "$venv"
"$venv/bin/python" -m pip install --quiet "${build_pins[@]}"
"$venv/bin/python" -m pip install --quiet --no-build-isolation "${runtime_pins[@]}"
check "${build_pins[@]}" "${runtime_pins[@]}"
echo "$venv: btf-extractor 1.7.0, mitsuba 3.9.1, zarr 3.1.5 ready"
