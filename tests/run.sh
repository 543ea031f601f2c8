#!/usr/bin/env bash
# The test command (README): formatting, lints, every Rust test, the reliability campaigns
# with their figures, then the interop checks against public readers and oracles (they
# need the venv that .ci/run installs; without it they are skipped with a notice, and
# under CI they fail).
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
echo "== campaign figures (kill -9, faults)"
cargo test -q -p gonio --test campaign_kill9 --test campaign_faults -- --nocapture 2>&1 \
  | grep -E "^(kill9:|fault|\||[a-z-]+ +\|)" || true
echo "== interop"
bash tests/interop/run.sh
