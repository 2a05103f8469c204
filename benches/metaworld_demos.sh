#!/usr/bin/env bash
# Every MetaWorld task with a preset (configs/metaworld/*.yml): one scripted demo generated with
# `rfcl demos generate --env metaworld/<task> -n N` and checked with `rfcl demos inspect --replay
# --config <its preset>`. Prints one table row per task and exits 1 when any task fails.
# Usage: benches/metaworld_demos.sh [-n N] [--out DIR]   (results: benches/RESULTS.md)
set -euo pipefail
cd "$(dirname "$0")/.."
N=1; OUT=$(mktemp -d)
while [ $# -gt 0 ]; do
  case "$1" in
    -n) N=$2; shift 2 ;;
    --out) OUT=$2; shift 2 ;;
    *) echo "metaworld_demos: unknown argument '$1' (expected -n N or --out DIR)" >&2; exit 2 ;;
  esac
done
RFCL=${RFCL:-target/release/rfcl}
[ -x "$RFCL" ] || { echo "metaworld_demos: $RFCL not built (make setup)" >&2; exit 2; }
mkdir -p "$OUT"
echo "| task | preset | generated | replay check | seconds |"
echo "|---|---|---|---|---|"
failed=0
for preset in configs/metaworld/*.yml; do
  case "$preset" in *_sample_efficient.yml) continue ;; esac
  task=$(awk '/^  env_id:/ {print $2}' "$preset")
  file="$OUT/$task.h5"
  start=$(date +%s)
  if "$RFCL" demos generate --env "metaworld/$task" -n "$N" --out "$file" >"$OUT/$task.generate.log" 2>&1; then
    generated="$N"
    if "$RFCL" demos inspect "$file" --replay --config "$preset" >"$OUT/$task.replay.log" 2>&1; then
      check=$(grep -o '[0-9]* of [0-9]* demos pass' "$OUT/$task.replay.log")
    else
      check="FAILED: $(grep -m1 -o 'FAILED: .*' "$OUT/$task.replay.log" || tail -1 "$OUT/$task.replay.log")"
      failed=1
    fi
  else
    generated="FAILED: $(tail -1 "$OUT/$task.generate.log")"; check="-"; failed=1
  fi
  echo "| $task | $(basename "$preset") | $generated | $check | $(( $(date +%s) - start )) |"
done
echo "logs and demo files: $OUT"
exit $failed
