"""What the continuous PPO scripts (cascade_ppo_continuous.py, ppo_baseline.py) share that is not their algorithm:
CleanRL's env wrapper stack, the checks of the PPO settings and of the env, the parameter count, and CleanRL's
diagnostics of an update as TensorBoard scalars."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn

from . import envs as envs_module
from .envs import OBS_CLIP
from .errors import fail


def make_env(env_id: str, gamma: float, normalize: bool, index: int = 0, video: bool = False) -> Callable[[], gym.Env]:
    """CleanRL's wrapper stack for one env: raw episode stats, action clip, obs/reward normalization, +-10 clips."""
    return envs_module.make_env(env_id, index, video, gym.wrappers.ClipAction, normalize, gamma, clip=OBS_CLIP)


def make_vector_env(args: Any) -> gym.vector.VectorEnv:
    """One env in this process, or --num-envs > 1 envs stepped in parallel worker processes."""
    return envs_module.make_vector_env([make_env(args.env_id, args.gamma, args.normalize, i, args.capture_video and i == 0)
                                        for i in range(args.num_envs)])


def check_ppo_settings(args: Any) -> int:
    """--learning-rate, --num-minibatches and --update-epochs, --num-envs and --num-steps (default: 2048 //
    num_envs, so a batch stays 2048 steps; set here), the batch's split into minibatches (naming the --num-envs that
    keep it whole) and the evaluation settings, refused in one line each. Returns the rollout batch size."""
    if not args.learning_rate >= 0:
        fail(f"--learning-rate must be >= 0 (got {args.learning_rate})")
    if args.num_minibatches < 1 or args.update_epochs < 1:
        fail(f"--num-minibatches and --update-epochs must be at least 1 (got {args.num_minibatches}, {args.update_epochs})")
    if args.num_envs < 1:
        fail(f"--num-envs must be at least 1 (got {args.num_envs})")
    steps_defaulted = args.num_steps is None
    if steps_defaulted:
        args.num_steps = max(2048 // args.num_envs, 1)
    if args.num_steps < 1:
        fail(f"--num-steps must be at least 1 (got {args.num_steps})")
    batch_size = args.num_envs * args.num_steps
    if batch_size % args.num_minibatches:
        hint = ""
        if steps_defaulted:  # the batch is 2048 // num_envs * num_envs: say which --num-envs keep it whole
            working = [e for e in range(1, 17) if (2048 // e * e) % args.num_minibatches == 0]
            hint = f"; with --num-minibatches {args.num_minibatches}, --num-envs {', '.join(map(str, working))} work"
        fail(f"the batch size {batch_size} (num_envs*num_steps) is not divisible by --num-minibatches "
             f"{args.num_minibatches}{hint}, or set --num-steps")
    if getattr(args, "norm_adv", False) and batch_size // args.num_minibatches < 2:  # (a std over one row is NaN)
        fail(f"a minibatch of one row (batch {batch_size} in --num-minibatches {args.num_minibatches}) cannot "
             "normalize its advantages (--norm-adv); lower --num-minibatches, raise --num-steps or --num-envs, or "
             "pass --no-norm-adv")
    if args.eval_every < 0 or args.eval_episodes < 1:  # (also with --eval-every 0: a negative count is no setting)
        fail("--eval-every must be >= 0 and --eval-episodes >= 1")
    return batch_size


def baseline_updates(args: Any, batch_size: int) -> int:
    """The updates of a PPO baseline run: --total-timesteps in whole rollouts; under `--lr-schedule cyclic`, whole
    cycles of `cycle_steps // batch_size` updates each (as Cascade's iterations of `k // batch_size`), then what
    remains. (Rounded as one total, 6M steps in cycles of 1M were 2929 updates of 2048 = 6 x 488 + 1: the last update
    began a 7th cycle, a fresh Adam at the full learning rate, just before the final evaluation.)"""
    if args.lr_schedule != "cyclic":
        return args.total_timesteps // batch_size
    cycles, rest = divmod(args.total_timesteps, args.cycle_steps)
    return cycles * (args.cycle_steps // batch_size) + rest // batch_size


def count_parameters(*modules: nn.Module) -> int:
    return sum(p.numel() for m in modules for p in m.parameters())


def log_ppo_update(writer: Any, global_step: int, optimizer: torch.optim.Optimizer, parts: dict,
                   old_approx_kl: torch.Tensor, approx_kl: torch.Tensor, ratios: torch.Tensor, b_values: torch.Tensor,
                   b_returns: torch.Tensor, clip_coef: float, fast: Any) -> None:
    """CleanRL's scalars of one update (ppo_continuous_action.py's names; the losses from the epoch's last
    minibatch's `parts`, and any other scalar part as `losses/<name>`) and the state of the fast paths (`fast`: cascade_plumbing.fast.FastPaths)."""
    write = writer.add_scalar
    y_pred, y_true = b_values.cpu().numpy(), b_returns.cpu().numpy()
    var_y = np.var(y_true)
    explained_var = np.nan if var_y == 0 else 1 - np.var(y_true - y_pred) / var_y
    write("charts/learning_rate", optimizer.param_groups[0]["lr"], global_step)
    write("losses/value_loss", parts["value_loss"].item(), global_step)
    write("losses/policy_loss", parts["policy_loss"].item(), global_step)
    write("losses/entropy", parts["entropy"].item(), global_step)
    write("losses/old_approx_kl", old_approx_kl.item(), global_step)
    write("losses/approx_kl", approx_kl.item(), global_step)
    write("losses/clipfrac", ((ratios - 1.0).abs() > clip_coef).float().mean().item(), global_step)
    write("losses/explained_variance", explained_var, global_step)
    written = {"value_loss", "policy_loss", "entropy", "old_approx_kl", "approx_kl", "clipfrac", "explained_variance"}
    for key, value in parts.items():  # a scalar part that an edit added to ppo_loss's dict, under its own name
        if key not in written and value.dim() == 0:  # (not the per-sample ratios, even of a one-row minibatch)
            write(f"losses/{key}", value.item(), global_step)
    write("charts/fast_acting", float(fast.acting), global_step)
    write("charts/fast_gradients", float(fast.gradients), global_step)
    write("charts/fast_path_check_seconds", fast.check_seconds, global_step)
