#!/usr/bin/env bash
# RLPD and RFCL side by side on PointMaze: the same demos, agent (configs/pointmaze_test.yml's small
# one), schedule and env-step budget; only `train.mode` differs (configs/baselines/
# pointmaze_test_rlpd.yml). S seeds per method, one run after another, the eval-success stop off.
#
#   benches/rlpd_vs_rfcl.sh [--seeds 1,2,3] [--steps 150000] [--demos FILE] [--out DIR]
#
# Each run is what a user would type:
#   target/release/rfcl train --run-dir DIR/<method>-sN CONFIG train.dataset_path=FILE seed=N \
#       train.steps=STEPS service.stop_at_eval_success=null
# Runs with a summary.json are kept (rerun to resume the table). Prints a Markdown table of eval
# success (the mean over seeds, and each seed) at every 10,000 env steps and writes both curves to
# DIR/rlpd_vs_rfcl.svg (matplotlib from the project's .venv).
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck source=benches/lib.sh
source benches/lib.sh

seeds=1,2,3
steps=150000
demos=runs/demos/pointmaze.h5
out=runs/rlpd_vs_rfcl
parse_flags "$0" seeds steps demos out -- "$@"

need_rfcl "$0"
demos_or_generate pointmaze "$demos"

declare -A config=(
    [rfcl]=configs/pointmaze_test.yml
    [rlpd]=configs/baselines/pointmaze_test_rlpd.yml
)
mkdir -p "$out"
for seed in ${seeds//,/ }; do
    for method in rfcl rlpd; do
        train_once "$method seed $seed" "$out/$method-s$seed" "${config[$method]}" \
            "train.dataset_path=$demos" "seed=$seed" "train.steps=$steps" \
            service.stop_at_eval_success=null
    done
done

python=python3
[[ -x .venv/bin/python ]] && python=.venv/bin/python
"$python" - "$out" "$seeds" "$steps" <<'PY'
import json, sys
from pathlib import Path
out, seeds, budget = Path(sys.argv[1]), sys.argv[2].split(","), int(sys.argv[3])
methods = ["rfcl", "rlpd"]
grid = list(range(10_000, budget + 1, 10_000))

def curve(method, seed):
    """Eval success at the end, per eval, as (env steps, success)."""
    path = out / f"{method}-s{seed}" / "summary.json"
    if not path.exists():
        return None
    return [(e["env_steps"], e["success_at_end"]) for e in json.loads(path.read_text())["evals"]]

def at(points, x):
    """The latest eval at or before x env steps (an eval lands a few steps past each multiple)."""
    before = [s for steps, s in points if steps <= x + 100]
    return before[-1] if before else None

curves = {(m, s): curve(m, s) for m in methods for s in seeds}
print("| env steps | " + " | ".join(f"{m.upper()} mean (seeds {', '.join(seeds)})" for m in methods) + " |")
print("|---|" + "---|" * len(methods))
means = {m: [] for m in methods}
for x in grid:
    cells = []
    for m in methods:
        vals = [at(curves[(m, s)], x) for s in seeds if curves[(m, s)]]
        vals = [v for v in vals if v is not None]
        mean = sum(vals) / len(vals) if vals else None
        means[m].append(mean)
        per_seed = " / ".join(f"{v:.2f}" for v in vals)
        cells.append(f"{mean:.2f} ({per_seed})" if mean is not None else "-")
    print(f"| {x:,} | " + " | ".join(cells) + " |")
for m in methods:
    firsts = []
    for s in seeds:
        pts = curves[(m, s)] or []
        hit = next((steps for steps, v in pts if v >= 0.9), None)
        firsts.append(f"{hit:,}" if hit is not None else "not reached")
    print(f"\n{m.upper()}: first eval ≥ 90 % at " + ", ".join(firsts) + " env steps (seeds " + ", ".join(seeds) + ")")

import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
sys.path.insert(0, "benches")  # the script runs from the repository root
from plot_style import finish_success_plot
fig, ax = plt.subplots(figsize=(7, 3.6))
for m, colour in zip(methods, ["tab:blue", "tab:orange"]):
    for s in seeds:
        pts = curves[(m, s)] or []
        ax.plot([p[0] for p in pts], [p[1] for p in pts], color=colour, alpha=0.25, linewidth=1)
    xs = [x for x, v in zip(grid, means[m]) if v is not None]
    ax.plot(xs, [v for v in means[m] if v is not None], color=colour, linewidth=2.5,
            label=f"{m.upper()} (mean of {len(seeds)} seeds)")
finish_success_plot(fig, ax, out / "rlpd_vs_rfcl.svg",
                    "PointMaze, small agent, 5 demos: RFCL vs RLPD", ylabel="eval success at the end")
PY
