#!/usr/bin/env bash
# The paper's stage-1 ablation: env steps until stage 1 ends for (a) the per-demo reverse
# curriculum with the dynamic time limit, (b) per-demo without it, (c) a global reverse curriculum
# with it, (d) uniform start states over the demos; S seeds per row, one after another.
#
#   benches/stage1_ablation.sh [--env pointmaze|pick_cube] [--seeds 1,2,3] [--rows a,b,c,d]
#                              [--demos FILE] [--out DIR]
#
# Each row is one preset of configs/ablations/ (docs/CONFIG.md, "Ablations"), run as a user would:
#   target/release/rfcl train --run-dir DIR/<row>-sN configs/ablations/<env>_stage1_<row>.yml \
#       train.dataset_path=FILE seed=N
# A run ends with stage 1, or at train.steps (1M env steps) for a row that never ends it.
# The demos default to runs/demos/pointmaze.h5 or runs/demos/pick_cube_5.h5 (5 demos made with
# `rfcl demos generate` when absent), the output to runs/stage1_ablation[_pick_cube]. Prints one
# Markdown table: per row, each seed's stage_1_env_steps (from summary.json; "not ended" at the
# budget), their mean and a 95 % t-interval, and wall time.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck source=benches/lib.sh
source benches/lib.sh

env=pointmaze
seeds=1,2,3
rows=a,b,c,d
demos=
out=
parse_flags "$0" env seeds rows demos out -- "$@"

case $env in
    pointmaze) env_id=pointmaze; demos=${demos:-runs/demos/pointmaze.h5}; out=${out:-runs/stage1_ablation} ;;
    pick_cube) env_id=PickCube-v1; demos=${demos:-runs/demos/pick_cube_5.h5}; out=${out:-runs/stage1_ablation_pick_cube} ;;
    *) echo "stage1_ablation.sh: --env is pointmaze or pick_cube, not $env" >&2; exit 2 ;;
esac

need_rfcl "$0"
demos_or_generate "$env_id" "$demos"

declare -A preset=(
    [a]=${env}_stage1_per_demo
    [b]=${env}_stage1_per_demo_no_time_limit
    [c]=${env}_stage1_global
    [d]=${env}_stage1_uniform
)
mkdir -p "$out"
for row in ${rows//,/ }; do
    name=${preset[$row]:?unknown row $row (a, b, c or d)}
    for seed in ${seeds//,/ }; do
        train_once "$name seed $seed" "$out/$row-s$seed" "configs/ablations/$name.yml" \
            "train.dataset_path=$demos" "seed=$seed"
    done
done

python3 - "$out" "$rows" "$seeds" <<'PY'
import json, math, statistics, sys
from pathlib import Path
out, rows, seeds = Path(sys.argv[1]), sys.argv[2].split(","), sys.argv[3].split(",")
names = {"a": "per-demo, dynamic time limit", "b": "per-demo, no time limit",
         "c": "global, dynamic time limit", "d": "uniform start states"}
# Two-sided 95 % Student-t quantiles by degrees of freedom.
T95 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262}
print("| row | variant | " + " | ".join(f"seed {s}" for s in seeds) + " | mean ± 95 % CI | wall time |")
print("|---|---|" + "---|" * len(seeds) + "---|---|")
for row in rows:
    cells, ended, walls = [], [], []
    for seed in seeds:
        path = out / f"{row}-s{seed}" / "summary.json"
        if not path.exists():
            cells.append("failed")
            continue
        s = json.loads(path.read_text())
        walls.append(s.get("wall_s") or 0.0)
        steps = s.get("stage_1_env_steps")
        if steps is None:
            cells.append(f"not ended ({s.get('env_steps', 0):,})")
        else:
            ended.append(steps)
            cells.append(f"{steps:,}")
    if len(ended) == len(seeds) and len(ended) > 1:
        mean = statistics.mean(ended)
        half = T95.get(len(ended) - 1, 1.96) * statistics.stdev(ended) / math.sqrt(len(ended))
        summary = f"{mean:,.0f} ± {half:,.0f}"
    elif len(ended) == len(seeds) == 1:
        summary = f"{ended[0]:,}"
    else:
        summary = f"{len(ended)}/{len(seeds)} ended"
    wall = f"{sum(walls) / 60:.0f} min" if walls else "-"
    print(f"| {row} | {names[row]} | " + " | ".join(cells) + f" | {summary} | {wall} |")
PY
