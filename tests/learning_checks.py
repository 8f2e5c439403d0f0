"""The learning checks: one short run per script on a small task, defined once.

`tests/` asserts on them; `benchmarks/learning_spread.py` runs the same configurations over many seeds,
with learning intact and with learning broken (learning rate 0), to measure the spread the tests'
thresholds are set from. A run on another CPU or math library is, after a few thousand updates, a
different trajectory (floating-point order differs), so a threshold is only portable if it holds for
every seed measured, with a wide margin, and fails for every broken run.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import cascade_ddpg  # noqa: E402
import cascade_ppo_continuous  # noqa: E402
import cascade_ppo_discrete  # noqa: E402
import cascade_sac  # noqa: E402
import ppo_baseline  # noqa: E402
from helpers import read_scalars  # noqa: E402

Curve = list[tuple[int, float]]

K_INVERTED_PENDULUM = 16_384
K_CARTPOLE = 32_768
K_SAC, K_DDPG = 3_000, 4_000


def eval_curve(module, args) -> Curve:
    """Train, then read back the evaluation returns (step, mean return) the run logged."""
    result = module.train(args)
    return read_scalars(result["run_dir"])["eval/episodic_return"]


def cascade_ppo_inverted_pendulum(seed: int, track_dir: str, broken: bool = False) -> Curve:
    """Cascade PPO, 2 nets of 16K steps on InvertedPendulum-v4, evaluated every 8K steps."""
    args = cascade_ppo_continuous.Args(
        env_id="InvertedPendulum-v4", n=2, k=K_INVERTED_PENDULUM, eval_every=8192, eval_episodes=10,
        track_dir=track_dir, seed=seed, quiet=True, learning_rate=0.0 if broken else 3e-4)
    return eval_curve(cascade_ppo_continuous, args)


def ppo_inverted_pendulum(seed: int, track_dir: str, broken: bool = False) -> Curve:
    """The PPO baseline, 32K steps on InvertedPendulum-v4, evaluated every 8K steps."""
    args = ppo_baseline.Args(
        env_id="InvertedPendulum-v4", total_timesteps=2 * K_INVERTED_PENDULUM, eval_every=8192, eval_episodes=10,
        track_dir=track_dir, seed=seed, quiet=True, learning_rate=0.0 if broken else 3e-4)
    return eval_curve(ppo_baseline, args)


def cascade_ppo_cartpole(seed: int, track_dir: str, broken: bool = False) -> Curve:
    """Discrete Cascade PPO, 2 nets of 32K steps on CartPole-v1 (natively discrete, no normalization),
    evaluated every 8K steps."""
    args = cascade_ppo_discrete.Args(
        env_id="CartPole-v1", n=2, k=K_CARTPOLE, eval_every=K_CARTPOLE // 4, eval_episodes=10,
        track_dir=track_dir, seed=seed, quiet=True, learning_rate=0.0 if broken else 2.5e-4)
    return eval_curve(cascade_ppo_discrete, args)


def sac_pendulum(seed: int, track_dir: str, broken: bool = False) -> Curve:
    """Cascade SAC, 2 nets of 3K steps on Pendulum-v1 (500 random steps first), evaluated every 1K steps."""
    args = cascade_sac.Args(
        env_id="Pendulum-v1", n=2, k=K_SAC, learning_starts=500, batch_size=128, eval_every=1000, eval_episodes=10,
        track_dir=track_dir, seed=seed, quiet=True, policy_lr=0.0 if broken else 3e-4)
    return eval_curve(cascade_sac, args)


def ddpg_inverted_pendulum(seed: int, track_dir: str, broken: bool = False) -> Curve:
    """Cascade DDPG with the paper code's 16-16 tanh nets, 2 nets of 4K steps on InvertedPendulum-v4 (500
    random steps at the start of each), evaluated every 1K steps. (Pendulum-v1 needs many more steps with these
    small nets and the annealed learning rate.)"""
    args = cascade_ddpg.Args(
        env_id="InvertedPendulum-v4", n=2, k=K_DDPG, learning_starts=500, batch_size=128, eval_every=1000,
        eval_episodes=10, eval_members=False, track_dir=track_dir, seed=seed, quiet=True,
        learning_rate=0.0 if broken else 3e-4)
    return eval_curve(cascade_ddpg, args)


CHECKS: dict[str, Callable[[int, str, bool], Curve]] = {
    "cascade_ppo_inverted_pendulum": cascade_ppo_inverted_pendulum,
    "ppo_inverted_pendulum": ppo_inverted_pendulum,
    "cascade_ppo_cartpole": cascade_ppo_cartpole,
    "sac_pendulum": sac_pendulum,
    "ddpg_inverted_pendulum": ddpg_inverted_pendulum,
}


def final_return(curve: Curve) -> float:
    """The last evaluation's mean return."""
    return curve[-1][1]


def mean_of_last_three(curve: Curve) -> float:
    """Mean of the last three evaluations (Pendulum's evaluations swing by a few hundred)."""
    return sum(v for _, v in curve[-3:]) / 3


def best_with_two_nets(curve: Curve) -> float:
    """The best evaluation after the second net was added (CartPole's returns swing between evaluations)."""
    return max(v for s, v in curve if s > K_CARTPOLE)


# check name -> (score of a run's evaluation curve, the threshold a learning run must reach).
# Set from benchmarks/learning_spread.py on the development machine (2-core x86-64, OpenBLAS/MKL torch
# CPU build), each threshold far from both sides (intact: learning rate as configured; broken: 0):
#   check                           intact seeds 1..N: min / median / max        broken (lr 0) max   threshold
#   cascade_ppo_inverted_pendulum   12 seeds: 186 / 325 / 734                      8 (3 seeds)         100
#   ppo_inverted_pendulum           12 seeds: 986 / 1000 / 1000                    8 (3 seeds)         300
#   cascade_ppo_cartpole            12 seeds: 187 / 234 / 269                      25 (3 seeds)        100
#   sac_pendulum                    12 seeds: -283 / -183 / -166                   -1213 (3 seeds)     -750
#   ddpg_inverted_pendulum          12 seeds: 55 / 84 / 159                        14.5 (3 seeds)      30
# The two PPO InvertedPendulum rows were measured on the PPO scripts before their rework into sections (issue 17);
# re-measured after it (6 seeds): Cascade 223 / 349 / 441, PPO 914 / 1000 / 1000. With learning rate 0 every
# check fails for all of seeds 1-3 (assert_learns raises), e.g. SAC's best broken seed scores -1213.
# The SAC and DDPG rows were measured after those scripts took the paper's code's defaults (issue 20: fixed
# alpha, a random warm-up with each net; DDPG's 16-16 tanh nets with an annealed learning rate, which learn
# Pendulum-v1 far too slowly for a test, hence InvertedPendulum-v4). Re-checked after the policy delay was counted
# per net (6 seeds): SAC -283 / -184 / -182, DDPG 61 / 76 / 97. Re-measured with their fast paths on (issue 30,
# 2026-12-04, 10 seeds): SAC -267 / -186 / -170, DDPG 58.5 / 72.9 / 97.3; and after they moved to numpy (10 seeds):
# SAC -346 / -181 / -168, DDPG 58.5 / 72.9 / 97.3 (DDPG's returns the same: its trajectories stayed
# within float32 rounding of the earlier ones over these short runs).
SCORES: dict[str, tuple[Callable[[Curve], float], float]] = {
    "cascade_ppo_inverted_pendulum": (final_return, 100.0),
    "ppo_inverted_pendulum": (final_return, 300.0),
    "cascade_ppo_cartpole": (best_with_two_nets, 100.0),
    "sac_pendulum": (mean_of_last_three, -750.0),
    "ddpg_inverted_pendulum": (mean_of_last_three, 30.0),
}


def assert_learns(name: str, track_dir: str, seeds: tuple[int, ...] = (1, 2, 3)) -> None:
    """Passes as soon as one seed's score reaches the check's threshold; fails, listing every seed's curve,
    when none does. Broken learning fails every seed by a wide margin (benchmarks/learning_spread.py), so
    the rule still catches it, while an intact run fails only if all seeds land far below the spread
    measured over many seeds: a machine whose floating point makes seed 1 another trajectory still passes."""
    score, threshold = SCORES[name]
    tried = []
    for seed in seeds:
        curve = CHECKS[name](seed, os.path.join(track_dir, f"seed_{seed}"))
        tried.append((seed, round(score(curve), 1), [(step, round(value, 1)) for step, value in curve]))
        if score(curve) >= threshold:
            return
    raise AssertionError(f"{name}: no seed reached {threshold}: " + "; ".join(
        f"seed {seed}: score {value}, returns {curve}" for seed, value, curve in tried))
