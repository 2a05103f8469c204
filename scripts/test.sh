#!/usr/bin/env bash
# Runs every test: the deploy files' syntax, the Python package's tests, the Rust workspace
# (release profile, so the set-up's build is reused), then the container tests: the compose stack
# (deploy/test-compose.sh) and the multi-host run (deploy/test-multihost.sh). Those install Docker
# and start its daemon when missing and build the images (about 12 min in all); they fail, never
# skip, when no daemon can be had. RFCL_TEST_DOCKER=0 leaves them out (say so when you do).
# Assumes scripts/setup.sh has run.
set -euo pipefail
cd "$(dirname "$0")/.."
# torch-sys asks `python` (with VIRTUAL_ENV set) for libtorch: it must be the venv's.
export VIRTUAL_ENV="$PWD/.venv" PATH="$PWD/.venv/bin:$PATH"
export LIBTORCH_USE_PYTORCH=1 PYO3_PYTHON="$PWD/.venv/bin/python"
echo "==> deploy files (shell syntax; the compose files when docker compose is installed)"
for f in deploy/*.sh; do bash -n "$f"; done
if docker compose version >/dev/null 2>&1; then
  docker compose -f deploy/docker-compose.yml config -q
  RFCL_LEARNER=remote:50052 RFCL_CURRICULUM=remote:50051 \
    docker compose -f deploy/docker-compose.remote.yml config -q
  echo "compose files valid"
else
  echo "docker compose not installed (deploy/setup-docker.sh): compose files not validated"
fi
echo "==> python tests (python/tests)"
.venv/bin/python -m pytest -q python/tests
echo "==> rust tests (cargo nextest, release profile)"
if cargo nextest --version >/dev/null 2>&1; then
  cargo nextest run --workspace --release --no-fail-fast
else
  echo "cargo-nextest not found: using cargo test"
  cargo test --workspace --release --no-fail-fast
fi
if [ "${RFCL_TEST_DOCKER:-1}" = 1 ]; then
  echo "==> containers: the compose stack (deploy/test-compose.sh)"
  deploy/test-compose.sh
  echo "==> containers: actors on their own network, faults, the run to its bar (deploy/test-multihost.sh)"
  deploy/test-multihost.sh --no-build
else
  echo "==> containers: left out (RFCL_TEST_DOCKER=0)"
fi
