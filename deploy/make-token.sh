#!/usr/bin/env bash
# The one preparation step of the compose deployment: writes a fresh random run token (64 hex
# characters, 256 bits) to deploy/secrets/rfcl_token, the file docker-compose.yml hands to every
# service as the secret `rfcl_token` (RFCL_TOKEN_FILE=/run/secrets/rfcl_token). Keeps an existing
# token unless --rotate is given (rotating needs every service restarted: `docker compose up -d
# --force-recreate`). The file is gitignored.
#
# Permissions: compose (outside swarm) bind-mounts the file as it is, and the services run as the
# image's user rfcl (uid 10001), so the file is world-readable (0644) inside a directory that only
# its owner may enter (0700): other users of this host cannot reach it.
# Usage: deploy/make-token.sh [--rotate] [--out FILE]
set -euo pipefail
cd "$(dirname "$0")"
out=secrets/rfcl_token
rotate=0
while [ $# -gt 0 ]; do
  case "$1" in
    --rotate) rotate=1 ;;
    --out) out=$2; shift ;;
    -h|--help) sed -n '2,12p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "make-token: unknown argument '$1'" >&2; exit 2 ;;
  esac
  shift
done
dir=$(dirname "$out")
mkdir -p "$dir"
chmod 700 "$dir"
if [ -s "$out" ] && [ $rotate = 0 ]; then
  echo "make-token: $PWD/$out present (kept; --rotate makes a new one)"
  exit 0
fi
tmp=$(mktemp "$dir/.rfcl_token.XXXXXX")
od -An -N32 -tx1 /dev/urandom | tr -d ' \n' >"$tmp"
echo >>"$tmp"
chmod 644 "$tmp"
mv -f "$tmp" "$out"
echo "make-token: wrote a new run token to $PWD/$out"
