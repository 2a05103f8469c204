#!/usr/bin/env bash
# The Rust learner's SAC update against a jitted JAX/Flax implementation of the same update
# (the goal is >= 1.5x), back to back in one run, on the same cores.
#
#   benches/compare_sac.sh [--threads N] [--rounds R] [--windows W] [--seconds S]
#                          [--schedules 80/20,16/1] [--max-load 0.5] [--max-wait-s 600]
#
# Each round runs the bench binary that `cargo bench -p rfcl-learner --bench sac_update` builds,
# once per learner backend (`learner.backend`: libtorch, fused), and then, right after them,
# benches/jax_sac_update.py (same shapes: obs 42, act 8, batch 256, hidden 256x3, 10 critics, min
# over 2 drawn members; best of W windows of S seconds per schedule), both pinned to the first N
# cores with taskset and with N compute threads. Before each round it waits (up to --max-wait-s)
# for the 1-minute load average to drop below --max-load, because other processes on a 2-core
# machine make either side several times slower; the load seen at each start is in the output.
# OMP_WAIT_POLICY defaults to PASSIVE, as `rfcl train` starts the learner; pass
# OMP_WAIT_POLICY=ACTIVE for libgomp's spinning (it suits per-op threads, not ensemble members).
#
# Needs: the venv with python/requirements-bench.txt (jax, flax, optax). Prints one JSON object:
# every run's report, the loads, and per round and schedule the ratio rust / jax.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck source=benches/lib.sh
source benches/lib.sh

threads=$(nproc)
rounds=2
windows=3
seconds=5
schedules=80/20,16/1
max_load=0.5
max_wait_s=600
parse_flags "$0" threads rounds windows seconds schedules max_load max_wait_s -- "$@"
if [[ ! -x .venv/bin/python ]]; then
    echo "compare_sac.sh: .venv is missing (scripts/setup.sh creates it)" >&2; exit 1
fi
if ! .venv/bin/python -c "import jax, flax, optax" 2>/dev/null; then
    echo "compare_sac.sh: jax/flax/optax missing: .venv/bin/pip install -r python/requirements-bench.txt" >&2
    exit 1
fi
# shellcheck disable=SC1091
source .venv/bin/activate
export LIBTORCH_USE_PYTORCH=1 PYO3_PYTHON=$PWD/.venv/bin/python
# The learner's default parallelism runs critic members on their own threads; a spinning OpenMP
# team then takes the core another member needs (members: 0.52-0.59x JAX under ACTIVE, 0.85-0.88x
# under PASSIVE, benches/RESULTS.md). Per-op threads are the other way round.
export OMP_WAIT_POLICY=${OMP_WAIT_POLICY:-PASSIVE}
cores="0-$((threads - 1))"
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT

echo "building the Rust bench (not timed) ..." >&2
bench_bin=$(cargo bench -q -p rfcl-learner --bench sac_update --no-run --message-format=json |
    python -c 'import json, sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m["target"]["name"] == "sac_update" and m.get("executable"):
        print(m["executable"])')
[[ -x "$bench_bin" ]] || { echo "compare_sac.sh: the sac_update bench did not build" >&2; exit 1; }
# What was built: the commit and how many files differed from it.
git_head=$(git rev-parse --short HEAD 2>/dev/null || echo unknown)
git_dirty=$(git status --porcelain 2>/dev/null | grep -c . || true)

load1() { cut -d' ' -f1 /proc/loadavg; }
wait_quiet() {
    local waited=0
    while awk -v l="$(load1)" -v m="$max_load" 'BEGIN { exit !(l >= m) }'; do
        if (( waited >= max_wait_s )); then
            echo "load $(load1) still >= $max_load after ${max_wait_s}s: measuring anyway" >&2
            break
        fi
        sleep 10; waited=$((waited + 10))
    done
    load1
}

for round in $(seq 1 "$rounds"); do
    load=$(wait_quiet)
    echo "round $round: rust (load $load) ..." >&2
    echo "$load" > "$out/rust_$round.load"
    for backend in libtorch fused; do
        RFCL_BENCH_THREADS=$threads RFCL_BENCH_WINDOWS=$windows RFCL_BENCH_SECONDS=$seconds \
        RFCL_BENCH_SCHEDULES=$schedules RFCL_BENCH_BACKEND=$backend \
            taskset -c "$cores" "$bench_bin" --bench > "$out/rust_${backend}_$round.json"
    done
    load=$(load1)
    echo "round $round: jax (load $load) ..." >&2
    echo "$load" > "$out/jax_$round.load"
    taskset -c "$cores" python benches/jax_sac_update.py --threads "$threads" --windows "$windows" \
        --window-seconds "$seconds" --schedules "$schedules" > "$out/jax_$round.json"
done

python - "$out" "$rounds" "$bench_bin" "$git_head" "$git_dirty" <<'EOF'
import json, os, platform, sys, time
out, rounds = sys.argv[1], int(sys.argv[2])
bench_bin, git_head, git_dirty = sys.argv[3], sys.argv[4], int(sys.argv[5])
def read(name):
    with open(os.path.join(out, name)) as f:
        return f.read()
cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), "?")
runs, ratios = [], []
for r in range(1, rounds + 1):
    jax = json.loads(read(f"jax_{r}.json"))
    rusts = {b: json.loads(read(f"rust_{b}_{r}.json")) for b in ("libtorch", "fused")}
    runs.append(dict(round=r, rust_load=float(read(f"rust_{r}.load")), jax_load=float(read(f"jax_{r}.load")),
                     rust=rusts, jax=jax))
    for backend, rust in rusts.items():
        # The Rust bench measures the machine's fp32 matmul peak (a 1024^3 GEMM in libtorch).
        peak = rust.get("matmul_peak_gflop_per_s")
        for a, b in zip(rust["results"], jax["results"]):
            ratios.append(dict(round=r, backend=backend, schedule=a["schedule"],
                               rust_updates_per_s=a["updates_per_s"],
                               jax_updates_per_s=b["updates_per_s"], ratio=a["updates_per_s"] / b["updates_per_s"],
                               rust_gflop_per_s=a["gflop_per_s"], jax_gflop_per_s=b["gflop_per_s"],
                               matmul_peak_gflop_per_s=peak,
                               jax_fraction_of_peak=b["gflop_per_s"] / peak if peak else None,
                               rust_fraction_of_peak=a["gflop_per_s"] / peak if peak else None))
print(json.dumps(dict(
    date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    machine=f"{cpu}, {os.cpu_count()} cores, {platform.node()}",
    omp_wait_policy=os.environ.get("OMP_WAIT_POLICY"),
    rust_bench=bench_bin, git_head=git_head, git_changed_files=git_dirty,
    summary=ratios, runs=runs), indent=2))
EOF
