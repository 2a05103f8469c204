#!/usr/bin/env bash
# Idempotent Docker set-up for a Debian 12 (bookworm) host, so that `docker compose -f
# deploy/docker-compose.yml up` works: Debian's docker.io (engine), Compose v2 from trixie (bookworm
# only has the old Python docker-compose 1.29) under a low apt pin, debootstrap and patchelf (for
# deploy/build-images.sh), a running dockerd,
# the `docker compose` plugin form, and the `debian:bookworm-slim` base image (made with debootstrap
# and `docker import` when it cannot be pulled). Each step says what it does and skips what is there.
# Usage: deploy/setup-docker.sh            (root, or sudo available)
# Env:   RFCL_DOCKERD_LOG (default /var/log/rfcl-dockerd.log)  DEBIAN_MIRROR (default deb.debian.org)
set -euo pipefail

step() { printf '==> %s\n' "$*"; }
fail() { printf 'setup-docker: FAILED: %s\n' "$*" >&2; exit 1; }
SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
DOCKERD_LOG=${RFCL_DOCKERD_LOG:-/var/log/rfcl-dockerd.log}
BASE_IMAGE=debian:bookworm-slim
export DEBIAN_FRONTEND=noninteractive

have_pkg() { dpkg -s "$1" >/dev/null 2>&1; }
APT_UPDATED=0
apt_update() { [ $APT_UPDATED = 1 ] || { $SUDO apt-get update -qq || fail "apt-get update"; APT_UPDATED=1; }; }

# ---------------------------------------------------------------- packages
missing=()
for p in docker.io debootstrap patchelf; do have_pkg "$p" || missing+=("$p"); done
if [ ${#missing[@]} -eq 0 ]; then
  step "docker.io, debootstrap, patchelf: present"
else
  step "installing ${missing[*]} (bookworm)"
  apt_update
  $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null || fail "apt-get install ${missing[*]}"
fi

# Compose v2: trixie's docker-compose (2.x, a static Go binary). The trixie source is pinned at 1 so
# nothing else ever comes from trixie unless asked for by name (pkg/trixie).
compose_v2() { have_pkg docker-compose && dpkg --compare-versions "$(dpkg-query -W -f='${Version}' docker-compose)" ge 2; }
if compose_v2; then
  step "docker-compose v2: present ($(dpkg-query -W -f='${Version}' docker-compose))"
else
  step "docker-compose v2: adding a trixie source pinned at priority 1, installing docker-compose/trixie only"
  if ! grep -rqs 'trixie' /etc/apt/sources.list.d/rfcl-trixie.list; then
    echo "deb $MIRROR trixie main" | $SUDO tee /etc/apt/sources.list.d/rfcl-trixie.list >/dev/null
  fi
  printf 'Package: *\nPin: release n=trixie\nPin-Priority: 1\n' | $SUDO tee /etc/apt/preferences.d/rfcl-trixie >/dev/null
  APT_UPDATED=0; apt_update
  $SUDO apt-get install -y -qq --no-install-recommends docker-compose/trixie >/dev/null \
    || fail "apt-get install docker-compose/trixie"
  compose_v2 || fail "docker-compose from trixie is not v2"
fi

# ---------------------------------------------------------------- dockerd
if docker info >/dev/null 2>&1; then
  step "dockerd: running"
else
  if pgrep -x dockerd >/dev/null; then
    step "dockerd: process present but not answering yet; waiting"
  else
    step "dockerd: starting in the background (log: $DOCKERD_LOG)"
    # containerd is started by dockerd itself when no system containerd runs.
    $SUDO sh -c "nohup /usr/sbin/dockerd >>'$DOCKERD_LOG' 2>&1 &"
  fi
  for _ in $(seq 60); do docker info >/dev/null 2>&1 && break; sleep 1; done
  docker info >/dev/null 2>&1 || { tail -20 "$DOCKERD_LOG" >&2; fail "dockerd did not answer within 60 s"; }
  step "dockerd: up ($(docker info --format '{{.ServerVersion}} storage={{.Driver}}'))"
fi

# ---------------------------------------------------------------- docker compose (plugin form)
if docker compose version >/dev/null 2>&1; then
  step "docker compose: works ($(docker compose version --short 2>/dev/null || docker compose version))"
else
  bin=""
  for c in /usr/libexec/docker/cli-plugins/docker-compose /usr/lib/docker/cli-plugins/docker-compose \
           "$(command -v docker-compose || true)"; do
    [ -n "$c" ] && [ -x "$c" ] && { bin=$(readlink -f "$c"); break; }
  done
  [ -n "$bin" ] || fail "no docker-compose binary found"
  step "docker compose: linking $bin into /usr/local/lib/docker/cli-plugins and /usr/libexec/docker/cli-plugins"
  for d in /usr/local/lib/docker/cli-plugins /usr/libexec/docker/cli-plugins; do
    $SUDO mkdir -p "$d"
    [ -e "$d/docker-compose" ] || $SUDO ln -s "$bin" "$d/docker-compose"
  done
  docker compose version >/dev/null 2>&1 || fail "docker compose still does not work"
  step "docker compose: works ($(docker compose version --short))"
fi

# ---------------------------------------------------------------- base image
if docker image inspect "$BASE_IMAGE" >/dev/null 2>&1; then
  step "base image $BASE_IMAGE: present"
elif docker pull -q "$BASE_IMAGE" >/dev/null 2>&1; then
  step "base image $BASE_IMAGE: pulled"
else
  step "base image $BASE_IMAGE: no registry; making it with debootstrap --variant=minbase (about 1-2 min)"
  dir=$(mktemp -d /tmp/rfcl-bookworm.XXXXXX)
  trap '$SUDO rm -rf "$dir"' EXIT
  t0=$(date +%s)
  $SUDO debootstrap --variant=minbase bookworm "$dir" "$MIRROR" >"$dir.log" 2>&1 \
    || { tail -20 "$dir.log" >&2; fail "debootstrap (log $dir.log)"; }
  # Like the official image: the bookworm, -updates and -security sources, and the -slim image's
  # dpkg/apt settings (no docs, man pages or translations installed; apt caches cleaned after use).
  $SUDO rm -f "$dir/etc/apt/sources.list"
  $SUDO tee "$dir/etc/apt/sources.list.d/debian.sources" >/dev/null <<EOS
Types: deb
URIs: $MIRROR
Suites: bookworm bookworm-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
URIs: ${MIRROR%/debian}/debian-security
Suites: bookworm-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOS
  $SUDO tee "$dir/etc/dpkg/dpkg.cfg.d/docker" >/dev/null <<'EOS'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/man/*
path-exclude /usr/share/groff/*
path-exclude /usr/share/info/*
path-exclude /usr/share/lintian/*
path-exclude /usr/share/linda/*
EOS
  $SUDO tee "$dir/etc/apt/apt.conf.d/docker-clean" >/dev/null <<'EOS'
DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
APT::Update::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
Dir::Cache::pkgcache "";
Dir::Cache::srcpkgcache "";
EOS
  echo 'Acquire::Languages "none";' | $SUDO tee "$dir/etc/apt/apt.conf.d/docker-no-languages" >/dev/null
  echo 'APT::AutoRemove::SuggestsImportant "false";' | $SUDO tee "$dir/etc/apt/apt.conf.d/docker-autoremove-suggests" >/dev/null
  # What debootstrap installed already is slimmed the same way.
  $SUDO rm -rf "$dir"/var/lib/apt/lists/* "$dir"/var/cache/apt/*.bin "$dir"/var/cache/apt/archives/*.deb \
    "$dir"/usr/share/man/* "$dir"/usr/share/info/* "$dir"/usr/share/locale/* "$dir"/var/log/*.log
  $SUDO find "$dir/usr/share/doc" -mindepth 1 -not -name copyright -not -type d -delete 2>/dev/null || true
  $SUDO tar -C "$dir" -c . | docker import -c 'CMD ["bash"]' - "$BASE_IMAGE" >/dev/null \
    || fail "docker import $BASE_IMAGE"
  rm -f "$dir.log"
  step "base image $BASE_IMAGE: imported in $(( $(date +%s) - t0 )) s, $(docker image inspect -f '{{.Size}}' "$BASE_IMAGE" | awk '{printf "%.0f MB", $1/1e6}')"
fi
step "docker set-up done"
