#!/usr/bin/env bash
# The multi-host tests: the servers (demos, curriculum server, learner) in their containers from
# deploy/docker-compose.yml, the actors in containers of their own (deploy/docker-compose.remote.yml)
# on the servers' private Docker network, so every transition, lease and report crosses a network
# over gRPC, as from another host. One PointMaze run (configs/pointmaze_test.yml: 0.9 eval success
# over the last 5 evals ends it) goes through, in order:
#   (e) an actor with a wrong token is refused, counted by the learner, and changes nothing;
#   (b) an actor container is killed (docker kill): its leases expire and are counted;
#   (c) another actor is cut off (docker network disconnect) for 30 s, then reconnected: it comes
#       back by itself (no restart), its leases expire and are counted, its late reports are
#       refused, not counted twice;
#   (d) the learner's process is killed (kill -9): the restart policy brings the container back and
#       the learner resumes from its checkpoint by itself; the actors reconnect by themselves;
#   (a) the run reaches its bar: the curriculum server ends the run (stop rule), the learner exits 0.
# Loopback and Docker's own networks only. About 6-10 min on 2 cores. Removes everything it made
# (down -v) at the end, whatever happened; --keep leaves it running for a look.
# Usage: deploy/test-multihost.sh [--keep] [--no-build]
set -euo pipefail
cd "$(dirname "$0")/.."
KEEP=0; BUILD=1
for arg in "$@"; do
  case "$arg" in
    --keep) KEEP=1 ;;
    --no-build) BUILD=0 ;;
    *) echo "test-multihost: unknown argument '$arg'" >&2; exit 2 ;;
  esac
done
P=rfcl-mh
PA=rfcl-mh-actors
TMP=$(mktemp -d /tmp/rfcl-multihost-test.XXXXXX)
export RFCL_DASHBOARD_BIND=127.0.0.1 RFCL_DASHBOARD_PORT=18180 RFCL_GRPC_BIND=127.0.0.1 \
  RFCL_CURRICULUM_PORT=15151 RFCL_LEARNER_PORT=15152 RFCL_METRICS_PORT=19190 \
  RFCL_TOKEN_PATH=$TMP/secrets/rfcl_token NO_COLOR=1 \
  RFCL_OVERRIDES="sac.save_freq=10000 service.lease_timeout_s=10"
export RFCL_TEST_NETWORK=${P}_default RFCL_LEARNER=learner:50052 \
  RFCL_CURRICULUM=curriculum-server:50051 RFCL_ACTORS=2 RFCL_EVAL_ACTORS=1 \
  RFCL_ACTOR_ARGS="--retry-for 120" RFCL_EVAL_ACTOR_ARGS="--retry-for 120"
SERVERS=(docker compose -p "$P" -f deploy/docker-compose.yml)
ACTORS=(docker compose -p "$PA" -f deploy/docker-compose.remote.yml -f deploy/test/actors-on-network.yml)
# shellcheck source=deploy/test/checks.sh
. deploy/test/checks.sh
cleanup() {
  if [ $failed -gt 0 ]; then
    step "logs (last 20 lines per service)"
    "${SERVERS[@]}" logs --no-color --tail 20 2>&1 | sed 's/^/    /' || true
    "${ACTORS[@]}" logs --no-color --tail 20 2>&1 | sed 's/^/    /' || true
  fi
  if [ $KEEP = 0 ]; then
    "${ACTORS[@]}" down -v --remove-orphans >/dev/null 2>&1 || true
    "${SERVERS[@]}" down -v --remove-orphans >/dev/null 2>&1 || true
  fi
  rm -rf "$TMP"
}
trap cleanup EXIT
# state FIELD: a number (or true/false) from the dashboard's /api/state, e.g. state env_steps,
# state refused_reports.expired.
state() {
  curl -fsS "http://127.0.0.1:$RFCL_DASHBOARD_PORT/api/state" 2>/dev/null | python3 -c '
import json, sys
v = json.load(sys.stdin)
for k in sys.argv[1].split("."):
    v = v[k]
print(str(v).lower() if isinstance(v, bool) else v)' "$1"
}
above() { local n; n=$(state "$1") && [ "${n:-0}" -gt "$2" ]; }
finished() { [ "$(state finished)" = true ]; }
learner_metric() {
  curl -fsS "http://127.0.0.1:$RFCL_METRICS_PORT/metrics" 2>/dev/null \
    | awk -v m="rfcl_learner_$1" '$1 == m {print $2}'
}
healthy() { [ "$(docker inspect -f '{{.State.Health.Status}}' "$P-$1-1" 2>/dev/null)" = healthy ]; }
logs_of() { docker logs "$1" 2>&1; }
logged() { logs_of "$1" | grep -q "$2"; }

step "docker, images, token"
if ! deploy/setup-docker.sh >"$TMP/setup.log" 2>&1; then
  cat "$TMP/setup.log"
  echo "test-multihost: no Docker daemon could be started (deploy/setup-docker.sh above): these tests need one" >&2
  echo "multihost: 0 passed, 1 failed"
  exit 1
fi
sed 's/^/    /' "$TMP/setup.log"
[ $BUILD = 1 ] && deploy/build-images.sh | sed 's/^/    /'
deploy/make-token.sh --out "$RFCL_TOKEN_PATH" | sed 's/^/    /'
"${ACTORS[@]}" down -v --remove-orphans >/dev/null 2>&1 || true
"${SERVERS[@]}" down -v --remove-orphans >/dev/null 2>&1 || true

step "servers up (project $P), actors up on its network (project $PA)"
"${SERVERS[@]}" up -d --quiet-pull demos curriculum-server learner 2>&1 | sed 's/^/    /'
wait_for 180 "curriculum-server healthy" healthy curriculum-server
wait_for 240 "learner healthy" healthy learner
"${ACTORS[@]}" up -d --quiet-pull 2>&1 | sed 's/^/    /'
A1=$PA-actor-1 A2=$PA-actor-2
wait_for 60 "actor 1 connected" logged "$A1" "connected to the"
if logged "$A1" "transport: gRPC"; then
  ok "actors use gRPC across the network: $(logs_of "$A1" | grep -m1 -o 'transport: gRPC.*')"
else
  bad "actor 1 did not choose gRPC: $(logs_of "$A1" | grep -m1 -o 'transport: .*' || echo 'no transport line')"
fi
wait_for 60 "dashboard answers on 127.0.0.1:$RFCL_DASHBOARD_PORT" \
  curl -fsS -o /dev/null "http://127.0.0.1:$RFCL_DASHBOARD_PORT/"
wait_for 180 "env steps growing (> 3000)" above env_steps 3000

step "(e) an actor with a wrong token"
refused_before=$(learner_metric unauthenticated_calls_total || echo 0)
episodes_before=$(state episodes)
out=$(docker run --rm --network "$RFCL_TEST_NETWORK" -e RFCL_TOKEN=not-the-run-token-0123456789 \
  -e NO_COLOR=1 rfcl:local actor --connect http://learner:50052 --curriculum \
  http://curriculum-server:50051 --retry-for 2 2>&1) && rc=0 || rc=$?
if [ $rc != 0 ] && grep -q "missing or wrong run token" <<<"$out"; then
  ok "refused: exit $rc, $(grep -m1 -o 'Unauthenticated.*token' <<<"$out" || grep -m1 'token' <<<"$out")"
else
  bad "an actor with a wrong token: exit $rc, $(tail -1 <<<"$out")"
fi
refused_after=$(learner_metric unauthenticated_calls_total || echo 0)
if [ "${refused_after:-0}" -gt "${refused_before:-0}" ]; then
  ok "the learner counted the refused call ($refused_before -> $refused_after)"
else
  bad "the learner's unauthenticated_calls did not grow ($refused_before -> $refused_after)"
fi
[ "$(state unauthenticated_calls)" = 0 ] && ok "the curriculum server saw no call from it" \
  || bad "the curriculum server counted $(state unauthenticated_calls) unauthenticated calls"
[ "$(state episodes)" -ge "$episodes_before" ] && ok "episodes still counted by the good actors"

step "(b) docker kill of actor 2 mid-run"
expired_before=$(state expired_leases)
docker kill "$A2" >/dev/null
wait_for 60 "its leases expire and are counted (expired_leases > $expired_before)" \
  above expired_leases "$expired_before"
steps=$(state env_steps)
wait_for 120 "training goes on without it (env steps > $steps)" above env_steps "$steps"

step "(c) actor 1 cut off the network for 30 s"
expired_before=$(state expired_leases)
restarts_before=$(docker inspect -f '{{.RestartCount}}' "$A1")
docker network disconnect "$RFCL_TEST_NETWORK" "$A1"
sleep 30
docker network connect "$RFCL_TEST_NETWORK" "$A1"
wait_for 10 "its leases expired while it was away (expired_leases > $expired_before)" \
  above expired_leases "$expired_before"
wait_for 90 "it reconnected by itself" logged "$A1" "reachable again"
if [ "$(docker inspect -f '{{.RestartCount}} {{.State.Running}}' "$A1")" = "$restarts_before true" ]; then
  ok "same process, no restart (restart count $restarts_before)"
else
  bad "actor 1 was restarted or stopped: $(docker inspect -f '{{.RestartCount}} {{.State.Status}}' "$A1")"
fi
steps=$(state env_steps)
wait_for 120 "its transitions arrive again (env steps > $steps)" above env_steps "$steps"
echo "    refused reports: $(curl -fsS "http://127.0.0.1:$RFCL_DASHBOARD_PORT/api/state" | python3 -c 'import json,sys; print(json.load(sys.stdin)["refused_reports"])')"
if above refused_reports.expired 0 || above refused_reports.unknown 0; then
  ok "its late reports of expired leases were refused, not counted twice"
else
  ok "it reported no expired lease late (none to refuse)"
fi

step "(d) kill -9 of the learner's process"
wait_for 300 "a learner checkpoint exists (env steps > 12000; sac.save_freq=10000)" above env_steps 12000
learner=$P-learner-1
restarts_before=$(docker inspect -f '{{.RestartCount}}' "$learner")
kill -9 "$(docker inspect -f '{{.State.Pid}}' "$learner")"
restarted() { [ "$(docker inspect -f '{{.RestartCount}}' "$learner")" -gt "$restarts_before" ]; }
wait_for 60 "the restart policy brought the learner back" restarted
wait_for 240 "learner healthy again" healthy learner
wait_for 10 "it resumed from its checkpoint by itself" logged "$learner" "found a learner checkpoint"
steps=$(learner_metric env_steps_total || echo 0)
grows() { local n; n=$(learner_metric env_steps_total) && [ "${n%.*}" -gt "${steps%.*}" ]; }
wait_for 180 "the actors reconnected by themselves (learner env steps > ${steps%.*})" grows

step "(a) the run reaches its bar"
wait_for 1200 "the curriculum server ended the run (stop rule: last 5 evals >= 0.9)" finished
curl -fsS "http://127.0.0.1:$RFCL_DASHBOARD_PORT/api/state" | python3 -c '
import json, sys
s = json.load(sys.stdin)
ev = [e for e in s["evals"] if e["episodes"] >= 34]
ev.sort(key=lambda e: e["env_steps"])
print("    env steps %d, expired leases %d, refused reports %s, last evals %s" % (
    s["env_steps"], s["expired_leases"], s["refused_reports"],
    [round(e["success_at_end"], 2) for e in ev[-5:]]))'
exited_ok() { [ "$(docker inspect -f '{{.State.Status}} {{.State.ExitCode}}' "$learner")" = "exited 0" ]; }
wait_for 120 "the learner wrote its final checkpoint and exited 0" exited_ok

step "result"
echo "multihost: $passed passed, $failed failed"
[ $failed = 0 ]
