#!/usr/bin/env bash
# Install (or re-use) the Khronos glTF-Validator from npm, pinned, into DIR/node_modules:
# the reader that checks `gonio export --format gltf` (tests/interop/gltf_validate.js).
#
# Usage: tests/interop/setup_node.sh DIR
# Then:  GONIO_NODE_MODULES=DIR/node_modules bash tests/interop/run.sh
set -euo pipefail
if [ $# -ne 1 ]; then
    echo "usage: $0 DIR" >&2
    exit 2
fi
dir=$(realpath -m "$1")
version=2.0.0-dev.3.10
pkg="$dir/node_modules/gltf-validator/package.json"
if [ -f "$pkg" ] && grep -q "\"version\": \"$version\"" "$pkg"; then
    echo "$dir: gltf-validator $version ready"
    exit 0
fi
mkdir -p "$dir"
npm install --prefix "$dir" --no-audit --no-fund --silent "gltf-validator@$version" >/dev/null
grep -q "\"version\": \"$version\"" "$pkg"
echo "$dir: gltf-validator $version ready"
