#!/usr/bin/env bash
# The embedded default: generate 5 PointMaze demos, then train on configs/pointmaze_test.yml (the
# small, fast PointMaze config: it reaches its eval-success bar in minutes on 2 cores; the paper-size
# preset configs/pointmaze.yml would take hours there). Extra arguments go to `rfcl train`, e.g.
# `scripts/run-default.sh --run-dir runs/mine` or a dotted override.
set -euo pipefail
cd "$(dirname "$0")/.."
RFCL=target/release/rfcl
mkdir -p runs/demos
[ -f runs/demos/pointmaze.h5 ] || $RFCL demos generate --env pointmaze -n 5 --out runs/demos/pointmaze.h5
exec $RFCL train configs/pointmaze_test.yml "train.dataset_path=$PWD/runs/demos/pointmaze.h5" "$@"
