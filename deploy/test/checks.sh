# Shared by the container tests (deploy/test-compose.sh, deploy/test-multihost.sh): sourced, not run.
# Counts checks in `passed` / `failed` and prints one `ok` or `FAIL` line per check.
passed=0; failed=0
ok() { printf 'ok   %s\n' "$*"; passed=$((passed + 1)); }
bad() { printf 'FAIL %s\n' "$*"; failed=$((failed + 1)); }
step() { printf '==> %s\n' "$*"; }
# wait_for SECONDS DESCRIPTION COMMAND...: polls every 2 s until COMMAND succeeds.
wait_for() {
  local limit=$1 what=$2; shift 2
  local t0=$SECONDS
  while [ $((SECONDS - t0)) -lt "$limit" ]; do
    if "$@" >/dev/null 2>&1; then ok "$what ($((SECONDS - t0)) s)"; return 0; fi
    sleep 2
  done
  bad "$what (not within $limit s)"; return 1
}
