#!/usr/bin/env bash
# Runs every test: the Rust workspace (release profile, so the set-up's build is reused) and the
# Python package's tests. Assumes scripts/setup.sh has run.
set -euo pipefail
cd "$(dirname "$0")/.."
# torch-sys asks `python` (with VIRTUAL_ENV set) for libtorch: it must be the venv's.
export VIRTUAL_ENV="$PWD/.venv" PATH="$PWD/.venv/bin:$PATH"
export LIBTORCH_USE_PYTORCH=1 PYO3_PYTHON="$PWD/.venv/bin/python"
echo "==> python tests (python/tests)"
.venv/bin/python -m pytest -q python/tests
echo "==> rust tests (cargo nextest, release profile)"
if cargo nextest --version >/dev/null 2>&1; then
  cargo nextest run --workspace --release --no-fail-fast
else
  echo "cargo-nextest not found: using cargo test"
  cargo test --workspace --release --no-fail-fast
fi
