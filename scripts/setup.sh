#!/usr/bin/env bash
# One idempotent set-up for a fresh Debian 12 machine: system packages, the Python venv with the
# pinned simulator/torch matrix, and the release build. Each step says what it does and skips what is
# already there. Usage: scripts/setup.sh [--no-build] [--no-python]
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
VENV=${RFCL_VENV:-$ROOT/.venv}
BUILD=1; PYTHON=1
for arg in "$@"; do
  case "$arg" in
    --no-build) BUILD=0 ;;
    --no-python) PYTHON=0 ;;
    *) echo "setup: unknown argument '$arg' (expected --no-build or --no-python)" >&2; exit 2 ;;
  esac
done

step() { printf '\n==> %s\n' "$*"; }
fail() { printf 'setup: FAILED: %s\n' "$*" >&2; exit 1; }
SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"

# ---------------------------------------------------------------- rust toolchain
# The workspace needs the Rust of its rust-version (Cargo.toml); Debian 12's own cargo is 1.63.
# Checked first, so that a machine without it learns so before anything is installed.
RUST_MIN=$(sed -n 's/^rust-version = "\(.*\)"/\1/p' "$ROOT/Cargo.toml" | head -n 1)
rust_ok() {
  local have
  have=$(cargo --version 2>/dev/null | awk '{print $2}')
  [ -n "$have" ] && dpkg --compare-versions "$have" ge "$RUST_MIN"
}
RUSTUP_LINE="curl --proto '=https' --tlsv1.2 -sSf https://sh.rustup.rs | sh -s -- -y --profile minimal && . \"\$HOME/.cargo/env\""
if [ $BUILD = 1 ]; then
  # A rustup install of an earlier session is on PATH only in shells that sourced its env.
  if ! rust_ok && [ -f "$HOME/.cargo/env" ]; then . "$HOME/.cargo/env"; fi
  if rust_ok; then
    step "rust toolchain: $(cargo --version) (>= $RUST_MIN)"
  else
    found=$(cargo --version 2>/dev/null || echo "no cargo")
    step "rust toolchain: $found, the workspace needs >= $RUST_MIN: installing the stable toolchain with rustup into $HOME/.cargo"
    if command -v rustup >/dev/null 2>&1; then
      rustup toolchain install stable --profile minimal && rustup default stable \
        || fail "rustup could not install the stable toolchain; install Rust >= $RUST_MIN, e.g.: $RUSTUP_LINE"
    else
      curl --proto '=https' --tlsv1.2 -sSf https://sh.rustup.rs | sh -s -- -y --profile minimal \
        || fail "Rust >= $RUST_MIN is needed ($found) and rustup could not be fetched; run: $RUSTUP_LINE"
      . "$HOME/.cargo/env"
    fi
    rust_ok || fail "Rust >= $RUST_MIN is still not the cargo on PATH ($(cargo --version 2>/dev/null || echo none)); run: $RUSTUP_LINE"
  fi
fi

# ---------------------------------------------------------------- system packages
# libpython3.11-dev: rfcl-sim-worker embeds Python (pyo3 links libpython3.11.so).
APT_PKGS=(pkg-config libhdf5-dev protobuf-compiler chromium curl ca-certificates libpython3.11-dev)
# Mesa from backports: Vulkan (lavapipe) for ManiSkill's CPU renderer, EGL for MuJoCo's
# (MetaWorld and Adroit eval videos render headless with MUJOCO_GL=egl).
BACKPORTS_PKGS=(mesa-vulkan-drivers libvulkan1 libegl1 libegl-mesa0)
missing=()
for p in "${APT_PKGS[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
mesa_ok=0
if dpkg -s mesa-vulkan-drivers >/dev/null 2>&1; then
  v=$(dpkg-query -W -f='${Version}' mesa-vulkan-drivers)
  dpkg --compare-versions "$v" ge 24.3 && mesa_ok=1
fi
for p in "${BACKPORTS_PKGS[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || mesa_ok=0; done
if [ ${#missing[@]} -eq 0 ] && [ $mesa_ok = 1 ]; then
  step "system packages: present (${APT_PKGS[*]}, Mesa >= 24.3)"
else
  step "system packages: installing ${missing[*]} ${BACKPORTS_PKGS[*]} (Mesa >= 24.3 from bookworm-backports)"
  if ! grep -rqs bookworm-backports /etc/apt/sources.list /etc/apt/sources.list.d/; then
    echo "deb http://deb.debian.org/debian bookworm-backports main" | $SUDO tee /etc/apt/sources.list.d/rfcl-backports.list >/dev/null
  fi
  $SUDO apt-get update -qq || fail "apt-get update (is a Debian mirror reachable?)"
  if [ ${#missing[@]} -gt 0 ]; then
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null \
      || fail "apt-get install ${missing[*]}"
  fi
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq -t bookworm-backports "${BACKPORTS_PKGS[@]}" >/dev/null \
    || fail "apt-get install -t bookworm-backports ${BACKPORTS_PKGS[*]} (ManiSkill's CPU renderer needs Mesa >= 24.3)"
fi

# ---------------------------------------------------------------- python venv
# torch 2.11.0 is pinned to match tch 0.24 (its libtorch is what the Rust learner and actors link).
# PyPI's wheel is a CUDA 13 build. A CPU-only install (torch --no-deps) was measured and does not
# work: `import torch` loads libtorch_python -> libtorch.so, which needs cuBLAS, cuDNN, NCCL, ... from
# the nvidia-* wheels, and ManiSkill imports torch. So the full wheel set is installed (~1 min here).
if [ $PYTHON = 1 ]; then
  PY=${RFCL_PYTHON:-python3}
  if [ ! -x "$VENV/bin/python" ]; then
    step "python venv: creating $VENV"
    "$PY" -m venv "$VENV" || fail "$PY -m venv $VENV (is python3-venv installed?)"
  else
    step "python venv: $VENV present"
  fi
  if "$VENV/bin/python" -c "import torch, sys; sys.exit(torch.__version__.split('+')[0] != '2.11.0')" 2>/dev/null; then
    step "torch 2.11.0: present"
  else
    step "torch 2.11.0: installing (CUDA 13 wheels from PyPI, ~2.7 GB download)"
    "$VENV/bin/pip" install -q --upgrade pip
    "$VENV/bin/pip" install -q torch==2.11.0 || fail "pip install torch==2.11.0"
  fi
  if "$VENV/bin/python" -c "import mani_skill, metaworld, gymnasium_robotics, h5py, pytest, tensorboard, kubernetes_validate" 2>/dev/null; then
    step "simulators (mani_skill, metaworld, gymnasium-robotics, h5py), tensorboard: present"
  else
    step "simulators: installing the pinned matrix from python/requirements.txt"
    "$VENV/bin/pip" install -q -r "$ROOT/python/requirements.txt" || fail "pip install -r python/requirements.txt"
  fi
  if ! "$VENV/bin/python" -c "import rfcl_sim" 2>/dev/null; then
    step "rfcl_sim (python/): installing in editable mode"
    "$VENV/bin/pip" install -q -e "$ROOT/python" --no-deps >/dev/null || fail "pip install -e python/"
  fi
  "$VENV/bin/python" -m rfcl_sim.check || fail "the simulator matrix in $VENV is not the tested one (see above)"
fi

# ---------------------------------------------------------------- rust build
if [ $BUILD = 1 ]; then
  step "cargo build --release (first build ~6 min on 2 cores; incremental builds take seconds)"
  # torch-sys asks `python` (with VIRTUAL_ENV set) for libtorch: it must be the venv's.
  export LIBTORCH_USE_PYTORCH=1 PYO3_PYTHON="$VENV/bin/python" VIRTUAL_ENV="$VENV" PATH="$VENV/bin:$PATH"
  cargo build --release --workspace --quiet || fail "cargo build --release --workspace"
fi
step "set-up done"
