"""Member returns (paper Section 4.2): the full stack vs the bottom net acting alone, at the end of each iteration.

At the end of every Cascade iteration the training script evaluates each base net acting alone
(`members/return/net_i`, its own mean and log-std, frozen observation statistics). The full stack's
return at that step is the regular evaluation `eval/episodic_return` logged at the same env step
(the evaluation at the last rollout step of the iteration, i.e. taken one PPO update before the
members'; if there is none at that step, the latest earlier one, with a note). Mean ± standard error
over seeds. Paper, Ant: full stack ~5.1k, bottom net alone ~3.2k.

    python plots/members.py --runs runs

Writes `<out>/<name>.png|.pdf`, `<out>/<name>.md` and `.csv`.
"""

from __future__ import annotations

import bisect
import os
import sys
from dataclasses import dataclass

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # for `python plots/<script>.py`
from plots import common  # noqa: E402

MEMBER = "members/return/net_"
FULL = "eval/episodic_return"


@dataclass
class Args:
    runs: tuple[str, ...] = ("runs",)
    """folders holding run folders `<env>__<exp_name>__<seed>__<time>` (searched at any depth)"""
    out: str = "figures"
    """folder the figure (PNG and PDF) and tables are written to"""
    name: str = "members"
    """file name (without extension) of the outputs"""
    envs: tuple[str, ...] = ()
    """env ids to include, one panel each, in this order (default: every env found)"""
    experiments: tuple[str, ...] = ()
    """Cascade experiment names (`--exp-name` of the runs), in this order (default: all that log member returns)"""
    split_by: tuple[str, ...] = ()
    """logged hyperparameters that further split an experiment, e.g. `fallback_init`"""
    labels: tuple[str, ...] = ()
    """display names as EXP=LABEL (defaults: cascade_ppo_continuous=Cascade)"""
    all_members: bool = False
    """also draw every other base net acting alone (thin dotted lines)"""
    columns: int = 3
    """panels per row"""


def full_stack_at(run: common.Run, steps: np.ndarray) -> np.ndarray:
    """The run's evaluation return at each of `steps` (or the latest earlier evaluation)."""
    evals = run.series(FULL).by_step()
    logged = sorted(evals)
    values = []
    for step in steps:
        i = bisect.bisect_right(logged, int(step)) - 1
        if i < 0:
            common.fail(f"run {run.path} has no '{FULL}' at or before step {int(step)}")
        if logged[i] != step:
            common.note(f"{run.name}: no evaluation at step {int(step)}; using the one at step {logged[i]}")
        values.append(evals[logged[i]])
    return np.array(values)


def main(args: Args) -> list[str]:
    selection = common.select_runs(args.runs, args.envs, args.experiments, args.split_by, args.labels,
                                   [f"{MEMBER}1", FULL])
    plt = common.pyplot()
    fig, axes = common.panels(plt, len(selection.envs), args.columns)
    md_rows, csv_rows = [], []
    nets_all = common.fallback_nets([r for rs in selection.groups.values() for r in rs], MEMBER)
    for ax, env in zip(axes, selection.envs):
        for label, runs in selection.in_env(env):
            color = selection.color(label)
            steps, bottom = common.stack_seeds(runs, f"{MEMBER}1")  # one step per finished iteration
            full = np.stack([full_stack_at(r, steps) for r in runs])
            members = {}
            for net in common.fallback_nets(runs, MEMBER):
                # a seed that stopped earlier (or a run with fewer nets) has no evaluation of the later nets: NaN
                per_run = [r.scalars[f"{MEMBER}{net}"].by_step() if f"{MEMBER}{net}" in r.scalars else {}
                           for r in runs]
                members[net] = np.array([[p.get(int(s), np.nan) for s in steps] for p in per_run])
            for values, style, marker, what in ((full, "-", "o", "full stack"), (bottom, "--", "s", "net 1 alone")):
                mean, sem = common.mean_sem(values)
                ax.errorbar(steps, mean, yerr=sem, color=color, ls=style, marker=marker, ms=4, capsize=3,
                            label=f"{label}: {what}")
            if args.all_members:
                for net, values in members.items():
                    logged = ~np.isnan(values).all(0)  # net i exists from iteration i on
                    if net > 1 and logged.any():
                        ax.plot(steps[logged], np.nanmean(values[:, logged], 0), color=color, ls=":", lw=0.9,
                                marker=".", alpha=0.6, label=f"{label}: net i ≥ 2 alone")
            for it, step in enumerate(steps):
                row = [env, label, it + 1, f"{int(step):,}", len(runs)]
                cells, numbers = [], []
                for values in [full[:, it]] + [members[n][:, it] if n in members else np.full(len(runs), np.nan)
                                               for n in nets_all]:
                    present = values[~np.isnan(values)]
                    if len(present):
                        m, e = common.mean_sem(present[:, None])
                        cells.append(common.fmt(float(m[0]), float(e[0]) if len(present) > 1 else None, 1))
                        numbers.append(float(m[0]))
                    else:
                        cells.append("–")
                        numbers.append("")
                md_rows.append(row + cells)
                csv_rows.append([env, label, it + 1, int(step), len(runs), *numbers])
        ax.set_title(env)
        common.steps_axis(ax)
        ax.set_ylabel("return at the end of an iteration")
    common.figure_legend(fig, axes)
    paths = common.save_figure(fig, args.out, args.name)
    net_headers = [f"net {n} alone" for n in nets_all]
    text = ("Return of the full stack and of each base net acting alone at the end of each iteration "
            "(mean ± standard error over seeds).\n\n"
            + common.markdown_table(["env", "experiment", "iteration", "step", "seeds", "full stack", *net_headers],
                                    md_rows))
    paths.append(common.write_text(args.out, f"{args.name}.md", text))
    paths.append(common.write_csv(args.out, f"{args.name}.csv",
                                  ["env", "experiment", "iteration", "step", "seeds", "full_stack",
                                   *(f"net_{n}" for n in nets_all)], csv_rows))
    common.report(paths)
    return paths


if __name__ == "__main__":
    main(common.parse_cli(Args, __doc__.split("\n\n")[0]))
