"""Fallback figures and tables: the fallback product (Fig. 6), each net's mean fallback (Fig. 7), Tables 1 and 3.

From the Cascade runs' logs (runs that do not log `cascade/fallback_product`, e.g. PPO, are left out):

- Fig. 6, `<name>_product`: `cascade/fallback_product`, the bottom net's share w_1 = Π_{j≥2} λ_j of
  the ensemble output, mean over each rollout, vs env steps; mean ± standard error over seeds;
- Fig. 7, `<name>_per_net`: `cascade/fallback/net_i`, net i's mean fallback λ_i over each rollout,
  one panel per (env, experiment), one line per net;
- Table 1: each net's final mean fallback λ_i (last `--final-window` logged values of a run, then the
  mean over seeds); Table 3: the standard deviation of λ_i within an episode
  (`cascade/fallback_std/net_i`, logged at each evaluation; its last value), mean over seeds.

    python plots/fallback.py --runs runs --split-by fallback_init

Writes `<out>/<name>_product.png|.pdf`, `<out>/<name>_per_net.png|.pdf`, `<out>/<name>_tables.md`
and `<out>/<name>_tables.csv`.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # for `python plots/<script>.py`
from plots import common  # noqa: E402

PRODUCT = "cascade/fallback_product"
FALLBACK = "cascade/fallback/net_"
FALLBACK_STD = "cascade/fallback_std/net_"


@dataclass
class Args:
    runs: tuple[str, ...] = ("runs",)
    """folders holding run folders `<env>__<exp_name>__<seed>__<time>` (searched at any depth)"""
    out: str = "figures"
    """folder the figures (PNG and PDF) and tables are written to"""
    name: str = "fallback"
    """prefix of the output file names"""
    envs: tuple[str, ...] = ()
    """env ids to include, in this order (default: every env found)"""
    experiments: tuple[str, ...] = ()
    """Cascade experiment names (`--exp-name` of the runs), in this order (default: all that log fallbacks)"""
    split_by: tuple[str, ...] = ()
    """logged hyperparameters that further split an experiment, e.g. `fallback_init` (Fig. 6, Table 1)"""
    labels: tuple[str, ...] = ()
    """display names as EXP=LABEL (defaults: cascade_ppo_continuous=Cascade)"""
    nets: tuple[int, ...] = ()
    """nets i (2..n) drawn in the per-net figure (default: all; Fig. 7 of the paper: 2)"""
    final_window: int = 1
    """Table 1 and 3 use the mean of a run's last this many logged values (in a run folder one per PPO update, in an
    exported run file one per evaluation); a run whose top net has logged fewer averages those (noted)"""
    columns: int = 3
    """panels per row"""
    allow_incomplete: bool = False
    """keep runs that stop before the others of their env and experiment in the final numbers (noted either way)"""


def stack_windows(runs: list[common.Run], window: int, say: bool = True) -> dict[int, int]:
    """id(run) -> how many of its last logged values its final λᵢ, σᵢ and w₁ average: `window`, or fewer where its
    top net has logged fewer (noted): the window lies within the run's last stack, or λᵢ and w₁ would average
    different stacks (a fault hunt: w₁ took in the 1.0 of before net 2 existed, λ₂ fewer values)."""
    windows = {}
    for run in runs:
        top = max(common.fallback_nets([run], FALLBACK), default=None)
        logged = len(run.scalars[f"{FALLBACK}{top}"].by_step()) if top is not None else window
        windows[id(run)] = min(window, logged)
        if logged < window and say:
            common.note(f"{run.name}: its final fallbacks average its last {logged} logged value(s), not {window}: "
                        f"its net {top} was added {logged} value(s) before its end")
    return windows


def final_value(runs: list[common.Run], tag: str, windows: dict[int, int]) -> tuple[float, float | None, int] | None:
    """(mean over seeds, standard error or None for one seed, seeds) of the runs' final values of `tag`, each the
    mean of its last `windows[id(run)]` values."""
    values = np.array([r.scalars[tag].last(windows[id(r)]) for r in runs if tag in r.scalars])
    if not len(values):
        return None
    sem = float(values.std(ddof=1) / np.sqrt(len(values))) if len(values) > 1 else None
    return float(values.mean()), sem, len(values)


def final_per_net(runs: list[common.Run], prefix: str, nets: list[int], windows: dict[int, int]) -> dict[int, tuple]:
    """net i -> `final_value` of `<prefix>i`, for the nets some run logs."""
    table = {net: final_value(runs, f"{prefix}{net}", windows) for net in nets}
    return {net: value for net, value in table.items() if value is not None}


def curve(ax, runs: list[common.Run], tag: str, color: str, label: str) -> None:
    steps, values = common.stack_seeds(runs, tag, curve=True)
    mean, sem = common.mean_sem(values)
    ax.plot(steps, mean, color=color, lw=1.4, label=label)
    ax.fill_between(steps, mean - sem, mean + sem, color=color, alpha=0.2, lw=0)


def net_markers(ax, runs: list[common.Run]) -> None:
    for step in sorted({s for r in runs for s in common.net_added_steps(r)}):
        ax.axvline(step, color="0.45", ls=":", lw=0.9, label="base net added")


def main(args: Args) -> list[str]:
    if args.final_window < 1:
        common.fail("--final-window must be at least 1")
    selection = common.select_runs(args.runs, args.envs, args.experiments, args.split_by, args.labels, [PRODUCT],
                                   complete_only=not args.allow_incomplete)
    logged = common.fallback_nets([r for runs in selection.groups.values() for r in runs], FALLBACK)
    unknown = [net for net in args.nets if net not in logged]
    if unknown:  # (it drew an empty panel, "no net with a fallback", exit 0)
        common.fail(f"--nets {unknown[0]}: the runs' nets with a fallback are {', '.join(map(str, logged)) or 'none'} "
                    "(net 1 has none)")
    plt = common.pyplot()
    paths = []

    # --- Fig. 6: the fallback product over training ---
    fig, axes = common.panels(plt, len(selection.envs), args.columns)
    for ax, env in zip(axes, selection.envs):
        groups = selection.in_env(env)
        for label, runs in groups:
            curve(ax, runs, PRODUCT, selection.color(label), label)
        net_markers(ax, [r for _, runs in groups for r in runs])
        ax.set_title(env)
        common.steps_axis(ax)
        ax.set_ylabel("fallback product  w₁ = Π λᵢ")
        ax.set_ylim(-0.02, 1.02)
    common.figure_legend(fig, axes)
    paths += common.save_figure(fig, args.out, f"{args.name}_product")

    # --- Fig. 7: each net's mean fallback over training ---
    keys = list(selection.groups)
    fig, axes = common.panels(plt, len(keys), args.columns)
    for ax, key in zip(axes, keys):
        runs = selection.groups[key]
        nets = [i for i in common.fallback_nets(runs, FALLBACK) if not args.nets or i in args.nets]
        for net in nets:  # seeds of a run with fewer nets do not count for net i
            curve(ax, [r for r in runs if f"{FALLBACK}{net}" in r.scalars], f"{FALLBACK}{net}",
                  common.OKABE_ITO[(net - 2) % len(common.OKABE_ITO)], f"net {net}")
        if not nets:
            ax.text(0.5, 0.5, "no net with a fallback", ha="center", va="center", transform=ax.transAxes)
        net_markers(ax, runs)
        ax.set_title(f"{key[0]}: {key[1]}")
        common.steps_axis(ax)
        ax.set_ylabel("mean fallback λᵢ over a rollout")
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlim(left=0)
    common.figure_legend(fig, axes)
    paths += common.save_figure(fig, args.out, f"{args.name}_per_net")

    # --- Tables 1 and 3 ---
    all_runs = [r for runs in selection.groups.values() for r in runs]
    windows = stack_windows(all_runs, args.final_window)
    nets = common.fallback_nets(all_runs, FALLBACK)
    std_nets = common.fallback_nets(all_runs, FALLBACK_STD)
    table1, table3, csv_rows = [], [], []
    for (env, label), runs in selection.groups.items():
        fallback = final_per_net(runs, FALLBACK, nets, windows)
        spread = final_per_net(runs, FALLBACK_STD, std_nets, windows)
        product = final_value(runs, PRODUCT, windows)
        cells = [common.fmt(*fallback[i][:2], 2) if i in fallback else "–" for i in nets]
        table1.append([env, label, len(runs), *cells, common.fmt(*product[:2], 3)])
        table3.append([env, label, len(runs), *(common.fmt(*spread[i][:2], 3) if i in spread else "–"
                                                for i in std_nets)])
        for quantity, values in (("fallback", fallback), ("fallback_std", spread), ("fallback_product", {0: product})):
            csv_rows += [(env, label, quantity, i if quantity != "fallback_product" else "", v[0],
                          "" if v[1] is None else v[1], v[2]) for i, v in values.items()]
    seeds = "mean ± standard error over seeds" if any(len(r) > 1 for r in selection.groups.values()) else "one seed"
    window = "last logged value" if args.final_window == 1 else f"mean of the last {args.final_window} logged values"
    text = (f"## Table 1: final mean fallback λᵢ of each base net\n\n"
            f"Per run: `{FALLBACK}i` (λᵢ averaged over a rollout), {window}; then the {seeds}. "
            f"w₁ is the fallback product, the bottom net's share of the output.\n\n"
            + common.markdown_table(["env", "experiment", "seeds", *(f"λ_{i}" for i in nets), "w₁ = Π λᵢ"], table1))
    if std_nets:
        text += (f"\n## Table 3: standard deviation of λᵢ within an episode\n\n"
                 f"Per run: `{FALLBACK_STD}i` (std of λᵢ over the steps of an evaluation episode, averaged over the "
                 f"evaluation's episodes), {window}; then the {seeds}.\n\n"
                 + common.markdown_table(["env", "experiment", "seeds", *(f"σ_{i}" for i in std_nets)], table3))
    else:
        common.note(f"no run logs {FALLBACK_STD}i (evaluation off?): Table 3 left out")
    paths.append(common.write_text(args.out, f"{args.name}_tables.md", text))
    paths.append(common.write_csv(args.out, f"{args.name}_tables.csv",
                                  ["env", "experiment", "quantity", "net", "mean", "sem", "seeds"], csv_rows))
    common.report(paths)
    return paths


if __name__ == "__main__":
    main(common.parse_cli(Args, __doc__.split("\n\n")[0]))
