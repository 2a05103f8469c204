#!/usr/bin/env bash
# A deliberately bad demo on PointMaze: what `rfcl demos select` buys in env steps to the run's bar.
#
#   benches/bad_demo.sh [--seeds 1,2] [--steps 300000] [--demos FILE] [--out DIR]
#
# The 5 demos of FILE (generated if absent) with the shortest one made bad: the first half of its
# states carry the collided flag, as if recorded after the point had hit a hazard wall. An episode
# started there earns nothing (docs/POINTMAZE.md), so that demo's frontier stalls where
# its valid states end and every stage-1 episode the curriculum spends on it is wasted; its recorded
# observations and actions (the learner's offline data) stay intact. Then, per seed, one after
# another, what a user would type:
#   target/release/rfcl train --run-dir DIR/bad-sN configs/pointmaze_test.yml \
#       train.dataset_path=DIR/bad.h5 seed=N train.steps=STEPS
#   target/release/rfcl demos select DIR/bad.h5 --run DIR/bad-s<first seed> --out DIR/selected.h5
#   target/release/rfcl train --run-dir DIR/selected-sN configs/pointmaze_test.yml \
#       train.dataset_path=DIR/selected.h5 train.num_demos=<kept> seed=N train.steps=STEPS
# The bar is the config's own stop: the mean eval success of the last 5 evaluations reaches 0.9
# (service.stop_at_eval_success). Runs with a summary.json are kept (rerun to resume the table).
# Prints a Markdown table per run and the mean over seeds.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck source=benches/lib.sh
source benches/lib.sh

seeds=1,2
steps=300000
demos=runs/demos/pointmaze.h5
out=runs/bad_demo
parse_flags "$0" seeds steps demos out -- "$@"

need_rfcl "$0"
python=python3
[[ -x .venv/bin/python ]] && python=.venv/bin/python
demos_or_generate pointmaze "$demos"
mkdir -p "$out"

if [[ ! -f $out/bad.h5 ]]; then
    cp "$demos" "$out/bad.h5.tmp"
    "$python" - "$out/bad.h5.tmp" <<'PY'
import sys
import h5py
with h5py.File(sys.argv[1], "r+") as f:
    name = min((k for k in f if k.startswith("traj_")), key=lambda k: len(f[k]["actions"]))
    collided = f[name]["env_states"]["collided"]
    half = (collided.shape[0] + 1) // 2
    collided[:half] = 1.0
    print(f"made {name} bad: states 0..{half - 1} of {collided.shape[0]} marked collided", file=sys.stderr)
PY
    mv "$out/bad.h5.tmp" "$out/bad.h5"
fi

first_seed=${seeds%%,*}
train() { # set seed extra...
    local set=$1 seed=$2
    shift 2
    train_once "$set seed $seed" "$out/$set-s$seed" configs/pointmaze_test.yml \
        "train.dataset_path=$out/$set.h5" "seed=$seed" "train.steps=$steps" "$@"
}

for seed in ${seeds//,/ }; do
    train bad "$seed"
done
if [[ ! -f $out/selected.h5 ]]; then
    "$rfcl" demos select "$out/bad.h5" --run "$out/bad-s$first_seed" --out "$out/selected.h5" \
        | tee "$out/select.txt"
fi
kept=$("$python" -c 'import h5py, sys; print(sum(k.startswith("traj_") for k in h5py.File(sys.argv[1], "r")))' "$out/selected.h5")
for seed in ${seeds//,/ }; do
    train selected "$seed" "train.num_demos=$kept"
done

"$python" - "$out" "$seeds" <<'PY'
import json, sys
from pathlib import Path
out, seeds = Path(sys.argv[1]), sys.argv[2].split(",")

def at_bar(evals, bar=0.9, window=5):
    """Env steps when the mean of the last `window` evals first reaches `bar` (the run's stop)."""
    for i in range(window - 1, len(evals)):
        if sum(e["success_at_end"] for e in evals[i - window + 1 : i + 1]) / window >= bar:
            return evals[i]["env_steps"]
    return None

reached = lambda v: f"{v:,}" if v is not None else "not reached"
ended = lambda v: f"{v:,}" if v is not None else "not ended"
print("| demos | seed | first eval ≥ 50 % / ≥ 90 % | bar: mean of last 5 evals ≥ 90 % | stage 1 ended | stalled (share of stage-1 episodes) | ended |")
print("|---|---|---|---|---|---|---|")
bars = {}
for set_ in ["bad", "selected"]:
    for s in seeds:
        path = out / f"{set_}-s{s}" / "summary.json"
        if not path.exists():
            continue
        summary = json.loads(path.read_text())
        # The summary's first eval at each threshold; the bar (its stop rule) is computed here.
        first = {t["threshold"]: t["env_steps"] for t in summary["to_success"]}
        bar = at_bar(summary["evals"])
        bars.setdefault(set_, []).append(bar)
        stalled = [f"episode {d['episode_id']} at state {d['t']} ({d['difficulty']['episode_share']:.2f})"
                   for d in summary.get("demos", []) if d["difficulty"]["stalled"]]
        label = "5 (one bad)" if set_ == "bad" else "selected"
        print(f"| {label} | {s} | {reached(first.get(0.5))} / {reached(first.get(0.9))} | {reached(bar)} "
              f"| {ended(summary.get('stage_1_env_steps'))} | {', '.join(stalled) or '-'} "
              f"| {summary['ending']} at {summary['env_steps']:,} |")
for set_, values in bars.items():
    reached = [v for v in values if v is not None]
    mean = f"{sum(reached) / len(reached):,.0f}" if reached else "-"
    print(f"\n{set_}: the bar reached in {len(reached)} of {len(values)} runs, mean {mean} env steps")
PY
