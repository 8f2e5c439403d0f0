"""Cascade trained with PPO on continuous-action tasks (single-file, CleanRL style).

Cascade grows an ensemble policy one base net at a time. Every `k` env steps a new base net b_i is
stacked on the ensemble C_{i-1}; besides its action mean it emits a fallback weight
lambda_i(x) in [0, 1] and the ensemble becomes

    C_i(x) = lambda_i(x) * C_{i-1}(x) + (1 - lambda_i(x)) * b_i(x)        (mean and log-std alike)

The whole stack is trained end to end with PPO; each iteration gets a fresh critic, a fresh Adam and
a fresh learning-rate cycle, while the observation/reward normalization statistics carry over.
Paper: Schmöcker & Dockhorn, "Cascade - A sequential ensemble method for continuous control tasks",
RLJ 2025: the method is Section 3 (pseudocode: Algorithm 1, Appendix A), the base nets and Cascade's own
hyperparameters Appendix B.1-B.3, PPO's Appendix B.4 (CleanRL's defaults), the evaluation protocol Appendix B.5; the ablations are the flags of `Args` (figure numbers in their help).

Reading order: `Args`; section 1, the algorithm in plain torch with autograd (the net, the policy and how
it acts, the loss, the training loop, the evaluation): the one definition of the math, and the place to
edit it. Section 2 switches on fast paths (cascade_plumbing/fast.py: a numpy acting forward and sampler,
hand-written gradients); they are checked against section 1 while training, and a run whose section 1 was
edited so that they no longer match on the checked inputs switches to section 1 by itself, with one warning
line (what the checks cannot see: docs/hacking.md). Section 3
wires the run to the shared plumbing (cascade_plumbing/: envs, logging, checkpoints, command line).

    python cascade_ppo_continuous.py --env-id Ant-v4 --n 6 --k 1000000
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
from cascade_plumbing.fast import FastPaths, cascade_ppo_gradients, numpy_cascade_policy, share_one_buffer
from cascade_plumbing.ppo import (
    check_ppo_settings,
    count_parameters,
    log_ppo_update,
    make_env,  # noqa: F401  (CleanRL's env stack, one env: for the tests and a hacker)
    make_vector_env,
)
from cascade_plumbing.record import RunRecord
from cascade_plumbing.runs import check_common_settings, run_device, run_main, script_name, seed_everything, set_threads

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
    """train on the GPU if torch sees one: slower for these small nets (~0.26x the steps/s of one CPU core, docs/performance.md); --evaluate runs on the CPU"""
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

    # Cascade
    n: int = 6
    """number of base nets, i.e. iterations of Cascade (the run lasts n*k steps, each k rounded down to whole rollouts)"""
    k: int = 1_000_000
    """environment steps per iteration; a new base net is added every k steps (rounded down to whole rollouts of num_envs*num_steps: k=1M with 2048-step rollouts gives 488 updates, 999,424 steps)"""
    hidden_size: int = 16
    """width of each hidden layer of a base net (paper: 16)"""
    num_layers: int = 2
    """number of hidden layers of a base net (Fig. 8's tiny nets: 1, with --hidden-size 1)"""
    fallback_init: float = 0.5
    """initial fallback weight lambda of each new base net, in (0, 1) (Fig. 11: 0.05, 0.5, 0.9)"""
    freeze_previous: bool = False
    """only the newest base net trains; older ones are frozen (Fig. 4, 13 ablation)"""
    start_full: bool = False
    """build all n base nets at the start instead of one per iteration (Fig. 5 ablation; as the paper's code, one critic for the whole run, while Adam and the LR cycle still restart every k)"""
    lr_schedule: Literal["cyclic", "global", "constant"] = "cyclic"
    """cyclic: linear decay to 0 within each iteration (standard); global: one decay over the whole run (Fig. 12); constant: no decay"""

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
    eval_members: bool = True
    """at the end of each iteration, also evaluate each base net acting alone (`members/return/net_i`; not with --eval-every 0)"""
    eval_in_worker: bool = True
    """run evaluations in a separate process beside training (same protocol and results, ~free on 2+ cores)"""

    # Checkpoints, resuming, evaluating a saved model
    checkpoint_every: int = 100_000
    """also checkpoint every this many env steps, besides the end of every iteration (0: iteration ends only)"""
    resume: str | None = None
    """continue a killed run: `runs/<run_name>` or a checkpoint file; the saved settings are used"""
    evaluate: str | None = None
    """evaluate a saved model (`runs/<run_name>` or a checkpoint file) for --eval-episodes episodes and exit"""
    deterministic: bool = False
    """with --evaluate: act with the mean action instead of sampling"""
    members: bool = False
    """with --evaluate: also report the return of each base net acting alone"""
    quiet: bool = False
    """no progress line and no messages while training (warnings and errors still go to stderr); sweep.py passes it"""


# ==============================================================================================
# 1. THE ALGORITHM, in plain torch with autograd: the one definition of the math (edit it here)
# ==============================================================================================
def orthogonal_linear(in_features: int, out_features: int, gain: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Weight [in, out] (orthogonal init with `gain`) and zero bias [1, out] of one linear layer."""
    weight = torch.empty(out_features, in_features)
    nn.init.orthogonal_(weight, gain)
    return weight.T.contiguous(), torch.zeros(1, out_features)


def stacked_affine(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """x @ weight + bias for every base net at once: x [B, in] (shared) or [n, B, in], weight [n, in, out],
    bias [n, 1, out] -> [n, B, out]; one batched matmul for all nets."""
    x = x if x.dim() == 3 else x.expand(weight.shape[0], *x.shape)
    return torch.baddbmm(bias, x, weight)


def contributions(fallback: torch.Tensor) -> torch.Tensor:
    """Share w_i of each base net in the ensemble output, from the fallbacks l [n-1, B] of nets 2..n.

    Unrolling C_i = l_i*C_{i-1} + (1-l_i)*b_i gives C_n = sum_i w_i*b_i with
    w_i = (1 - l_i) * prod_{j>i} l_j and l_1 := 0; w_1 = prod_{j>=2} l_j is the fallback product.
    Returns w [n, B], summing to 1 over nets.
    """
    ones = fallback.new_ones((1, *fallback.shape[1:]))
    later = torch.cat([fallback, ones]).flip(0).cumprod(0).flip(0)  # row of net i: prod_{j>i} l_j
    return torch.cat([ones, 1 - fallback]) * later


class CascadeActor(nn.Module):
    """A stack of base nets `obs -> H -> ... -> H -> mean (+ fallback logit)`, tanh, evaluated together.

    The base nets' weights are stacked along a leading net axis ([n, in, out]) so every layer of all
    nets is one batched matmul; the nets are then combined with the closed form of `contributions`.
    Net 1 (the bottom) has no fallback head, so the fallback head holds nets 2..n only.
    Each net also owns a state-independent log-std vector. Anything the policy needs to act must be a Parameter
    or a buffer (`register_buffer`): evaluations and checkpoints rebuild the actor from its `state_dict`.
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden_size: int, num_layers: int, fallback_init: float):
        super().__init__()
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.hidden_size, self.num_layers = hidden_size, num_layers
        self.fallback_init = fallback_init
        self.num_frozen = 0  # base nets 1..num_frozen get no gradient (--freeze-previous)
        dims = [obs_dim] + [hidden_size] * num_layers
        self.hidden_weights = nn.ParameterList(
            [nn.Parameter(torch.empty(0, i, o)) for i, o in zip(dims[:-1], dims[1:])]
        )
        self.hidden_biases = nn.ParameterList([nn.Parameter(torch.empty(0, 1, o)) for o in dims[1:]])
        self.mean_weight = nn.Parameter(torch.empty(0, hidden_size, act_dim))
        self.mean_bias = nn.Parameter(torch.empty(0, 1, act_dim))
        self.fallback_weight = nn.Parameter(torch.empty(0, hidden_size, 1))
        self.fallback_bias = nn.Parameter(torch.empty(0, 1, 1))
        self.log_std = nn.Parameter(torch.empty(0, act_dim))
        self._refresh()

    def _refresh(self) -> None:
        # The hidden layers' (weight, bias) pairs as a plain tuple: each access to a ParameterList element
        # costs ~3 us, more than a layer's matmul at these sizes. Rebuilt whenever Parameters are replaced.
        self.hidden_layers = tuple(zip(self.hidden_weights, self.hidden_biases))

    def _apply(self, fn, recurse=True):  # .to(device), .double() and friends may replace the Parameters
        module = super()._apply(fn, recurse)
        self._refresh()
        return module

    @property
    def size(self) -> int:
        """number of base nets in the cascade"""
        return self.mean_weight.shape[0]

    def add_base_net(self) -> None:
        """Stack a freshly initialized base net on top (new stacked Parameters: rebuild the optimizer)."""
        dims = [self.obs_dim] + [self.hidden_size] * self.num_layers
        grown: dict[str, torch.Tensor] = {}
        for i, (d_in, d_out) in enumerate(zip(dims[:-1], dims[1:])):
            grown[f"hidden_weights.{i}"], grown[f"hidden_biases.{i}"] = orthogonal_linear(d_in, d_out, math.sqrt(2))
        is_bottom = self.size == 0
        weight, bias = orthogonal_linear(self.hidden_size, self.act_dim + (0 if is_bottom else 1), 0.01)
        grown["mean_weight"], grown["mean_bias"] = weight[:, : self.act_dim], bias[:, : self.act_dim]
        grown["log_std"] = torch.zeros(self.act_dim)
        if not is_bottom:
            grown["fallback_weight"] = weight[:, self.act_dim :]
            # sigmoid(logit(l0)) = l0: the new net starts by deferring a share l0 to the nets below
            grown["fallback_bias"] = torch.full((1, 1), math.log(self.fallback_init / (1 - self.fallback_init)))
        for name, param, _ in self.base_net_parameters():
            if name in grown:
                new = torch.cat([param.data, grown[name].unsqueeze(0).to(param.device)])
                self._replace(name, nn.Parameter(new))
        self._refresh()

    def freeze_below(self, num_frozen: int) -> None:
        """Give no gradient to base nets 1..num_frozen (the rest train). They stay in the optimizer, which does not
        move them with Adam (zero gradients, fresh moments each iteration) but would with weight decay."""
        self.num_frozen = num_frozen

    def trainable(self, param: torch.Tensor, first_net: int) -> torch.Tensor:
        """`param` with the rows of frozen nets detached, so that no gradient reaches them."""
        rows = self.frozen_rows(first_net)
        if rows == 0:  # nothing frozen in this parameter (the default)
            return param
        return torch.cat([param[:rows].detach(), param[rows:]])

    def base_nets(self, obs: torch.Tensor, cache: dict | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """obs [B, obs_dim] -> every base net's mean [n, B, A], log-std [n, A] and fallback logit [n-1, B]
        (nets 2..n). `cache`, when given, keeps the activations for the hand-written backward (section 2)."""
        hidden = obs  # every base net reads the same observation
        activations = [hidden]
        for weight, bias in self.hidden_layers:
            hidden = torch.tanh(stacked_affine(hidden, self.trainable(weight, 0), self.trainable(bias, 0)))
            activations.append(hidden)  # [n, B, H], all nets at once
        means = stacked_affine(hidden, self.trainable(self.mean_weight, 0), self.trainable(self.mean_bias, 0))
        fallback_logit = stacked_affine(hidden[1:], self.trainable(self.fallback_weight, 1),
                                        self.trainable(self.fallback_bias, 1))[..., 0]
        if cache is not None:
            cache.update(activations=activations, means=means)
        return means, self.trainable(self.log_std, 0), fallback_logit

    def forward(self, obs: torch.Tensor, cache: dict | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """obs [B, obs_dim] -> the ensemble's mean [B, A] and log-std [B, A], each net's fallback
        l_i = sigmoid(z_i) [n-1, B] (nets 2..n) and contribution w_i [n, B]. `cache` is section 2's: it
        receives the activations, means, fallback logits and contributions (a forward that no longer fills them
        makes the hand-written backward raise, and its check switches it off)."""
        if self.size == 0:  # the empty stack (evaluated at step 0, before net 1 exists): N(0, 1)
            zeros = obs.new_zeros(obs.shape[0], self.act_dim)
            return zeros, zeros, obs.new_zeros(0, obs.shape[0]), obs.new_zeros(0, obs.shape[0])
        means, log_stds, fallback_logit = self.base_nets(obs, cache)
        fallback = torch.sigmoid(fallback_logit)  # l_i, nets 2..n
        contribution = contributions(fallback)  # w_i [n, B]
        mean = (contribution[..., None] * means).sum(0)  # C_n = sum_i w_i b_i
        log_std = contribution.T @ log_stds  # the same sum for the per-net log-std vectors
        if cache is not None:
            cache.update(fallback_logit=fallback_logit, contribution=contribution)
        return mean, log_std, fallback, contribution

    def member(self, obs: torch.Tensor, net: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std of base net `net` (0-based) acting alone."""
        means, log_stds, _ = self.base_nets(obs)
        return means[net], log_stds[net].expand_as(means[net])

    # --- bookkeeping of the stacked parameters ---
    def base_net_parameters(self) -> list[tuple[str, nn.Parameter, int]]:
        """(name, stacked parameter, index of the net its first row belongs to)."""
        params = [(f"hidden_weights.{i}", p, 0) for i, p in enumerate(self.hidden_weights)]
        params += [(f"hidden_biases.{i}", p, 0) for i, p in enumerate(self.hidden_biases)]
        params += [("mean_weight", self.mean_weight, 0), ("mean_bias", self.mean_bias, 0)]
        params += [("log_std", self.log_std, 0)]
        params += [("fallback_weight", self.fallback_weight, 1), ("fallback_bias", self.fallback_bias, 1)]
        return params

    def frozen_rows(self, first_net: int) -> int:
        """Leading rows of a stacked parameter whose first row is net `first_net` (0-based) that are frozen."""
        return max(self.num_frozen - first_net, 0)

    def _replace(self, name: str, param: nn.Parameter) -> None:
        if "." in name:
            list_name, index = name.split(".")
            getattr(self, list_name)[int(index)] = param
        else:
            setattr(self, name, param)


class TanhMLP(nn.Module):
    """x -> tanh(x W_1 + b_1) -> ... -> x W_L + b_L, weights stored [in, out], orthogonal init (CleanRL)."""

    def __init__(self, sizes: list[int], gains: list[float]):
        super().__init__()
        self.weights, self.biases = nn.ParameterList(), nn.ParameterList()
        for d_in, d_out, gain in zip(sizes[:-1], sizes[1:], gains):
            weight, bias = orthogonal_linear(d_in, d_out, gain)
            self.weights.append(nn.Parameter(weight))
            self.biases.append(nn.Parameter(bias[0]))
        self._refresh()

    def _refresh(self) -> None:  # (weight, bias) pairs as a plain tuple, as in CascadeActor
        self.layers = tuple(zip(self.weights, self.biases))

    def _apply(self, fn, recurse=True):
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


def make_critic(obs_dim: int) -> TanhMLP:
    """The PPO value net, obs -> 64 -> 64 -> 1 (tanh), recreated at every Cascade iteration (except with --start-full, which keeps one critic)."""
    return TanhMLP([obs_dim, 64, 64, 1], [math.sqrt(2), math.sqrt(2), 1.0])


def action_distribution(mean: torch.Tensor, log_std: torch.Tensor) -> Normal:
    """The policy pi(.|s): a diagonal Gaussian. Rollouts, evaluations and videos all sample it (`sample_action`)."""
    return Normal(mean, log_std.exp(), validate_args=False)


def sample_action(mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """An action drawn from pi(.|s), from torch's RNG (CleanRL's `probs.sample()`)."""
    return action_distribution(mean, log_std).sample()


def act(actor: CascadeActor, obs: np.ndarray) -> np.ndarray:
    """The rollout's actions for a batch of observations [E, obs_dim]: samples of the current policy.
    Evaluations act through `Evaluator` below (the same `sample_action`), not through this function."""
    with torch.inference_mode():
        mean, log_std, _, _ = actor(torch.as_tensor(obs, device=actor.log_std.device))
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


def autograd_gradients(actor: CascadeActor, critic: TanhMLP, params: list[nn.Parameter], minibatch: tuple,
                       args: Args) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The loss of one minibatch and its gradient by autograd, written into every parameter's .grad.
    Keep it (and `ppo_loss`, `optimizer_step`) free of side effects: on the fast path it runs only inside the
    run-time checks, on float64 copies (see docs/hacking.md)."""
    obs, actions, old_logprob, advantages, returns, old_value = minibatch
    with torch.enable_grad():
        mean, log_std, _, _ = actor(obs)
        loss, parts = ppo_loss(mean, log_std, critic(obs).squeeze(1), actions, old_logprob, advantages, returns,
                               old_value, args)
        grads = torch.autograd.grad(loss, params, allow_unused=True)  # unused: the empty fallback head at n = 1
    for param, grad in zip(params, grads):
        param.grad.copy_(grad) if grad is not None else param.grad.zero_()
    return loss.detach(), {key: value.detach() for key, value in parts.items()}


def make_optimizer(actor: CascadeActor, critic: TanhMLP, flat_params: nn.Parameter,
                   learning_rate: float) -> torch.optim.Adam:
    """PPO's Adam (eps 1e-5, CleanRL) over `flat_params`, the one buffer that every parameter of the actor and
    critic (and their .grad) is a view of (`share_one_buffer`): the fused kernel updates them all at once, ~3x
    faster on CPU. Any other optimizer works too, also one over parameter groups with their own learning rates
    (e.g. `[{"params": actor.parameters()}, {"params": critic.parameters(), "lr": 1e-3}]`: each group's LR
    follows the schedule from its own initial value). The fast path calls the fused Adam kernel directly only
    for this exact Adam over `[flat_params]`, checked against `optimizer_step` below; otherwise it steps aside."""
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
def train(args: Args, checkpoint: dict | None = None,
          on_iteration_start: Callable[[dict], None] | None = None) -> dict:
    """Runs Cascade (from scratch, or continuing `checkpoint`); returns the final actor, critic, run folder.
    `on_iteration_start` sees the fresh state of each iteration (used by the tests)."""
    validate(args)
    set_threads(args.torch_threads)
    seed_everything(args.seed, args.torch_deterministic)
    device = run_device(args.cuda)
    envs = make_vector_env(args)
    obs_dim = int(np.prod(envs.single_observation_space.shape))
    act_dim = int(np.prod(envs.single_action_space.shape))
    batch_size = args.num_envs * args.num_steps
    minibatch_size = batch_size // args.num_minibatches
    updates_per_iteration = args.k // batch_size
    total_updates = args.n * updates_per_iteration
    run = RunLog(args, checkpoint, obs_dim, act_dim, envs, total_updates * batch_size)
    fast = make_fast_paths(args, device, run)  # section 2, checked against this section while the run trains

    actor = CascadeActor(obs_dim, act_dim, args.hidden_size, args.num_layers, args.fallback_init).to(device)
    if args.start_full:
        for _ in range(args.n):
            actor.add_base_net()
    # rollout storage, numpy: the env takes and gives numpy (and the fast acting path runs in numpy)
    obs = np.zeros((args.num_steps, args.num_envs, obs_dim), dtype=np.float32)
    actions = np.zeros((args.num_steps, args.num_envs, act_dim), dtype=np.float32)
    rewards = np.zeros((args.num_steps, args.num_envs), dtype=np.float32)
    dones = np.zeros((args.num_steps, args.num_envs), dtype=np.float32)

    if checkpoint is None:
        global_step, start_iteration, start_update = 0, 1, 1
        next_obs = envs.reset(seed=args.seed)[0].astype(np.float32)
        next_done = np.zeros(args.num_envs, dtype=np.float32)
        run.evaluate(0, actor)
    else:  # the saved nets, env states, RNG streams and position in the run
        actor, global_step, next_obs, next_done, start_iteration, start_update = run.restore(
            checkpoint, updates_per_iteration, device)

    critic = None  # each iteration makes its own (a resumed run that had finished has none left to make)
    if checkpoint is not None and args.start_full:
        critic = run.saved_critic(checkpoint, device)  # --start-full keeps one critic for the whole run
    for iteration in range(start_iteration, args.n + 1):
        continuing = checkpoint is not None and iteration == start_iteration and start_update > 1
        if continuing:
            critic, flat_params, optimizer = run.restore_mid_iteration(checkpoint, actor, device)
        else:
            # --- a new Cascade iteration: new base net, fresh critic, fresh Adam, fresh LR cycle ---
            if not args.start_full:
                actor.add_base_net()
            if args.freeze_previous:
                actor.freeze_below(actor.size - 1)
            if critic is None or not args.start_full:  # --start-full: the paper's code keeps its one critic
                critic = make_critic(obs_dim).to(device)
            flat_params = share_one_buffer([*actor.parameters(), *critic.parameters()])
            optimizer = make_optimizer(actor, critic, flat_params, args.learning_rate)
        run.iteration_start(iteration, actor.size, count_parameters(actor, critic), "actor + critic", global_step,
                            continuing)
        if on_iteration_start is not None:
            on_iteration_start(
                {"iteration": iteration, "actor": actor, "critic": critic, "optimizer": optimizer, "envs": envs}
            )

        for update in range(start_update if iteration == start_iteration else 1, updates_per_iteration + 1):
            if args.lr_schedule == "cyclic":
                frac = 1.0 - (update - 1.0) / updates_per_iteration
            elif args.lr_schedule == "global":
                frac = 1.0 - ((iteration - 1) * updates_per_iteration + update - 1.0) / total_updates
            else:
                frac = 1.0
            for group in optimizer.param_groups:  # one group here (the flat buffer); an edit may make more, each
                group["lr"] = frac * group.setdefault("initial_lr", group["lr"])  # with its own initial LR

            # --- rollout: the weights do not change during it; values, log-probs and fallback
            # statistics are computed for the whole batch afterwards ---
            # `act`, or its numpy twin once the two draw the same actions on these observations (the next one and
            # 8 of the previous rollout's; zeros before the first rollout); every action is checked after the rollout
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
            b_mean, b_log_std, batch_fallback, batch_contribution = actor(b_obs)
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

            # --- PPO update of the whole stack and the critic ---
            # what a minibatch holds (the order `autograd_gradients` unpacks)
            batch = (b_obs, b_actions, b_logprobs, b_advantages, b_returns, b_values)
            all_params = [*actor.parameters(), *critic.parameters()]
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

            run.update_done(global_step, optimizer, parts, old_approx_kl, approx_kl, torch.cat(ratios),
                            b_values, b_returns, batch_fallback, batch_contribution, actor.size, fast)
            # --- non-finite guard: stop before anything bad is written to the checkpoint ---
            run.stop_if_non_finite(loss, {"actor": actor, "critic": critic},
                                   f"global_step={global_step} (iteration {iteration}, update {update})")
            if update == updates_per_iteration and args.eval_members:  # each base net alone, at the iteration's end
                run.evaluate(global_step, actor, members=True)
            run.maybe_checkpoint(iteration, update, updates_per_iteration, global_step, actor, critic, optimizer,
                                 next_obs, next_done)
        run.iteration_done(iteration, global_step)

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
    def __call__(
        self,
        policy: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor]],
        stats: tuple[np.ndarray, np.ndarray] | None,
        call: int = 0,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Runs `policy` (obs -> mean, log-std, fallbacks [m, B]); returns each episode's undiscounted
        raw return and the std of each fallback within each episode [episodes, m]. The episodes'
        seeds and the action noise depend only on (seed, call): evaluation never touches training's RNG."""
        base_seed = self.base_seed(call)
        fallbacks: list[list[np.ndarray]] = [[] for _ in self.envs]

        def act_frozen(raw_obs: np.ndarray, running: list[int]) -> np.ndarray:
            mean, log_std, fallback = policy(torch.as_tensor(normalize_obs(raw_obs, stats)))
            for row, i in enumerate(running):
                fallbacks[i].append(fallback[:, row].numpy())
            action = action_distribution(mean, log_std).mean if deterministic else sample_action(mean, log_std)
            return action.numpy()

        with torch.random.fork_rng(devices=[]):  # the action noise: sample_action on a stream of its own
            torch.default_generator.manual_seed(base_seed)  # the CPU's only: a GPU run's stream is untouched
            returns = self.run_episodes(act_frozen, base_seed)
        return returns, np.stack([np.stack(f).std(0) for f in fallbacks])


def full_policy(actor: CascadeActor) -> Callable:
    return lambda x: actor(x)[:3]


def member_policy(actor: CascadeActor, net: int) -> Callable:
    """Base net `net` (0-based) acting alone with its own mean and log-std; it has no fallbacks."""
    return lambda x: (*actor.member(x, net), x.new_zeros(0, x.shape[0]))


def policy_of(actor: CascadeActor, kind: int) -> Callable:
    """kind 0: the whole cascade; kind i >= 1: base net i alone."""
    return full_policy(actor) if kind == 0 else member_policy(actor, kind - 1)


# ==============================================================================================
# 2. FAST PATHS: the same acting and update, faster (cascade_plumbing/fast.py), checked against section 1
# ==============================================================================================
# Acting runs a numpy copy of the forward and samples the Gaussian in numpy; the update writes its
# gradients by hand. Neither is a definition: at every rollout start `act` above (the forward and
# `sample_action`) and the numpy path draw actions from the same seeded RNG, and on the last minibatch of
# every update (every minibatch of an iteration's first) `autograd_gradients` above (loss, parts, gradients)
# and `optimizer_step` are compared with the hand-written update, in float64. An edit of section 1 that the
# fast paths do not reproduce, or that makes them raise, switches them off with one warning line, and the run
# continues exactly as --autograd runs it. On the CPU only: on a GPU, act() draws from the CUDA generator.
def make_fast_paths(args: Args, device: torch.device, run: RunLog | None = None) -> FastPaths:
    return FastPaths(not args.autograd and device.type == "cpu", numpy_cascade_policy, cascade_ppo_gradients,
                     None if run is None else run.fast_path_off, definition=(autograd_gradients, optimizer_step))


# ==============================================================================================
# 3. PLUMBING: environments, evaluation, checkpoints, progress, command line
# ==============================================================================================
# ----------------------------------------------------------------------------------------------
# Evaluating a frozen copy (in the evaluation worker, or inline)
# ----------------------------------------------------------------------------------------------
def frozen_actor(obs_dim: int, act_dim: int, args: Args, size: int, state: dict) -> CascadeActor:
    """A `size`-net CascadeActor holding `state`; building it draws no number from the caller's torch RNG
    (training's, when evaluations run inline)."""
    with torch.random.fork_rng(devices=[]):
        actor = CascadeActor(obs_dim, act_dim, args.hidden_size, args.num_layers, args.fallback_init)
        for _ in range(size):
            actor.add_base_net()
    actor.load_state_dict(state)
    return actor


def evaluate_request(args_dict: dict, obs_dim: int, act_dim: int, evaluator: Evaluator, call: int,
                     request: tuple) -> tuple:
    """One evaluation (in the worker process, or inline): rebuild the frozen policy and run the episodes."""
    kind, size, state, stats = request
    actor = frozen_actor(obs_dim, act_dim, Args(**args_dict), size, state)
    return (kind, *evaluator(policy_of(actor, kind), stats, call))


# ----------------------------------------------------------------------------------------------
# The run's bookkeeping: TensorBoard, evaluations, checkpoints and resume, progress
# ----------------------------------------------------------------------------------------------
class RunLog(RunRecord):
    """What `train` records about a Cascade run and restores when it is resumed (the generic part: RunRecord)."""

    def __init__(self, args: Args, checkpoint: dict | None, obs_dim: int, act_dim: int,
                 envs: gym.vector.VectorEnv, total_steps: int):
        batch_size = args.num_envs * args.num_steps
        if args.k % batch_size and checkpoint is None:
            print(f"note: k={args.k} is not a multiple of the batch size {batch_size}; each iteration runs "
                  f"{args.k // batch_size} updates = {args.k // batch_size * batch_size} steps")
        super().__init__(args, checkpoint, envs, total_steps,
                         at_iteration_end=checkpoint is not None and checkpoint["updates_done"] == args.k // batch_size)
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.runner = None
        if args.eval_every:
            self.runner = EvaluationRunner(partial(Evaluator, args.env_id, args.eval_episodes, args.seed),
                                           partial(evaluate_request, asdict(args), obs_dim, act_dim),
                                           args.eval_in_worker, calls=0 if checkpoint is None else checkpoint["eval_calls"])

    # --- resume ---
    def restore(self, checkpoint: dict, updates_per_iteration: int, device: torch.device) -> tuple:
        """The saved nets, env states and RNG streams; returns (actor, global_step, next_obs, next_done,
        iteration, update) of where the run continues."""
        actor = actor_from_checkpoint(checkpoint, device)
        global_step, next_obs = self.restore_envs(checkpoint)
        iteration, update = checkpoint["iteration"], checkpoint["updates_done"] + 1
        if update > updates_per_iteration:  # saved at the end of an iteration
            iteration, update = iteration + 1, 1
        return actor, global_step, next_obs, checkpoint["next_done"], iteration, update

    def saved_critic(self, checkpoint: dict, device: torch.device) -> nn.Module:
        """The critic the checkpoint holds."""
        rng = torch.get_rng_state()  # the critic's init draws must not shift the restored RNG stream
        critic = make_critic(self.obs_dim).to(device)
        torch.set_rng_state(rng)
        critic.load_state_dict(checkpoint["critic"])
        return critic

    def restore_mid_iteration(self, checkpoint: dict, actor: CascadeActor, device: torch.device) -> tuple:
        """The saved critic and optimizer of an iteration the checkpoint was written in the middle of."""
        critic = self.saved_critic(checkpoint, device)
        flat_params = share_one_buffer([*actor.parameters(), *critic.parameters()])
        optimizer = make_optimizer(actor, critic, flat_params, self.args.learning_rate)
        checkpoints.load_optimizer(optimizer, checkpoint["optimizer"])
        return critic, flat_params, optimizer

    # --- logging ---
    def update_done(self, global_step: int, optimizer: torch.optim.Optimizer, parts: dict,
                    old_approx_kl: torch.Tensor, approx_kl: torch.Tensor, ratios: torch.Tensor,
                    b_values: torch.Tensor, b_returns: torch.Tensor, batch_fallback: torch.Tensor,
                    batch_contribution: torch.Tensor, size: int, fast: FastPaths) -> None:
        """CleanRL's scalars and the fallback metrics (paper Section 4.2, Table 1) after one update."""
        log_ppo_update(self.writer, global_step, optimizer, parts, old_approx_kl, approx_kl, ratios, b_values,
                       b_returns, self.args.clip_coef, fast)
        self.log_fallbacks(batch_fallback, batch_contribution, global_step)  # over the rollout the policy acted in
        self.writer.add_scalar("cascade/size", size, global_step)
        self.tick(global_step, size)

    def iteration_done(self, iteration: int, global_step: int) -> None:
        self.progress.message(f"iteration {iteration} done: global_step={global_step}, SPS={int(self.sps(global_step))}")

    # --- evaluation (paper Appendix B.5) ---
    def evaluate(self, step: int, actor: CascadeActor, members: bool = False) -> None:
        """Freeze the current policy and observation statistics and evaluate them (or each net alone)."""
        if self.runner is None:
            return
        stats = obs_statistics(self.envs)
        state = {k: v.detach().cpu().clone() for k, v in actor.state_dict().items()}
        for kind in range(1, actor.size + 1) if members else [0]:
            self.runner.submit(step, (kind, actor.size, state, stats))
        self.log_evaluations()

    def log_evaluations(self, wait: bool = False) -> None:
        if self.runner is None:
            return
        for step, (kind, returns, fallback_std) in self.runner.results(wait):
            if kind == 0:
                self.writer.add_scalar("eval/episodic_return", returns.mean(), step)
                self.writer.add_scalar("eval/episodic_return_std", returns.std(), step)
                for j, std in enumerate(fallback_std.mean(0)):
                    self.writer.add_scalar(f"cascade/fallback_std/net_{j + 2}", std, step)
                self.progress.last_eval = float(returns.mean())
                self.progress.message(f"global_step={step}, eval/episodic_return={returns.mean():.1f} "
                                      f"± {returns.std():.1f}")
            else:
                self.writer.add_scalar(f"members/return/net_{kind}", returns.mean(), step)
                self.progress.message(f"global_step={step}, members/return/net_{kind}={returns.mean():.1f}")

    # --- checkpoints ---
    def maybe_checkpoint(self, iteration: int, update: int, updates_per_iteration: int, global_step: int,
                         actor: CascadeActor, critic: nn.Module, optimizer: torch.optim.Optimizer,
                         next_obs: np.ndarray, next_done: np.ndarray) -> None:
        """At the end of an iteration and every --checkpoint-every steps, once every evaluation asked for so far
        (the members' at an iteration's end among them) is logged."""
        end_of_iteration = update == updates_per_iteration
        due = self.checkpoint_due(global_step)
        if end_of_iteration and iteration == self.args.n:  # the final checkpoint: the final evaluation before it,
            self.final_evaluation(global_step, actor)  # so that a stop right after it loses nothing
        self.log_evaluations(wait=end_of_iteration or due)  # finished evaluations; before a checkpoint, all
        if not (end_of_iteration or due):
            return
        payload = {
            "format": CHECKPOINT_FORMAT, "args": asdict(self.args), "obs_dim": self.obs_dim, "act_dim": self.act_dim,
            "iteration": iteration, "updates_done": update,
            "actor": actor.state_dict(), "actor_size": actor.size, "num_frozen": actor.num_frozen,
            "critic": critic.state_dict(), "optimizer": optimizer.state_dict(), "obs_stats": obs_statistics(self.envs),
            "next_obs": next_obs.copy(), "next_done": next_done.copy(),
            "eval_calls": 0 if self.runner is None else self.runner.calls,
        }
        self.save(payload, global_step, iteration if end_of_iteration else None)

    def final_evaluation(self, global_step: int, actor: CascadeActor) -> None:
        """The final policy, if the last step was not an eval step; logged before the final checkpoint."""
        if self.runner is not None and global_step % self.args.eval_every >= self.args.num_envs:
            self.evaluate(global_step, actor)

    def close(self, global_step: int) -> None:
        if self.runner is not None:
            self.log_evaluations(wait=True)
            self.runner.close()
        super().close(global_step)


# ----------------------------------------------------------------------------------------------
# Checkpoints: one file with everything needed to continue and to act
# ----------------------------------------------------------------------------------------------
CHECKPOINT_FORMAT = "cascade_ppo_continuous/2"


def load_checkpoint(path: str, reader_flag: str = "") -> dict:
    """A run folder's latest checkpoint, or a checkpoint file, of this script (one-line error otherwise; a caller
    that only reads it names in `reader_flag` the flag that takes another file, for the advice)."""
    return checkpoints.load_checkpoint(path, CHECKPOINT_FORMAT, reader_flag=reader_flag)


def finished(args: Args, checkpoint: dict) -> bool:
    """Whether the checkpoint is the end of the run (resuming it would only evaluate its last step again)."""
    return checkpoint["iteration"] == args.n and checkpoint["updates_done"] == args.k // (args.num_envs * args.num_steps)


def actor_from_checkpoint(checkpoint: dict, device: str | torch.device = "cpu") -> CascadeActor:
    actor = frozen_actor(checkpoint["obs_dim"], checkpoint["act_dim"], Args(**checkpoint["args"]),
                         checkpoint["actor_size"], checkpoint["actor"])
    actor.num_frozen = checkpoint["num_frozen"]  # as saved: through an edited freeze_below it would change twice
    return actor.to(device)


# ----------------------------------------------------------------------------------------------
# Input checks, seeding
# ----------------------------------------------------------------------------------------------
def validate(args: Args) -> None:
    """Reject bad input with one clear line before anything is created."""
    check_common_settings(args)
    if args.n < 1:
        fail(f"--n must be at least 1 (got {args.n})")
    if not 0.0 < args.fallback_init < 1.0:
        fail(f"--fallback-init must lie strictly between 0 and 1 (got {args.fallback_init})")
    if args.hidden_size < 1 or args.num_layers < 1:
        fail("--hidden-size and --num-layers must be at least 1")
    batch_size = check_ppo_settings(args)
    if args.k < batch_size:
        fail(f"--k {args.k} is smaller than one rollout batch (num_envs*num_steps = {batch_size}); raise --k")
    if args.freeze_previous and args.start_full:
        fail("--freeze-previous and --start-full cannot be combined (no such ablation in the paper)")
    check_box_env(args.env_id, discrete_script="cascade_ppo_discrete.py")


# ----------------------------------------------------------------------------------------------
# Command line: train, resume, or evaluate a saved model
# ----------------------------------------------------------------------------------------------
def evaluate_saved(args: Args) -> dict:
    """--evaluate: the saved policy with its saved observation statistics frozen."""
    checkpoint = open_saved_model(args, load_checkpoint)
    saved = Args(**checkpoint["args"])
    actor = actor_from_checkpoint(checkpoint)
    stats = checkpoint["obs_stats"]
    with mean_action_defined(args.deterministic):  # --deterministic: a distribution without a mean, one line
        evaluator = Evaluator(saved.env_id, args.eval_episodes, args.seed)
        returns, _ = evaluator(full_policy(actor), stats, 0, args.deterministic)
        mode = "deterministic" if args.deterministic else "stochastic"
        print(f"{saved.env_id}, {actor.size} base net(s), step {checkpoint['global_step']}: "
              f"return {returns.mean():.1f} ± {returns.std():.1f} over {len(returns)} {mode} episodes")
        result = {"returns": returns, "members": []}
        if args.members:
            for net in range(actor.size):
                member_returns, _ = evaluator(member_policy(actor, net), stats, 0, args.deterministic)
                result["members"].append(member_returns)
                print(f"  net {net + 1} alone: {member_returns.mean():.1f} ± {member_returns.std():.1f}")
        evaluator.close()
        if args.capture_video:  # (needs an OpenGL backend for MuJoCo)
            save_video_of_one_episode(checkpoint["path"], mode, Evaluator(saved.env_id, 1, args.seed, render=True),
                                      lambda video: video(full_policy(actor), stats, 0, args.deterministic)[0][0])
    return result


def main() -> None:
    run_main(Args, train, evaluate_saved, load_checkpoint, finished, description=__doc__.split("\n\n")[0])


if __name__ == "__main__":
    main()
