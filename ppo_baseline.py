"""PPO for continuous-action tasks, the baseline of the Cascade paper (single-file, CleanRL style).

Equivalent to CleanRL's `ppo_continuous_action.py` (same network, wrappers and hyperparameters) on
gymnasium 1.x, with the paper's extra baseline flags: `--hidden-size`, `--lr-schedule cyclic
--cycle-steps` (Fig. 3: one 16-wide net whose LR restarts every 1M steps) and `--no-normalize`.

Reading order as in cascade_ppo_continuous.py: `Args`; section 1, the algorithm in plain torch with
autograd (the one definition of the math, and the place to edit it); section 2, fast paths derived
from it and checked against it while training (an edited section 1 makes the run switch to autograd
by itself, with a one-line warning); section 3, plumbing.

    python ppo_baseline.py --env-id Ant-v4 --total-timesteps 6000000
    tensorboard --logdir runs
"""

from __future__ import annotations

import collections
import contextlib
import copy
import errno
import glob
import math
import multiprocessing
import os
import pickle
import random
import shutil
import signal
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Literal

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import tyro
from gymnasium.wrappers.utils import RunningMeanStd
from torch.distributions import Normal

# The paper used the v4 MuJoCo tasks; gymnasium warns on every make that they are out of date.
warnings.filterwarnings("ignore", message=".*is out of date.*")
# A stopped run (Ctrl-C, SIGTERM) closes its --num-envs workers mid-step; that is expected, not worth a warning.
warnings.filterwarnings("ignore", message=".*Calling `close` while waiting for a pending call.*")


@dataclass
class Args:
    exp_name: str = "ppo_baseline"
    """the name of this experiment (part of the run name)"""
    seed: int = 1
    """seed of the experiment (python, numpy, torch and the environments)"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    torch_threads: int = 1
    """torch CPU threads; 1 is fastest for these small nets"""
    cuda: bool = False
    """use CUDA if available (small nets are usually faster on the CPU)"""
    track_dir: str = "runs"
    """folder for the run folders `<track-dir>/<run_name>` (TensorBoard logs, checkpoints); W&B is --track"""
    track: bool = False
    """also log to Weights & Biases (CleanRL's --track): every TensorBoard scalar under its name, the args, this script, the videos; WANDB_MODE=offline logs locally"""
    wandb_project_name: str = "cascade"
    """the W&B project (with --track)"""
    wandb_entity: str | None = None
    """the W&B entity, a user or team (with --track; default: your default entity)"""
    wandb_group: str | None = None
    """the W&B group of the run (with --track; sweep.py gives the runs of one sweep one group)"""
    capture_video: bool = False
    """mp4s of training episodes 0, 1, 8, 27, ..., 1000, 2000, ... of the first env in videos/<run_name>/ (to W&B with --track); with --evaluate: one episode next to the checkpoint. Needs MUJOCO_GL=egl or osmesa"""
    autograd: bool = False
    """act through the torch forward and update with autograd, no fast paths (slower; same results up to rounding)"""

    # Environment
    env_id: str = "Ant-v4"
    """the id of a gymnasium environment with a Box action space (MuJoCo v4 or v5 ids)"""
    normalize: bool = True
    """observation and reward normalization; `--no-normalize` is the Fig. 13 ablation; observations and rewards are clipped to ±10 either way (the paper's code clips raw values too)"""

    # Network and schedule
    total_timesteps: int = 6_000_000
    """total environment steps of the run (the paper's baselines: 2M..6M, Fig. 9)"""
    hidden_size: int = 64
    """width of the two hidden layers of the actor (the critic stays 64-64)"""
    lr_schedule: Literal["global", "cyclic", "constant"] = "global"
    """global: linear decay to 0 over the run (CleanRL); cyclic: decay restarts every --cycle-steps, with a fresh Adam at each restart as the paper's code ran Fig. 3 (a new PPO instance per cycle, the nets kept)"""
    cycle_steps: int = 1_000_000
    """length of one learning-rate cycle in env steps, with --lr-schedule cyclic"""

    # PPO (CleanRL ppo_continuous_action defaults)
    learning_rate: float = 3e-4
    """initial learning rate of the optimizer"""
    num_envs: int = 1
    """training envs; above 1 they step in parallel worker processes (for machines with more cores)"""
    num_steps: int | None = None
    """steps per environment per rollout; default 2048 // num_envs, so a batch stays 2048 steps"""
    gamma: float = 0.99
    """discount factor"""
    gae_lambda: float = 0.95
    """lambda of generalized advantage estimation"""
    num_minibatches: int = 32
    """number of minibatches per epoch"""
    update_epochs: int = 10
    """number of epochs over each rollout"""
    norm_adv: bool = True
    """normalize advantages per minibatch"""
    clip_coef: float = 0.2
    """surrogate clipping coefficient"""
    clip_vloss: bool = True
    """use a clipped value loss"""
    ent_coef: float = 0.0
    """entropy bonus coefficient"""
    vf_coef: float = 0.5
    """value loss coefficient"""
    max_grad_norm: float = 0.5
    """global gradient-norm clip"""
    target_kl: float | None = None
    """stop an update early when the approximate KL exceeds this (off by default)"""

    # Evaluation (SPEC §6)
    eval_every: int = 10_000
    """evaluate the frozen current policy every this many env steps (0 turns evaluation off)"""
    eval_episodes: int = 10
    """episodes per evaluation (stochastic policy, frozen observation statistics)"""
    eval_in_worker: bool = True
    """run evaluations in a separate process beside training (same protocol and results, ~free on 2+ cores)"""

    # Checkpoints, resuming, evaluating a saved model
    checkpoint_every: int = 100_000
    """checkpoint every this many env steps, and at the end of the run (0: at the end only)"""
    resume: str | None = None
    """continue a killed run: `runs/<run_name>` or a checkpoint file; the saved settings are used"""
    evaluate: str | None = None
    """evaluate a saved model (`runs/<run_name>` or a checkpoint file) for --eval-episodes episodes and exit"""
    deterministic: bool = False
    """with --evaluate: act with the mean action instead of sampling"""
    quiet: bool = False
    """no progress display"""



# ==============================================================================================
# 1. THE ALGORITHM, in plain torch with autograd: the one definition of the math (edit it here)
# ==============================================================================================
class TanhMLP(nn.Module):
    """x -> tanh(x W_1 + b_1) -> ... -> x W_L + b_L, weights stored [in, out], orthogonal init (CleanRL)."""

    def __init__(self, sizes: list[int], gains: list[float]):
        super().__init__()
        self.weights, self.biases = nn.ParameterList(), nn.ParameterList()
        for d_in, d_out, gain in zip(sizes[:-1], sizes[1:], gains):
            weight = torch.empty(d_out, d_in)
            nn.init.orthogonal_(weight, gain)
            self.weights.append(nn.Parameter(weight.T.contiguous()))
            self.biases.append(nn.Parameter(torch.zeros(d_out)))
        self._refresh()

    def _refresh(self) -> None:
        # The (weight, bias) pairs as a plain tuple: each access to a ParameterList element costs ~3 us,
        # more than a layer's matmul at these sizes. Rebuilt whenever the Parameters are replaced.
        self.layers = tuple(zip(self.weights, self.biases))

    def _apply(self, fn, recurse=True):  # .to(device), .double() and friends may replace the Parameters
        module = super()._apply(fn, recurse)
        self._refresh()
        return module

    def forward(self, x: torch.Tensor, hidden: list[torch.Tensor] | None = None) -> torch.Tensor:
        """Output [B, out]; appends each hidden activation to `hidden` when given (for the hand-written backward)."""
        *layers, last = self.layers
        for weight, bias in layers:
            x = torch.tanh(torch.addmm(bias, x, weight))
            if hidden is not None:
                hidden.append(x)
        return torch.addmm(last[1], x, last[0])


class Actor(nn.Module):
    """Gaussian policy: mean MLP obs -> H -> H -> A (tanh) and one state-independent log-std vector."""

    def __init__(self, obs_dim: int, act_dim: int, hidden_size: int):
        super().__init__()
        self.mean_net = TanhMLP([obs_dim, hidden_size, hidden_size, act_dim], [math.sqrt(2), math.sqrt(2), 0.01])
        self.log_std = nn.Parameter(torch.zeros(1, act_dim))

    def forward(self, obs: torch.Tensor, hidden: list[torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        mean = self.mean_net(obs, hidden)
        return mean, self.log_std.expand_as(mean)


def make_critic(obs_dim: int) -> TanhMLP:
    """The PPO value net, obs -> 64 -> 64 -> 1 (tanh)."""
    return TanhMLP([obs_dim, 64, 64, 1], [math.sqrt(2), math.sqrt(2), 1.0])


def count_parameters(*modules: nn.Module) -> int:
    return sum(p.numel() for m in modules for p in m.parameters())


def action_distribution(mean: torch.Tensor, log_std: torch.Tensor) -> Normal:
    """The policy pi(.|s): a diagonal Gaussian. Acting samples it as mean + std * noise."""
    return Normal(mean, log_std.exp(), validate_args=False)


def ppo_loss(mean: torch.Tensor, log_std: torch.Tensor, value: torch.Tensor, actions: torch.Tensor,
             old_logprob: torch.Tensor, advantages: torch.Tensor, returns: torch.Tensor, old_value: torch.Tensor,
             args: Args) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """CleanRL's PPO loss on one minibatch (ppo_continuous_action.py); returns the loss and its parts."""
    dist = action_distribution(mean, log_std)
    logratio = dist.log_prob(actions).sum(1) - old_logprob
    ratio = logratio.exp()
    if args.norm_adv:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    pg_loss1 = -advantages * ratio
    pg_loss2 = -advantages * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)
    pg_loss = torch.max(pg_loss1, pg_loss2).mean()
    if args.clip_vloss:
        v_clipped = old_value + torch.clamp(value - old_value, -args.clip_coef, args.clip_coef)
        v_loss = 0.5 * torch.max((value - returns) ** 2, (v_clipped - returns) ** 2).mean()
    else:
        v_loss = 0.5 * ((value - returns) ** 2).mean()
    entropy_loss = dist.entropy().sum(1).mean()
    loss = pg_loss - args.ent_coef * entropy_loss + v_loss * args.vf_coef
    return loss, {"policy_loss": pg_loss, "value_loss": v_loss, "entropy": entropy_loss, "logratio": logratio,
                  "ratio": ratio}


def autograd_gradients(actor: Actor, critic: TanhMLP, params: list[nn.Parameter], minibatch: tuple,
                       args: Args) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The loss of one minibatch and its gradient by autograd, written into every parameter's .grad."""
    obs, actions, old_logprob, advantages, returns, old_value = minibatch
    with torch.enable_grad():
        mean, log_std = actor(obs)
        loss, parts = ppo_loss(mean, log_std, critic(obs).squeeze(1), actions, old_logprob, advantages, returns,
                               old_value, args)
        grads = torch.autograd.grad(loss, params, allow_unused=True)
    for param, grad in zip(params, grads):
        param.grad.copy_(grad) if grad is not None else param.grad.zero_()
    return loss.detach(), {key: value.detach() for key, value in parts.items()}


def compute_gae(rewards: np.ndarray, dones: np.ndarray, values: np.ndarray, next_value: np.ndarray,
                next_done: np.ndarray, gamma: float, gae_lambda: float) -> np.ndarray:
    """Generalized advantage estimates [T, E]. dones[t] marks that obs[t] began a new episode, so the
    step before it does not bootstrap (CleanRL: termination and truncation alike). Plain numpy: the
    backward recursion is 2048 tiny steps, far cheaper than as tensor ops."""
    advantages = np.zeros_like(rewards)
    last = np.zeros_like(next_value)
    for t in reversed(range(len(rewards))):
        not_done = 1.0 - (next_done if t == len(rewards) - 1 else dones[t + 1])
        next_v = next_value if t == len(rewards) - 1 else values[t + 1]
        delta = rewards[t] + gamma * next_v * not_done - values[t]
        last = delta + gamma * gae_lambda * not_done * last
        advantages[t] = last
    return advantages


@torch.no_grad()  # autograd is switched on where a gradient is taken (autograd_gradients, FastPaths checks)
def train(args: Args, checkpoint: dict | None = None) -> dict:
    """Runs PPO (from scratch, or continuing `checkpoint`); returns the final actor, critic and run folder."""
    validate(args)
    torch.set_num_threads(args.torch_threads)
    seed_everything(args.seed, args.torch_deterministic)
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    envs = make_vector_env(args)
    obs_dim = int(np.prod(envs.single_observation_space.shape))
    act_dim = int(np.prod(envs.single_action_space.shape))
    batch_size = args.num_envs * args.num_steps
    minibatch_size = batch_size // args.num_minibatches
    total_updates = args.total_timesteps // batch_size
    updates_per_cycle = max(args.cycle_steps // batch_size, 1)
    run = RunLog(args, checkpoint, obs_dim, act_dim, envs, total_updates * batch_size)
    fast = FastPaths(enabled=not args.autograd, run=run)

    actor = Actor(obs_dim, act_dim, args.hidden_size).to(device)
    critic = make_critic(obs_dim).to(device)
    params = share_one_buffer([*actor.parameters(), *critic.parameters()])
    optimizer = make_optimizer([params], args.learning_rate)
    all_params = [*actor.parameters(), *critic.parameters()]
    run.parameters(count_parameters(actor, critic), checkpoint is None)
    # rollout storage, numpy: the env takes and gives numpy, and the fast acting path runs in numpy
    obs = np.zeros((args.num_steps, args.num_envs, obs_dim), dtype=np.float32)
    actions = np.zeros((args.num_steps, args.num_envs, act_dim), dtype=np.float32)
    rewards = np.zeros((args.num_steps, args.num_envs), dtype=np.float32)
    dones = np.zeros((args.num_steps, args.num_envs), dtype=np.float32)

    def unpack(rows: torch.Tensor) -> tuple[torch.Tensor, ...]:  # obs, actions, old logprob, adv., returns, value
        mb_obs, mb_actions, rest = rows.split([obs_dim, act_dim, 4], 1)
        return (mb_obs, mb_actions, *rest.unbind(1))

    if checkpoint is None:
        global_step, start_update = 0, 1
        next_obs = envs.reset(seed=args.seed)[0].astype(np.float32)
        next_done = np.zeros(args.num_envs, dtype=np.float32)
        run.evaluate(0, actor)
    else:  # the saved nets, optimizer, env states, RNG streams and position in the run
        global_step, next_obs, next_done, start_update = run.restore(checkpoint, actor, critic, optimizer)

    for update in range(start_update, total_updates + 1):
        if args.lr_schedule == "global":
            frac = 1.0 - (update - 1.0) / total_updates
        elif args.lr_schedule == "cyclic":
            frac = 1.0 - ((update - 1) % updates_per_cycle) / updates_per_cycle
            if update > 1 and (update - 1) % updates_per_cycle == 0:
                optimizer = make_optimizer([params], args.learning_rate)  # a new cycle: fresh Adam moments
        else:
            frac = 1.0
        optimizer.param_groups[0]["lr"] = frac * args.learning_rate

        # --- rollout: the weights do not change during it; values and log-probs are computed for the
        # whole batch afterwards ---
        policy = fast.acting_policy(actor, np.concatenate([next_obs, obs[:: max(args.num_steps // 8, 1), 0]]),
                                    global_step)
        noise = torch.randn((args.num_steps, args.num_envs, act_dim))  # torch's RNG stream, used from numpy
        noise_np = noise.numpy()
        for step in range(args.num_steps):
            global_step += args.num_envs
            obs[step] = next_obs
            dones[step] = next_done
            mean, log_std = policy(next_obs)
            actions[step] = mean + np.exp(log_std) * noise_np[step]  # a sample of N(mean, std)
            next_obs, reward, terminations, truncations, infos = envs.step(actions[step])
            rewards[step] = reward
            next_obs = next_obs.astype(np.float32)
            next_done = np.logical_or(terminations, truncations).astype(np.float32)
            run.episodes(infos, global_step)
            if args.eval_every and global_step % args.eval_every < args.num_envs:
                run.evaluate(global_step, actor)

        b_obs = torch.as_tensor(obs, device=device).reshape(-1, obs_dim)
        b_actions = torch.as_tensor(actions, device=device).reshape(-1, act_dim)
        b_logprobs = action_distribution(*actor(b_obs)).log_prob(b_actions).sum(1)
        values = critic(b_obs).reshape(args.num_steps, args.num_envs)
        next_value = critic(torch.as_tensor(next_obs, device=device)).reshape(args.num_envs)
        advantages = compute_gae(rewards, dones, values.cpu().numpy(), next_value.cpu().numpy(), next_done,
                                 args.gamma, args.gae_lambda)
        b_advantages = torch.as_tensor(advantages, device=device).reshape(-1)
        b_values = values.reshape(-1)
        b_returns = b_advantages + b_values

        # --- PPO update ---
        # one [B, D] tensor holding all a minibatch needs, so each minibatch is a single gather
        batch = torch.cat([b_obs, b_actions, b_logprobs[:, None], b_advantages[:, None], b_returns[:, None],
                           b_values[:, None]], dim=1)
        fast.check_gradients(actor, critic, unpack(batch[:minibatch_size]), args, global_step)
        ratios = []  # of every minibatch, for the clip fraction
        with torch.inference_mode(fast.gradients):  # the fast path needs no autograd bookkeeping at all
            for _epoch in range(args.update_epochs):
                b_inds = torch.randperm(batch_size, device=device)
                for start in range(0, batch_size, minibatch_size):
                    minibatch = unpack(torch.index_select(batch, 0, b_inds[start : start + minibatch_size]))
                    if fast.gradients:  # section 2: hand-written gradients, checked against the ones below
                        loss, parts = fast_gradients(actor, critic, minibatch, args)
                        fast_optimizer_step(params, optimizer, args.max_grad_norm)
                    else:
                        loss, parts = autograd_gradients(actor, critic, all_params, minibatch, args)
                        nn.utils.clip_grad_norm_([params], args.max_grad_norm)
                        optimizer.step()
                    ratios.append(parts["ratio"])

                # CleanRL's diagnostics, from the epoch's last minibatch
                old_approx_kl = (-parts["logratio"]).mean()
                approx_kl = ((parts["ratio"] - 1) - parts["logratio"]).mean()
                if args.target_kl is not None and approx_kl > args.target_kl:
                    break

        run.update_done(global_step, optimizer, parts, old_approx_kl, approx_kl, torch.cat(ratios), b_values,
                        b_returns, fast)
        # --- non-finite guard: stop before anything bad is written to the checkpoint ---
        if not math.isfinite(loss.item()) or not torch.isfinite(params).all():
            run.stop_non_finite(global_step, update)
        run.maybe_checkpoint(update, total_updates, global_step, actor, critic, optimizer, next_obs, next_done)

    run.close(global_step, actor)
    final_stats = obs_statistics(envs)
    envs.close()
    return {"actor": actor, "critic": critic, "run_dir": run.run_dir, "global_step": global_step,
            "obs_stats": final_stats, "fast_paths": fast}
# ==============================================================================================
# 2. FAST PATHS: derived from section 1, checked against it while training
# ==============================================================================================
# A rollout acts 2048 times on one observation, and a PPO minibatch is 64 samples through nets of a
# few thousand weights (~1 MFLOP): per-call overhead, not arithmetic, sets the speed. So acting runs in numpy on
# copies of the weights, and the update's gradients are written out by hand (no autograd graph).
# Both are derived from section 1 and checked against it while the run trains (`FastPaths`): the
# acting forward at every rollout start, the gradients on the first minibatch of every update, in
# float64 so that the check separates rounding (~1e-15) from a real difference (an edit: >= 1e-6).
# A run whose section 1 was edited without this section says so in one line and continues through
# section 1 (torch forward, autograd); to make it fast again, edit the matching function below until
# the check passes (tests/test_gradients.py runs the same comparison).
def numpy_mlp_forward(layers: tuple, x: np.ndarray) -> np.ndarray:
    """`TanhMLP.forward` in numpy, on ((W, b), ...): at batch size 1 numpy's per-call overhead is a third of
    torch's, and its smaller code path leaves the simulator's own code in the CPU caches."""
    *inner, (last_weight, last_bias) = layers
    for weight, bias in inner:
        x = np.tanh(x @ weight + bias)
    return x @ last_weight + last_bias


def numpy_policy(actor: Actor) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """obs [B, obs_dim] (numpy) -> mean [B, A], log-std [1, A], as `actor.forward`, computed on numpy copies
    of the current weights (in their dtype): for acting during a rollout (the copies do not follow updates)."""
    layers = tuple((w.detach().cpu().numpy().copy(), b.detach().cpu().numpy().copy()) for w, b in actor.mean_net.layers)
    log_std = actor.log_std.detach().cpu().numpy().copy()
    return lambda obs: (numpy_mlp_forward(layers, obs), log_std)


def torch_policy(actor: Actor) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """The same interface through section 1's forward (the autograd path's acting)."""
    device = actor.log_std.device

    def act(obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with torch.inference_mode():
            mean, log_std = actor(torch.as_tensor(obs, device=device))
        return mean.cpu().numpy(), log_std.cpu().numpy()

    return act


LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)
# g * (1 - h^2) for h = tanh(z): autograd's own kernel for tanh's derivative, one op instead of two
tanh_backward = torch.ops.aten.tanh_backward


def gaussian_entropy(log_std: torch.Tensor) -> torch.Tensor:
    return (0.5 + LOG_SQRT_2PI + log_std).sum(-1)


def ppo_loss_gradients(
    mean: torch.Tensor, log_std: torch.Tensor, value: torch.Tensor, actions: torch.Tensor, old_logprob: torch.Tensor,
    advantages: torch.Tensor, returns: torch.Tensor, old_value: torch.Tensor, args: Args,
) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor, torch.Tensor]:
    """`ppo_loss` and its gradient w.r.t. the nets' outputs, written out by hand.

    mean, log_std [B, A] (log_std per sample), value [B]. Returns (losses, dL/dmean [B, A],
    dL/dlog_std [B, A], dL/dvalue [B, 1]); `losses` holds the loss, its terms, the log-ratio and ratio.
    """
    batch = len(value)
    # log pi(a|s) = sum_j -u_j^2/2 - log_std_j - log sqrt(2 pi), with u = (a - mean) / std
    inv_std = torch.exp(-log_std)
    u = (actions - mean) * inv_std
    u2 = u * u
    newlogprob = (u2.mul(-0.5) - log_std).sum(1) - LOG_SQRT_2PI * u.shape[1]
    logratio = newlogprob - old_logprob
    ratio = logratio.exp()
    if args.norm_adv:
        adv_std, adv_mean = torch.std_mean(advantages)
        advantages = (advantages - adv_mean) / (adv_std + 1e-8)

    # Policy loss mean(max(-A r, -A clip(r, 1-eps, 1+eps))). Its gradient w.r.t. r is -A/B wherever
    # the unclipped term is the max (inside the clip range both terms are equal: autograd's halves
    # add up to the same) and 0 elsewhere; dr/dlogprob = r, so dL/dlogprob = (-A r)/B there.
    pg_loss1 = -advantages * ratio
    pg_loss2 = -advantages * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)
    pg_loss = torch.max(pg_loss1, pg_loss2).mean()
    grad_logprob = (pg_loss1 * (pg_loss1 >= pg_loss2)).div_(batch).unsqueeze(1)
    # dlogprob/dmean = u / std, dlogprob/dlog_std = u^2 - 1
    grad_mean = grad_logprob * u * inv_std
    grad_log_std = grad_logprob * u2 - grad_logprob

    # Value loss 0.5 mean(max((v - R)^2, (v_clip - R)^2)) with v_clip = v_old + clip(v - v_old, -eps, eps);
    # the clipped branch passes a gradient only where v - v_old is inside the clip range.
    if args.clip_vloss:
        v_clipped = old_value + torch.clamp(value - old_value, -args.clip_coef, args.clip_coef)
        v_loss_unclipped, v_loss_clipped = (value - returns) ** 2, (v_clipped - returns) ** 2
        v_loss = 0.5 * torch.max(v_loss_unclipped, v_loss_clipped).mean()
        inside = (value - old_value).abs() <= args.clip_coef
        grad_v = torch.where(v_loss_unclipped >= v_loss_clipped, value - returns,
                             torch.where(inside, v_clipped - returns, 0.0))
    else:
        v_loss = 0.5 * ((value - returns) ** 2).mean()
        grad_v = value - returns
    grad_value = grad_v.mul_(args.vf_coef / batch)[:, None]

    loss = pg_loss + args.vf_coef * v_loss
    if args.ent_coef:  # loss - c * mean_b entropy_b; d/dlog_std_bj = -c/B (with the default c = 0: skipped)
        loss = loss - args.ent_coef * gaussian_entropy(log_std).mean()
        grad_log_std -= args.ent_coef / batch
    # the entropy is only logged (from the epoch's last minibatch): `log_std` lets the logger compute it
    losses = {"loss": loss, "policy_loss": pg_loss, "value_loss": v_loss, "log_std": log_std,
              "logratio": logratio, "ratio": ratio}
    return losses, grad_mean, grad_log_std, grad_value


def mlp_backward(mlp: TanhMLP, x: torch.Tensor, hidden: list[torch.Tensor], grad_output: torch.Tensor) -> None:
    """Write dL/dW and dL/db into the parameters' .grad, given dL/d(output) of `mlp(x, hidden)`."""
    inputs = [x, *hidden]
    for i in reversed(range(len(mlp.layers))):
        weight, bias = mlp.layers[i]
        torch.mm(inputs[i].T, grad_output, out=weight.grad)  # dL/dW = input^T dL/dz
        torch.sum(grad_output, 0, out=bias.grad)
        if i:  # dL/dz of the layer below: g * tanh'(z) = g * (1 - h^2), with g = dL/dz W^T
            grad_output = tanh_backward(torch.mm(grad_output, weight.T), inputs[i])


def actor_backward(actor: Actor, obs: torch.Tensor, hidden: list[torch.Tensor], grad_mean: torch.Tensor,
                   grad_log_std: torch.Tensor) -> None:
    """Write the actor's .grad from dL/dmean and dL/dlog_std [B, A] of `actor(obs, hidden)`."""
    mlp_backward(actor.mean_net, obs, hidden, grad_mean)
    torch.sum(grad_log_std, 0, keepdim=True, out=actor.log_std.grad)  # one vector shared by the batch


def fast_gradients(actor: Actor, critic: TanhMLP, minibatch: tuple, args: Args,
                   output_grads: list | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """`autograd_gradients` by hand: the loss of one minibatch, its gradient written into every .grad.
    `output_grads` receives dL/dmean, dL/dlog_std, dL/dvalue (for the check)."""
    obs, actions, old_logprob, advantages, returns, old_value = minibatch
    actor_hidden, critic_hidden = [], []
    mean, log_std = actor(obs, actor_hidden)
    value = critic(obs, critic_hidden).squeeze(1)
    losses, grad_mean, grad_log_std, grad_value = ppo_loss_gradients(
        mean, log_std, value, actions, old_logprob, advantages, returns, old_value, args)
    if output_grads is not None:
        output_grads += [grad_mean, grad_log_std, grad_value.squeeze(1)]
    actor_backward(actor, obs, actor_hidden, grad_mean, grad_log_std)
    mlp_backward(critic, obs, critic_hidden, grad_value)
    return losses.pop("loss"), losses


def share_one_buffer(params: list[nn.Parameter]) -> nn.Parameter:
    """Make every parameter, and its .grad, a view into one flat buffer; return that buffer as a Parameter.

    The optimizer then updates a single tensor and the gradient norm is one reduction, instead of
    one small op per parameter. Values are unchanged; both gradient paths overwrite the .grad views
    every minibatch (so there is no zero_grad)."""
    flat = nn.Parameter(torch.cat([p.detach().reshape(-1) for p in params]))
    flat.grad = torch.zeros_like(flat)
    offset = 0
    for p in params:
        p.data = flat.data[offset : offset + p.numel()].view_as(p)
        p.grad = flat.grad[offset : offset + p.numel()].view_as(p)
        offset += p.numel()
    return flat


def clip_grad_norm(flat: nn.Parameter, max_norm: float) -> None:
    """torch.nn.utils.clip_grad_norm_ on the one gradient buffer: scale by min(1, max_norm / (norm + 1e-6))."""
    flat.grad.mul_(torch.clamp(max_norm / (flat.grad.norm() + 1e-6), max=1.0))


def make_optimizer(params: list[nn.Parameter], learning_rate: float) -> torch.optim.Adam:
    """PPO's Adam (eps 1e-5); the fused kernel updates all parameters at once, ~3x faster on CPU."""
    return torch.optim.Adam(params, lr=learning_rate, eps=1e-5, fused=True)


def adam_step(optimizer: torch.optim.Adam) -> None:
    """`optimizer.step()` for our one flat parameter: a direct call of the fused kernel that step() ends in.

    step() spends ~30 us per call grouping tensors and checking options (~4x the kernel itself) in a
    tight loop, and measured ~100 us per minibatch inside the training loop: ~30 ms of an update's 320
    minibatches. The state stays in the optimizer as usual (checkpoints unchanged);
    tests/test_gradients.py checks this against step() bit for bit, so a torch that changes the kernel's
    signature fails there.
    """
    group = optimizer.param_groups[0]
    (param,) = group["params"]
    state = optimizer.state.get(param)
    if not state:  # the first step creates the state
        optimizer.step()
        return
    state["step"] += 1  # as step() does before the kernel
    beta1, beta2 = group["betas"]
    torch._fused_adam_([param], [param.grad], [state["exp_avg"]], [state["exp_avg_sq"]], [], [state["step"]],
                       amsgrad=False, lr=group["lr"], beta1=beta1, beta2=beta2, weight_decay=group["weight_decay"],
                       eps=group["eps"], maximize=False)


def fast_optimizer_step(flat: nn.Parameter, optimizer: torch.optim.Adam, max_norm: float) -> None:
    """nn.utils.clip_grad_norm_ and optimizer.step() on the one parameter buffer, without their overhead."""
    clip_grad_norm(flat, max_norm)
    adam_step(optimizer)


# Relative disagreement (max |fast - reference| / max |reference|, in float64) above which a fast path
# counts as not matching section 1. Measured on the unmodified script: at most ~1e-13 (README, "Hacking
# Cascade"); the smallest edit tried (0.01 * mean.pow(2).mean() added to the loss) differs by ~2e-7 at the
# first update, when the means are still ~0.01, and by more as they grow.
FAST_PATH_TOLERANCE = 1e-9


def relative_error(fast: list[torch.Tensor], reference: list[torch.Tensor]) -> float:
    fast_flat = torch.cat([t.reshape(-1) for t in fast])
    reference_flat = torch.cat([t.reshape(-1) for t in reference])
    scale = max(reference_flat.abs().max().item() if len(reference_flat) else 0.0, 1e-30)
    return (fast_flat - reference_flat).abs().max().item() / scale if len(reference_flat) else 0.0


def float64_copy(module: nn.Module) -> nn.Module:
    """A float64 copy with zeroed .grad buffers; copying draws no random numbers (the run's RNG is untouched)."""
    twin = copy.deepcopy(module).double()
    for param in twin.parameters():
        param.grad = torch.zeros_like(param)
    return twin


class FastPaths:
    """Which fast paths are on, and their checks against section 1 (float64 copies of the nets).

    A check that fails turns its path off for the rest of the run: the run then acts through
    `torch_policy` / updates through `autograd_gradients`, and says so once, in one line."""

    def __init__(self, enabled: bool, run: RunLog | None = None):
        self.acting = self.gradients = enabled
        self.run = run
        self.worst = {"acting": 0.0, "gradients": 0.0}  # largest disagreement seen by the checks that passed
        self.check_seconds = 0.0
        self.messages: list[str] = []
        self._twin: tuple = (None, None, None)  # (actor, fingerprint of its weights, float64 copy)

    def float64_actor(self, actor: nn.Module) -> nn.Module:
        """A float64 copy of `actor`, reused while its weights are unchanged (the acting check at a rollout's
        start, then the gradient check after it); the weights' sums tell whether they changed."""
        with torch.no_grad():
            fingerprint = torch.stack([p.sum() for p in actor.parameters()])
        if self._twin[0] is not actor or not torch.equal(self._twin[1], fingerprint):
            self._twin = (actor, fingerprint, float64_copy(actor))
        return self._twin[2]

    def acting_policy(self, actor: Actor, check_obs: np.ndarray, step: int) -> Callable:
        """The rollout's acting function: the numpy forward if it matches `actor.forward` on `check_obs`."""
        if not self.acting:
            return torch_policy(actor)
        start = time.perf_counter()
        twin = self.float64_actor(actor)
        obs = torch.as_tensor(check_obs, dtype=torch.float64)
        reference = twin(obs.to(twin.log_std.device))
        reference = [r.cpu() for r in reference]
        fast = [torch.as_tensor(np.broadcast_to(a, r.shape).copy())
                for a, r in zip(numpy_policy(twin)(obs.numpy()), reference)]
        error = relative_error(fast, reference)
        self.check_seconds += time.perf_counter() - start
        if error > FAST_PATH_TOLERANCE:
            self.switch_off("acting", f"the numpy acting forward (numpy_policy) differs from Actor.forward "
                            f"(max relative error {error:.1e})", step)
            return torch_policy(actor)
        self.worst["acting"] = max(self.worst["acting"], error)
        return numpy_policy(actor)

    def check_gradients(self, actor: Actor, critic: TanhMLP, minibatch: tuple, args: Args, step: int) -> None:
        """Compare the hand-written gradients with autograd through section 1 on one minibatch."""
        if not self.gradients:
            return
        start = time.perf_counter()
        actor64, critic64 = self.float64_actor(actor), float64_copy(critic)
        params = [*actor64.parameters(), *critic64.parameters()]
        obs, *rest = (t.detach().double() for t in minibatch)
        with torch.enable_grad():
            mean, log_std = actor64(obs)
            value = critic64(obs).squeeze(1)
            loss, _ = ppo_loss(mean, log_std, value, *rest, args)
            grads = torch.autograd.grad(loss, [mean, log_std, value, *params], allow_unused=True)
        grads = [torch.zeros_like(t) if g is None else g for t, g in zip([mean, log_std, value, *params], grads)]
        output_grads: list[torch.Tensor] = []
        with torch.no_grad():
            fast_loss, _ = fast_gradients(actor64, critic64, (obs, *rest), args, output_grads)
        num_actor = len(list(actor64.parameters()))
        comparisons = [
            ("loss", "ppo_loss_gradients computes another loss than ppo_loss", [fast_loss], [loss.detach()]),
            ("loss gradient", "ppo_loss_gradients' gradient differs from autograd through ppo_loss",
             output_grads, grads[:3]),
            ("actor gradient", "actor_backward differs from autograd through Actor.forward",
             [p.grad for p in params[:num_actor]], grads[3 : 3 + num_actor]),
            ("critic gradient", "mlp_backward differs from autograd through TanhMLP.forward",
             [p.grad for p in params[num_actor:]], grads[3 + num_actor :]),
        ]
        self.check_seconds += time.perf_counter() - start
        if not all(torch.isfinite(g).all() for g in grads) or not math.isfinite(loss.item()):
            return  # non-finite values are the non-finite guard's business
        worst = 0.0
        for _, what, fast, reference in comparisons:
            error = relative_error(fast, reference)
            if error > FAST_PATH_TOLERANCE:
                self.switch_off("gradients", f"{what} (max relative error {error:.1e})", step)
                return
            worst = max(worst, error)
        self.worst["gradients"] = max(self.worst["gradients"], worst)

    def switch_off(self, path: str, what: str, step: int) -> None:
        setattr(self, path, False)
        remedy = ("acting through Actor.forward" if path == "acting"
                  else "updating with autograd through ppo_loss and the nets' forward")
        message = (f"fast path check at global_step={step}: {what}; continuing by {remedy} (as --autograd). "
                   f"If section 1 was edited on purpose, this is expected; edit section 2 to match it to get the speed back")
        self.messages.append(message)
        if self.run is not None:
            self.run.fast_path_off(message, step)


# ==============================================================================================
# 3. PLUMBING: environments, evaluation, checkpoints, progress, command line
# ==============================================================================================
OBS_CLIP = 10.0
REWARD_CLIP = 10.0
NORM_EPS = 1e-8  # the epsilon of gymnasium's NormalizeObservation


def fail(message: str) -> None:
    """Stop with a one-line error and a non-zero exit code."""
    raise SystemExit(f"error: {message}")


def check_env_id(env_id: str) -> None:
    if env_id not in gym.envs.registry:
        import difflib

        close = difflib.get_close_matches(env_id, list(gym.envs.registry), n=3)
        hint = f" Did you mean {', '.join(close)}?" if close else ""
        fail(f"unknown env id '{env_id}'.{hint} (see gymnasium's registry, e.g. Ant-v4, Hopper-v5)")


def make_env(env_id: str, gamma: float, normalize: bool, index: int = 0, video: bool = False) -> Callable[[], gym.Env]:
    """CleanRL's wrapper stack, per env: raw episode stats, action clip, obs/reward normalization, +-10 clips
    (and with `video`, the --capture-video recorder under them all)."""

    def thunk() -> gym.Env:
        if multiprocessing.current_process().name != "MainProcess":  # a --num-envs worker: stops are for training
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            signal.signal(signal.SIGTERM, signal.SIG_DFL)  # not the training process's handler it was forked with
        env = gym.make(env_id, render_mode="rgb_array") if video else gym.make(env_id)
        if video:
            env = TrainingVideo(env)
        env = gym.wrappers.RecordEpisodeStatistics(env)  # raw, unnormalized returns
        env = gym.wrappers.ClipAction(env)
        if normalize:
            env = gym.wrappers.NormalizeObservation(env)
        # clipped to +-10 with or without normalization: the paper's code clips raw values in its norm:False runs
        env = gym.wrappers.TransformObservation(env, lambda obs: np.clip(obs, -OBS_CLIP, OBS_CLIP), env.observation_space)
        if normalize:
            env = gym.wrappers.NormalizeReward(env, gamma=gamma)
        env = gym.wrappers.TransformReward(env, lambda r: np.clip(r, -REWARD_CLIP, REWARD_CLIP))
        return RunState(env, index)

    return thunk


def make_vector_env(args: Args) -> gym.vector.VectorEnv:
    """One env in this process, or --num-envs > 1 envs stepped in parallel worker processes."""
    fns = [make_env(args.env_id, args.gamma, args.normalize, i, video=args.capture_video and i == 0)
           for i in range(args.num_envs)]
    # SAME_STEP: the obs returned on a done step is already the reset one, so every stored
    # transition is real (the default NEXT_STEP mode inserts a fake step after each episode).
    mode = gym.vector.AutoresetMode.SAME_STEP
    if args.num_envs == 1:
        return gym.vector.SyncVectorEnv(fns, autoreset_mode=mode)
    return gym.vector.AsyncVectorEnv(fns, autoreset_mode=mode)


def find_wrapper(env: gym.Env, wrapper_type: type) -> gym.Wrapper | None:
    while isinstance(env, gym.Wrapper):
        if isinstance(env, wrapper_type):
            return env
        env = env.env
    return None


# Plain-data attributes of an env and its wrappers: step counters, episode statistics, running
# normalization statistics, the env's RNG. Saved and restored so a resumed run continues the very
# same trajectories (MuJoCo's simulation state, MjData, is saved whole).
ENV_STATE_TYPES = (bool, int, float, np.ndarray, np.generic, np.random.Generator, RunningMeanStd, collections.deque)


class RunState(gym.Wrapper):
    """Outermost wrapper that reads and restores what a run needs of its env. The vector env calls
    these methods by name, so they work the same when the env lives in a worker process."""

    def __init__(self, env: gym.Env, index: int):
        super().__init__(env)
        self.index = index

    def obs_statistics(self) -> tuple[np.ndarray, np.ndarray] | None:
        norm = find_wrapper(self.env, gym.wrappers.NormalizeObservation)
        return None if norm is None else (norm.obs_rms.mean.copy(), norm.obs_rms.var.copy())

    def get_state(self) -> dict:
        layers, layer = [], self.env
        while True:
            layers.append({k: copy.deepcopy(v) for k, v in vars(layer).items() if isinstance(v, ENV_STATE_TYPES)})
            if not isinstance(layer, gym.Wrapper):
                break
            layer = layer.env
        sim = pickle.dumps(layer.data) if hasattr(layer, "data") and hasattr(layer, "model") else None
        return {"layers": layers, "sim": sim}

    def set_state(self, states: list[dict]) -> None:
        """Restore this env's entry of `states` (one per env of the vector env)."""
        state, layer = states[self.index], self.env
        if len(state["layers"]) != wrapper_depth(self.env):
            raise SystemExit("error: the checkpoint's env wrappers differ from this script's (it was written by an "
                             "older version); it cannot be resumed exactly: start a new run")
        for attrs in state["layers"]:
            for key, value in attrs.items():
                setattr(layer, key, copy.deepcopy(value))
            if not isinstance(layer, gym.Wrapper):
                break
            layer = layer.env
        if state["sim"] is not None:
            import mujoco

            # into the env's own MjData, which its renderer (--capture-video) holds on to
            mujoco.mj_copyData(layer.data, layer.model, pickle.loads(state["sim"]))
        recorder = find_wrapper(self.env, TrainingVideo)
        if recorder is not None:  # the killed run's video of this episode is lost; the next trigger records again
            recorder.stop(keep=False)

    def record_videos_to(self, folder: str) -> None:
        """--capture-video: where the first env writes its videos, known once the run has its name."""
        recorder = find_wrapper(self.env, TrainingVideo)
        if recorder is not None:
            recorder.folder = folder


def capped_cubic_video_schedule(episode_id: int) -> bool:
    """CleanRL's video trigger (the default of gymnasium's RecordVideo): episodes 0, 1, 8, 27, ..., 729, 1000, 2000, ..."""
    if episode_id < 1000:
        return round(episode_id ** (1 / 3)) ** 3 == episode_id
    return episode_id % 1000 == 0


class TrainingVideo(gym.Wrapper):
    """--capture-video, CleanRL's training videos: the episodes of this env that `capped_cubic_video_schedule`
    picks become `<folder>/rl-video-episode-<i>.mp4` when they end (gymnasium's RecordVideo would need moviepy).
    Rendering only reads the simulation: observations, rewards and every RNG stream of training are the same
    with and without it."""

    PARTIAL = ".recording.mp4"  # the episode being recorded; renamed when it ends

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.folder: str | None = None
        self.episode_id = -1  # an int, so checkpoints keep it: a resumed run continues the numbering
        self.writer = None  # the open mp4 while an episode is recorded

    def reset(self, **kwargs):
        obs, info = super().reset(**kwargs)
        self.stop(keep=True)  # the recorded episode has ended
        self.episode_id += 1
        if self.folder is not None and capped_cubic_video_schedule(self.episode_id):
            import imageio.v2 as imageio  # with imageio-ffmpeg (requirements.txt) for mp4

            os.makedirs(self.folder, exist_ok=True)
            self.writer = imageio.get_writer(os.path.join(self.folder, self.PARTIAL),
                                             fps=self.metadata.get("render_fps", 30))
            self.writer.append_data(self.env.render())
        return obs, info

    def step(self, action):
        result = super().step(action)
        if self.writer is not None:
            self.writer.append_data(self.env.render())
        return result

    def stop(self, keep: bool) -> None:
        """Close the video being written: keep it as its episode's mp4, or drop it (an unfinished episode)."""
        if self.writer is None:
            return
        self.writer.close()
        self.writer = None
        partial = os.path.join(self.folder, self.PARTIAL)
        if keep:
            os.replace(partial, os.path.join(self.folder, f"rl-video-episode-{self.episode_id}.mp4"))
        else:
            os.remove(partial)

    def close(self) -> None:
        self.stop(keep=False)  # the episode running at the end of training is not whole
        super().close()


def wrapper_depth(env: gym.Env) -> int:
    """Number of layers (wrappers and the env itself) below RunState."""
    depth = 1
    while isinstance(env, gym.Wrapper):
        env, depth = env.env, depth + 1
    return depth


def obs_statistics(envs: gym.vector.VectorEnv) -> tuple[np.ndarray, np.ndarray] | None:
    """Copy of the first training env's observation mean/var (None without normalization)."""
    return envs.call("obs_statistics")[0]


def normalize_obs(obs: np.ndarray, stats: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """What the training wrappers do to a raw observation, with frozen statistics (None: clipping only)."""
    if stats is None:
        return np.clip(obs, -OBS_CLIP, OBS_CLIP).astype(np.float32)
    mean, var = stats
    return np.clip((obs - mean) / np.sqrt(var + NORM_EPS), -OBS_CLIP, OBS_CLIP).astype(np.float32)



# ----------------------------------------------------------------------------------------------
# Weights & Biases (--track), CleanRL's way: it mirrors the TensorBoard logs; wandb is imported only then
# ----------------------------------------------------------------------------------------------
VIDEO_ROOT = "videos"  # --capture-video writes videos/<run_name>/ in the working directory, as CleanRL
NO_WANDB = "or set WANDB_MODE=offline to log locally and `wandb sync` later"


def check_wandb() -> None:
    """--track before anything is created: wandb installed and, unless offline, logged in (wandb itself would
    prompt for a key, which in a sweep or a batch job waits forever)."""
    try:
        import wandb
    except ImportError:
        fail("--track needs wandb: pip install -r requirements.txt")
    if wandb.setup().settings.mode in ("offline", "dryrun", "disabled"):
        return
    if not wandb.login(prompt=False, verify=False):
        fail(f"--track: no W&B login found; run `wandb login` (or set WANDB_API_KEY), {NO_WANDB}")


def start_wandb(args: Args, run_name: str, run_dir: str, run_id: str | None) -> str:
    """wandb.init as CleanRL calls it, before the SummaryWriter is made so that every scalar reaches W&B under
    its TensorBoard name; `run_id` continues a resumed run's W&B run. Returns the W&B run's id."""
    import wandb

    # The run folder is TensorBoard's root: no prefix on the names, and wandb need not wait 10 s to guess it.
    wandb.tensorboard.patch(root_logdir=run_dir)
    try:
        timeout = float(os.environ.get("WANDB_INIT_TIMEOUT", 20))  # wandb's default, 90 s, looks like a hang
        run = wandb.init(project=args.wandb_project_name, entity=args.wandb_entity, group=args.wandb_group,
                         sync_tensorboard=True, config=asdict(args), name=run_name, monitor_gym=True,
                         save_code=True, id=run_id, resume="must" if run_id else None,
                         settings=wandb.Settings(init_timeout=timeout))
    except Exception as exc:  # no answer from the server, a wrong entity, a run id it does not know, ...
        wandb.tensorboard.unpatch()
        first_line = (str(exc).splitlines() or [""])[0][:200]
        fail(f"--track: cannot start the W&B run ({type(exc).__name__}: {first_line}); check `wandb login` and "
             f"the network, {NO_WANDB}")
    return run.id


def finished_videos(folder: str | None) -> set[str]:
    return set(glob.glob(os.path.join(glob.escape(folder), "rl-video-episode-*.mp4"))) if folder else set()


def log_new_videos(folder: str | None, sent: set[str], global_step: int) -> None:
    """--track --capture-video: each finished training video goes to W&B once, under CleanRL's key `videos`
    (the recording env may live in a --num-envs worker, so its folder is watched from here)."""
    if folder is None:
        return
    import wandb

    for path in sorted(finished_videos(folder) - sent, key=os.path.getmtime):
        wandb.log({"videos": wandb.Video(path, format="mp4"), "global_step": global_step})
        sent.add(path)


def finish_wandb(exit_code: int) -> None:
    """End the W&B run --track started, if one is open: 0 at the end of training, non-zero after an error or a
    stop (W&B marks the run failed)."""
    wandb = sys.modules.get("wandb")  # never imported without --track
    if wandb is not None and wandb.run is not None:
        wandb.finish(exit_code=exit_code)
        wandb.tensorboard.unpatch()


# ----------------------------------------------------------------------------------------------
# The run's bookkeeping: TensorBoard, evaluations, checkpoints and resume, progress
# ----------------------------------------------------------------------------------------------
class RunLog:
    """Everything `train` records about a run and restores when it is resumed; no algorithm here."""

    def __init__(self, args: Args, checkpoint: dict | None, obs_dim: int, act_dim: int,
                 envs: gym.vector.VectorEnv, total_steps: int):
        from torch.utils.tensorboard import SummaryWriter

        self.args, self.envs, self.obs_dim, self.act_dim = args, envs, obs_dim, act_dim
        if args.capture_video:  # here, once the --num-envs workers exist: forked after a render, they hang
            make_render_env(args.env_id).close()  # no OpenGL backend: one line now, not a traceback later
        batch_size = args.num_envs * args.num_steps
        if args.total_timesteps % batch_size and checkpoint is None:
            updates = args.total_timesteps // batch_size
            print(f"note: total_timesteps={args.total_timesteps} is not a multiple of the batch size {batch_size}; "
                  f"the run does {updates} updates = {updates * batch_size} steps")
        if checkpoint is None:
            self.run_dir = os.path.join(args.track_dir, f"{args.env_id}__{args.exp_name}__{args.seed}__{int(time.time())}")
        else:
            self.run_dir = os.path.dirname(checkpoint["path"])
        run_name = os.path.basename(self.run_dir)
        # kept through an untracked resume, so that a later --track continues the same W&B run
        self.wandb_run_id = None if checkpoint is None else checkpoint.get("wandb_run_id")
        if args.track:
            self.wandb_run_id = start_wandb(args, run_name, self.run_dir, self.wandb_run_id)
        if checkpoint is None:
            self.writer = SummaryWriter(self.run_dir)
            self.writer.add_text(
                "hyperparameters",
                "|param|value|\n|-|-|\n" + "\n".join(f"|{key}|{value}|" for key, value in asdict(args).items()),
            )
        else:  # purge_step hides whatever the killed run logged after its last checkpoint
            self.writer = SummaryWriter(self.run_dir, purge_step=checkpoint["global_step"] + 1)
        self.video_folder = os.path.join(VIDEO_ROOT, run_name) if args.capture_video else None
        if self.video_folder is not None:
            envs.call("record_videos_to", self.video_folder)
        self.videos_sent = finished_videos(self.video_folder)  # a resumed run's earlier ones went to W&B already
        self.checkpoint_path = os.path.join(self.run_dir, CHECKPOINT_NAME)
        self.runner = None
        if args.eval_every:
            self.runner = EvaluationRunner(args, obs_dim, act_dim,
                                           calls=0 if checkpoint is None else checkpoint["eval_calls"])
        self.progress = Progress(total_steps, args.quiet)
        self.start_time = time.time()
        self.last_checkpoint_step = 0

    def parameters(self, count: int, fresh: bool) -> None:
        self.progress.message(f"PPO: {count} parameters (actor + critic)")
        if fresh:
            self.writer.add_scalar("charts/parameters", count, 0)

    def restore(self, checkpoint: dict, actor: Actor, critic: nn.Module, optimizer: torch.optim.Optimizer) -> tuple:
        """The saved nets, optimizer, env states and RNG streams; returns (global_step, next_obs, next_done,
        update) of where the run continues."""
        global_step = checkpoint["global_step"]
        self.start_time = time.time() - checkpoint["elapsed"]
        self.last_checkpoint_step = global_step
        self.envs.reset(seed=self.args.seed)  # sets up the vector env; then every env gets its saved state back
        self.envs.call("set_state", checkpoint["env_states"])
        actor.load_state_dict(checkpoint["actor"])
        critic.load_state_dict(checkpoint["critic"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        set_rng_states(checkpoint["rng"])
        self.progress.message(f"resumed {checkpoint['path']} at global_step={global_step}")
        return (global_step, np.asarray(checkpoint["next_obs"], dtype=np.float32), checkpoint["next_done"],
                checkpoint["updates_done"] + 1)

    def episodes(self, infos: dict, global_step: int) -> None:
        """Raw returns and lengths of the training episodes that ended at this step."""
        if "final_info" in infos and "episode" in infos["final_info"]:
            finished = infos["final_info"]["_episode"]
            for ret, length in zip(infos["final_info"]["episode"]["r"][finished],
                                   infos["final_info"]["episode"]["l"][finished]):
                self.writer.add_scalar("charts/episodic_return", ret, global_step)
                self.writer.add_scalar("charts/episodic_length", length, global_step)

    def update_done(self, global_step: int, optimizer: torch.optim.Optimizer, parts: dict,
                    old_approx_kl: torch.Tensor, approx_kl: torch.Tensor, ratios: torch.Tensor,
                    b_values: torch.Tensor, b_returns: torch.Tensor, fast: FastPaths) -> None:
        """CleanRL's scalars after one update."""
        write = self.writer.add_scalar
        y_pred, y_true = b_values.cpu().numpy(), b_returns.cpu().numpy()
        var_y = np.var(y_true)
        explained_var = np.nan if var_y == 0 else 1 - np.var(y_true - y_pred) / var_y
        write("charts/learning_rate", optimizer.param_groups[0]["lr"], global_step)
        write("losses/value_loss", parts["value_loss"].item(), global_step)
        write("losses/policy_loss", parts["policy_loss"].item(), global_step)
        entropy = parts["entropy"] if "entropy" in parts else gaussian_entropy(parts["log_std"]).mean()
        write("losses/entropy", entropy.item(), global_step)
        write("losses/old_approx_kl", old_approx_kl.item(), global_step)
        write("losses/approx_kl", approx_kl.item(), global_step)
        write("losses/clipfrac", ((ratios - 1.0).abs() > self.args.clip_coef).float().mean().item(), global_step)
        write("losses/explained_variance", explained_var, global_step)
        sps = global_step / (time.time() - self.start_time)
        write("charts/SPS", int(sps), global_step)
        write("charts/fast_acting", float(fast.acting), global_step)
        write("charts/fast_gradients", float(fast.gradients), global_step)
        write("charts/fast_path_check_seconds", fast.check_seconds, global_step)
        if self.args.track:
            log_new_videos(self.video_folder, self.videos_sent, global_step)
        self.progress.update(global_step, sps)

    def fast_path_off(self, message: str, step: int) -> None:
        """A fast path failed its check: one line on stderr (also with --quiet), a TensorBoard text."""
        print(f"\r\033[Kwarning: {message}" if self.progress.tty else f"warning: {message}", file=sys.stderr,
              flush=True)
        self.writer.add_text("fast_paths", message, step)
        self.progress.note = " | autograd (fast path check failed)"

    def stop_non_finite(self, global_step: int, update: int) -> None:
        self.writer.close()
        fail(f"non-finite loss or parameters at global_step={global_step} (update {update}); "
             f"{non_finite_advice(self.checkpoint_path)}")

    # --- evaluation (SPEC §6) ---
    def evaluate(self, step: int, actor: Actor) -> None:
        """Freeze the current policy and observation statistics and evaluate them."""
        if self.runner is None:
            return
        self.runner.submit(step, actor, obs_statistics(self.envs))
        self.log_evaluations()

    def log_evaluations(self, wait: bool = False) -> None:
        if self.runner is None:
            return
        for step, returns in self.runner.results(wait):
            self.writer.add_scalar("eval/episodic_return", returns.mean(), step)
            self.writer.add_scalar("eval/episodic_return_std", returns.std(), step)
            self.progress.last_eval = float(returns.mean())
            self.progress.message(f"global_step={step}, eval/episodic_return={returns.mean():.1f} "
                                  f"± {returns.std():.1f}")

    # --- checkpoints ---
    def maybe_checkpoint(self, update: int, total_updates: int, global_step: int, actor: Actor, critic: nn.Module,
                         optimizer: torch.optim.Optimizer, next_obs: np.ndarray, next_done: np.ndarray) -> None:
        """At the end of the run and every --checkpoint-every steps."""
        args = self.args
        now = update == total_updates or (
            args.checkpoint_every and global_step - self.last_checkpoint_step >= args.checkpoint_every)
        self.log_evaluations(wait=bool(now))  # finished evaluations; before a checkpoint, all of them
        if not now:
            return
        save_checkpoint(self.checkpoint_path, {
            "format": "ppo_baseline/2", "args": asdict(args), "obs_dim": self.obs_dim, "act_dim": self.act_dim,
            "updates_done": update, "global_step": global_step, "elapsed": time.time() - self.start_time,
            "actor": actor.state_dict(), "critic": critic.state_dict(), "optimizer": optimizer.state_dict(),
            "obs_stats": obs_statistics(self.envs), "env_states": self.envs.call("get_state"),
            "next_obs": next_obs.copy(), "next_done": next_done.copy(), "rng": rng_states(),
            "eval_calls": 0 if self.runner is None else self.runner.calls, "wandb_run_id": self.wandb_run_id,
        })
        self.last_checkpoint_step = global_step

    def close(self, global_step: int, actor: Actor) -> None:
        if self.runner is not None:
            if global_step % self.args.eval_every >= self.args.num_envs:
                self.evaluate(global_step, actor)  # the final policy, if the last step was not an eval step
            self.log_evaluations(wait=True)
            self.runner.close()
        self.writer.close()
        if self.args.track:
            log_new_videos(self.video_folder, self.videos_sent, global_step)
            finish_wandb(exit_code=0)


# ----------------------------------------------------------------------------------------------
# Evaluation (SPEC §6): frozen policy, frozen obs statistics, separate envs, stochastic actions
# ----------------------------------------------------------------------------------------------
class Evaluator:
    """Runs `episodes` episodes side by side on its own envs; never touches the training envs."""

    def __init__(self, env_id: str, episodes: int, seed: int):
        self.envs = [gym.make(env_id) for _ in range(episodes)]
        self.seed = seed

    @torch.inference_mode()
    def __call__(
        self,
        actor: Actor,
        stats: tuple[np.ndarray, np.ndarray] | None,
        call: int = 0,
        deterministic: bool = False,
    ) -> np.ndarray:
        """Returns each episode's undiscounted raw return. The episodes' seeds and the action noise
        depend only on (seed, call): evaluation never touches training's RNG."""
        episodes = len(self.envs)
        base_seed = self.seed + 100_003 * (call + 1)
        generator = torch.Generator().manual_seed(base_seed)
        obs = np.stack([env.reset(seed=base_seed + i)[0] for i, env in enumerate(self.envs)])
        low, high = self.envs[0].action_space.low, self.envs[0].action_space.high
        returns = np.zeros(episodes)
        active = list(range(episodes))
        while active:
            x = torch.as_tensor(normalize_obs(obs[active], stats))
            mean, log_std = actor(x)
            action = mean if deterministic else mean + torch.exp(log_std) * torch.randn(
                mean.shape, generator=generator
            )
            action = np.clip(action.numpy(), low, high)
            still_active = []
            for row, i in enumerate(active):
                o, r, terminated, truncated, _ = self.envs[i].step(action[row])
                returns[i] += r
                obs[i] = o
                if not (terminated or truncated):
                    still_active.append(i)
            active = still_active
        return returns

    def close(self) -> None:
        for env in self.envs:
            env.close()


def evaluation_worker(conn, args_dict: dict, obs_dim: int, act_dim: int) -> None:
    """Worker process: rebuilds the frozen policy of each request and evaluates it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the training process's to handle
    torch.set_num_threads(1)
    args = Args(**args_dict)
    evaluator = Evaluator(args.env_id, args.eval_episodes, args.seed)
    actor = Actor(obs_dim, act_dim, args.hidden_size)
    try:
        while (request := conn.recv()) is not None:
            step, call, state, stats = request
            actor.load_state_dict(state)
            conn.send((step, evaluator(actor, stats, call)))
    except (EOFError, ConnectionError):  # the training process stopped: so do we, quietly
        return


class EvaluationRunner:
    """Evaluations of frozen copies of the policy, in a worker process beside training or inline.

    Each request carries the exact current policy and observation statistics; results come back
    tagged with the step they belong to. Evaluation costs as many env steps as training under the
    paper's protocol, so on 2+ cores a worker nearly hides it."""

    def __init__(self, args: Args, obs_dim: int, act_dim: int, calls: int = 0):
        self.calls, self.pending, self.done = calls, 0, []
        self.conn = self.process = self.evaluator = None
        if args.eval_in_worker:
            ctx = multiprocessing.get_context("spawn")  # fork is unsafe with torch threads
            self.conn, child = ctx.Pipe()
            self.process = ctx.Process(target=evaluation_worker, args=(child, asdict(args), obs_dim, act_dim),
                                       daemon=True)
            self.process.start()
        else:
            self.evaluator = Evaluator(args.env_id, args.eval_episodes, args.seed)

    def submit(self, step: int, actor: Actor, stats) -> None:
        if self.conn is not None:
            state = {k: v.detach().cpu().clone() for k, v in actor.state_dict().items()}
            self.conn.send((step, self.calls, state, stats))
            self.pending += 1
        else:
            self.done.append((step, self.evaluator(actor, stats, self.calls)))
        self.calls += 1

    def results(self, wait: bool = False) -> list[tuple]:
        """Finished evaluations (all outstanding ones with `wait`)."""
        while self.pending and (wait or self.conn.poll()):
            try:
                if not self.process.is_alive() and not self.conn.poll():
                    raise EOFError
                self.done.append(self.conn.recv())
            except (EOFError, ConnectionError):  # it can also die while we wait on it
                fail("the evaluation worker process died; rerun with --no-eval-in-worker to see why")
            self.pending -= 1
        done, self.done = self.done, []
        return done

    def close(self) -> None:
        if self.conn is not None:
            self.conn.send(None)
            self.process.join(timeout=10)
        else:
            self.evaluator.close()


def make_render_env(env_id: str) -> gym.Env:
    """An env that renders rgb arrays, or a one-line error naming the GL backends to try."""
    try:
        with warnings.catch_warnings():  # e.g. glfw's about a missing display, before it fails
            warnings.simplefilter("ignore")
            env = gym.make(env_id, render_mode="rgb_array")
            env.reset(seed=0)
            env.render()
        return env
    except Exception as exc:  # no usable OpenGL backend: say so instead of a long traceback
        first_line = (str(exc).splitlines() or [""])[0][:160]
        if isinstance(exc, gym.error.DependencyNotInstalled):  # e.g. pygame for the classic-control envs
            fail(f"cannot render {env_id}: {first_line}")
        fail(f"cannot render {env_id} with MUJOCO_GL={os.environ.get('MUJOCO_GL', '(unset)')} "
             f"({type(exc).__name__}: {first_line}); try MUJOCO_GL=egl, or MUJOCO_GL=osmesa with libosmesa installed")


def record_video(actor: Actor, stats, env_id: str, path: str, deterministic: bool, seed: int) -> float:
    """Write an mp4 of one episode; returns its return. Needs an OpenGL backend for MuJoCo."""
    env = make_render_env(env_id)
    obs, _ = env.reset(seed=seed)
    frames = [env.render()]
    import imageio.v2 as imageio  # with imageio-ffmpeg (requirements.txt) for mp4

    writer = imageio.get_writer(path, fps=env.metadata.get("render_fps", 30))
    generator = torch.Generator().manual_seed(seed)
    total, done = 0.0, False
    with torch.inference_mode():
        while not done:
            mean, log_std = actor(torch.as_tensor(normalize_obs(obs[None], stats)))
            if not deterministic:
                mean = mean + torch.exp(log_std) * torch.randn(mean.shape, generator=generator)
            action = np.clip(mean[0].numpy(), env.action_space.low, env.action_space.high)
            obs, reward, terminated, truncated, _ = env.step(action)
            total += float(reward)
            done = terminated or truncated
            frames.append(env.render())
    for frame in frames:
        writer.append_data(frame)
    writer.close()
    env.close()
    return total

# ----------------------------------------------------------------------------------------------
# Checkpoints: one file with everything needed to continue and to act
# ----------------------------------------------------------------------------------------------
CHECKPOINT_NAME = "checkpoint.pt"


def save_checkpoint(path: str, payload: dict) -> None:
    """Atomic: write a temp file, fsync, then rename over the old one (which stays intact until then).
    A failed write (a full disk, most often) removes the temp file and stops the run in one line."""
    tmp = f"{path}.tmp"
    with write_failures(path, tmp), open(tmp, "wb") as f:
        torch.save(payload, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


@contextlib.contextmanager
def write_failures(path: str, tmp: str):
    """Turn a failed write of `tmp` into one line naming the cause, after removing `tmp` (a full disk would stay
    full otherwise); the file at `path` is untouched. torch.save reports a full disk as a RuntimeError."""
    try:
        yield
    except (OSError, RuntimeError) as exc:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        folder = os.path.dirname(os.path.abspath(path))
        full = getattr(exc, "errno", None) == errno.ENOSPC or shutil.disk_usage(folder).free < 1 << 20
        previous = f"the previous {os.path.basename(path)} is intact" if os.path.exists(path) else \
            f"no earlier {os.path.basename(path)} exists"
        if full:
            fail(f"no space left on {folder}; {previous}; free some space and continue with --resume {folder}")
        fail(f"cannot write {tmp} ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}); {previous}; "
             f"fix that and continue with --resume {folder}")
    except BaseException:  # stopped mid-write (Ctrl-C, SIGTERM): no partial file is left behind either
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise


def non_finite_advice(checkpoint_path: str) -> str:
    """What the non-finite guard's line says about the checkpoint it kept, and what to change."""
    remedy = "start a new run with a lower --learning-rate (or another --seed)"
    if not os.path.exists(checkpoint_path):
        return f"no checkpoint was written yet; {remedy}"
    return (f"the last good checkpoint {checkpoint_path} is intact, but resuming it repeats the same updates exactly "
            f"and diverges again; {remedy}")


def load_checkpoint(path: str) -> dict:
    """Load `runs/<run>` (its latest checkpoint) or a checkpoint file; one-line error if missing or corrupt."""
    if os.path.isdir(path):
        path = os.path.join(path, CHECKPOINT_NAME)
    if not os.path.isfile(path):
        fail(f"no checkpoint at {path}; pass a run folder holding {CHECKPOINT_NAME} or a checkpoint file")
    try:
        # weights_only=False: the file holds numpy statistics and the simulator state; load only your own runs
        checkpoint = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:
        fail(f"cannot read checkpoint {path} (corrupt or not a checkpoint: {type(exc).__name__})")
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != "ppo_baseline/2":
        fail(f"{path} is not a ppo_baseline checkpoint")
    checkpoint["path"] = path
    return checkpoint


def actor_from_checkpoint(checkpoint: dict, device: str | torch.device = "cpu") -> Actor:
    saved = Args(**checkpoint["args"])
    rng = torch.get_rng_state()  # building the net draws random inits; keep the caller's RNG untouched
    actor = Actor(checkpoint["obs_dim"], checkpoint["act_dim"], saved.hidden_size)
    torch.set_rng_state(rng)
    actor.load_state_dict(checkpoint["actor"])
    return actor.to(device)


class Progress:
    """One self-updating line on a terminal; plain lines every `interval` seconds otherwise."""

    def __init__(self, total_steps: int, quiet: bool, interval: float = 30.0):
        self.total, self.quiet, self.interval = total_steps, quiet, interval
        self.tty = sys.stdout.isatty()
        self.last_print = 0.0
        self.last_eval: float | None = None
        self.note = ""  # e.g. that a fast path was switched off

    def update(self, step: int, sps: float, force: bool = False) -> None:
        now = time.time()
        if self.quiet or (not force and now - self.last_print < (0.5 if self.tty else self.interval)):
            return
        self.last_print = now
        eta = (self.total - step) / max(sps, 1e-9)
        ev = "-" if self.last_eval is None else f"{self.last_eval:.1f}"
        line = (f"{step:>10,}/{self.total:,} steps ({100 * step / self.total:5.1f}%) | {sps:6.0f} SPS | "
                f"eval {ev} | ETA {time.strftime('%H:%M:%S', time.gmtime(eta))}{self.note}")
        print(f"\r{line}" if self.tty else line, end="" if self.tty else "\n", flush=True)

    def message(self, text: str) -> None:
        """A normal line that does not garble the progress line."""
        if self.quiet:
            return
        print(f"\r\033[K{text}" if self.tty else text, flush=True)

# ----------------------------------------------------------------------------------------------
# Input checks, seeding
# ----------------------------------------------------------------------------------------------
def check_run_settings(args: Args) -> None:
    """Settings every run shares, refused in one line each (instead of a traceback later, or a run folder left)."""
    if args.seed < 0:
        fail(f"--seed must be a non-negative integer (got {args.seed}); numpy and gymnasium refuse negative seeds")
    if args.torch_threads < 1:
        fail(f"--torch-threads must be at least 1 (got {args.torch_threads})")
    if args.checkpoint_every < 0:
        fail(f"--checkpoint-every must be >= 0 (0: only the checkpoints a run always writes; got {args.checkpoint_every})")
    if not args.learning_rate >= 0:
        fail(f"--learning-rate must be >= 0 (got {args.learning_rate})")
    if args.num_minibatches < 1 or args.update_epochs < 1:
        fail(f"--num-minibatches and --update-epochs must be at least 1 (got {args.num_minibatches}, {args.update_epochs})")
    check_track_dir(args.track_dir)
    if args.track:
        check_wandb()


def check_track_dir(track_dir: str) -> None:
    """Run folders can be created under `track_dir` (probed in its nearest existing ancestor, nothing left behind)."""
    if os.path.exists(track_dir) and not os.path.isdir(track_dir):
        fail(f"--track-dir {track_dir} is a file, not a folder; pass a folder for the run folders")
    ancestor = os.path.abspath(track_dir)
    while not os.path.exists(ancestor):
        ancestor = os.path.dirname(ancestor)
    try:
        os.rmdir(tempfile.mkdtemp(dir=ancestor))
    except OSError as exc:
        fail(f"cannot create run folders under --track-dir {track_dir} ({exc.strerror or exc} in {ancestor}); "
             "pass a writable folder")


def validate(args: Args) -> None:
    """Reject bad input with one clear line before anything is created."""
    check_run_settings(args)
    if args.hidden_size < 1:
        fail(f"--hidden-size must be at least 1 (got {args.hidden_size})")
    if args.num_envs < 1:
        fail(f"--num-envs must be at least 1 (got {args.num_envs})")
    steps_defaulted = args.num_steps is None
    if steps_defaulted:
        args.num_steps = max(2048 // args.num_envs, 1)
    if args.num_steps < 1:
        fail(f"--num-steps must be at least 1 (got {args.num_steps})")
    batch_size = args.num_envs * args.num_steps
    if args.total_timesteps < batch_size:
        fail(f"--total-timesteps {args.total_timesteps} is smaller than one rollout batch "
             f"(num_envs*num_steps = {batch_size}); raise it")
    if args.lr_schedule == "cyclic" and args.cycle_steps < batch_size:
        fail(f"--cycle-steps {args.cycle_steps} is smaller than one rollout batch ({batch_size})")
    if batch_size % args.num_minibatches:
        hint = ""
        if steps_defaulted:  # the batch is 2048 // num_envs * num_envs: say which --num-envs keep it whole
            working = [e for e in range(1, 17) if (2048 // e * e) % args.num_minibatches == 0]
            hint = f"; with --num-minibatches {args.num_minibatches}, --num-envs {', '.join(map(str, working))} work"
        fail(f"the batch size {batch_size} (num_envs*num_steps) is not divisible by --num-minibatches "
             f"{args.num_minibatches}{hint}, or set --num-steps")
    if args.eval_every < 0 or (args.eval_every and args.eval_episodes < 1):
        fail("--eval-every must be >= 0 and --eval-episodes >= 1")
    check_env_id(args.env_id)
    probe = gym.make(args.env_id)
    action_space = probe.action_space
    probe.close()
    if not isinstance(action_space, gym.spaces.Box):
        fail(f"{args.env_id} has a {type(action_space).__name__} action space; this script needs a Box "
             "(continuous) one: use cascade_ppo_discrete.py")


def seed_everything(seed: int, torch_deterministic: bool) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    torch.backends.cudnn.deterministic = torch_deterministic


def rng_states() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def set_rng_states(states: dict) -> None:
    torch.set_rng_state(states["torch"])
    np.random.set_state(states["numpy"])
    random.setstate(states["python"])




# ----------------------------------------------------------------------------------------------
# Command line: train, resume, or evaluate a saved model
# ----------------------------------------------------------------------------------------------
# Settings a resumed run may change; every other flag must match the checkpoint.
RESUME_OVERRIDABLE = {"resume", "quiet", "checkpoint_every", "torch_threads", "cuda", "track", "wandb_project_name",
                      "wandb_entity", "wandb_group"}


def explicit_fields(argv: list[str]) -> set[str]:
    """Names of the Args fields given on the command line (`--env-id X`, `--no-normalize`, ...)."""
    names = {f for f in Args.__dataclass_fields__}
    given = set()
    for token in argv:
        if not token.startswith("--"):
            continue
        name = token[2:].split("=")[0].replace("-", "_")
        if name not in names and name.startswith("no_") and name[3:] in names:
            name = name[3:]
        if name in names:
            given.add(name)
    return given


def resumed_args(args: Args, checkpoint: dict, given: set[str]) -> Args:
    """The checkpoint's settings; a conflicting flag on the command line is an error."""
    saved = Args(**checkpoint["args"])
    for name in sorted(given - RESUME_OVERRIDABLE):
        if getattr(args, name) != getattr(saved, name):
            fail(f"--{name.replace('_', '-')} {getattr(args, name)} differs from the checkpoint's "
                 f"{getattr(saved, name)}; a resumed run keeps its settings (drop the flag)")
    for name in given & RESUME_OVERRIDABLE:
        setattr(saved, name, getattr(args, name))
    return saved


def evaluate_saved(args: Args) -> dict:
    """--evaluate: the saved policy with its saved observation statistics frozen."""
    if args.eval_episodes < 1:
        fail(f"--eval-episodes must be at least 1 (got {args.eval_episodes})")
    checkpoint = load_checkpoint(args.evaluate)
    saved = Args(**checkpoint["args"])
    if args.capture_video:
        make_render_env(saved.env_id).close()  # fail early, before any episode is run
    torch.set_num_threads(args.torch_threads)
    actor = actor_from_checkpoint(checkpoint)
    stats = checkpoint["obs_stats"]
    evaluator = Evaluator(saved.env_id, args.eval_episodes, args.seed)
    returns = evaluator(actor, stats, 0, args.deterministic)
    mode = "deterministic" if args.deterministic else "stochastic"
    print(f"{saved.env_id}, PPO, step {checkpoint['global_step']}: "
          f"return {returns.mean():.1f} ± {returns.std():.1f} over {len(returns)} {mode} episodes")
    result = {"returns": returns}
    evaluator.close()
    if args.capture_video:
        path = os.path.splitext(checkpoint["path"])[0] + f"_{mode}.mp4"
        video_return = record_video(actor, stats, saved.env_id, path, args.deterministic, args.seed)
        print(f"video of one episode (return {video_return:.1f}): {path}")
    return result


def stop_signal(signum, frame) -> None:
    """SIGTERM stops a run as Ctrl-C does (the exit code tells them apart)."""
    STOPPED_BY.append(signum)
    raise KeyboardInterrupt


STOPPED_BY: list[int] = []


def stopped(args: Args, checkpoint: dict | None, started: float) -> None:
    """One line on where a stopped run's last checkpoint is and how to continue; exit 130 (SIGINT) / 143 (SIGTERM)."""
    if checkpoint is not None:
        run_dir = os.path.dirname(checkpoint["path"])
    else:  # this run's folder: the newest of its name, made since it started
        pattern = os.path.join(glob.escape(args.track_dir), f"{glob.escape(args.env_id)}__{glob.escape(args.exp_name)}__{args.seed}__*")
        mine = [d for d in glob.glob(pattern) if int(d.rsplit("__", 1)[1]) >= int(started)]
        run_dir = max(mine, key=os.path.getmtime) if mine else None
    signum = STOPPED_BY[-1] if STOPPED_BY else signal.SIGINT
    name = signal.Signals(signum).name
    script = os.path.basename(sys.argv[0])
    if run_dir is not None and os.path.exists(os.path.join(run_dir, CHECKPOINT_NAME)):
        where = f"the last checkpoint is {os.path.join(run_dir, CHECKPOINT_NAME)}; continue with: python {script} --resume {run_dir}"
    else:
        where = "no checkpoint was written yet, so there is nothing to resume"
    print(f"\rstopped by {name}: {where}", file=sys.stderr, flush=True)
    sys.exit(128 + signum)


def main() -> None:
    args = tyro.cli(Args, description=__doc__.split("\n\n")[0])
    if args.evaluate:
        evaluate_saved(args)
        return
    checkpoint = None
    if args.resume:
        checkpoint = load_checkpoint(args.resume)
        args = resumed_args(args, checkpoint, explicit_fields(sys.argv[1:]))
    signal.signal(signal.SIGTERM, stop_signal)
    started = time.time()
    try:
        train(args, checkpoint)
    except BaseException as exc:
        finish_wandb(exit_code=1)  # an error or a stop: the W&B run ends as failed, before the last line
        if isinstance(exc, KeyboardInterrupt):
            stopped(args, checkpoint, started)
        raise


if __name__ == "__main__":
    main()
