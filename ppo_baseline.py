"""PPO for continuous-action tasks, the baseline of the Cascade paper (single-file, CleanRL style).

Equivalent to CleanRL's `ppo_continuous_action.py` (same network, wrappers and hyperparameters) on
gymnasium 1.x, with the paper's extra baseline flags: `--hidden-size`, `--lr-schedule cyclic
--cycle-steps` and `--no-normalize`. Paper: Schmöcker & Dockhorn, "Cascade - A sequential ensemble method
for continuous control tasks", RLJ 2025: the defaults are the PPO baseline that Cascade is compared with in
Fig. 2 (Section 4.2; setup: Section 4.1, hyperparameters: CleanRL's, Appendix B.4; other run lengths: Fig. 9),
and `--hidden-size 16 --lr-schedule cyclic --cycle-steps 1000000` is the single base net of Fig. 3, trained with
a learning rate that restarts every 1M steps; evaluation as in Appendix B.5.

Reading order as in cascade_ppo_continuous.py: `Args`; section 1, the algorithm in plain torch with autograd
(the nets, the policy and how it acts, the loss, the training loop, the evaluation): the one definition of the
math, and the place to edit it. Section 2 switches on fast paths (cascade_plumbing/fast.py: a numpy acting
forward and sampler, hand-written gradients); they are checked against section 1 while training, and a run
whose section 1 was edited so that they no longer match on the checked inputs switches to section 1 by
itself, with one warning line (what the checks cannot see: docs/hacking.md). Section 3 wires the run to the shared plumbing (cascade_plumbing/: envs, logging, checkpoints, command
line).

    python ppo_baseline.py --env-id Ant-v4 --total-timesteps 6000000
    tensorboard --logdir runs
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from functools import partial
from typing import Literal

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
from torch.distributions import Normal

import cascade_plumbing.checkpoints as checkpoints
from cascade_plumbing.envs import check_box_env, normalize_obs, obs_statistics
from cascade_plumbing.errors import fail
from cascade_plumbing.evaluation import (
    EvaluationEnvs,
    EvaluationRunner,
    mean_action_defined,
    open_saved_model,
    save_video_of_one_episode,
)
from cascade_plumbing.fast import FastPaths, mlp_ppo_gradients, numpy_mlp_policy, share_one_buffer
from cascade_plumbing.ppo import (
    baseline_updates,
    check_ppo_settings,
    count_parameters,
    log_ppo_update,
    make_env,  # noqa: F401 (part of this script's interface: tests and tools call ppo_baseline.make_env)
    make_vector_env,
)
from cascade_plumbing.record import RunRecord
from cascade_plumbing.runs import (
    asked_for,
    check_common_settings,
    run_device,
    run_main,
    script_name,
    seed_everything,
    set_threads,
)

# The paper used the v4 MuJoCo tasks; gymnasium warns on every make that they are out of date.
warnings.filterwarnings("ignore", message=".*is out of date.*")
# A stopped run (Ctrl-C, SIGTERM) closes its --num-envs workers mid-step; that is expected, not worth a warning.
warnings.filterwarnings("ignore", message=".*Calling `close` while waiting for a pending call.*")


@dataclass
class Args:
    exp_name: str = field(default_factory=lambda: script_name(__file__))
    """the name of this experiment (part of the run name); default: this file's name, so a copy's runs are its own"""
    seed: int = 1
    """seed of the experiment (python, numpy, torch and the environments)"""
    torch_deterministic: bool = True
    """CleanRL's flag: `torch.backends.cudnn.deterministic` (GPU runs only; a CPU run repeats exactly on the same machine either way)"""
    torch_threads: int = 1
    """torch CPU threads (numpy's BLAS: one); 1 is fastest for these small nets"""
    cuda: bool = False
    """train on the GPU if torch sees one: slower for these small nets (measured for Cascade: docs/performance.md); --evaluate runs on the CPU"""
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
    """total environment steps of the run (the paper's baselines: 6M in Fig. 2 and 3; 2M..6M in Fig. 9)"""
    hidden_size: int = 64
    """width of the two hidden layers of the actor (the critic stays 64-64)"""
    lr_schedule: Literal["global", "cyclic", "constant"] = "global"
    """global: linear decay to 0 over the run (CleanRL); cyclic: decay restarts every --cycle-steps, with a fresh Adam at each restart as the paper's code ran Fig. 3 (a new PPO instance per cycle, the nets kept; Section 4.2); constant: no decay"""
    cycle_steps: int = 1_000_000
    """length of one learning-rate cycle in env steps, with --lr-schedule cyclic (a cycle is cycle_steps // batch updates, as a Cascade iteration; the run is whole cycles, then the rest)"""

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
    """clip range of the surrogate objective (PPO's epsilon) and, with --clip-vloss, of the value loss"""
    clip_vloss: bool = True
    """use a clipped value loss"""
    ent_coef: float = 0.0
    """entropy bonus coefficient"""
    vf_coef: float = 0.5
    """value loss coefficient"""
    max_grad_norm: float = 0.5
    """global gradient-norm clip"""
    target_kl: float | None = None
    """skip an update's remaining epochs once the approximate KL of an epoch's last minibatch exceeds this (CleanRL; unset: never)"""

    # Evaluation (paper Appendix B.5)
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
    """no progress line and no messages while training (warnings and errors still go to stderr); sweep.py passes it"""


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
    """Gaussian policy: mean MLP obs -> H -> H -> A (tanh) and one state-independent log-std vector. Anything the
    policy needs to act must be a Parameter or a buffer: evaluations and checkpoints rebuild it from its state_dict."""

    def __init__(self, obs_dim: int, act_dim: int, hidden_size: int):
        super().__init__()
        self.mean_net = TanhMLP([obs_dim, hidden_size, hidden_size, act_dim], [math.sqrt(2), math.sqrt(2), 0.01])
        self.log_std = nn.Parameter(torch.zeros(1, act_dim))

    def forward(self, obs: torch.Tensor, hidden: list[torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """obs [B, obs_dim] -> mean and log-std [B, A]; `hidden` as in TanhMLP.forward."""
        mean = self.mean_net(obs, hidden)
        return mean, self.log_std.expand_as(mean)


def make_critic(obs_dim: int) -> TanhMLP:
    """The PPO value net, obs -> 64 -> 64 -> 1 (tanh)."""
    return TanhMLP([obs_dim, 64, 64, 1], [math.sqrt(2), math.sqrt(2), 1.0])


def action_distribution(mean: torch.Tensor, log_std: torch.Tensor) -> Normal:
    """The policy pi(.|s): a diagonal Gaussian. Rollouts, evaluations and videos all sample it (`sample_action`)."""
    return Normal(mean, log_std.exp(), validate_args=False)


def sample_action(mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """An action drawn from pi(.|s), from torch's RNG (CleanRL's `probs.sample()`)."""
    return action_distribution(mean, log_std).sample()


def act(actor: Actor, obs: np.ndarray) -> np.ndarray:
    """The rollout's actions for a batch of observations [E, obs_dim]: samples of the current policy.
    Evaluations act through `Evaluator` below (the same `sample_action`), not through this function."""
    with torch.inference_mode():
        mean, log_std = actor(torch.as_tensor(obs, device=actor.log_std.device))
        return sample_action(mean, log_std).cpu().numpy()


def ppo_loss(mean: torch.Tensor, log_std: torch.Tensor, value: torch.Tensor, actions: torch.Tensor,
             old_logprob: torch.Tensor, advantages: torch.Tensor, returns: torch.Tensor, old_value: torch.Tensor,
             args: Args) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """CleanRL's PPO loss on one minibatch (ppo_continuous_action.py); returns the loss and its parts (a scalar
    part added here is logged as `losses/<name>`)."""
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
    """The loss of one minibatch and its gradient by autograd, written into every parameter's .grad.
    Keep it (and `ppo_loss`, `optimizer_step`) free of side effects: on the fast path it runs only inside the
    run-time checks, on float64 copies (see docs/hacking.md)."""
    obs, actions, old_logprob, advantages, returns, old_value = minibatch
    with torch.enable_grad():
        mean, log_std = actor(obs)
        loss, parts = ppo_loss(mean, log_std, critic(obs).squeeze(1), actions, old_logprob, advantages, returns,
                               old_value, args)
        grads = torch.autograd.grad(loss, params, allow_unused=True)
    for param, grad in zip(params, grads):
        param.grad.copy_(grad) if grad is not None else param.grad.zero_()
    return loss.detach(), {key: value.detach() for key, value in parts.items()}


def make_optimizer(actor: Actor, critic: TanhMLP, flat_params: nn.Parameter, learning_rate: float) -> torch.optim.Adam:
    """PPO's Adam (eps 1e-5) over `flat_params`, the one buffer every parameter of the actor and critic is a view
    of: the fused kernel updates them all at once, ~3x faster on CPU. Any other optimizer works too, also one over
    parameter groups with their own learning rates (`actor.parameters()`, `critic.parameters()`: each group's LR
    follows the schedule from its own initial value). The fast path calls the fused Adam kernel directly only for
    this exact Adam over `[flat_params]`, checked against `optimizer_step` below; otherwise it steps aside."""
    return torch.optim.Adam([flat_params], lr=learning_rate, eps=1e-5, fused=True)


def optimizer_step(flat_params: nn.Parameter, optimizer: torch.optim.Optimizer, args: Args) -> None:
    """One step on the gradients in .grad: the global gradient-norm clip, then the optimizer (CleanRL).
    No side effects here either: the fast path's checks call it twice (on float64 copies), not once a step."""
    nn.utils.clip_grad_norm_([flat_params], args.max_grad_norm)
    optimizer.step()


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
    validate(args, new_run=checkpoint is None)
    set_threads(args.torch_threads)
    seed_everything(args.seed, args.torch_deterministic)
    device = run_device(args.cuda)
    envs = make_vector_env(args)
    obs_dim = int(np.prod(envs.single_observation_space.shape))
    act_dim = int(np.prod(envs.single_action_space.shape))
    batch_size = args.num_envs * args.num_steps
    minibatch_size = batch_size // args.num_minibatches
    total_updates = baseline_updates(args, batch_size)  # (under a cyclic LR: whole cycles, then the rest)
    updates_per_cycle = max(args.cycle_steps // batch_size, 1)
    run = RunLog(args, checkpoint, obs_dim, act_dim, envs, total_updates * batch_size)
    fast = make_fast_paths(args, device, run)  # section 2, checked against this section while the run trains

    actor = Actor(obs_dim, act_dim, args.hidden_size).to(device)
    critic = make_critic(obs_dim).to(device)
    flat_params = share_one_buffer([*actor.parameters(), *critic.parameters()])
    optimizer = make_optimizer(actor, critic, flat_params, args.learning_rate)
    all_params = [*actor.parameters(), *critic.parameters()]
    run.parameters(count_parameters(actor, critic), checkpoint is None)
    # rollout storage, numpy: the env takes and gives numpy (and the fast acting path runs in numpy)
    obs = np.zeros((args.num_steps, args.num_envs, obs_dim), dtype=np.float32)
    actions = np.zeros((args.num_steps, args.num_envs, act_dim), dtype=np.float32)
    rewards = np.zeros((args.num_steps, args.num_envs), dtype=np.float32)
    dones = np.zeros((args.num_steps, args.num_envs), dtype=np.float32)

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
                # a new cycle: fresh Adam moments
                optimizer = make_optimizer(actor, critic, flat_params, args.learning_rate)
        else:
            frac = 1.0
        for group in optimizer.param_groups:  # one group here (the flat buffer); an edit may make more, each
            group["lr"] = frac * group.setdefault("initial_lr", group["lr"])  # with its own initial LR

        # --- rollout: the weights do not change during it; values and log-probs are computed for the
        # whole batch afterwards ---
        # `act`, or its numpy twin once it draws what `act` draws on the next observation and 8 of the last rollout's
        check_obs = np.concatenate([next_obs, obs[:: max(args.num_steps // 8, 1), 0]])
        policy = fast.acting_function(act, actor, check_obs, global_step, args.num_steps)
        for step in range(args.num_steps):
            global_step += args.num_envs
            obs[step] = next_obs
            dones[step] = next_done
            actions[step] = policy(next_obs)  # a sample of pi(.|obs)
            next_obs, reward, terminations, truncations, infos = envs.step(actions[step])
            rewards[step] = reward
            next_obs = next_obs.astype(np.float32)
            next_done = np.logical_or(terminations, truncations).astype(np.float32)
            run.episodes(infos, global_step)
            if args.eval_every and global_step % args.eval_every < args.num_envs:
                run.evaluate(global_step, actor)

        b_obs = torch.as_tensor(obs, device=device).reshape(-1, obs_dim)
        b_actions = torch.as_tensor(actions, device=device).reshape(-1, act_dim)
        b_mean, b_log_std = actor(b_obs)
        # every action of the rollout against section 1's forward over its observations (the fast path's only)
        fast.rollout_done(act, actor, b_obs, b_mean, b_log_std, global_step)
        b_logprobs = action_distribution(b_mean, b_log_std).log_prob(b_actions).sum(1)
        values = critic(b_obs).reshape(args.num_steps, args.num_envs)
        next_value = critic(torch.as_tensor(next_obs, device=device)).reshape(args.num_envs)
        advantages = compute_gae(rewards, dones, values.cpu().numpy(), next_value.cpu().numpy(), next_done,
                                 args.gamma, args.gae_lambda)
        b_advantages = torch.as_tensor(advantages, device=device).reshape(-1)
        b_values = values.reshape(-1)
        b_returns = b_advantages + b_values

        # --- PPO update ---
        # what a minibatch holds (the order `autograd_gradients` unpacks)
        batch = (b_obs, b_actions, b_logprobs, b_advantages, b_returns, b_values)
        ratios = []  # of every minibatch, for the clip fraction
        for _epoch in range(args.update_epochs):
            b_inds = torch.randperm(batch_size, device=device)
            for start in range(0, batch_size, minibatch_size):
                minibatch = tuple(tensor[b_inds[start : start + minibatch_size]] for tensor in batch)
                # One step: edit `autograd_gradients` and `optimizer_step`, not these lines. The fast path
                # replaces the two calls below by the same step by hand, checked against those two functions (which
                # then run only inside the checks: log or count things here in the loop, not inside them).
                if fast.gradients:
                    loss, parts = fast.update(actor, critic, flat_params, optimizer, minibatch, args, global_step)
                if not fast.gradients:  # the definition (also right after the fast path switched itself off)
                    flat_params.grad.zero_()  # CleanRL's zero_grad(), in place: the nets' .grad are views of it
                    loss, parts = autograd_gradients(actor, critic, all_params, minibatch, args)
                    optimizer_step(flat_params, optimizer, args)
                ratios.append(parts["ratio"])

            # CleanRL's diagnostics, from the epoch's last minibatch
            old_approx_kl = (-parts["logratio"]).mean()
            approx_kl = ((parts["ratio"] - 1) - parts["logratio"]).mean()
            if args.target_kl is not None and approx_kl > args.target_kl:
                break

        run.update_done(global_step, optimizer, parts, old_approx_kl, approx_kl, torch.cat(ratios), b_values,
                        b_returns, fast)
        # --- non-finite guard: stop before anything bad is written to the checkpoint ---
        run.stop_if_non_finite(loss, {"actor": actor, "critic": critic}, f"global_step={global_step} (update {update})")
        run.maybe_checkpoint(update, total_updates, global_step, actor, critic, optimizer, next_obs, next_done)

    run.close(global_step)
    final_stats = obs_statistics(envs)
    envs.close()
    return {"actor": actor, "critic": critic, "run_dir": run.run_dir, "global_step": global_step,
            "obs_stats": final_stats, "fast_paths": fast}


# ----------------------------------------------------------------------------------------------
# Evaluation (paper Appendix B.5): the frozen policy and observation statistics, separate envs, sampled actions
# ----------------------------------------------------------------------------------------------
class Evaluator(EvaluationEnvs):
    """Runs `episodes` episodes side by side on its own envs (cascade_plumbing.evaluation.EvaluationEnvs, with
    `render` for a video); never touches the training envs."""

    @torch.inference_mode()
    def __call__(self, policy: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
                 stats: tuple[np.ndarray, np.ndarray] | None, call: int = 0, deterministic: bool = False) -> np.ndarray:
        """Runs `policy` (obs -> mean, log-std: the actor); returns each episode's undiscounted raw return. The
        episodes' seeds and the action noise depend only on (seed, call): evaluation never touches training's RNG."""
        base_seed = self.base_seed(call)

        def act_frozen(raw_obs: np.ndarray, _running: list[int]) -> np.ndarray:
            mean, log_std = policy(torch.as_tensor(normalize_obs(raw_obs, stats)))
            action = action_distribution(mean, log_std).mean if deterministic else sample_action(mean, log_std)
            return action.numpy()

        with torch.random.fork_rng(devices=[]):  # the action noise: sample_action on a stream of its own
            torch.default_generator.manual_seed(base_seed)  # the CPU's only: a GPU run's stream is untouched
            return self.run_episodes(act_frozen, base_seed)


# ==============================================================================================
# 2. FAST PATHS: the same acting and update, faster (cascade_plumbing/fast.py), checked against section 1
# ==============================================================================================
# Acting runs a numpy copy of the mean net and samples the Gaussian in numpy; the update writes its
# gradients by hand. Neither is a definition: at every rollout start `act` above (the forward and
# `sample_action`) and the numpy path draw actions from the same seeded RNG, and on the last minibatch of
# every update (every minibatch of an iteration's first) `autograd_gradients` above (loss, parts, gradients)
# and `optimizer_step` are compared with the hand-written update, in float64. An edit of section 1 that the
# fast paths do not reproduce, or that makes them raise, switches them off with one warning line, and the run
# continues exactly as --autograd runs it. On the CPU only: on a GPU, act() draws from the CUDA generator.
def make_fast_paths(args: Args, device: torch.device, run: RunLog | None = None) -> FastPaths:
    return FastPaths(not args.autograd and device.type == "cpu", numpy_mlp_policy, mlp_ppo_gradients,
                     None if run is None else run.fast_path_off, definition=(autograd_gradients, optimizer_step))


# ==============================================================================================
# 3. PLUMBING: environments, evaluation, checkpoints, progress, command line
# ==============================================================================================
# The envs are CleanRL's wrapper stack (cascade_plumbing/ppo.py, the flagship's stack): `make_env(env_id, gamma,
# normalize)` for one env (raw episode statistics, action clip, obs/reward normalization, +-10 clips),
# `make_vector_env(args)` for the --num-envs training envs.


# ----------------------------------------------------------------------------------------------
# Evaluating a frozen copy (in the evaluation worker, or inline)
# ----------------------------------------------------------------------------------------------
def frozen_actor(obs_dim: int, act_dim: int, hidden_size: int, state: dict) -> Actor:
    """An Actor holding `state`; building it draws no number from the caller's torch RNG (training's, when
    evaluations run inline)."""
    with torch.random.fork_rng(devices=[]):
        actor = Actor(obs_dim, act_dim, hidden_size)
    actor.load_state_dict(state)
    return actor


def evaluate_request(args_dict: dict, obs_dim: int, act_dim: int, evaluator: Evaluator, call: int,
                     request: tuple) -> np.ndarray:
    """One evaluation (in the worker process, or inline): rebuild the frozen policy and run the episodes."""
    state, stats = request
    return evaluator(frozen_actor(obs_dim, act_dim, Args(**args_dict).hidden_size, state), stats, call)



# ----------------------------------------------------------------------------------------------
# The run's bookkeeping: TensorBoard, evaluations, checkpoints and resume, progress
# ----------------------------------------------------------------------------------------------
class RunLog(RunRecord):
    """What `train` records about a PPO run and restores when it is resumed (the generic part: RunRecord)."""

    def __init__(self, args: Args, checkpoint: dict | None, obs_dim: int, act_dim: int,
                 envs: gym.vector.VectorEnv, total_steps: int):
        batch_size = args.num_envs * args.num_steps
        if total_steps != args.total_timesteps and checkpoint is None:
            cycles = f" or of --cycle-steps {args.cycle_steps}" if args.lr_schedule == "cyclic" else ""
            print(f"note: total_timesteps={args.total_timesteps} is not a multiple of the batch size {batch_size}"
                  f"{cycles}; the run does {total_steps // batch_size} updates = {total_steps} steps")
        super().__init__(args, checkpoint, envs, total_steps, at_iteration_end=False, iteration_files=False)  # no iterations
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.runner = EvaluationRunner(
            partial(Evaluator, args.env_id, args.eval_episodes, args.seed),
            partial(evaluate_request, asdict(args), obs_dim, act_dim), args.eval_in_worker,
            calls=0 if checkpoint is None else checkpoint["eval_calls"]) if args.eval_every else None

    def parameters(self, count: int, fresh: bool) -> None:
        self.progress.message(f"PPO: {count} parameters (actor + critic)")
        if fresh:
            self.writer.add_scalar("charts/parameters", count, 0)

    def restore(self, checkpoint: dict, actor: Actor, critic: nn.Module, optimizer: torch.optim.Optimizer) -> tuple:
        """The saved nets, optimizer, env states and RNG streams; returns (global_step, next_obs, next_done,
        update) of where the run continues."""
        global_step, next_obs = self.restore_envs(checkpoint)
        actor.load_state_dict(checkpoint["actor"])
        critic.load_state_dict(checkpoint["critic"])
        checkpoints.load_optimizer(optimizer, checkpoint["optimizer"])
        return global_step, next_obs, checkpoint["next_done"], checkpoint["updates_done"] + 1

    def update_done(self, global_step: int, optimizer: torch.optim.Optimizer, parts: dict,
                    old_approx_kl: torch.Tensor, approx_kl: torch.Tensor, ratios: torch.Tensor,
                    b_values: torch.Tensor, b_returns: torch.Tensor, fast: FastPaths) -> None:
        """CleanRL's scalars after one update, the fast paths' state, SPS and the progress line."""
        log_ppo_update(self.writer, global_step, optimizer, parts, old_approx_kl, approx_kl, ratios, b_values,
                       b_returns, self.args.clip_coef, fast)
        self.tick(global_step, 1)

    # --- evaluation (paper Appendix B.5) ---
    def evaluate(self, step: int, actor: Actor) -> None:
        """Freeze the current policy and observation statistics and evaluate them."""
        if self.runner is None:
            return
        state = {k: v.detach().cpu().clone() for k, v in actor.state_dict().items()}
        self.runner.submit(step, (state, obs_statistics(self.envs)))
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
        now = update == total_updates or self.checkpoint_due(global_step)
        if update == total_updates and self.args.eval_every and global_step % self.args.eval_every >= self.args.num_envs:
            # the final policy, if the last step was not an eval step: logged before the final checkpoint, so
            # that a stop right after it loses nothing
            self.evaluate(global_step, actor)
        self.log_evaluations(wait=now)  # finished evaluations; before a checkpoint, all of them
        if now:
            self.save({
                "format": CHECKPOINT_FORMAT, "args": asdict(self.args), "obs_dim": self.obs_dim,
                "act_dim": self.act_dim, "updates_done": update, "actor": actor.state_dict(),
                "critic": critic.state_dict(), "optimizer": optimizer.state_dict(),
                "obs_stats": obs_statistics(self.envs), "next_obs": next_obs.copy(), "next_done": next_done.copy(),
                "eval_calls": 0 if self.runner is None else self.runner.calls,
            }, global_step)

    def close(self, global_step: int) -> None:
        if self.runner is not None:
            self.log_evaluations(wait=True)
            self.runner.close()
        super().close(global_step)


# ----------------------------------------------------------------------------------------------
# Checkpoints: one file with everything needed to continue and to act
# ----------------------------------------------------------------------------------------------
CHECKPOINT_FORMAT = "ppo_baseline/2"


def load_checkpoint(path: str, reader_flag: str = "") -> dict:
    """A run folder's latest checkpoint, or a checkpoint file, of this script (one-line error otherwise)."""
    return checkpoints.load_checkpoint(path, CHECKPOINT_FORMAT, reader_flag=reader_flag)


def finished(args: Args, checkpoint: dict) -> bool:
    """Whether the checkpoint is the end of the run (resuming it would have nothing left to do)."""
    # (>=: a cyclic run finished before its budget was counted in whole cycles made one update more)
    return checkpoint["updates_done"] >= baseline_updates(args, args.num_envs * args.num_steps)


def actor_from_checkpoint(checkpoint: dict, device: str | torch.device = "cpu") -> Actor:
    hidden_size = Args(**checkpoint["args"]).hidden_size
    return frozen_actor(checkpoint["obs_dim"], checkpoint["act_dim"], hidden_size, checkpoint["actor"]).to(device)


# ----------------------------------------------------------------------------------------------
# Input checks, command line: train, resume, or evaluate a saved model
# ----------------------------------------------------------------------------------------------
def validate(args: Args, new_run: bool = True) -> None:
    """Reject bad input with one clear line before anything is created."""
    check_common_settings(args)
    batch_size = check_ppo_settings(args)
    if args.hidden_size < 1:
        fail(f"--hidden-size must be at least 1 (got {args.hidden_size})")
    if args.total_timesteps < batch_size:
        fail(f"--total-timesteps {args.total_timesteps} is smaller than one rollout batch "
             f"(num_envs*num_steps = {batch_size}); raise it")
    if args.lr_schedule == "cyclic" and args.cycle_steps < batch_size:
        fail(f"--cycle-steps {args.cycle_steps} is smaller than one rollout batch ({batch_size})")
    if new_run and args.lr_schedule != "cyclic" and asked_for(args, "cycle_steps", Args.cycle_steps):  # (older runs resume)
        fail(f"--cycle-steps has no effect with --lr-schedule {args.lr_schedule}; add --lr-schedule cyclic or drop "
             "--cycle-steps")
    check_box_env(args.env_id, discrete_script="ppo_baseline_discrete.py")


def evaluate_saved(args: Args) -> dict:
    """--evaluate: the saved policy with its saved observation statistics frozen."""
    checkpoint = open_saved_model(args, load_checkpoint)
    env_id, stats = checkpoint["args"]["env_id"], checkpoint["obs_stats"]
    actor = actor_from_checkpoint(checkpoint)
    with mean_action_defined(args.deterministic):  # --deterministic: a distribution without a mean, one line
        evaluator = Evaluator(env_id, args.eval_episodes, args.seed)
        returns = evaluator(actor, stats, 0, args.deterministic)
        evaluator.close()
        mode = "deterministic" if args.deterministic else "stochastic"
        print(f"{env_id}, PPO, step {checkpoint['global_step']}: "
              f"return {returns.mean():.1f} ± {returns.std():.1f} over {len(returns)} {mode} episodes")
        if args.capture_video:  # (needs an OpenGL backend for MuJoCo)
            save_video_of_one_episode(checkpoint["path"], mode, Evaluator(env_id, 1, args.seed, render=True),
                                      lambda video: video(actor, stats, 0, args.deterministic)[0])
    return {"returns": returns}


def main() -> None:
    run_main(Args, train, evaluate_saved, load_checkpoint, finished, description=__doc__.split("\n\n")[0])


if __name__ == "__main__":
    main()
