"""Rebuild every figure and table of the paper reproduction from the committed per-run files alone.

Reads `results/per_run/*.json` (written by plots/export_results.py from finished runs of
`python sweep.py --preset reproduce`: standard Cascade, n=6, k=1M, against PPO for 6M steps, both
evaluated every 50,000 steps with 10 episodes) and writes to `results/figures/`:

- `fig2_learning_curves.png|pdf`: evaluation return over env steps per env, mean ± standard error over
  seeds (the paper's Fig. 2 layout);
- `final_performance.*`: a run's score is the mean of its last 3 evaluations; IQM with 95% stratified
  bootstrap CIs and the probability that Cascade beats PPO (rliable), and rliable's performance profiles;
- `fallback_tables.md` (Tables 1 and 3), `members.*` (Section 4.2), `runtime.md` (Table 2's runtime);
- `summary.md`: the tables above next to the paper's numbers.

    python plots/reproduce.py                       # results/per_run -> results/figures
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass

import numpy as np
import tyro
from rliable import metrics

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # for `python plots/<script>.py`
from plots import analyze, common, fallback, final_performance, learning_curves, members  # noqa: E402

ENV_ORDER = ("HalfCheetah-v4", "Ant-v4", "Hopper-v4", "Walker2d-v4", "Humanoid-v4")
LABELS = ("cascade=Cascade", "ppo=PPO")
# The paper's numbers (Schmöcker & Dockhorn, RLJ 2025: Table 1, Section 4.5; Table 2, Appendix K, its runtimes on a
# 28-core Xeon Gold 5120, Ant; Table 3, Appendix L; the verdicts of Fig. 2, Section 4.2)
PAPER_TABLE1 = {"Ant-v4": [0.96, 0.96, 0.96, 0.96, 0.88], "Walker2d-v4": [0.82, 0.85, 0.92, 0.90, 0.81]}
PAPER_TABLE3 = {"Ant-v4": [0.051, 0.039, 0.041, 0.046, 0.087], "Walker2d-v4": [0.198, 0.174, 0.144, 0.113, 0.095]}
PAPER_VERDICT = {"HalfCheetah-v4": "Cascade better", "Ant-v4": "Cascade better", "Hopper-v4": "draw",
                 "Walker2d-v4": "draw", "Humanoid-v4": "Cascade better"}


@dataclass
class Args:
    runs: str = "results/per_run"
    """folder of exported runs (JSON)"""
    out: str = "results/figures"
    """folder the figures and tables are written to"""
    final_window: int = 3
    """a run's final score: the mean of its last this many evaluations"""
    reps: int = 2000
    """bootstrap replicates of the confidence intervals"""
    allow_incomplete: bool = False
    """keep runs that stop before the others of their env and experiment in the final numbers (noted either way)"""


def final_scores(runs: list[common.Run], window: int) -> np.ndarray:
    return np.array([r.series("eval/episodic_return").last(window) for r in runs])


def summary(args: Args) -> str:
    """The reproduction next to the paper's numbers, per env."""
    selection = common.select_runs((args.runs,), [e for e in ENV_ORDER if e in envs_present(args.runs)],
                                   ("cascade", "ppo"), labels=LABELS, complete_only=not args.allow_incomplete)
    lines = ["# Reproduction of the paper's Fig. 2 (our runs, results/per_run)", "",
             f"Score of a run: mean evaluation return over its last {args.final_window} evaluations (every 50k steps, "
             "10 stochastic episodes each). Mean ± standard error over seeds; P(Cascade > PPO) is the share of "
             "(Cascade run, PPO run) pairs where Cascade scored higher.", ""]
    rows = []
    for env in selection.envs:
        groups = {label: selection.groups.get((env, label), []) for label in ("Cascade", "PPO")}
        scores = {label: final_scores(runs, args.final_window) for label, runs in groups.items() if runs}
        cells = []
        for label in ("Cascade", "PPO"):
            s = scores.get(label)
            if s is None:
                cells.append("–")
            else:
                mean, sem = common.mean_sem(s)
                cells.append(f"{common.fmt(float(mean), float(sem) if len(s) > 1 else None, 0)} (n={len(s)})")
        if len(scores) == 2:
            p = float(metrics.probability_of_improvement(np.asarray(scores["Cascade"])[:, None],
                                                         np.asarray(scores["PPO"])[:, None]))
            cells.append(f"{p:.2f}")
        else:
            cells.append("–")
        steps = max((r.last_step() for runs in groups.values() for r in runs), default=0)
        rows.append([env, f"{steps:,}", *cells, PAPER_VERDICT.get(env, "–")])
    lines.append(common.markdown_table(["env", "steps", "Cascade", "PPO", "P(Cascade > PPO)", "paper (Fig. 2)"], rows))
    for env, paper in PAPER_TABLE1.items():
        runs = selection.groups.get((env, "Cascade"), [])
        if not runs:
            continue
        ours = fallback.final_per_net(runs, "cascade/fallback/net_", list(range(2, 7)), args.final_window)
        std = fallback.final_per_net(runs, "cascade/fallback_std/net_", list(range(2, 7)), args.final_window)
        lines += ["", f"## {env}: Table 1 (final mean fallback λ, nets 2..6) and Table 3 (std of λ within an episode)",
                  "", common.markdown_table(
                      ["", *(f"net {i}" for i in range(2, 7))],
                      [["Table 1, ours", *(f"{ours[i][0]:.2f}" if i in ours else "–" for i in range(2, 7))],
                       ["Table 1, paper", *(f"{v:.2f}" for v in paper)],
                       ["Table 3, ours", *(f"{std[i][0]:.3f}" if i in std else "–" for i in range(2, 7))],
                       ["Table 3, paper", *(f"{v:.3f}" for v in PAPER_TABLE3[env])]])]
    ant = selection.groups.get(("Ant-v4", "Cascade"), [])
    if ant:
        bottom = [r.series("members/return/net_1").values[-1] for r in ant if "members/return/net_1" in r.scalars]
        full = [r.series("eval/episodic_return").values[-1] for r in ant]
        lines += ["", "## Ant-v4, Section 4.2: the full stack against the bottom net alone (final evaluation)", "",
                  common.markdown_table(["", "full stack", "bottom net alone"],
                                        [["ours", f"{np.mean(full):.0f}", f"{np.mean(bottom):.0f}" if bottom else "–"],
                                         ["paper", "~5.1k", "~3.2k"]])]
    runtime_rows = []
    for env in selection.envs:
        for label in ("Cascade", "PPO"):
            runs = selection.groups.get((env, label), [])
            if runs:
                hours = np.array([analyze.run_seconds(r) for r in runs]) / 3600
                millions = np.mean([r.last_step() for r in runs]) / 1e6
                runtime_rows.append([env, label, len(runs), f"{hours.mean():.2f} h", f"{hours.mean() / millions:.2f} h"])
    lines += ["", "## Runtime (Table 2): training time per run on this 2-core machine, two runs side by side", "",
              common.markdown_table(["env", "algorithm", "runs", "per run", "per 1M steps"], runtime_rows),
              "", "Paper (28-core Xeon Gold 5120, 6M steps on Ant): PPO 5.5 h, Cascade 8.6 h."]
    return "\n".join(lines) + "\n"


def envs_present(folder: str) -> set[str]:
    return {common.parse_run_name(p)[0] for p in common.find_run_dirs([folder])}


def main(args: Args) -> list[str]:
    envs = tuple(e for e in ENV_ORDER if e in envs_present(args.runs))
    if not envs:
        common.fail(f"no exported runs of {', '.join(ENV_ORDER)} in {args.runs}")
    runs = (args.runs,)
    paths = learning_curves.main(learning_curves.Args(runs=runs, out=args.out, name="fig2_learning_curves",
                                                      envs=envs, labels=LABELS))
    paths += final_performance.main(final_performance.Args(runs=runs, out=args.out, envs=envs, labels=LABELS,
                                                           baseline="ppo", final_window=args.final_window,
                                                           reps=args.reps, allow_incomplete=args.allow_incomplete))
    paths += fallback.main(fallback.Args(runs=runs, out=args.out, envs=envs, experiments=("cascade",),
                                         labels=LABELS, final_window=args.final_window,
                                         allow_incomplete=args.allow_incomplete))
    paths += members.main(members.Args(runs=runs, out=args.out, envs=envs, experiments=("cascade",), labels=LABELS))
    paths += analyze.table2(analyze.Table2(runs=runs, out=args.out, name="runtime", envs=envs, labels=LABELS,
                                           allow_incomplete=args.allow_incomplete))
    paths.append(common.write_text(args.out, "summary.md", summary(args)))
    return paths


if __name__ == "__main__":
    main(tyro.cli(Args, description=__doc__.split("\n\n")[0]))
