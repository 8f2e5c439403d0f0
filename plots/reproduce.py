"""Rebuild every figure and table of the paper reproduction from the committed per-run files alone.

Reads `results/per_run/*.json` (written by plots/export_results.py from finished runs of
`python sweep.py --preset reproduce`: standard Cascade, n=6, k=1M, against PPO for 6M steps, both
evaluated every 50,000 steps with 10 episodes) and writes to `results/figures/`:

- `fig2_learning_curves.png|pdf`: evaluation return over env steps per env, mean ± standard error over
  seeds (the paper's Fig. 2 layout);
- `final_performance.*`: a run's score is the mean of its last 3 evaluations; IQM with 95% stratified
  bootstrap CIs and the probability that Cascade beats PPO (rliable), and rliable's performance profiles;
- `fallback_tables.md` (Tables 1 and 3), `members.*` (Section 4.2), `runtime.md` (Table 2's runtime);
- `summary.md`: the tables above next to the paper's numbers;
- for each ablation of `python sweep.py --preset ablations` with exported runs (Fig. 3, 4, 5, 10, 11, 12,
  13 on Ant-v4 and Walker2d-v4; Fig. 8 of `--preset tiny` on its envs): `<fig>_*.png|pdf`, its curves beside
  the standard Cascade runs of the same envs and seeds, and a section of `summary.md` with each variant's final score and the paper's statement;
  from the fallback-init runs of Fig. 11 also the paper's Fig. 6 and 7 and Table 1 for each initial fallback
  (`fig6_fig7_fallback_init_product.*`, `_per_net.*`, `_tables.md`);
- for the other scripts, with exported runs of `python sweep.py --preset discrete`, `--preset sac` or `--preset ddpg`: Fig. 16
  (discrete Cascade against discrete PPO), Fig. 14 (Cascade-SAC against SAC) and Fig. 15 (Cascade-DDPG against
  DDPG), drawn and summarized as the ablations are, on the envs with runs; a folder with these runs alone (no
  Fig. 2 runs) gets these figures only.

    python plots/reproduce.py                       # results/per_run -> results/figures
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass

import numpy as np
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


# The ablations (Section 4.3-4.4, Appendix C-G): figure file, paper figure, experiments drawn (exp names of
# `sweep.py --preset ablations`, and `reproduce` for the standard runs), their labels, the paper's statement, and
# the envs drawn (None: every env with a run of a variant)
ABLATION_ENVS = ("Ant-v4", "Walker2d-v4")
ABLATIONS = (
    ("fig3_cyclic_base_net", "Fig. 3", ("cascade", "ppo_h16_cyclic"),
     ("cascade=Cascade", "ppo_h16_cyclic=PPO, one 16-wide net, cyclic LR"),
     "a clear gap between one base net trained by PPO with the cyclic LR and Cascade, on both envs "
     "(Section 4.1)", ABLATION_ENVS),
    ("fig4_frozen", "Fig. 4", ("cascade", "cascade_frozen"),
     ("cascade=Cascade", "cascade_frozen=only the newest net trains"),
     "keeping the earlier nets frozen severely worsens performance (Section 4.3)", ABLATION_ENVS),
    ("fig5_start_full", "Fig. 5", ("cascade", "cascade_start_full"),
     ("cascade=Cascade", "cascade_start_full=the 6-net stack from the start"),
     "the sequential variant clearly outperforms the full stack trained from the start; on Ant-v4 it ends at "
     "almost twice its score (Section 4.4)", ABLATION_ENVS),
    ("fig10_nets", "Fig. 10", ("cascade_n2", "cascade_n4", "cascade"),
     ("cascade_n2=a new net every 3M", "cascade_n4=every 1.5M", "cascade=every 1M (standard)"),
     "more nets within the 6M steps score higher, up to n = 6 (Appendix D)", ABLATION_ENVS),
    ("fig11_fallback_init", "Fig. 11", ("cascade_fallback0.05", "cascade", "cascade_fallback0.9"),
     ("cascade_fallback0.05=fallback init 0.05", "cascade=0.5 (standard)", "cascade_fallback0.9=0.9"),
     "0.5 is the strongest initial fallback on both envs; 0.05 performs poorly (Appendix E)", ABLATION_ENVS),
    ("fig12_global_lr", "Fig. 12", ("cascade", "cascade_global_lr"),
     ("cascade=Cascade (cyclic LR)", "cascade_global_lr=one LR decay over the whole run"),
     "no significant difference, apart from a dip in the last iteration of the global schedule (Appendix F)",
     ABLATION_ENVS),
    ("fig13_frozen_nonorm", "Fig. 13", ("cascade_nonorm", "cascade_frozen_nonorm"),
     ("cascade_nonorm=Cascade, no normalization", "cascade_frozen_nonorm=frozen, no normalization"),
     "without normalization, frozen and standard Cascade end at about the same score (Appendix G)", ABLATION_ENVS),
    ("fig8_tiny", "Fig. 8", ("cascade_tiny_k500k", "cascade_tiny_k1M"),
     ("cascade_tiny_k500k=16 nets of one hidden unit, a new one every 0.5M", "cascade_tiny_k1M=every 1M"),
     "the ensemble's performance increases with each added base net, even when weak nets are added in large "
     "numbers (the paper's abstract; runs: `sweep.py --preset tiny`)", None),
    # the other three scripts (Appendix H and I; runs: `sweep.py --preset discrete`, `sac` and `ddpg`)
    ("fig16_discrete", "Fig. 16", ("cascade_discrete", "ppo_discrete"),
     ("cascade_discrete=Cascade, discrete actions", "ppo_discrete=discrete PPO"),
     "over 10M steps on the discretized envs Cascade ends slightly ahead of discrete PPO on Walker2d and Hopper and "
     "level on HalfCheetah, and takes longer to converge (Appendix I)", ("Hopper-v4", "Walker2d-v4", "HalfCheetah-v4")),
    ("fig14_sac", "Fig. 14", ("cascade_sac", "sac"), ("cascade_sac=Cascade-SAC", "sac=SAC"),
     "over 2M steps Cascade with SAC yields very little or no improvement over SAC (Appendix H.1)", ENV_ORDER),
    ("fig15_ddpg", "Fig. 15", ("cascade_ddpg", "ddpg"), ("cascade_ddpg=Cascade-DDPG", "ddpg=DDPG"),
     "over 6M steps Cascade with DDPG yields very little to no improvement over DDPG (Appendix H.2)", ENV_ORDER),
)


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
    return np.array([common.final_score(r, "eval/episodic_return", window) for r in runs])


def mean_and_error(scores: np.ndarray) -> str:
    """`mean ± standard error` of final scores over seeds (the mean alone for one seed), rounded to integers."""
    mean, sem = common.mean_sem(scores)
    return common.fmt(float(mean), float(sem) if len(scores) > 1 else None, 0)


def summary(args: Args) -> str:
    """The reproduction next to the paper's numbers, per env."""
    selection = common.select_runs((args.runs,), [e for e in ENV_ORDER if e in envs_present(args.runs)],
                                   ("cascade", "ppo"), labels=LABELS, complete_only=not args.allow_incomplete)
    lines = [f"# Reproduction of the paper's Fig. 2 (the runs of {os.path.normpath(args.runs)})", "",
             f"Score of a run: mean evaluation return over its last {args.final_window} evaluations "
             f"({common.evaluation_protocol([r for runs in selection.groups.values() for r in runs])}, stochastic "
             "policy). Mean ± standard error over seeds; P(Cascade > PPO) is the share of "
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
                cells.append(f"{mean_and_error(s)} (n={len(s)})")
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
        windows = fallback.stack_windows(runs, args.final_window, say=False)  # (fallback.py notes them)
        ours = fallback.final_per_net(runs, "cascade/fallback/net_", list(range(2, 7)), windows)
        std = fallback.final_per_net(runs, "cascade/fallback_std/net_", list(range(2, 7)), windows)
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
    ours = " (ours: 2 cores, two runs side by side)" if os.path.normpath(args.runs) == "results/per_run" else ""
    lines += ["", f"## Runtime (Table 2): training time per run, as the runs logged it{ours}", "",
              common.markdown_table(["env", "algorithm", "runs", "per run", "per 1M steps"], runtime_rows),
              "", "Paper (28-core Xeon Gold 5120, 6M steps on Ant): PPO 5.5 h, Cascade 8.6 h."]
    return "\n".join(lines) + "\n"


def envs_present(folder: str) -> set[str]:
    return {common.parse_run_name(p)[0] for p in common.find_run_dirs([folder])}


def main(args: Args) -> list[str]:
    if args.final_window < 1 or args.reps < 1:  # before anything is written, as the missing runs below
        common.fail("--final-window and --reps must be at least 1")
    envs = tuple(e for e in ENV_ORDER if e in envs_present(args.runs))
    if not envs:
        common.fail(f"no exported runs of {', '.join(ENV_ORDER)} in {args.runs}")
    runs = (args.runs,)
    fig2 = ("cascade", "ppo")  # the ablations' runs share the folder
    exported = {common.parse_run_name(p)[1] for p in common.find_run_dirs([args.runs])}
    ablations = ablations_present(args.runs)
    # Fig. 2 needs both of its runs, an ablation drawn beside standard Cascade needs those; a folder of the other
    # scripts' runs only (Fig. 14-16) needs neither (a fault hunt: it was refused for want of Fig. 2's runs)
    needed = {*(fig2 if exported & set(fig2) else ()),
              *("cascade" for ablation in ablations if "cascade" in ablation[2])}
    missing = [exp for exp in fig2 if exp in needed and exp not in exported]
    if missing:  # checked before anything is written: a half-rebuilt figures folder would mix two sets of runs
        common.fail(f"{args.runs} has no exported runs of {' or '.join(missing)}; Fig. 2 compares standard Cascade "
                    "and PPO, and the ablations compare with standard Cascade (`sweep.py --preset reproduce`, then "
                    "plots/export_results.py)")
    if not needed and not ablations:
        common.fail(f"{args.runs} has runs of none of the paper's experiments (Fig. 2's cascade and ppo, the "
                    f"ablations', Fig. 14-16's); export finished runs of `sweep.py --preset ...` there first")
    for path in common.find_run_dirs([args.runs]):  # a damaged file stops here, not after half the figures
        common.read_run(path)
    before = set(os.listdir(args.out)) if os.path.isdir(args.out) else set()
    paths = fig2_and_tables(args, envs) if needed else []
    sections = []
    for name, figure, experiments, labels, paper, ablation_envs in ablations:
        paths += learning_curves.main(learning_curves.Args(runs=runs, out=args.out, name=name, envs=ablation_envs,
                                                          experiments=experiments, labels=labels))
        sections.append(ablation_summary(args, figure, experiments, labels, paper, ablation_envs))
        if name == "fig11_fallback_init":  # Fig. 6 (fallback product) and 7 (each net's fallback) per initial fallback
            paths += fallback.main(fallback.Args(runs=runs, out=args.out, name="fig6_fig7_fallback_init",
                                                 envs=ablation_envs, experiments=experiments, labels=labels,
                                                 final_window=args.final_window,
                                                 allow_incomplete=args.allow_incomplete))
    head = summary(args) if needed else (f"# Reproduction of the paper's figures (the runs of "
                                         f"{os.path.normpath(args.runs)})\n\nNo runs of Fig. 2 (standard Cascade "
                                         "and PPO) here: only the figures below.\n")
    paths.append(common.write_text(args.out, "summary.md", head + "".join(sections)))
    left = sorted(before - {os.path.basename(path) for path in paths})
    if left:  # (not removed: a file of the user's own may be among them)
        common.note(f"{len(left)} file(s) in {args.out} are not from these runs (an earlier build's, not in its new "
                    f"summary.md): {common.short_list(left)}; remove them, or give a new --out")
    return paths


def fig2_and_tables(args: Args, envs: tuple) -> list[str]:
    """Fig. 2, the final performance, the fallback tables, the members and the runtime, from the standard runs."""
    runs, fig2 = (args.runs,), ("cascade", "ppo")
    paths = learning_curves.main(learning_curves.Args(runs=runs, out=args.out, name="fig2_learning_curves",
                                                      envs=envs, experiments=fig2, labels=LABELS))
    paths += final_performance.main(final_performance.Args(runs=runs, out=args.out, envs=envs, experiments=fig2,
                                                           labels=LABELS,
                                                           baseline="ppo", final_window=args.final_window,
                                                           reps=args.reps, allow_incomplete=args.allow_incomplete))
    paths += fallback.main(fallback.Args(runs=runs, out=args.out, envs=envs, experiments=("cascade",),
                                         labels=LABELS, final_window=args.final_window,
                                         allow_incomplete=args.allow_incomplete))
    paths += members.main(members.Args(runs=runs, out=args.out, envs=envs, experiments=("cascade",), labels=LABELS))
    paths += analyze.table2(analyze.Table2(runs=runs, out=args.out, name="runtime", envs=envs, experiments=fig2,
                                           labels=LABELS, allow_incomplete=args.allow_incomplete))
    return paths


def ablations_present(folder: str) -> list[tuple]:
    """The ablations with at least one exported run of a variant (an experiment other than standard Cascade), each
    with the envs it is drawn for: those of its list that have runs (every env with a variant's run if None)."""
    names = [common.parse_run_name(path) for path in common.find_run_dirs([folder])]
    exported = {(name[0], name[1]) for name in names if name is not None}
    present = []
    for name, figure, experiments, labels, paper, envs in ABLATIONS:
        variants = [exp for exp in experiments if exp != "cascade"]
        with_runs = tuple(env for env in (envs or ENV_ORDER) if any((env, exp) in exported for exp in variants))
        elsewhere = sorted({env for env, exp in exported if exp in variants and envs and env not in envs})
        if elsewhere:  # (a fault hunt: sweep.py's default env, Hopper-v4, gave ablation runs no figure, silently)
            common.note(f"{figure}: the runs of {', '.join(variants)} on {', '.join(elsewhere)} are not drawn (the "
                        f"paper draws it on {', '.join(envs)} only)")
        if with_runs:
            drawn = tuple(env for env in envs if any((env, exp) in exported for exp in experiments)) if envs else with_runs
            present.append((name, figure, experiments, labels, paper, drawn))
    return present


def ablation_summary(args: Args, figure: str, experiments: tuple, labels: tuple, paper: str, envs: tuple) -> str:
    """One ablation's final scores per env and experiment (mean ± standard error, seeds) and the paper's statement."""
    selection = common.select_runs((args.runs,), envs, experiments, labels=labels,
                                   complete_only=not args.allow_incomplete)
    names = [label.split("=", 1)[1] for label in labels]
    rows = []
    for env in envs:
        cells = []
        for label in names:
            runs = selection.groups.get((env, label), [])
            if runs:
                cells.append(f"{mean_and_error(final_scores(runs, args.final_window))} "
                             f"(seeds {', '.join(str(r.seed) for r in runs)})")
            else:
                cells.append("–")
        rows.append([env, *cells])
    return "\n".join(["", f"## {figure}: final score (mean of the last {args.final_window} evaluations)", "",
                      common.markdown_table(["env", *names], rows), "", f"Paper: {paper}.", ""])


if __name__ == "__main__":
    main(common.parse_cli(Args, __doc__.split("\n\n")[0]))
