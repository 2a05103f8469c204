"""One run's curves from its summary.json: eval success against env steps and wall time, and each
demo's reverse-curriculum frontier (t_i, the start state) against env steps, with its stall flag;
for the long runs of the hard tasks (benches/RESULTS.md).

    .venv/bin/python benches/run_curves.py RUN_DIR/summary.json --svg OUT.svg [--title TITLE]
        [--beside OTHER_RUN/summary.json ...]

`--beside` draws other runs' eval curves on the same axes (e.g. RLPD from the same demos, seed
and settings, `train.mode: rlpd`), labelled by their run names.

A run stopped and resumed over several sessions has one summary.json (its evals and frontiers
span every session). Prints the Markdown rows of benches/RESULTS.md: the evals, and per demo its
length, frontier, when it was solved and whether it was flagged as stalled.
"""

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 (after choosing the backend)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("summary", type=Path)
    parser.add_argument("--svg", type=Path, required=True)
    parser.add_argument("--title", default=None)
    parser.add_argument("--beside", type=Path, action="append", default=[],
                        help="another run's summary.json whose eval curve is drawn beside")
    args = parser.parse_args()
    s = json.loads(args.summary.read_text())
    evals = s.get("evals", [])
    demos = s.get("demos", [])

    print(f"run {s['run_name']} ({s['env_id']}): {s['env_steps']:,} env steps, "
          f"{s['wall_s'] / 3600:.2f} h over {s['sessions']} session(s), ending {s['ending']}, "
          f"stage {s['stage']}, stage 1 ended at {s.get('stage_1_env_steps')}")
    print(f"env steps/s over the run: {s['env_steps'] / s['wall_s']:.1f}")
    first = next((e for e in evals if (e.get("success_at_end") or 0) > 0), None)
    print("first nonzero eval:",
          f"{first['env_steps']:,} env steps ({first['success_at_end']:.2f})" if first else "none")
    print("\n| eval at env steps | wall time (h) | success at the end | success once | episodes |")
    print("|---|---|---|---|---|")
    for e in evals:
        print(f"| {e['env_steps']:,} | {e.get('wall_s', 0) / 3600:.2f} | "
              f"{e.get('success_at_end', 0):.2f} | {e.get('success_once', 0):.2f} | "
              f"{e.get('episodes', '')} |")
    print("\n| demo (episode) | states | frontier t_i | solved at env steps | stalled | "
          "episodes (share) |")
    print("|---|---|---|---|---|---|")
    for d in demos:
        diff = d.get("difficulty", {})
        print(f"| {d['demo']} ({d['episode_id']}) | {d['states']} | {d['t']} | "
              f"{diff.get('solved_env_steps') or '-'} | {'yes' if diff.get('stalled') else 'no'} | "
              f"{diff.get('episodes', 0)} ({diff.get('episode_share', 0):.2f}) |")

    fig, (ax_eval, ax_front) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    ax_eval.plot([e["env_steps"] for e in evals], [e.get("success_at_end", 0) for e in evals],
                 marker="o", label=f"{s['run_name']}: eval success at the end")
    for path in args.beside:
        other = json.loads(path.read_text())
        ev = other.get("evals", [])
        ax_eval.plot([e["env_steps"] for e in ev], [e.get("success_at_end", 0) for e in ev],
                     marker="s", linestyle="--", label=f"{other['run_name']}: eval success at the end")
        print(f"beside: {other['run_name']} ({other['env_id']}), {other['env_steps']:,} env steps; "
              f"evals (env steps: success at the end): "
              + ", ".join(f"{e['env_steps']:,}: {e.get('success_at_end', 0):.2f}" for e in ev))
    ax_eval.set_ylabel("eval success")
    ax_eval.set_ylim(-0.05, 1.05)
    if s.get("stage_1_env_steps"):
        for ax in (ax_eval, ax_front):
            ax.axvline(s["stage_1_env_steps"], color="grey", linestyle="--", linewidth=1)
    hours = ax_eval.secondary_xaxis("top", functions=(
        lambda x: x / max(s["env_steps"], 1) * s["wall_s"] / 3600,
        lambda h: h * 3600 / max(s["wall_s"], 1e-9) * s["env_steps"]))
    hours.set_xlabel("wall time (h, at the run's mean rate)")
    ax_eval.legend(loc="upper left")
    for d in demos:
        frontier = d.get("difficulty", {}).get("frontier", [])
        if not frontier:
            continue
        xs = [p[0] for p in frontier] + [s["env_steps"]]
        ys = [p[1] / max(d["states"] - 1, 1) for p in frontier] + [d["t"] / max(d["states"] - 1, 1)]
        stalled = d.get("difficulty", {}).get("stalled")
        ax_front.step(xs, ys, where="post",
                      label=f"demo {d['demo']} ({d['states']} states){' stalled' if stalled else ''}")
    ax_front.set_ylabel("frontier t_i / (S_i - 1)")
    ax_front.set_xlabel("env steps")
    ax_front.set_ylim(-0.05, 1.05)
    ax_front.legend(loc="upper right", fontsize=8)
    fig.suptitle(args.title or f"{s['env_id']} ({s['run_name']})")
    fig.tight_layout()
    fig.savefig(args.svg)
    print(f"\nwrote {args.svg}")


if __name__ == "__main__":
    main()
