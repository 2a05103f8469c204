#!/usr/bin/env bash
# Scaling of a containerised run: whole-run env steps/s and learner critic updates/s of
# configs/pointmaze_test.yml under deploy/docker-compose.yml with K = 1, 2, 4, 8 co-located actor
# containers (shared memory), next to the same runs under `rfcl train` (`rfcl bench e2e`). Both in
# `async` UTD mode (learner and actors flat out, as `rfcl bench e2e` measures), the same 8 train
# envs split over the K actors, 1 eval actor, the stop rule off. Each point: SECONDS of training
# after a WARMUP, rates from the learner's /metrics (compose) or metrics.csv (rfcl train).
# Loopback only; removes its compose project. Usage: benches/compose_scaling.sh [SECONDS] [WARMUP]
set -euo pipefail
cd "$(dirname "$0")/.."
SECONDS_PER_POINT=${1:-45}
WARMUP=${2:-20}
P=rfcl-bench
TMP=$(mktemp -d /tmp/rfcl-scaling.XXXXXX)
export RFCL_DASHBOARD_BIND=127.0.0.1 RFCL_DASHBOARD_PORT=18280 RFCL_GRPC_BIND=127.0.0.1 \
  RFCL_CURRICULUM_PORT=15251 RFCL_LEARNER_PORT=15252 RFCL_METRICS_PORT=19290 \
  RFCL_TOKEN_PATH=$TMP/secrets/rfcl_token RFCL_EVAL_ACTORS=1 \
  RFCL_OVERRIDES="sac.utd_mode=async train.steps=1000000000 service.stop_at_eval_success=1.0"
DC=(docker compose -p "$P" -f deploy/docker-compose.yml)
trap '"${DC[@]}" down -v --remove-orphans >/dev/null 2>&1 || true; rm -rf "$TMP"' EXIT
metric() {
  curl -fsS "http://127.0.0.1:$RFCL_METRICS_PORT/metrics" | awk -v m="rfcl_learner_$1" '$1 == m {print $2}'
}
deploy/make-token.sh --out "$RFCL_TOKEN_PATH" >/dev/null
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(date -u +%F)"
echo "compose (actor containers on shared memory):"
printf '%8s %14s %14s %10s\n' actors env_steps/s updates/s utd
for k in 1 2 4 8; do
  envs=$((8 / k)); [ "$envs" -lt 1 ] && envs=1
  "${DC[@]}" down -v --remove-orphans >/dev/null 2>&1 || true
  RFCL_ACTORS=$k RFCL_ACTOR_ARGS="--envs $envs" "${DC[@]}" up -d --quiet-pull >/dev/null 2>&1
  for _ in $(seq 60); do metric env_steps_total >/dev/null 2>&1 && break; sleep 2; done
  sleep "$WARMUP"
  s0=$(metric env_steps_total); u0=$(metric critic_updates_total); t0=$(date +%s.%N)
  sleep "$SECONDS_PER_POINT"
  s1=$(metric env_steps_total); u1=$(metric critic_updates_total); t1=$(date +%s.%N)
  python3 - "$k" "$s0" "$s1" "$u0" "$u1" "$t0" "$t1" <<'EOF'
import sys
k, s0, s1, u0, u1, t0, t1 = sys.argv[1], *map(float, sys.argv[2:])
dt = t1 - t0
steps, updates = (s1 - s0) / dt, (u1 - u0) / dt
print("%8s %14.0f %14.1f %10.2f" % (k, steps, updates, updates / steps if steps else 0))
EOF
done
"${DC[@]}" down -v --remove-orphans >/dev/null 2>&1 || true
echo "rfcl train (rfcl bench e2e, same settings):"
target/release/rfcl bench e2e --actors 1,2,4,8 --seconds "$SECONDS_PER_POINT"
