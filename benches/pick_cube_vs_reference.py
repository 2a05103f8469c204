"""The full PickCube-v1 preset run beside the official JAX implementation's run on the same kind of
machine (2 cores, CPU only, 5 motion-planned demos, seed 1, its ManiSkill3 CPU config).

    .venv/bin/python benches/pick_cube_vs_reference.py RUN_DIR [--state STATE.json] [--svg OUT.svg]
        [--also LABEL=SUMMARY.json ...]

RUN_DIR is an `rfcl train` run of configs/maniskill3/pick_cube.yml with `sac.eval_freq=20000`
(its summary.json and metrics.csv); STATE.json is the run's dashboard /api/state saved near its end,
whose progress history gives the first train success (the summary keeps only the last rate).
`--also` adds another rfcl run of the same preset (another seed) by its summary.json alone: its
eval column and curve, and its stage-1 end.
Prints the Markdown tables of benches/RESULTS.md (the per-demo stage-1 table too) and draws every
eval curve on one SVG.
"""

import argparse
import csv
import json
from pathlib import Path

import matplotlib
import yaml

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 (after choosing the backend)
from plot_style import finish_success_plot  # noqa: E402 (benches/ is the script's directory)

# The reference run's figures (benches/RESULTS.md, "PickCube-v1 at the paper's settings"): eval
# success at every 20,000 env steps where it was recorded (at 260k it was between 0.60 and 0.70),
# its milestones and its rate.
REFERENCE_EVALS = {k * 20_000: 0.0 for k in range(1, 8)} | {
    160_000: 0.10,
    200_000: 0.05,
    220_000: 0.20,
    240_000: 0.50,
    260_000: 0.65,
}
REFERENCE_260K_RANGE = (0.60, 0.70)
REFERENCE_STAGE_1 = 168_416
REFERENCE = {
    "env steps/s (with updates)": "36.5",
    "first train success": "about 50,000",
    "stage 1 ends": f"{REFERENCE_STAGE_1:,} (77 min)",
    "eval success ≥ 50 %": "240,000 (110 min)",
    "eval success ≥ 90 %": "not reached by 260,000",
}


def first_train_success(state):
    """Env steps of the first progress sample with a train success, from a saved /api/state."""
    if state is None:
        return None
    return next((p["env_steps"] for p in state["history"] if p["train_success_rate"] > 0), None)


def wall_at(metrics, env_steps):
    """Wall seconds (all sessions) when the learner had `env_steps`, from metrics.csv."""
    for row in metrics:
        if int(row["env_steps"]) >= env_steps:
            return float(row["time/total"])
    return None


def on_grid(evals):
    """Each eval under its nearest multiple of 10,000 env steps; where several share one, the
    eval nearest to it (a resumed run's eval actor adds an eval at once, a few hundred or thousand
    env steps after the one due on the grid)."""
    out = {}
    for e in evals:
        x = round(e["env_steps"], -4)
        if x not in out or abs(e["env_steps"] - x) < abs(out[x]["env_steps"] - x):
            out[x] = e
    return out


def wilson(successes, n, z=1.96):
    """The 95 % Wilson score interval of a success rate of `successes` in `n` episodes."""
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    center = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * (p * (1 - p) / n + z * z / (4 * n * n)) ** 0.5
    return (max(0.0, center - half), min(1.0, center + half))


def stage_1_by_demo(summary):
    """Per demo, from the summary's frontier history (`[env steps, t_i]` after each move): when the
    frontier first moved, reached t_i = 0 and was solved, its longest wait and the t_i it waited at
    (the grasp, in PickCube), and its share of the stage-1 episodes."""
    rows = []
    for demo in summary["demos"]:
        d = demo["difficulty"]
        moves = d["frontier"]
        waits = [(b[0] - a[0], a[1]) for a, b in zip(moves, moves[1:])]
        wait, at = max(waits) if waits else (None, None)
        at_zero = next((steps for steps, t in moves if t == 0), None)
        rows.append(
            (
                demo["episode_id"],
                demo["states"],
                moves[0][0] if moves else None,
                at_zero,
                d["solved_env_steps"],
                wait,
                at,
                d["episode_share"],
                d["frontier_success_rate"],
            )
        )
    return rows


def labelled_summary(spec, parser, flag):
    """`LABEL=SUMMARY.json` given with `flag`: the label and the parsed summary."""
    label, sep, path = spec.partition("=")
    if not sep:
        parser.error(f"{flag} {spec!r}: expected LABEL=SUMMARY.json")
    return label, json.loads(Path(path).read_text())


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--state", type=Path)
    parser.add_argument("--svg", type=Path, default=Path("benches/pick_cube_vs_reference.svg"))
    parser.add_argument("--also", action="append", default=[], metavar="LABEL=SUMMARY.json")
    parser.add_argument("--label", default="rfcl", help="this run's name in the tables and plot")
    args = parser.parse_args()
    others = [labelled_summary(also, parser, "--also") for also in args.also]
    summary = json.loads((args.run_dir / "summary.json").read_text())
    with open(args.run_dir / "metrics.csv") as f:
        metrics = list(csv.DictReader(f))
    state = json.loads(args.state.read_text()) if args.state else None
    evals = summary["evals"]

    minutes = lambda s: f"{s / 60:.0f} min" if s is not None else "-"
    steps = lambda v: f"{v:,}" if v is not None else "-"
    config = yaml.safe_load((args.run_dir / "config.yml").read_text())
    seeded = int(config["sac"]["num_seed_steps"])
    after_seed = [r for r in metrics if int(r["env_steps"]) > seeded]
    rate = None
    if len(after_seed) > 1:
        first, last = after_seed[0], after_seed[-1]
        rate = (int(last["env_steps"]) - int(first["env_steps"])) / (
            float(last["time/total"]) - float(first["time/total"])
        )
    stage_1 = summary.get("stage_1_env_steps")
    to = {t["threshold"]: t for t in summary["to_success"]}

    def milestone(threshold):
        hit = to.get(threshold, {})
        if not hit.get("env_steps"):
            return "not reached"
        return f"{steps(hit['env_steps'])} ({minutes(hit['wall_s'])})"

    ours = {
        "env steps/s (with updates)": f"{summary['env_steps'] / summary['wall_s']:.1f} overall, "
        + (f"{rate:.1f} after the seed steps" if rate else "-"),
        "first train success": steps(first_train_success(state)),
        "stage 1 ends": f"{steps(stage_1)} ({minutes(wall_at(metrics, stage_1))})"
        if stage_1
        else f"not ended by {summary['env_steps']:,}",
        "eval success ≥ 50 %": milestone(0.5),
        "eval success ≥ 90 %": milestone(0.9),
    }
    print(f"| | official JAX implementation | {args.label} |")
    print("|---|---|---|")
    for key, value in REFERENCE.items():
        print(f"| {key} | {value} | {ours[key]} |")
    for label, other in others:
        end = other.get("stage_1_env_steps")
        print(f"\n{label}: stage 1 ends at {steps(end) if end else '-'}")

    print(
        "\n| demo (episode) | states | first frontier move | t_i = 0 | solved "
        "| longest wait (at t_i) | share of stage-1 episodes | frontier success |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for ep, states, first, zero, solved, wait, at, share, success in stage_1_by_demo(summary):
        print(
            f"| {ep} | {states} | {steps(first)} | {steps(zero)} | {steps(solved)} "
            f"| {steps(wait)} ({at}) | {share:.2f} | {success:.2f} |"
        )

    extra_heads = "".join(
        f" {label}: success at end (once) [95 % interval] |" for label, _ in others
    )
    print(
        f"\n| env steps | official: eval success | {args.label}: success at end (success once) [95 % interval] "
        f"| {args.label} wall time |{extra_heads}"
    )
    print("|---|---|---|---|" + "---|" * len(others))
    grid = sorted(
        set(REFERENCE_EVALS)
        | {round(e["env_steps"], -4) for run in [summary] + [o for _, o in others] for e in run["evals"]}
    )
    by_step = on_grid(evals)
    others_by_step = [on_grid(o["evals"]) for _, o in others]

    def success_text(e, x):
        if not e:
            return "-"
        low, high = wilson(round(e["success_at_end"] * e["episodes"]), e["episodes"])
        text = f"{e['success_at_end']:.2f} ({e['success_once']:.2f}) [{low:.2f}-{high:.2f}]"
        return text + (f" at {e['env_steps']:,}" if e["env_steps"] != x else "")
    for x in grid:
        ref = REFERENCE_EVALS.get(x)
        if x == 260_000:
            ref_text = "{:.2f}-{:.2f}".format(*REFERENCE_260K_RANGE)
        else:
            ref_text = f"{ref:.2f}" if ref is not None else "-"

        e = by_step.get(x)
        extra = "".join(f" {success_text(o.get(x), x)} |" for o in others_by_step)
        print(
            f"| {x:,} | {ref_text} | {success_text(e, x)} "
            f"| {minutes(e['wall_s']) if e else '-'} |{extra}"
        )

    fig, ax = plt.subplots(figsize=(7.5, 3.8))
    ref_x = sorted(REFERENCE_EVALS)
    ax.plot(ref_x, [REFERENCE_EVALS[x] for x in ref_x], "o-", color="tab:gray",
            label="official JAX implementation")
    ax.vlines(260_000, *REFERENCE_260K_RANGE, color="tab:gray")
    ax.axvline(REFERENCE_STAGE_1, color="tab:gray", linestyle=":", label="stage 1 ends (official)")
    # Matplotlib's colour cycle (C0 is tab:blue, C1 tab:orange, ...), one colour per run.
    for i, (label, run) in enumerate([(args.label, summary)] + others):
        color = f"C{i}"
        run_evals = run["evals"]
        ax.plot([e["env_steps"] for e in run_evals], [e["success_at_end"] for e in run_evals],
                "o-", color=color, label=f"{label} (success at end)")
        if run.get("stage_1_env_steps"):
            ax.axvline(run["stage_1_env_steps"], color=color, linestyle=":",
                       label=f"stage 1 ends ({label})")
    finish_success_plot(
        fig, ax, args.svg, "PickCube-v1, 5 demos, full preset, 2-core CPU",
        ylabel="eval success (20 episodes)",
    )


if __name__ == "__main__":
    main()
