"""Final performance over seeds with robust statistics: IQM, 95% stratified bootstrap CIs, probability of improvement.

The statistics of Agarwal et al. (2021, "Deep RL at the edge of the statistical precipice"), computed with
their library, rliable (`rliable.library.get_interval_estimates`, `rliable.metrics`):

- a run's score is its mean `eval/episodic_return` over its last `--final-window` evaluations;
- IQM, the interquartile mean (`metrics.aggregate_iqm`: `scipy.stats.trim_mean(scores, 0.25)`, which drops
  the lowest and the highest floor(n/4); with fewer than 4 seeds it is the plain mean);
- 95% CIs by the stratified percentile bootstrap: a replicate resamples, with replacement, as many runs as
  there are within each stratum (env; for a comparison, within each env and experiment separately),
  recomputes the statistic, and the CI is the 2.5th..97.5th percentile over `--reps` replicates;
- probability of improvement P(X > Y) of experiment X over the baseline Y on one env
  (`metrics.probability_of_improvement`): the share of (run of X, run of Y) pairs where X scored higher,
  ties counting 1/2 (the Mann-Whitney U statistic over n·m); over several envs, the mean of the per-env
  probabilities;
- "all envs" IQM: scores divided by the baseline's mean score on the same env (so envs with returns of
  different scale can be pooled), then the IQM of all (env, seed) scores, CI stratified by env; and the
  performance profile of those normalized scores (`library.create_performance_profile`: the fraction of
  runs scoring above tau, with CIs). Left out when the baseline is missing on an env, its mean score is not
  positive, or an experiment has different numbers of seeds on different envs (rliable takes a runs x envs
  matrix).

`tests/test_plots.py` checks these numbers against a plain numpy implementation of the same statistics.

    python plots/final_performance.py --runs runs --baseline ppo_baseline

Writes `<out>/<name>.png|.pdf` (IQM and CI per env), `<out>/<name>_improvement.png|.pdf`,
`<out>/<name>_profile.png|.pdf` (performance profiles over all envs), `<out>/<name>.md` and `.csv`.
"""

from __future__ import annotations

import itertools
import os
import sys
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from rliable import library as rly
from rliable import metrics, plot_utils

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # for `python plots/<script>.py`
from plots import common  # noqa: E402

ALL_ENVS = "all envs"


@dataclass
class Args:
    runs: tuple[str, ...] = ("runs",)
    """folders holding run folders `<env>__<exp_name>__<seed>__<time>` (searched at any depth)"""
    out: str = "figures"
    """folder the figures (PNG and PDF) and tables are written to"""
    name: str = "final_performance"
    """file name (without extension) of the outputs"""
    envs: tuple[str, ...] = ()
    """env ids to include, in this order (default: every env found)"""
    experiments: tuple[str, ...] = ()
    """experiment names (`--exp-name` of the runs) to compare, in this order (default: all found)"""
    split_by: tuple[str, ...] = ()
    """logged hyperparameters that further split an experiment, e.g. `fallback_init`"""
    labels: tuple[str, ...] = ()
    """display names as EXP=LABEL (defaults: cascade_ppo_continuous=Cascade, ppo_baseline=PPO)"""
    baseline: str = "ppo_baseline"
    """experiment name (or display label) every other experiment is compared with"""
    scalar: str = "eval/episodic_return"
    """the TensorBoard scalar whose final value is a run's score"""
    final_window: int = 1
    """a run's score is the mean of its last this many logged values"""
    reps: int = 2000
    """bootstrap replicates"""
    confidence: float = 0.95
    """confidence level of the intervals"""
    seed: int = 0
    """seed of the bootstrap's random generator"""
    allow_incomplete: bool = False
    """keep runs that stop before the others of their env and experiment in the final numbers (noted either way)"""


def interval_estimate(scores: np.ndarray | tuple[np.ndarray, np.ndarray], statistic: Callable[..., float],
                      args: Args, call: int) -> tuple[float, tuple[float, float]]:
    """rliable's point estimate and stratified percentile-bootstrap CI of `statistic` on a runs x envs score matrix
    (or a pair of them, for a comparison). `call` numbers the estimates, so each has its own reproducible seed."""
    # rliable 1.2.0's stratified bootstraps draw their indices from numpy's global generator, whatever random_state
    # says: seeded here (and restored after), or a figure's CIs would change with whatever ran before
    global_state = np.random.get_state()
    np.random.seed([args.seed, call])
    try:
        with warnings.catch_warnings():  # arch (rliable's bootstrap) deprecates the RandomState rliable hands it
            warnings.simplefilter("ignore", FutureWarning)
            points, intervals = rly.get_interval_estimates(
                {"x": scores}, lambda *m: np.array([statistic(*m)]), reps=args.reps,
                confidence_interval_size=args.confidence, random_state=np.random.RandomState([args.seed, call]))
    finally:
        np.random.set_state(global_state)
    return float(points["x"][0]), (float(intervals["x"][0, 0]), float(intervals["x"][1, 0]))


def run_scores(runs: Sequence[common.Run], scalar: str, window: int) -> np.ndarray:
    ends = {r.series(scalar).steps.max() for r in runs}
    if len(ends) > 1:
        common.note(f"runs of {runs[0].env_id}/{runs[0].exp_name} end at different steps "
                    f"({', '.join(f'{int(e):,}' for e in sorted(ends))}); each is scored at its own end")
    return np.array([common.final_score(r, scalar, window) for r in runs])


def note_different_budgets(selection: common.Selection, scalar: str) -> None:
    """Groups of one env compared at different step counts (a 6M-step Cascade against a 1M-step PPO) are not a
    like-for-like comparison: say so (a difference of less than 5%, from rounding to whole rollouts, is none)."""
    for env in selection.envs:
        ends = {label: max(int(r.series(scalar).steps.max()) for r in runs) for label, runs in selection.in_env(env)}
        if min(ends.values()) < 0.95 * max(ends.values()):  # not a rollout's rounding (5,996,544 vs 5,998,592)
            common.note(f"on {env} the experiments end at different steps ("
                        f"{', '.join(f'{label}: {step:,}' for label, step in ends.items())}): their final scores "
                        "compare different budgets")


def find_baseline(selection: common.Selection, baseline: str) -> str | None:
    for (_env, label), runs in selection.groups.items():
        if label == baseline or runs[0].exp_name == baseline:
            return label
    return None


def main(args: Args) -> list[str]:
    if args.final_window < 1 or args.reps < 1 or not 0 < args.confidence < 1:
        common.fail("--final-window and --reps must be at least 1 and --confidence within (0, 1)")
    selection = common.select_runs(args.runs, args.envs, args.experiments, args.split_by, args.labels, [args.scalar],
                                   complete_only=not args.allow_incomplete)
    scores = {key: run_scores(runs, args.scalar, args.final_window) for key, runs in selection.groups.items()}
    note_different_budgets(selection, args.scalar)
    base = find_baseline(selection, args.baseline)
    if base is None:
        common.note(f"no runs of the baseline '{args.baseline}' (found {common.short_list(selection.labels)}); "
                    "probability of improvement left out (set --baseline)")
    others = [label for label in selection.labels if label != base]
    calls = itertools.count()  # numbers the estimates: each gets its own seed

    def matrix(label: str, envs: list[str], what: str) -> np.ndarray | None:
        """runs x envs scores of `label` (rliable's layout), or None (with a note) if the seed counts differ."""
        counts = {len(scores[(e, label)]) for e in envs}
        if len(counts) > 1:
            common.note(f"no all-envs {what} for {label}: it has different numbers of seeds on different envs")
            return None
        return np.stack([scores[(e, label)] for e in envs], axis=1)

    # --- per env: IQM with CI, probability of improvement over the baseline with CI ---
    stats: dict[tuple[str, str], dict] = {}
    for (env, label), s in scores.items():
        point, ci = interval_estimate(s[:, None], metrics.aggregate_iqm, args, next(calls))
        sem = float(s.std(ddof=1) / np.sqrt(len(s))) if len(s) > 1 else None
        stats[(env, label)] = {"scores": s, "mean": float(s.mean()), "sem": sem, "median": float(np.median(s)),
                               "iqm": point, "ci": ci}
    improvement: dict[tuple[str, str], tuple[float, tuple[float, float]]] = {}
    normalized: dict[str, np.ndarray] = {}  # runs x envs, scores / the baseline's mean score on the env
    if base is not None:
        for label in others:
            envs = [e for e in selection.envs if (e, label) in scores and (e, base) in scores]
            for env in envs:
                improvement[(env, label)] = interval_estimate(
                    (scores[(env, label)][:, None], scores[(env, base)][:, None]), metrics.probability_of_improvement,
                    args, next(calls))
            if len(envs) > 1:
                x, y = matrix(label, envs, "probability of improvement"), matrix(base, envs, "comparison")
                if x is not None and y is not None:
                    improvement[(ALL_ENVS, label)] = interval_estimate((x, y), metrics.probability_of_improvement,
                                                                       args, next(calls))
        # pooled over envs: scores normalized by the baseline's mean score on each env
        if len(selection.envs) > 1:
            base_means = {e: scores[(e, base)].mean() for e in selection.envs if (e, base) in scores}
            for label in selection.labels:
                envs = [e for e in selection.envs if (e, label) in scores]
                if set(envs) - set(base_means) or min(base_means[e] for e in envs) <= 0:
                    common.note(f"no all-envs IQM for {label}: the baseline is missing or scores <= 0 on some env")
                    continue
                m = matrix(label, envs, "IQM")
                if m is None:
                    continue
                normalized[label] = m / np.array([base_means[e] for e in envs])
                point, ci = interval_estimate(normalized[label], metrics.aggregate_iqm, args, next(calls))
                pooled = normalized[label].ravel()
                stats[(ALL_ENVS, label)] = {"scores": pooled, "mean": float(pooled.mean()), "sem": None,
                                            "median": float(np.median(pooled)), "iqm": point, "ci": ci,
                                            "normalized": True}

    # --- tables ---
    level = f"{round(100 * args.confidence)}%"
    headers = ["env", "experiment", "seeds", "mean ± SE", "median", "IQM", f"IQM {level} CI"]
    if base is not None:
        headers.append(f"P(better than {base}) [{level} CI]")
    md_rows, csv_rows = [], []
    for (env, label), st in stats.items():
        digits = 2 if st.get("normalized") else 1
        poi = improvement.get((env, label))
        row = [env + (f" (score / {base} mean)" if st.get("normalized") else ""), label, len(st["scores"]),
               common.fmt(st["mean"], st["sem"], digits), f"{st['median']:.{digits}f}", f"{st['iqm']:.{digits}f}",
               f"[{st['ci'][0]:.{digits}f}, {st['ci'][1]:.{digits}f}]"]
        if base is not None:
            row.append("–" if poi is None else f"{poi[0]:.2f} [{poi[1][0]:.2f}, {poi[1][1]:.2f}]")
        md_rows.append(row)
        csv_rows.append([env, label, len(st["scores"]), st["mean"], st["median"], st["iqm"], *st["ci"],
                         *((poi[0], *poi[1]) if poi else ("", "", ""))])
    for (env, label), poi in improvement.items():
        if (env, label) not in stats:  # the all-envs probability when there is no pooled IQM
            csv_rows.append([env, label, "", "", "", "", "", "", poi[0], *poi[1]])
            md_rows.append([env, label, "", "", "", "", "", f"{poi[0]:.2f} [{poi[1][0]:.2f}, {poi[1][1]:.2f}]"])
    window = "last evaluation" if args.final_window == 1 else f"mean of the last {args.final_window} evaluations"
    text = (f"Score of a run: `{args.scalar}`, {window}. IQM: interquartile mean over seeds; CIs: stratified "
            f"percentile bootstrap, {args.reps} replicates, by rliable (see plots/final_performance.py).\n\n"
            + common.markdown_table(headers, md_rows))
    paths = [common.write_text(args.out, f"{args.name}.md", text),
             common.write_csv(args.out, f"{args.name}.csv",
                              ["env", "experiment", "seeds", "mean", "median", "iqm", "iqm_ci_low", "iqm_ci_high",
                               "p_improvement", "p_ci_low", "p_ci_high"], csv_rows)]

    # --- figures ---
    plt = common.pyplot()
    rows = [env for env in [*selection.envs, ALL_ENVS] if any(k[0] == env for k in stats)]
    fig, axes = common.panels(plt, len(rows), columns=3, height=0.55 * len(selection.labels) + 1.6)
    for ax, env in zip(axes, rows):
        labels = [lab for lab in selection.labels if (env, lab) in stats]
        for y, label in enumerate(labels):
            st, color = stats[(env, label)], selection.color(label)
            ax.errorbar(st["iqm"], y, xerr=[[st["iqm"] - st["ci"][0]], [st["ci"][1] - st["iqm"]]], fmt="o",
                        color=color, capsize=4, lw=2, label=label)
            jitter = np.linspace(-0.12, 0.12, len(st["scores"])) if len(st["scores"]) > 1 else [0.0]
            ax.scatter(st["scores"], y + np.asarray(jitter), s=10, color=color, alpha=0.45, lw=0)
        ax.set_yticks(range(len(labels)), labels)
        ax.set_ylim(-0.6, len(labels) - 0.4)
        ax.invert_yaxis()
        ax.set_title(env)
        ax.set_xlabel(f"final return / {base} mean" if env == ALL_ENVS else "final evaluation return")
    fig.suptitle(f"IQM with {level} stratified bootstrap CI; dots: single runs", fontsize=9, color="0.3")
    paths += common.save_figure(fig, args.out, args.name)

    if improvement:
        keys = list(improvement)
        fig, ax = plt.subplots(figsize=(6, 0.45 * len(keys) + 1.4), layout="constrained")
        for y, (env, label) in enumerate(keys):
            point, (low, high) = improvement[(env, label)]
            ax.errorbar(point, y, xerr=[[point - low], [high - point]], fmt="o", color=selection.color(label),
                        capsize=4, lw=2)
        ax.axvline(0.5, color="0.5", ls="--", lw=1)
        ax.set_yticks(range(len(keys)), [f"{env}: {label}" for env, label in keys])
        ax.invert_yaxis()
        ax.set_xlim(-0.02, 1.02)
        ax.set_xlabel(f"P(experiment > {base}) with {level} CI")
        paths += common.save_figure(fig, args.out, f"{args.name}_improvement")

    if normalized:  # rliable's performance profile: the fraction of (env, seed) runs scoring above tau
        taus = np.linspace(0.0, max(1.5, max(float(m.max()) for m in normalized.values()) * 1.05), 101)
        np.random.seed(args.seed)  # create_performance_profile bootstraps with numpy's global generator
        profiles, profile_cis = rly.create_performance_profile(normalized, taus, reps=args.reps,
                                                               confidence_interval_size=args.confidence)
        fig, ax = plt.subplots(figsize=(6, 3.6), layout="constrained")
        plot_utils.plot_performance_profiles(profiles, taus, performance_profile_cis=profile_cis, ax=ax,
                                             colors={label: selection.color(label) for label in profiles},
                                             xlabel=f"final return / {base} mean on the env (tau)",
                                             ylabel="fraction of runs with score > tau", labelsize="medium",
                                             ticklabelsize="small")
        ax.axvline(1.0, color="0.5", ls="--", lw=1)
        ax.legend([plt.Line2D([], [], color=selection.color(label), lw=2) for label in profiles], list(profiles),
                  loc="upper right", fontsize=8)
        ax.set_title(f"performance profiles over {len(selection.envs)} envs, {level} CIs", fontsize=9)
        paths += common.save_figure(fig, args.out, f"{args.name}_profile")
    common.report(paths)
    return paths


if __name__ == "__main__":
    main(common.parse_cli(Args, __doc__.split("\n\n")[0]))
