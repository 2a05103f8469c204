#!/usr/bin/env bash
# The embedded default: generate PointMaze demos, then train on configs/pointmaze.yml.
set -euo pipefail
cd "$(dirname "$0")/.."
RFCL=target/release/rfcl
mkdir -p runs/demos
[ -f runs/demos/pointmaze.h5 ] || $RFCL demos generate --env pointmaze -n 5 --out runs/demos/pointmaze.h5
exec $RFCL train configs/pointmaze.yml "train.dataset_path=$PWD/runs/demos/pointmaze.h5" "$@"
