#!/usr/bin/env bash
# End-to-end check of deploy/docker-compose.yml on this host, bounded in time (about 3-5 min on 2
# cores) and on loopback only: builds the images, starts the stack as its own compose project
# (rfcl-test, its own volumes, ports 18080/15005x/19090 on 127.0.0.1), then checks that
#   1. demos are generated, the servers become healthy (rfcl-health), the actors connect;
#   2. the co-located actors took shared memory (their log says which transport and why);
#   3. the dashboard answers on the published port, shows env steps growing, and its learner panel
#      polls the learner's Health across the compose network (learner --advertise);
#   4. a wrong token is refused; a killed actor process (kill -9, a crash) is brought back by the
#      restart policy;
#   5. `down` then `up` resumes the run (the curriculum server logs the resume, the learner's env
#      steps do not restart from 0);
# and removes the project (down -v) at the end, whatever happened.
# Usage: deploy/test-compose.sh [--keep]   (--keep leaves the stack running for a look)
# Run by scripts/test.sh when RFCL_TEST_DOCKER=1.
set -euo pipefail
cd "$(dirname "$0")/.."
KEEP=0; [ "${1:-}" = --keep ] && KEEP=1
P=rfcl-test
TMP=$(mktemp -d /tmp/rfcl-compose-test.XXXXXX)
export RFCL_DASHBOARD_BIND=127.0.0.1 RFCL_DASHBOARD_PORT=18080 RFCL_GRPC_BIND=127.0.0.1 \
  RFCL_CURRICULUM_PORT=15051 RFCL_LEARNER_PORT=15052 RFCL_METRICS_PORT=19090 \
  RFCL_TOKEN_PATH=$TMP/secrets/rfcl_token RFCL_ACTORS=2 RFCL_EVAL_ACTORS=1
DC=(docker compose -p "$P" -f deploy/docker-compose.yml)
# shellcheck source=deploy/test/checks.sh
. deploy/test/checks.sh
cleanup() {
  if [ $failed -gt 0 ]; then
    step "logs (last 15 lines per service)"
    "${DC[@]}" logs --no-color --tail 15 2>&1 | sed 's/^/    /' || true
  fi
  if [ $KEEP = 0 ]; then "${DC[@]}" down -v --remove-orphans >/dev/null 2>&1 || true; fi
  rm -rf "$TMP"
}
trap cleanup EXIT
env_steps() {
  curl -fsS "http://127.0.0.1:$RFCL_DASHBOARD_PORT/api/state" 2>/dev/null \
    | python3 -c 'import json,sys; s=json.load(sys.stdin); print(int(s["env_steps"]))' 2>/dev/null
}
steps_above() { local n; n=$(env_steps) && [ "${n:-0}" -gt "$1" ]; }
healthy() { [ "$(docker inspect -f '{{.State.Health.Status}}' "$P-$1-1" 2>/dev/null)" = healthy ]; }
# Logs into a variable first: `compose logs | grep -q` would fail under pipefail (SIGPIPE).
logs_of() { "${DC[@]}" logs --no-color "$@" 2>&1 || true; }
actor_logged() { local l; l=$(logs_of actor); grep -q "$1" <<<"$l"; }
shm_records() {
  curl -fsS "http://127.0.0.1:$RFCL_METRICS_PORT/metrics" 2>/dev/null \
    | sed -n 's/^rfcl_learner_ingest_records_total{transport="shm"} \([0-9]*\).*/\1/p'
}
shm_flowing() { local n; n=$(shm_records) && [ "${n:-0}" -gt 0 ]; }
# The dashboard's learner panel has an answer from http://learner:50052 with updates running.
learner_panel() {
  curl -fsS "http://127.0.0.1:$RFCL_DASHBOARD_PORT/api/state" 2>/dev/null | python3 -c '
import json, sys
p = json.load(sys.stdin).get("learner") or {}
w = p.get("window") or {}
ok = p.get("address") == "http://learner:50052" and p.get("error") is None \
    and p.get("seconds_since_answer") is not None and w.get("updates_per_s", 0) > 0
sys.exit(0 if ok else 1)' 2>/dev/null
}
# The eval-actor container records its first evaluation's first episode and sends it to the
# curriculum server over gRPC; the dashboard lists it and serves the GIF from the runs volume.
eval_video() {
  local url
  url=$(curl -fsS "http://127.0.0.1:$RFCL_DASHBOARD_PORT/api/state" 2>/dev/null | python3 -c '
import json, sys
v = json.load(sys.stdin).get("videos") or []
sys.exit(1) if not v else print(v[0]["url"])' 2>/dev/null) || return 1
  curl -fsS -o "$TMP/eval_video.gif" "http://127.0.0.1:$RFCL_DASHBOARD_PORT$url" 2>/dev/null || return 1
  [ "$(head -c 6 "$TMP/eval_video.gif")" = GIF89a ]
}

step "docker, images, token"
deploy/setup-docker.sh | sed 's/^/    /'
deploy/build-images.sh | sed 's/^/    /'
deploy/make-token.sh --out "$TMP/secrets/rfcl_token" | sed 's/^/    /'
"${DC[@]}" down -v --remove-orphans >/dev/null 2>&1 || true

step "up (project $P)"
"${DC[@]}" up -d --quiet-pull 2>&1 | sed 's/^/    /'
wait_for 120 "curriculum-server healthy" healthy curriculum-server
wait_for 180 "learner healthy" healthy learner
wait_for 60 "actors connected" actor_logged "connected to the"
logs=$(logs_of actor)
if grep -q "transport: shared memory" <<<"$logs" && ! grep -q "transport: gRPC" <<<"$logs"; then
  ok "actors on shared memory: $(grep -m1 -o 'transport: shared memory ([^)]*)' <<<"$logs")"
else
  bad "actors did not all take shared memory: $(grep -o 'transport: .*' <<<"$logs" | sort | uniq -c | tr '\n' ' ')"
fi
wait_for 60 "the learner takes records over shared memory (its /metrics)" shm_flowing
wait_for 60 "dashboard answers on 127.0.0.1:$RFCL_DASHBOARD_PORT" \
  curl -fsS -o /dev/null "http://127.0.0.1:$RFCL_DASHBOARD_PORT/"
wait_for 120 "env steps growing on the dashboard (> 2000)" steps_above 2000
wait_for 60 "the dashboard's learner panel polls http://learner:50052 (updates/s > 0)" learner_panel
wait_for 180 "an eval video from the eval-actor container, served by the dashboard" eval_video

step "a wrong token is refused"
out=$(docker run --rm --network "${P}_default" -e RFCL_TOKEN=not-the-run-token-0123456789 -e NO_COLOR=1 \
  rfcl:local actor --connect http://learner:50052 --retry-for 2 2>&1) && rc=0 || rc=$?
if [ $rc != 0 ] && grep -q "wrong run token" <<<"$out"; then
  ok "an actor with a wrong token exits $rc: $(grep -o 'missing or wrong run token' <<<"$out" | head -1)"
else
  bad "an actor with a wrong token: exit $rc, $(tail -1 <<<"$out")"
fi

step "crash an actor (kill -9 of its process)"
c=$P-actor-1
before=$(docker inspect -f '{{.RestartCount}}' "$c")
kill -9 "$(docker inspect -f '{{.State.Pid}}' "$c")"
restarted() { [ "$(docker inspect -f '{{.RestartCount}} {{.State.Running}}' "$c")" = "$((before + 1)) true" ]; }
wait_for 30 "$c restarted by the restart policy" restarted

step "down, then up again: the run resumes"
steps_before=$(env_steps || echo 0)
"${DC[@]}" down 2>&1 | sed 's/^/    /'
"${DC[@]}" up -d 2>&1 | sed 's/^/    /'
wait_for 120 "curriculum-server healthy again" healthy curriculum-server
resumed() { local l; l=$(logs_of curriculum-server); grep -q "resumed the curriculum" <<<"$l"; }
learner_resumed() { local l; l=$(logs_of learner); grep -q "resumed from checkpoint" <<<"$l"; }
wait_for 10 "curriculum-server resumed from its snapshot" resumed
wait_for 180 "learner healthy again" healthy learner
wait_for 10 "learner resumed from its checkpoint (written on SIGTERM at down)" learner_resumed
n=$(env_steps || echo 0)
if [ "${n:-0}" -ge "$((steps_before / 2))" ] && [ "${steps_before:-0}" -gt 0 ]; then
  ok "env steps after resume: $n (before down: $steps_before)"
else
  bad "env steps after resume: $n (before down: $steps_before)"
fi

step "result"
echo "compose: $passed passed, $failed failed"
[ $failed = 0 ]
