#!/usr/bin/env bash
# The test command (README): formatting, lints, every Rust test, then the interop checks
# against public readers (they need the venv that .ci/run installs; without it they are
# skipped with a notice, never silently passed).
set -euo pipefail
cd "$(dirname "$0")/.."
export GONIO_VENV="${GONIO_VENV:-$PWD/target/venv}"
if [ -x "$GONIO_VENV/bin/python" ]; then
  export GONIO_PYTHON="$GONIO_VENV/bin/python"
fi

echo "== cargo fmt --check"
cargo fmt --all -- --check
echo "== cargo clippy (warnings denied)"
cargo clippy --workspace --all-targets -- -D warnings
echo "== cargo test"
cargo test --workspace
echo "== interop"
bash tests/interop/run.sh
