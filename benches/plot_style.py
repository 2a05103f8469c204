"""What the bench scripts' eval-success plots share, so that their SVGs in benches/RESULTS.md read
alike. Scripts in benches/ import it as `plot_style` (their own directory is on sys.path)."""

import matplotlib.ticker


def finish_success_plot(
    fig, ax, path, title, ylabel, xlabel="env steps", tick_prefix="", legend_fontsize=None
):
    """Labels `ax` (env steps in thousands, each tick with `tick_prefix`, against an eval success
    from 0 to 1), puts the legend right of the axes, saves `fig` to `path` and prints where."""
    ax.xaxis.set_major_formatter(
        matplotlib.ticker.FuncFormatter(lambda x, _: f"{tick_prefix}{x / 1000:.0f}k")
    )
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(title)
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=legend_fontsize)
    fig.tight_layout()
    fig.savefig(path)
    print(f"\ncurves: {path}")
