"""Learning curves: evaluation return vs env steps, mean ± standard error over seeds (paper Fig. 2, 4, 5).

One panel per env, one curve per experiment (runs are grouped by the `exp_name` part of their folder
name), dotted vertical lines where Cascade added a base net (read from `cascade/size`).

    python plots/learning_curves.py --runs runs --out figures
    python plots/learning_curves.py --experiments cascade_ppo_continuous ppo_baseline --envs Ant-v4 Hopper-v4

Writes `<out>/<name>.png`, `.pdf`, `.csv` (every plotted point: mean, standard error, number of
seeds) and `.md` (the value at the last common step of each curve).
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # for `python plots/<script>.py`
from plots import common  # noqa: E402


@dataclass
class Args:
    runs: tuple[str, ...] = ("runs",)
    """folders holding run folders `<env>__<exp_name>__<seed>__<time>` (searched at any depth)"""
    out: str = "figures"
    """folder the figure (PNG and PDF) and its tables are written to"""
    name: str = "learning_curves"
    """file name (without extension) of the outputs"""
    envs: tuple[str, ...] = ()
    """env ids to draw, one panel each, in this order (default: every env found)"""
    experiments: tuple[str, ...] = ()
    """experiment names (`--exp-name` of the runs) to overlay, in this order (default: all found)"""
    split_by: tuple[str, ...] = ()
    """logged hyperparameters that further split an experiment into curves, e.g. `fallback_init`"""
    labels: tuple[str, ...] = ()
    """display names as EXP=LABEL (defaults: cascade_ppo_continuous=Cascade, ppo_baseline=PPO)"""
    scalar: str = "eval/episodic_return"
    """the TensorBoard scalar to draw"""
    ylabel: str = ""
    """y-axis label (default: derived from --scalar)"""
    markers: bool = True
    """dotted vertical lines where a base net was added (from `cascade/size`)"""
    columns: int = 3
    """panels per row"""


def ylabel_for(scalar: str, selection: common.Selection) -> str:
    if scalar == "eval/episodic_return":
        episodes = {r.hparams.get("eval_episodes") for rs in selection.groups.values() for r in rs} - {None}
        per = f"mean of {episodes.pop()} episodes" if len(episodes) == 1 else "mean over evaluation episodes"
        return f"evaluation return ({per})"
    if scalar == "charts/episodic_return":
        return "training episode return"
    return scalar


def main(args: Args) -> list[str]:
    selection = common.select_runs(args.runs, args.envs, args.experiments, args.split_by, args.labels, [args.scalar])
    plt = common.pyplot()
    fig, axes = common.panels(plt, len(selection.envs), args.columns)
    csv_rows, md_rows = [], []
    for ax, env in zip(axes, selection.envs):
        groups = selection.in_env(env)
        marker_sets = {label: sorted({s for r in runs for s in common.net_added_steps(r)}) for label, runs in groups}
        shared_markers = len({tuple(m) for m in marker_sets.values() if m}) == 1
        for label, runs in groups:
            color = selection.color(label)
            steps, values = common.stack_seeds(runs, args.scalar, curve=True)
            mean, sem = common.mean_sem(values)
            ax.plot(steps, mean, color=color, lw=1.6, label=label)
            ax.fill_between(steps, mean - sem, mean + sem, color=color, alpha=0.2, lw=0)
            if args.markers and not shared_markers:
                for step in marker_sets[label]:
                    ax.axvline(step, color=color, ls=":", lw=0.9, alpha=0.7)
            csv_rows += [(env, label, int(s), float(m), float(e), len(runs)) for s, m, e in zip(steps, mean, sem)]
            if len(steps):
                md_rows.append((env, label, len(runs), f"{int(steps[-1]):,}", common.fmt(mean[-1], sem[-1] if len(runs) > 1 else None, 1)))
        if args.markers and shared_markers:
            for step in next(m for m in marker_sets.values() if m):
                ax.axvline(step, color="0.45", ls=":", lw=0.9, label="base net added")
        ax.set_title(env)
        common.steps_axis(ax)
        ax.set_ylabel(args.ylabel or ylabel_for(args.scalar, selection))
    seed_counts = sorted({len(runs) for runs in selection.groups.values()})
    fig.suptitle(f"mean ± standard error over {'/'.join(map(str, seed_counts))} seed(s)", fontsize=9, color="0.3")
    common.figure_legend(fig, axes)
    paths = common.save_figure(fig, args.out, args.name)
    paths.append(common.write_csv(args.out, f"{args.name}.csv", ["env", "experiment", "step", "mean", "sem", "seeds"],
                                  csv_rows))
    seeds = "mean ± standard error over seeds" if any(len(r) > 1 for r in selection.groups.values()) else "one seed"
    text = (f"`{args.scalar}` at the last step every seed of the experiment reached ({seeds}).\n\n"
            + common.markdown_table(["env", "experiment", "seeds", "step", args.scalar], md_rows))
    paths.append(common.write_text(args.out, f"{args.name}.md", text))
    common.report(paths)
    return paths


if __name__ == "__main__":
    main(common.parse_cli(Args, __doc__.split("\n\n")[0]))
