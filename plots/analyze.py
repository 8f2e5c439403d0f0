"""Analyses of saved Cascade models and of run logs: fallback course, plasticity, parameters and runtime.

    python plots/analyze.py fallback-course --checkpoint runs/<run>            # Fig. 17
    python plots/analyze.py plasticity --checkpoint runs/<run>                 # Appendix J
    python plots/analyze.py table2 --runs runs                                 # Table 2

fallback-course: one episode (capped at --max-steps) of the saved policy, with its saved
observation-normalization statistics, recording λ_i(x_t) of every net i ≥ 2 at every step.

plasticity (Appendix J, after Lyle et al. 2023), measured for the stack right before a base net is
added (`iteration_<i>.pt`, default i = 1) and right after (the same stack plus net i+1):
- f(x, θ) = the ensemble's action mean averaged over the action dims (the log-std is left out);
- X = `--observations` observations drawn uniformly from a pool 5× that size, collected by rolling
  out the stochastic policy of the stack after adding (`--observations-from before` for the one before),
  normalized with the checkpoint's observation statistics; the same X for both stacks;
- for each of `--samples` draws ω from the init distribution of the same architecture (a freshly built
  stack of as many nets; the draws are seeded, so both stacks share the first net's ω), the targets are
  a + sin(1e5·f(x, ω)) with a = mean_x f(x, θ); a copy of θ is fitted to them by `--updates` full-batch
  Adam steps (lr 3e-4, eps 1e-5: PPO's optimizer, without gradient clipping) on the squared error;
- plasticity = b − mean final loss, with b = mean over x and ω of sin²(1e5·f(x, ω)): the loss of the
  constant prediction a. (Eq. 4 of the paper writes b without the square; E[sin] is ~0, and the paper's
  reported b of 0.50-0.56 is the mean square, which is what we use.)
The stack after adding is built exactly as training builds it: the checkpoint's net stack, the torch
RNG state saved in the checkpoint restored, then `add_base_net()`, which draws the very init the run
drew for net i+1 (the checkpoint is written right before training adds the next net); with
--freeze-previous runs only the new net is trained, as in training.

table2: per env and experiment, the parameter count (last `cascade/parameters`, actor + critic, or
`charts/parameters` for PPO) and the training time, mean ± std over seeds: for a run exported to results/,
the time its final checkpoint recorded (a killed run's downtime excluded); for a raw run folder, the wall time
from its first to its last logged event (a resumed run's downtime included).
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
import tyro

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # for `python plots/<script>.py`
import cascade_ppo_continuous as cpc  # noqa: E402
from cascade_plumbing.errors import parse_command_line  # noqa: E402
from plots import common  # noqa: E402


@dataclass
class FallbackCourse:
    """the fallback λ_i of each net over one episode of a saved Cascade policy (paper Fig. 17)"""

    checkpoint: str
    """a run folder (its latest `checkpoint.pt`) or a checkpoint file of cascade_ppo_continuous.py"""
    out: str = "figures"
    """folder the figure (PNG and PDF) and tables are written to"""
    name: str = "fallback_course"
    """file name (without extension) of the outputs"""
    nets: tuple[int, ...] = ()
    """nets i (2..n) to draw (default: all; the paper shows the second oldest and the latest)"""
    max_steps: int = 1000
    """episode length cap (the paper: 1000)"""
    deterministic: bool = False
    """act with the mean action instead of sampling"""
    seed: int = 1
    """seed of the episode's reset and of the action noise"""


@dataclass
class Plasticity:
    """plasticity of the net stack right before and right after a base net is added (paper Appendix J)"""

    checkpoint: str
    """`iteration_<i>.pt`, or a run folder (its `iteration_1.pt`): the stack right before net i+1 is added"""
    out: str = "figures"
    """folder the tables are written to"""
    name: str = "plasticity"
    """file name (without extension) of the outputs"""
    updates: int = 10_000
    """optimizer steps per fit (the paper: 10^4)"""
    samples: int = 10
    """draws of the random target parameters ω (the paper: 10)"""
    observations: int = 1000
    """observations the targets are fitted on (the paper: 1000)"""
    observations_from: Literal["after", "before"] = "after"
    """whose policy collects the observations: the stack after adding the net (the paper) or before"""
    learning_rate: float = 3e-4
    """Adam's learning rate (training's initial rate)"""
    seed: int = 0
    """seed of the rollouts, the subsampling and the draws of ω"""


@dataclass
class Table2:
    """parameter count and runtime per env and experiment from run logs (paper Table 2)"""

    runs: tuple[str, ...] = ("runs",)
    """folders holding run folders `<env>__<exp_name>__<seed>__<time>` (searched at any depth)"""
    out: str = "figures"
    """folder the tables are written to"""
    name: str = "table2"
    """file name (without extension) of the outputs"""
    envs: tuple[str, ...] = ()
    """env ids to include, in this order (default: every env found)"""
    experiments: tuple[str, ...] = ()
    """experiment names (`--exp-name` of the runs), in this order (default: all found)"""
    labels: tuple[str, ...] = ()
    """display names as EXP=LABEL (defaults: cascade_ppo_continuous=Cascade, ppo_baseline=PPO)"""
    allow_incomplete: bool = False
    """keep runs that stop before the others of their env and experiment in the final numbers (noted either way)"""


# ----------------------------------------------------------------------------------------------
# Shared: acting with a saved policy
# ----------------------------------------------------------------------------------------------
def make_env(env_id: str):
    import gymnasium as gym

    return gym.make(env_id)


def rollout(actor: cpc.CascadeActor, stats, env_id: str, steps: int, seed: int, deterministic: bool = False,
            one_episode: bool = False) -> dict[str, np.ndarray | float]:
    """Act with `actor` on raw observations normalized by the frozen `stats`.

    Returns the raw observations [T, obs_dim], the fallbacks [T, n-1] and the first episode's return.
    Runs `steps` steps over as many episodes as needed (or stops at the end of the first with one_episode).
    """
    env = make_env(env_id)
    generator = torch.Generator().manual_seed(seed)
    obs, _ = env.reset(seed=seed)
    observations, fallbacks, episode_return, first_return = [], [], 0.0, None
    with torch.inference_mode():
        while len(observations) < steps:
            observations.append(obs)
            mean, log_std, fallback, _ = actor(torch.as_tensor(cpc.normalize_obs(obs[None], stats)))
            fallbacks.append(fallback[:, 0].numpy())
            if not deterministic:
                mean = mean + torch.exp(log_std) * torch.randn(mean.shape, generator=generator)
            action = np.clip(mean[0].numpy(), env.action_space.low, env.action_space.high)
            obs, reward, terminated, truncated, _ = env.step(action)
            episode_return += float(reward)
            if terminated or truncated:
                first_return = episode_return if first_return is None else first_return
                if one_episode:
                    break
                obs, _ = env.reset()
                episode_return = 0.0
    env.close()
    return {"observations": np.array(observations), "fallbacks": np.array(fallbacks),
            "return": episode_return if first_return is None else first_return}


def checkpoint_args(checkpoint: dict) -> cpc.Args:
    return cpc.Args(**checkpoint["args"])


# ----------------------------------------------------------------------------------------------
# fallback-course (Fig. 17)
# ----------------------------------------------------------------------------------------------
def fallback_course(args: FallbackCourse) -> list[str]:
    checkpoint = cpc.load_checkpoint(args.checkpoint, reader_flag="--checkpoint")
    saved = checkpoint_args(checkpoint)
    actor = cpc.actor_from_checkpoint(checkpoint)
    if actor.size < 2:
        later = ("pass a later iteration_<i>.pt or the run's checkpoint.pt" if saved.n > 1
                 else "its run has no other (--n 1): pass a checkpoint of a run with --n 2 or more")
        common.fail(f"{checkpoint['path']} holds 1 base net, which has no fallback; {later}")
    nets = list(args.nets) or list(range(2, actor.size + 1))
    bad = [i for i in nets if not 2 <= i <= actor.size]
    if bad:
        common.fail(f"--nets {' '.join(map(str, bad))}: this checkpoint's nets with a fallback are 2..{actor.size}")
    result = rollout(actor, checkpoint["obs_stats"], saved.env_id, args.max_steps, args.seed, args.deterministic,
                     one_episode=True)
    fallbacks = result["fallbacks"]  # [T, n-1], column j is net j+2
    steps = np.arange(len(fallbacks))

    plt = common.pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 3.6), layout="constrained")
    for i in nets:
        latest_or_second = i in (2, actor.size)
        ax.plot(steps, fallbacks[:, i - 2], color=common.OKABE_ITO[(i - 2) % len(common.OKABE_ITO)],
                lw=1.5 if latest_or_second else 0.9, alpha=1.0 if latest_or_second else 0.7, label=f"λ_{i} (net {i})")
    ax.set_xlabel("step of the episode")
    ax.set_ylabel("fallback λᵢ(x)")
    ax.set_ylim(-0.02, 1.02)
    mode = "deterministic" if args.deterministic else "stochastic"
    ax.set_title(f"{saved.env_id}: {actor.size} nets after {checkpoint['global_step']:,} steps; "
                 f"{mode} episode, return {result['return']:.0f}", fontsize=10)
    ax.legend(frameon=False, ncol=min(3, len(nets)))
    paths = common.save_figure(fig, args.out, args.name)
    paths.append(common.write_csv(args.out, f"{args.name}.csv", ["step", *(f"lambda_{i}" for i in nets)],
                                  [[int(t), *(float(fallbacks[t, i - 2]) for i in nets)] for t in steps]))
    rows = [[f"λ_{i}", f"{fallbacks[:, i - 2].mean():.3f}", f"{fallbacks[:, i - 2].std():.3f}"] for i in nets]
    text = (f"Fallback course over one {mode} episode of {len(steps)} steps (return {result['return']:.1f}) of "
            f"{checkpoint['path']}.\n\n" + common.markdown_table(["net", "mean λ", "std λ within the episode"], rows))
    paths.append(common.write_text(args.out, f"{args.name}.md", text))
    common.report(paths)
    return paths


# ----------------------------------------------------------------------------------------------
# plasticity (Appendix J)
# ----------------------------------------------------------------------------------------------
def build_actor(saved: cpc.Args, obs_dim: int, act_dim: int, size: int) -> cpc.CascadeActor:
    """A freshly initialized stack of `size` nets (draws from the global torch RNG)."""
    actor = cpc.CascadeActor(obs_dim, act_dim, saved.hidden_size, saved.num_layers, saved.fallback_init)
    for _ in range(size):
        actor.add_base_net()
    return actor


def clone_actor(actor: cpc.CascadeActor, saved: cpc.Args) -> cpc.CascadeActor:
    with torch.random.fork_rng():
        clone = build_actor(saved, actor.obs_dim, actor.act_dim, actor.size)
    clone.load_state_dict(actor.state_dict())
    clone.freeze_below(actor.num_frozen)
    return clone


def stack_after_adding(checkpoint: dict) -> cpc.CascadeActor:
    """The checkpoint's stack plus the base net training adds next, with the run's own init draw."""
    saved = checkpoint_args(checkpoint)
    actor = cpc.actor_from_checkpoint(checkpoint)
    with torch.random.fork_rng():
        if "rng" in checkpoint:
            torch.set_rng_state(checkpoint["rng"]["torch"])
        else:
            common.note(f"{checkpoint['path']} holds no RNG state; the added net is drawn with seed {saved.seed}")
            torch.manual_seed(saved.seed)
        actor.add_base_net()
    if saved.freeze_previous:
        actor.freeze_below(actor.size - 1)
    return actor


def f_out(actor: cpc.CascadeActor, x: torch.Tensor) -> torch.Tensor:
    """The one-dimensional output of Appendix J: the ensemble's action mean averaged over action dims."""
    return actor(x)[0].mean(-1)


def measure_plasticity(actor: cpc.CascadeActor, saved: cpc.Args, x: torch.Tensor, samples: int, updates: int,
                       learning_rate: float, seed: int) -> dict[str, np.ndarray]:
    """Per draw of ω: b (mean sin²), the loss before fitting and after `updates` Adam steps."""
    with torch.no_grad():
        a = f_out(actor, x).mean()
    result = {"b": [], "initial_loss": [], "final_loss": []}
    for sample in range(samples):
        with torch.random.fork_rng():
            torch.manual_seed(seed + sample)
            omega = build_actor(saved, actor.obs_dim, actor.act_dim, actor.size)
        with torch.no_grad():
            wave = torch.sin(1e5 * f_out(omega, x))
            target = a + wave
        theta = clone_actor(actor, saved)
        optimizer = torch.optim.Adam(theta.parameters(), lr=learning_rate, eps=1e-5)
        with torch.no_grad():
            result["initial_loss"].append(float(((f_out(theta, x) - target) ** 2).mean()))
        for _ in range(updates):
            loss = ((f_out(theta, x) - target) ** 2).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        with torch.no_grad():
            result["final_loss"].append(float(((f_out(theta, x) - target) ** 2).mean()))
        result["b"].append(float((wave ** 2).mean()))
    return {key: np.array(values) for key, values in result.items()}


def resolve_iteration_checkpoint(path: str) -> str:
    if os.path.isdir(path):
        path = os.path.join(path, "iteration_1.pt")
        if not os.path.isfile(path):
            common.fail(f"no {path}: pass a run folder of cascade_ppo_continuous.py or an iteration_<i>.pt file")
    return path


def plasticity(args: Plasticity) -> dict:
    if min(args.updates, args.samples, args.observations) < 1:
        common.fail("--updates, --samples and --observations must be at least 1")
    if not args.learning_rate > 0:
        common.fail(f"--learning-rate {args.learning_rate}: Adam's learning rate must be positive (training's: 3e-4)")
    checkpoint = cpc.load_checkpoint(resolve_iteration_checkpoint(args.checkpoint), reader_flag="--checkpoint")
    saved = checkpoint_args(checkpoint)
    if saved.start_full:
        common.fail(f"{checkpoint['path']} is a --start-full run: it never adds a net, so there is no before/after")
    updates_per_iteration = saved.k // (saved.num_envs * saved.num_steps)
    if checkpoint.get("updates_done", updates_per_iteration) != updates_per_iteration:
        common.fail(f"{checkpoint['path']} was written in the middle of iteration {checkpoint['iteration']}; "
                    "pass an iteration_<i>.pt, written right before net i+1 is added")
    torch.set_num_threads(1)
    before = cpc.actor_from_checkpoint(checkpoint)
    after = stack_after_adding(checkpoint)
    stats = checkpoint["obs_stats"]
    collector = after if args.observations_from == "after" else before
    pool = rollout(collector, stats, saved.env_id, 5 * args.observations, args.seed)["observations"]
    chosen = np.random.default_rng(args.seed).choice(len(pool), size=args.observations, replace=False)
    x = torch.as_tensor(cpc.normalize_obs(pool[chosen], stats))

    rows, csv_rows, result = [], [], {}
    for which, actor in (("before", before), ("after", after)):
        measured = measure_plasticity(actor, saved, x, args.samples, args.updates, args.learning_rate, args.seed)
        p = measured["b"] - measured["final_loss"]
        result[which] = {**measured, "plasticity": p, "nets": actor.size}

        def cell(values: np.ndarray) -> str:
            sem = values.std(ddof=1) / np.sqrt(len(values)) if len(values) > 1 else None
            return common.fmt(float(values.mean()), sem, 4)

        rows.append([which, actor.size, cell(measured["b"]), cell(measured["initial_loss"]),
                     cell(measured["final_loss"]), cell(p)])
        csv_rows += [[which, actor.size, s, measured["b"][s], measured["initial_loss"][s], measured["final_loss"][s],
                      p[s]] for s in range(args.samples)]
    text = (f"Plasticity of {checkpoint['path']} ({saved.env_id}, after {checkpoint['global_step']:,} steps) "
            f"right before and right after base net {before.size + 1} is added: {args.samples} draws of ω, "
            f"{args.updates} Adam updates on {args.observations} observations collected by the policy "
            f"{args.observations_from} adding (mean ± standard error over draws; see plots/analyze.py).\n\n"
            + common.markdown_table(["stack", "nets", "b = E[sin²]", "loss before fit", "loss after fit",
                                     "plasticity b − loss"], rows))
    paths = [common.write_text(args.out, f"{args.name}.md", text),
             common.write_csv(args.out, f"{args.name}.csv",
                              ["stack", "nets", "sample", "b", "initial_loss", "final_loss", "plasticity"], csv_rows)]
    print(text)
    common.report(paths)
    return result


# ----------------------------------------------------------------------------------------------
# table2 (Table 2)
# ----------------------------------------------------------------------------------------------
PARAMETER_TAGS = ("cascade/parameters", "charts/parameters")


def run_parameters(run: common.Run) -> float | None:
    for tag in PARAMETER_TAGS:
        if tag in run.scalars:
            return float(run.scalars[tag].values[-1])
    return None


def run_seconds(run: common.Run) -> float:
    """Training time: an exported run's (from its final checkpoint), else the wall time from the first to
    the last logged scalar event."""
    if run.meta.get("seconds"):
        return float(run.meta["seconds"])
    first = min(float(s.wall_times.min()) for s in run.scalars.values() if len(s.wall_times))
    last = max(float(s.wall_times.max()) for s in run.scalars.values() if len(s.wall_times))
    return last - first


def fmt_duration(seconds: float) -> str:
    if seconds >= 360:
        return f"{seconds / 3600:.1f} h"
    if seconds >= 60:
        return f"{seconds / 60:.1f} min"
    return f"{seconds:.1f} s"


def table2(args: Table2) -> list[str]:
    selection = common.select_runs(args.runs, args.envs, args.experiments, labels=args.labels,
                                   complete_only=not args.allow_incomplete)
    everything = [r for runs in selection.groups.values() for r in runs]
    if all(run_parameters(r) is None for r in everything):
        logged = sorted({t for r in everything for t in r.scalars})
        common.fail(f"no run logs {' or '.join(repr(t) for t in PARAMETER_TAGS)} (looked in "
                    f"{common.describe(everything)}; they log: {common.short_list(logged)})")
    long_rows, csv_rows, pivot = [], [], {}
    for (env, label), runs in selection.groups.items():
        params = sorted({run_parameters(r) for r in runs} - {None})
        if len(params) > 1:
            common.note(f"runs of {env}/{label} differ in parameter count ({', '.join(f'{p:.0f}' for p in params)})")
        seconds = np.array([run_seconds(r) for r in runs])
        steps = int(np.mean([r.last_step() for r in runs]))
        spread = f" ± {fmt_duration(seconds.std(ddof=1))}" if len(runs) > 1 else ""
        param_text = "–" if not params else " / ".join(f"{p:.0f}" for p in params)
        runtime = fmt_duration(seconds.mean()) + spread
        per_million = fmt_duration(seconds.mean() / steps * 1e6) if steps else "–"
        long_rows.append([env, label, len(runs), f"{steps:,}", param_text, runtime, per_million])
        csv_rows.append([env, label, len(runs), steps, params[0] if len(params) == 1 else "", float(seconds.mean()),
                         float(seconds.std(ddof=1)) if len(runs) > 1 else ""])
        pivot.setdefault(env, {})[label] = (param_text, runtime)
    labels = selection.labels
    pivot_rows = [[env, *(pivot[env].get(lab, ("–", "–"))[0] for lab in labels),
                   *(pivot[env].get(lab, ("–", "–"))[1] for lab in labels)] for env in selection.envs]
    text = ("## Table 2: parameters (actor + critic) and runtime\n\n"
            "Runtime: training time with evaluation, mean ± std over seeds. For an exported run (results/per_run) it is "
            "the time its final checkpoint recorded, without the downtime of a resumed run; for a run folder, the "
            "wall time from its first to its last logged event, downtime included.\n\n"
            + common.markdown_table(["Env", *(f"Parameters {lab}" for lab in labels),
                                     *(f"Runtime {lab}" for lab in labels)], pivot_rows)
            + "\n" + common.markdown_table(["env", "experiment", "seeds", "steps", "parameters", "runtime",
                                            "runtime per 1M steps"], long_rows))
    paths = [common.write_text(args.out, f"{args.name}.md", text),
             common.write_csv(args.out, f"{args.name}.csv",
                              ["env", "experiment", "seeds", "steps", "parameters", "seconds_mean", "seconds_std"],
                              csv_rows)]
    print(text)
    common.report(paths)
    return paths


COMMANDS = {"fallback-course": FallbackCourse, "plasticity": Plasticity, "table2": Table2}


def main(args: FallbackCourse | Plasticity | Table2) -> object:
    if isinstance(args, FallbackCourse):
        return fallback_course(args)
    if isinstance(args, Plasticity):
        return plasticity(args)
    return table2(args)


if __name__ == "__main__":
    parsed = parse_command_line(lambda: tyro.extras.subcommand_cli_from_dict(COMMANDS, description=__doc__.split("\n\n")[0]))
    common.check_cli(parsed)
    main(parsed)
