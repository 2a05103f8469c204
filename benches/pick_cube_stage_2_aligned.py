"""PickCube-v1 stage 2 counted from each run's own stage-1 end, beside the official implementation's
run (benches/pick_cube_vs_reference.py has its figures).

    .venv/bin/python benches/pick_cube_stage_2_aligned.py --run LABEL=SUMMARY.json ...
        [--variant LABEL=SUMMARY.json ...] [--svg OUT.svg]

Every run is an `rfcl train` run of configs/maniskill3/pick_cube.yml with `sac.eval_freq=20000`
that reached stage 2 (its summary.json). `--run` marks a run of the preset as it ships, `--variant`
one with an option changed; both are shown run by run, the preset runs pooled on their own and all
runs pooled together.

Runs end stage 1 at different env steps, so an eval at 240,000 env steps comes 31,000 env steps
into stage 2 in one run and 72,000 in another. Here each eval after the stage-1 end is placed at
its distance from that end and put in the window of ±10,000 env steps around the nearest of the
reference's own distances (its evals at 200,000-260,000, after its stage 1 ended at 168,416), so
that each window holds one eval per run (where two fall in one, the nearer to its centre). Prints the Markdown table of benches/RESULTS.md (per run,
pooled successes with the 95 % Wilson interval) and draws the curves on one SVG.
"""

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 (after choosing the backend)
from pick_cube_vs_reference import (  # noqa: E402 (benches/ is the script's directory)
    REFERENCE_260K_RANGE,
    REFERENCE_EVALS,
    REFERENCE_STAGE_1,
    labelled_summary,
    wilson,
)
from plot_style import finish_success_plot  # noqa: E402

WINDOW = 20_000
# The reference's evals after its stage 1 ended, by their distance from that end.
REFERENCE_AFTER = {
    x - REFERENCE_STAGE_1: v for x, v in REFERENCE_EVALS.items() if x > REFERENCE_STAGE_1
}
FIRST_CENTRE = min(REFERENCE_AFTER)


def window_centre(after):
    """The centre of the window that an eval `after` env steps into stage 2 falls in: the
    reference's distances, continued every 20,000 env steps either side; the first window takes
    everything from the stage-1 end on (an eval just after it: the stage-1 policy)."""
    k = max(round((after - FIRST_CENTRE) / WINDOW), -1)
    return FIRST_CENTRE + k * WINDOW


def window_text(centre):
    low = 0 if centre < FIRST_CENTRE else centre - WINDOW / 2
    return f"+{centre / 1000:.1f}k (+{low / 1000:.1f}k to +{(centre + WINDOW / 2) / 1000:.1f}k)"


def stage_2_evals(summary):
    """(distance from the stage-1 end, successes, episodes) of every eval after stage 1."""
    end = summary["stage_1_env_steps"]
    return [
        (e["env_steps"] - end, round(e["success_at_end"] * e["episodes"]), e["episodes"])
        for e in summary["evals"]
        if e["env_steps"] > end
    ]


def by_window(summary):
    """Each window's eval of one run: (distance, successes, episodes); where two share a window
    (an eval just after the stage-1 end and the next one due), the one nearer its centre."""
    out = {}
    for after, s, n in stage_2_evals(summary):
        c = window_centre(after)
        if c not in out or abs(after - c) < abs(out[c][0] - c):
            out[c] = (after, s, n)
    return out


def read_runs(specs, parser, flag):
    """(label, its evals by window) of each `LABEL=SUMMARY.json`."""
    runs = []
    for spec in specs:
        label, summary = labelled_summary(spec, parser, flag)
        if not summary.get("stage_1_env_steps"):
            parser.error(f"{flag} {spec!r}: the summary has no stage-1 end (stage_1_env_steps)")
        runs.append((label, by_window(summary)))
    return runs


def pooled(runs, centre):
    """Successes and episodes of every run's eval in the window around `centre`."""
    hits = [windows.get(centre) for _, windows in runs]
    return sum(h[1] for h in hits if h), sum(h[2] for h in hits if h)


def rate_text(successes, episodes):
    if episodes == 0:
        return "-"
    low, high = wilson(successes, episodes)
    return f"{successes}/{episodes} = {successes / episodes:.2f} [{low:.2f}-{high:.2f}]"


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--run", action="append", default=[], metavar="LABEL=SUMMARY.json")
    parser.add_argument("--variant", action="append", default=[], metavar="LABEL=SUMMARY.json")
    parser.add_argument(
        "--svg", type=Path, default=Path("benches/pick_cube_stage_2_aligned.svg")
    )
    args = parser.parse_args()
    preset = read_runs(args.run, parser, "--run")
    variants = read_runs(args.variant, parser, "--variant")
    if not preset:
        parser.error("give at least one --run")
    everything = preset + variants

    centres = sorted({c for _, windows in everything for c in windows})
    heads = "".join(f" {label} |" for label, _ in everything)
    print(
        "| after stage 1 (window) | official (one run) |"
        f"{heads} preset runs pooled | all runs pooled |"
    )
    print("|---|---|" + "---|" * (len(everything) + 2))
    for c in centres:
        ref = REFERENCE_AFTER.get(c)
        if ref is None:
            ref_text = "-"
        elif c + REFERENCE_STAGE_1 == 260_000:
            ref_text = "{:.2f}-{:.2f}".format(*REFERENCE_260K_RANGE)
        else:
            ref_text = f"{ref:.2f}"
        cells = ""
        for _, windows in everything:
            hit = windows.get(c)
            cells += f" {hit[1] / hit[2]:.2f} (+{hit[0] / 1000:.0f}k) |" if hit else " - |"
        print(
            f"| {window_text(c)} | {ref_text} |{cells} {rate_text(*pooled(preset, c))} "
            f"| {rate_text(*pooled(everything, c))} |"
        )

    fig, ax = plt.subplots(figsize=(7.5, 3.8))
    ref_x = sorted(REFERENCE_AFTER)
    ax.plot(ref_x, [REFERENCE_AFTER[x] for x in ref_x], "o-", color="tab:gray", linewidth=2,
            label="official JAX implementation")
    ax.vlines(260_000 - REFERENCE_STAGE_1, *REFERENCE_260K_RANGE, color="tab:gray")
    for label, windows in everything:
        points = sorted(windows.values())
        ax.plot([a for a, _, _ in points], [s / n for _, s, n in points], ".-", alpha=0.35,
                linewidth=0.8, label=label)
    # The two pooled curves are drawn a little apart so that their intervals do not hide each other.
    for runs, name, color, shift in [
        (preset, "preset runs", "C3", -700),
        (everything, "all runs", "k", 700),
    ]:
        xs, ys, lows, highs = [], [], [], []
        for c in centres:
            s, n = pooled(runs, c)
            if n:
                low, high = wilson(s, n)
                xs.append(c + shift)
                ys.append(s / n)
                lows.append(s / n - low)
                highs.append(high - s / n)
        ax.errorbar(xs, ys, yerr=[lows, highs], fmt="s-", color=color, capsize=3,
                    label=f"{name} pooled (95 % interval)")
    finish_success_plot(
        fig, ax, args.svg, "PickCube-v1 stage 2, aligned at each run's stage-1 end",
        ylabel="eval success (20 episodes)",
        xlabel="env steps after the run's own stage 1 ended",
        tick_prefix="+",
        legend_fontsize="small",
    )


if __name__ == "__main__":
    main()
