"""Cascade trained with SAC on continuous-action tasks (single-file, CleanRL style; paper Appendix H.1).
`--n 1 --hidden-size 256 --k 2000000` is exactly the paper's SAC baseline (its code: CleanRL
sac_continuous_action with orthogonal init and alpha fixed at 0.2).

The actor is a Cascade of base nets `obs -> 128 -> 128 -> (mean, log-std)` (ReLU). Every `k` env steps a
new base net b_i is stacked on the ensemble C_{i-1}; besides its mean and state-dependent log-std it emits
a fallback weight lambda_i(x) in [0, 1] and the ensemble becomes (Section 3, Eq. 1; Appendix B.2)

    C_i(x) = lambda_i(x) * C_{i-1}(x) + (1 - lambda_i(x)) * b_i(x)     (mean and raw log-std, before the log-std bound and the tanh squash)

The whole stack is trained end to end by SAC. When a net is added, as in the paper's code (a new SAC
instance per net): the replay buffer is emptied, `--learning-starts` uniform-random steps without updates
follow, the twin critics are kept but their targets are re-copied from them and their optimizer is
recreated, and the actor optimizer is recreated over all actor nets (`--no-restart-on-new-net`: the
paper's text read literally, targets and critic optimizer kept, the current policy collects the warm-up).
`--keep-buffer` and `--reset-critic` are the ablations. Alpha is fixed at 0.2 (the paper's code;
`--autotune` is CleanRL's default). No observation/reward normalization; raw observations and rewards are
clipped to +-10 (the paper's code, `--obs-reward-clip 0` turns that off).
Paper: Schmöcker & Dockhorn, "Cascade - A sequential ensemble method for continuous control tasks",
RLJ 2025, Appendix H.1 (SAC), with the evaluation protocol of Appendix B.5.

    python cascade_sac.py --env-id Hopper-v4                                              # Cascade: 4 nets, a new one every 500k steps
    python cascade_sac.py --env-id Hopper-v4 --n 1 --hidden-size 256 --k 2000000 --exp-name sac_baseline
    tensorboard --logdir runs
"""

from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from cascade_plumbing.checkpoints import load_checkpoint as load_script_checkpoint
from cascade_plumbing.checkpoints import load_optimizer
from cascade_plumbing.envs import make_env, make_vector_env
from cascade_plumbing.errors import fail
from cascade_plumbing.fast_offpolicy import OffPolicyFastPath, SACFast
from cascade_plumbing.offpolicy import OffPolicyRun, Policy, check_replay_settings, evaluate_saved_policy, minimize
from cascade_plumbing.replay import ReplayBuffer, buffer_capacity
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


@dataclass
class Args:
    exp_name: str = field(default_factory=lambda: script_name(__file__))
    """the name of this experiment (part of the run name; default: this script's file name); give the baseline its own, e.g. `sac_baseline`"""
    seed: int = 1
    """seed of the experiment (python, numpy, torch and the environments)"""
    torch_deterministic: bool = True
    """CleanRL's flag: `torch.backends.cudnn.deterministic` (GPU runs only; a CPU run repeats exactly on the same machine either way)"""
    torch_threads: int = 1
    """torch CPU threads (numpy's BLAS: one); 1: a second made the SAC baseline slower, not faster (docs/performance.md, "SAC and DDPG"): run one run per core"""
    autograd: bool = False
    """act with `explore` and update with `sac_update` (autograd) only, no fast paths (slower; the same results up to float rounding)"""
    cuda: bool = False
    """train on the GPU if torch sees one (~1.4x the steps/s of one CPU core on an H200 machine, docs/performance.md, "SAC and DDPG on a GPU"); --evaluate runs on the CPU"""
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
    """mp4s of training episodes 0, 1, 8, 27, ..., 1000, 2000, ... of the first env in videos/<run_name>/ (to W&B with --track); with --evaluate: one episode next to the checkpoint. MuJoCo needs MUJOCO_GL=egl or osmesa"""

    # Environment
    env_id: str = "Hopper-v4"
    """the id of a gymnasium environment with a bounded Box action space (MuJoCo v4 or v5 ids)"""

    # Cascade
    n: int = 4
    """number of base nets, i.e. iterations of Cascade (the run lasts n*k steps); `--n 1 --hidden-size 256 --k 2000000` is exactly the SAC baseline"""
    k: int = 500_000
    """environment steps per iteration; a new base net is added every k steps (paper: 500k of 2M)"""
    hidden_size: int = 128
    """width of each hidden layer of a base net (paper: 128 for Cascade, 256 for the SAC baseline)"""
    num_layers: int = 2
    """number of hidden layers of a base net"""
    fallback_init: float = 0.5
    """initial fallback weight lambda of each new base net, in (0, 1)"""
    keep_buffer: bool = False
    """ablation: keep the replay buffer when a base net is added (standard Cascade empties it)"""
    reset_critic: bool = False
    """ablation: fresh critics, targets and critic optimizer when a base net is added (standard: the critics are kept; their targets are re-copied and their optimizer recreated, see --restart-on-new-net)"""
    restart_on_new_net: bool = True
    """when a net is added, restart as the paper's code does: --learning-starts uniform-random steps without updates, target critics re-copied, critic optimizer recreated; `--no-restart-on-new-net`: target critics and critic optimizer kept, the current policy collects the warm-up (the paper's text); the actor optimizer is new either way"""

    # SAC (CleanRL sac_continuous_action's defaults, except where the paper's code differs: docs/sac_ddpg.md)
    buffer_size: int = 1_000_000
    """the replay memory capacity (float32 numpy, preallocated; the memory it takes: docs/sac_ddpg.md, "Replay-buffer memory")"""
    gamma: float = 0.99
    """the discount factor gamma"""
    tau: float = 0.005
    """target smoothing coefficient"""
    batch_size: int = 256
    """the batch size sampled from the replay memory"""
    learning_starts: int = 5_000
    """uniform-random steps without updates at the start of each net (with `--no-restart-on-new-net`: transitions in the buffer before updates start)"""
    policy_lr: float = 3e-4
    """the learning rate of the actor optimizer"""
    q_lr: float = 1e-3
    """the learning rate of the critic optimizer (and of the entropy temperature)"""
    policy_frequency: int = 2
    """delayed actor updates: every this many steps, this many actor (and alpha) updates"""
    target_network_frequency: int = 1
    """update the target critics every this many steps"""
    alpha: float = 0.2
    """entropy regularization coefficient, fixed (the paper's code; the start value is 1.0 with --autotune)"""
    autotune: bool = False
    """automatic tuning of alpha towards the target entropy -action_dims (CleanRL's default and the paper's text; the paper's code keeps alpha fixed)"""
    obs_reward_clip: float = 10.0
    """clip raw observations and rewards to +-this, as the paper's code does in its unnormalized runs (0: no clipping, CleanRL)"""

    # Evaluation (the paper's protocol, Appendix B.5)
    eval_every: int = 10_000
    """evaluate the frozen current policy every this many env steps (0 turns evaluation off)"""
    eval_episodes: int = 10
    """episodes per evaluation (on separate envs)"""
    eval_deterministic: bool = False
    """evaluate with the squashed mean action instead of sampling (default: stochastic policy, as the paper evaluates, Appendix B.5)"""
    eval_members: bool = True
    """at the end of each iteration, also evaluate each base net acting alone (`members/return/net_i`; not with --eval-every 0)"""

    # Checkpoints, resuming, evaluating a saved model
    checkpoint_every: int = 50_000
    """also checkpoint every this many env steps, besides the end of every iteration and the step after a stop (Ctrl-C, SIGTERM) (0: only those); a checkpoint holds the replay buffer (the rows added since the previous one go to the run folder's replay/)"""
    resume: str | None = None
    """continue a killed run exactly: `runs/<run_name>` (its latest checkpoint) or a checkpoint file (checkpoint.pt, iteration_<i>.pt), replay buffer included; the saved settings are used"""
    evaluate: str | None = None
    """evaluate a saved model (`runs/<run_name>` or a checkpoint file) for --eval-episodes episodes and exit"""
    members: bool = False
    """with --evaluate: also report the return of each base net acting alone"""
    quiet: bool = False
    """no progress line and no messages while training (warnings and errors still go to stderr); sweep.py passes it"""


# ----------------------------------------------------------------------------------------------
# The Cascade net (Section 3, Appendix B.2): the base nets stacked [n, in, out], combined by their fallbacks
# ----------------------------------------------------------------------------------------------
LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0
LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


def orthogonal_linear(in_features: int, out_features: int, gain: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Weight [in, out] (orthogonal init with `gain`) and zero bias [1, out] of one linear layer."""
    weight = torch.empty(out_features, in_features)
    nn.init.orthogonal_(weight, gain)
    return weight.T.contiguous(), torch.zeros(1, out_features)


def default_linear(in_features: int, out_features: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Weight [in, out] and bias [1, out] as torch's nn.Linear initializes them: uniform in +-1/sqrt(in)."""
    layer = nn.Linear(in_features, out_features)
    return layer.weight.detach().T.contiguous(), layer.bias.detach().reshape(1, out_features)


def contributions(fallback: torch.Tensor) -> torch.Tensor:
    """Share w_i of each base net in the ensemble output, from the fallbacks of nets 2..n.

    Unrolling C_i = l_i*C_{i-1} + (1-l_i)*b_i gives C_n = sum_i w_i*b_i with
    w_i = (1 - l_i) * prod_{j>i} l_j and l_1 := 0; w_1 = prod_{j>=2} l_j is the fallback product.
    fallback: [n-1, B, 1] -> contributions [n, B, 1], summing to 1 over nets.
    """
    ones = fallback.new_ones((1, *fallback.shape[1:]))
    if len(fallback) == 0:
        return ones
    later = torch.cat([fallback, ones]).flip(0).cumprod(0).flip(0)  # prod_{j>i} l_j
    return torch.cat([ones, torch.rsub(fallback, 1.0)]) * later


def bounded_log_std(raw: torch.Tensor) -> torch.Tensor:
    """CleanRL's log-std bounds: tanh rescaled to [LOG_STD_MIN, LOG_STD_MAX] (from SpinUp / Denis Yarats)."""
    return LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (torch.tanh(raw) + 1)


def squashed_sample(mean: torch.Tensor, log_std: torch.Tensor, scale: torch.Tensor, bias: torch.Tensor,
                    generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """CleanRL's `get_action`: a reparameterized sample of N(mean, exp(log_std)) squashed by tanh and rescaled
    to the action bounds, its log-prob [B, 1] (with the tanh correction) and the squashed mean action."""
    noise = torch.randn(mean.shape, generator=generator, device=mean.device)
    y = torch.tanh(mean + torch.exp(log_std) * noise)
    # log N(mean + std*noise; mean, std) = -noise^2/2 - log std - log sqrt(2 pi)
    log_prob = -0.5 * noise.pow(2) - log_std - LOG_SQRT_2PI - torch.log(scale * (1 - y.pow(2)) + 1e-6)
    return y * scale + bias, log_prob.sum(1, keepdim=True), torch.tanh(mean) * scale + bias


class CascadeActor(nn.Module):
    """A stack of base nets `obs -> H -> ... -> H -> (mean, log-std) (+ fallback logit)`, ReLU, evaluated together.

    The base nets' weights are stacked along a leading net axis ([n, in, out]) so every layer of all nets is
    one batched matmul; the nets' means and raw log-stds are then combined with the closed form of
    `contributions`, and the combined log-std is bounded, before the tanh squash (the paper's code).
    Net 1 (the bottom) has no fallback head.
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden_size: int, num_layers: int, fallback_init: float,
                 action_low: np.ndarray, action_high: np.ndarray):
        super().__init__()
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.hidden_size, self.num_layers = hidden_size, num_layers
        self.fallback_init = fallback_init
        self.register_buffer("action_scale", torch.as_tensor((action_high - action_low) / 2.0, dtype=torch.float32))
        self.register_buffer("action_bias", torch.as_tensor((action_high + action_low) / 2.0, dtype=torch.float32))
        dims = [obs_dim] + [hidden_size] * num_layers
        self.hidden_weights = nn.ParameterList(
            [nn.Parameter(torch.empty(0, i, o)) for i, o in zip(dims[:-1], dims[1:])]
        )
        self.hidden_biases = nn.ParameterList([nn.Parameter(torch.empty(0, 1, o)) for o in dims[1:]])
        self.head_weight = nn.Parameter(torch.empty(0, hidden_size, 2 * act_dim))  # [mean | log-std]
        self.head_bias = nn.Parameter(torch.empty(0, 1, 2 * act_dim))
        self.fallback_weight = nn.Parameter(torch.empty(0, hidden_size, 1))
        self.fallback_bias = nn.Parameter(torch.empty(0, 1, 1))
        self._cache_parameters()

    def _cache_parameters(self) -> None:
        # Plain references for the hot path (nn.Module attribute lookups cost ~1 us each); rebuilt whenever
        # the Parameters are replaced.
        self._hidden = tuple(zip(self.hidden_weights, self.hidden_biases))
        self._heads = (self.head_weight, self.head_bias, self.fallback_weight, self.fallback_bias)

    @property
    def size(self) -> int:
        """number of base nets in the cascade"""
        return self.head_weight.shape[0]

    def base_net_parameters(self) -> list[tuple[str, nn.Parameter]]:
        params = [(f"hidden_weights.{i}", p) for i, p in enumerate(self.hidden_weights)]
        params += [(f"hidden_biases.{i}", p) for i, p in enumerate(self.hidden_biases)]
        params += [("head_weight", self.head_weight), ("head_bias", self.head_bias)]
        return params + [("fallback_weight", self.fallback_weight), ("fallback_bias", self.fallback_bias)]

    def add_base_net(self) -> None:
        """Stack a freshly initialized base net on top (new stacked Parameters: rebuild the optimizer).
        As the paper's code: orthogonal init, gain sqrt(2) for the hidden layers, 0.01 for the mean head and the
        fallback logit (one orthogonal [H, A+1] layer), zero biases; the log-std head keeps torch's nn.Linear
        default init (uniform in +-1/sqrt(H), weight and bias)."""
        dims = [self.obs_dim] + [self.hidden_size] * self.num_layers
        grown: dict[str, torch.Tensor] = {}
        for i, (d_in, d_out) in enumerate(zip(dims[:-1], dims[1:])):
            grown[f"hidden_weights.{i}"], grown[f"hidden_biases.{i}"] = orthogonal_linear(d_in, d_out, math.sqrt(2))
        is_bottom = self.size == 0
        a = self.act_dim
        weight, bias = orthogonal_linear(self.hidden_size, a + (0 if is_bottom else 1), 0.01)  # [mean | fallback]
        log_std_weight, log_std_bias = default_linear(self.hidden_size, a)
        grown["head_weight"] = torch.cat([weight[:, :a], log_std_weight], 1)
        grown["head_bias"] = torch.cat([bias[:, :a], log_std_bias], 1)
        if not is_bottom:
            grown["fallback_weight"] = weight[:, a:]
            # sigmoid(logit(l0)) = l0: the new net starts by deferring a share l0 to the nets below
            grown["fallback_bias"] = torch.full((1, 1), math.log(self.fallback_init / (1 - self.fallback_init)))
        for name, param in self.base_net_parameters():
            if name in grown:
                new = torch.cat([param.data, grown[name].unsqueeze(0).to(param.device)])
                self._replace(name, nn.Parameter(new))
        self._cache_parameters()

    def _apply(self, fn, recurse=True):  # .to(device) and friends may swap the Parameters
        module = super()._apply(fn, recurse)
        self._cache_parameters()
        return module

    def _replace(self, name: str, param: nn.Parameter) -> None:
        if "." in name:
            list_name, index = name.split(".")
            getattr(self, list_name)[int(index)] = param
        else:
            setattr(self, name, param)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """obs [B, obs_dim] -> mean [B, A], log-std [B, A] (pre-squash), fallback [n-1, B], contribution [n, B]."""
        head_weight, head_bias, fallback_weight, fallback_bias = self._heads
        hidden = obs.expand(len(head_weight), *obs.shape)  # every base net reads the same observation
        for weight, bias in self._hidden:
            hidden = torch.relu(torch.baddbmm(bias, hidden, weight))  # [n, B, H], all nets at once
        out = torch.baddbmm(head_bias, hidden, head_weight)  # [n, B, 2A]: each net's mean and raw log-std
        fallback = torch.sigmoid(torch.baddbmm(fallback_bias, hidden[1:], fallback_weight))  # [n-1, B, 1]
        contribution = contributions(fallback)  # w_i [n, B, 1]
        combined = (contribution * out).sum(0)  # C_n = sum_i w_i b_i, for mean and raw log-std at once
        # the paper's code bounds the combined raw log-std (SAC's get_action), not each net's
        return combined[:, : self.act_dim], bounded_log_std(combined[:, self.act_dim :]), fallback.squeeze(-1), \
            contribution.squeeze(-1)

    def get_action(self, obs: torch.Tensor, generator: torch.Generator | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(sampled action in the env's bounds, its log-prob [B, 1], squashed mean action) of the whole cascade: the
        policy that `explore`, `sac_update` and the evaluations act with."""
        mean, log_std, _, _ = self(obs)
        return squashed_sample(mean, log_std, self.action_scale, self.action_bias, generator)

    def member(self, obs: torch.Tensor, net: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std of base net `net` (0-based) acting alone."""
        hidden = obs
        for weight, bias in zip(self.hidden_weights, self.hidden_biases):
            hidden = torch.relu(torch.addmm(bias[net], hidden, weight[net]))
        out = torch.addmm(self.head_bias[net], hidden, self.head_weight[net])
        return out[:, : self.act_dim], bounded_log_std(out[:, self.act_dim :])


def count_parameters(*modules: nn.Module) -> int:
    return sum(p.numel() for m in modules for p in m.parameters())


# ----------------------------------------------------------------------------------------------
# The critics: twin Q-networks (CleanRL's, orthogonal init), kept when a net is added (Appendix H.1)
# ----------------------------------------------------------------------------------------------
class QNetworks(nn.Module):
    """`num_q` critics Q(s, a): `[obs, action] -> 256 -> 256 -> 1` (ReLU, CleanRL's SoftQNetwork with
    orthogonal init: gain sqrt(2) hidden, 1.0 output). Stacked [num_q, in, out] so the twins run in one pass."""

    def __init__(self, obs_dim: int, act_dim: int, num_q: int = 2, hidden_size: int = 256):
        super().__init__()
        dims = [obs_dim + act_dim, hidden_size, hidden_size, 1]
        weights, biases = [], []
        for layer, (d_in, d_out) in enumerate(zip(dims[:-1], dims[1:])):
            gain = 1.0 if layer == len(dims) - 2 else math.sqrt(2)
            pairs = [orthogonal_linear(d_in, d_out, gain) for _ in range(num_q)]
            weights.append(nn.Parameter(torch.stack([w for w, _ in pairs])))
            biases.append(nn.Parameter(torch.stack([b for _, b in pairs])))
        self.weights, self.biases = nn.ParameterList(weights), nn.ParameterList(biases)

    def forward(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """obs [B, obs_dim], actions [B, A] -> Q values [num_q, B]."""
        x = torch.cat([obs, actions], 1)
        x = x.expand(len(self.weights[0]), *x.shape)
        last = len(self.weights) - 1
        for i, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            x = torch.baddbmm(bias, x, weight)
            if i < last:
                x = torch.relu(x)
        return x.squeeze(-1)


@torch.no_grad()
def soft_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """target <- tau * source + (1 - tau) * target, for all parameters at once."""
    torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)


def explore(actor: CascadeActor, obs: torch.Tensor) -> torch.Tensor:
    """The action taken in the training env for obs [B, obs_dim]: a sample of the whole cascade's squashed Gaussian."""
    action, _, _ = actor.get_action(obs)
    return action


# ----------------------------------------------------------------------------------------------
# The SAC update (CleanRL's sac_continuous_action, the whole cascade as the actor)
# ----------------------------------------------------------------------------------------------
def make_adam(params: list[nn.Parameter], lr: float) -> torch.optim.Adam:
    """CleanRL's Adam (default eps); the fused kernel updates all parameters at once."""
    return torch.optim.Adam(params, lr=lr, fused=True)


def sac_update(args: Args, step_in_iteration: int, batch: tuple[torch.Tensor, ...], actor: CascadeActor,
               qf: QNetworks, qf_target: QNetworks, q_optimizer: torch.optim.Optimizer,
               actor_optimizer: torch.optim.Optimizer, alpha: float, log_alpha: torch.Tensor,
               a_optimizer: torch.optim.Optimizer) -> dict:
    """One SAC update on a replay batch (obs, actions, rewards, next_obs, dones): the twin critics towards the
    soft Bellman target, then every `policy_frequency` steps as many actor updates (each followed, with
    --autotune, by an update of the temperature towards the target entropy -act_dim), then every
    `target_network_frequency` steps the soft target update. Returns what it computed for the logs: the critics'
    values and losses, the actor's (and alpha's) loss when the actor was updated, and alpha after the update."""
    b_obs, b_actions, b_rewards, b_next_obs, b_dones = batch
    with torch.no_grad():
        next_actions, next_log_pi, _ = actor.get_action(b_next_obs)
        min_qf_next = qf_target(b_next_obs, next_actions).min(0).values - alpha * next_log_pi.view(-1)
        # b_dones are terminations only: truncated episodes bootstrap
        next_q_value = b_rewards + (1 - b_dones) * args.gamma * min_qf_next
    qf_a_values = qf(b_obs, b_actions)  # [2, B]
    qf1_loss = F.mse_loss(qf_a_values[0], next_q_value)
    qf2_loss = F.mse_loss(qf_a_values[1], next_q_value)
    qf_loss = qf1_loss + qf2_loss
    minimize(q_optimizer, qf_loss)  # zero_grad(); backward(); step(), bit for bit
    # (cascade_plumbing.offpolicy; it leaves no .grad: to clip or log gradients, write those three lines here)
    out = {"qf_a_values": qf_a_values, "qf1_loss": qf1_loss, "qf2_loss": qf2_loss, "qf_loss": qf_loss}

    # TD3-style delay, compensated by as many updates; counted from 0 with each net, as the paper's
    # code (a new instance per net) and CleanRL (a 0-based step) count it
    if step_in_iteration % args.policy_frequency == 0:
        for _ in range(args.policy_frequency):  # (minimize: the actor's gradients only, dQ/da, none of the critics')
            pi, log_pi, _ = actor.get_action(b_obs)
            min_qf_pi = qf(b_obs, pi).min(0).values
            out["actor_loss"] = actor_loss = (alpha * log_pi.view(-1) - min_qf_pi).mean()
            minimize(actor_optimizer, actor_loss)
            if args.autotune:
                with torch.no_grad():
                    _, log_pi, _ = actor.get_action(b_obs)
                target_entropy = -float(actor.act_dim)
                out["alpha_loss"] = alpha_loss = (-log_alpha.exp() * (log_pi + target_entropy)).mean()
                minimize(a_optimizer, alpha_loss)
                alpha = log_alpha.exp().item()

    if step_in_iteration % args.target_network_frequency == 0:
        soft_update(qf_target, qf, args.tau)
    out["alpha"] = alpha
    return out


# ----------------------------------------------------------------------------------------------
# Training: a new base net every k steps (Algorithm 1; Appendix H.1)
# ----------------------------------------------------------------------------------------------
def train(args: Args, checkpoint: dict | None = None,
          on_iteration_start: Callable[[dict], None] | None = None) -> dict:
    """Runs Cascade-SAC (from scratch, or continuing a `checkpoint` exactly); returns the final actor,
    critics, alpha, buffer and run folder. `on_iteration_start` sees the state of each iteration (used by the tests)."""
    validate(args, new_run=checkpoint is None)
    set_threads(args.torch_threads)
    seed_everything(args.seed, args.torch_deterministic)
    device = run_device(args.cuda)
    # CleanRL's SAC env (raw episode statistics, no normalization, no action wrapper: actions are squashed into the
    # bounds), plus the paper's code's clipping of raw observations and rewards to +-obs_reward_clip (0: none)
    envs = make_vector_env([make_env(args.env_id, video=args.capture_video, clip=args.obs_reward_clip)])
    run = OffPolicyRun(args, checkpoint, envs, CHECKPOINT_FORMAT, rates="--policy-lr / --q-lr")
    fast = make_fast_paths(args, device, run)  # the fast paths, checked against explore and sac_update as the run trains
    obs_dim, act_dim = run.obs_dim, run.act_dim

    actor = CascadeActor(obs_dim, act_dim, args.hidden_size, args.num_layers, args.fallback_init,
                         run.action_low, run.action_high).to(device)
    qf = QNetworks(obs_dim, act_dim).to(device)
    qf_target = copy.deepcopy(qf)
    q_optimizer = make_adam(list(qf.parameters()), args.q_lr)
    log_alpha = torch.zeros(1, requires_grad=True, device=device)
    a_optimizer = make_adam([log_alpha], args.q_lr)
    alpha = log_alpha.exp().item() if args.autotune else args.alpha
    buffer = ReplayBuffer(buffer_capacity(args.buffer_size, args.n, args.k, args.keep_buffer), obs_dim, act_dim)

    if checkpoint is None:
        global_step, start_iteration, start_step = run.start()
        if args.eval_every:
            evaluate(run, actor, args, global_step)  # step 0, before the first net: the empty cascade outputs zeros (raw)
    else:  # the saved nets, replay buffer, env state, RNG streams and position in the run
        global_step, start_iteration, start_step = run.restore(checkpoint, buffer)
        actor = actor_from_checkpoint(checkpoint, device)
        qf.load_state_dict(checkpoint["qf"])
        qf_target.load_state_dict(checkpoint["qf_target"])
        load_optimizer(q_optimizer, checkpoint["q_optimizer"])
        with torch.no_grad():
            log_alpha.copy_(checkpoint["log_alpha"])
        load_optimizer(a_optimizer, checkpoint["a_optimizer"])
        alpha = checkpoint["alpha"]

    for iteration in range(start_iteration, args.n + 1):
        mid_iteration = iteration == start_iteration and start_step > 0
        if not mid_iteration:  # (else: continuing the iteration a checkpoint was written in)
            # --- a new Cascade iteration: new base net, emptied buffer; the critics kept (fresh
            # with --reset-critic), their targets re-copied and their optimizer renewed (the restart) ---
            actor.add_base_net()
            if iteration > 1 and (args.reset_critic or args.restart_on_new_net):
                if args.reset_critic:  # the ablation: fresh critics
                    qf = QNetworks(obs_dim, act_dim).to(device)
                # targets copied anew from the (kept or fresh) critics, a new critic optimizer: the paper's code starts
                # a new SAC instance per net
                qf_target = copy.deepcopy(qf)
                q_optimizer = make_adam(list(qf.parameters()), args.q_lr)
            if not args.keep_buffer:
                buffer.clear()
        # a fresh actor optimizer each iteration (over all its nets); continuing one, the saved one
        actor_optimizer = make_adam(list(actor.parameters()), args.policy_lr)
        if mid_iteration:
            load_optimizer(actor_optimizer, checkpoint["actor_optimizer"])
        run.iteration_start(iteration, actor.size, count_parameters(actor, qf), "actor + critics", global_step,
                            continuing=mid_iteration)
        if on_iteration_start is not None:
            on_iteration_start({"iteration": iteration, "actor": actor, "qf": qf, "qf_target": qf_target,
                                "q_optimizer": q_optimizer, "actor_optimizer": actor_optimizer,
                                "log_alpha": log_alpha, "a_optimizer": a_optimizer, "buffer": buffer,
                                "envs": envs, "next_obs": run.next_obs, "global_step": global_step})

        # the latest update's values; the actor's loss from the iteration's first actor update on
        logged: dict = checkpoint["logged"] if mid_iteration else {}
        for step_in_iteration in range(start_step if mid_iteration else 0, args.k):
            global_step += 1
            # CleanRL: uniform actions for the first learning_starts steps, updates after learning_starts + 1.
            # The paper's code restarts that count with each net; without the restart, only the run's first
            # learning_starts steps are random and updates wait for learning_starts + 1 stored transitions.
            if args.restart_on_new_net:
                random_action = step_in_iteration < args.learning_starts
                learning = step_in_iteration > args.learning_starts
            else:
                random_action = iteration == 1 and len(buffer) < args.learning_starts
                learning = len(buffer) > args.learning_starts
            if random_action:
                actions = run.random_actions()
            else:  # explore(actor, obs), by the fast path when it is on: edit explore, not this line
                actions = fast.act(explore, actor, run.next_obs, step=global_step)
            run.step(actions, buffer, global_step)

            if learning:
                batch = buffer.sample(args.batch_size, device)
                # sac_update(...), by the fast path when it is on: edit sac_update, not this line
                logged.update(fast.update(sac_update, args, step_in_iteration, batch, actor, qf, qf_target,
                                          q_optimizer, actor_optimizer, alpha, log_alpha, a_optimizer, step=global_step))
                alpha = logged["alpha"]
                if global_step % 100 == 0 and "actor_loss" in logged:
                    write = run.writer.add_scalar
                    write("losses/qf1_values", logged["qf_a_values"][0].mean().item(), global_step)
                    write("losses/qf2_values", logged["qf_a_values"][1].mean().item(), global_step)
                    write("losses/qf1_loss", logged["qf1_loss"].item(), global_step)
                    write("losses/qf2_loss", logged["qf2_loss"].item(), global_step)
                    write("losses/qf_loss", logged["qf_loss"].item() / 2.0, global_step)
                    write("losses/actor_loss", logged["actor_loss"].item(), global_step)
                    write("losses/alpha", alpha, global_step)
                    if args.autotune:
                        write("losses/alpha_loss", logged["alpha_loss"].item(), global_step)
                    # fallback metrics: means over the sampled replay batch (states of this iteration's data)
                    with torch.no_grad():
                        _, _, batch_fallback, batch_contribution = actor(batch[0])
                    run.log_fallbacks(batch_fallback, batch_contribution, global_step)
                    run.guard_non_finite([actor, qf], global_step, iteration,
                                           [logged["qf_loss"].item(), logged["actor_loss"].item(), alpha])

            run.tick(global_step, actor.size)
            if args.eval_every and global_step % args.eval_every == 0:
                evaluate(run, actor, args, global_step)
            if run.checkpoint_due(global_step) and step_in_iteration + 1 < args.k:  # (the iteration's end: below)
                run.guard_non_finite([actor, qf], global_step, iteration)
                run.save_progress(iteration, step_in_iteration + 1, global_step, saved_nets(
                    actor, qf, qf_target, q_optimizer, actor_optimizer, log_alpha, a_optimizer, alpha, logged), buffer)

        # --- end of the iteration: member returns (and at the run's end the final policy's), then an atomic
        # checkpoint: a run stopped after it has nothing left to log ---
        if args.eval_every and args.eval_members:
            evaluate(run, actor, args, global_step, members=True)
        if iteration == args.n and args.eval_every and global_step % args.eval_every:
            evaluate(run, actor, args, global_step)  # the final policy, if the last step was not an eval step
        run.guard_non_finite([actor, qf], global_step, iteration)
        run.save_progress(iteration, args.k, global_step, saved_nets(
            actor, qf, qf_target, q_optimizer, actor_optimizer, log_alpha, a_optimizer, alpha, logged), buffer)

    run.close(global_step)
    return {"actor": actor, "qf": qf, "qf_target": qf_target, "buffer": buffer, "run_dir": run.run_dir,
            "global_step": global_step, "alpha": alpha, "fast_path": fast}


# ----------------------------------------------------------------------------------------------
# Evaluation (Appendix B.5): every --eval-every steps the frozen current policy, stochastic, on
# --eval-episodes episodes of separate envs with their own seeds and RNG; each net alone at the end of
# each iteration
# ----------------------------------------------------------------------------------------------
def evaluate(run: OffPolicyRun, actor: CascadeActor, args: Args, step: int, members: bool = False) -> None:
    """Freeze the current policy (or, with `members`, each net acting alone) and evaluate it."""
    frozen = actor if actor.action_scale.device.type == "cpu" else copy.deepcopy(actor).cpu()
    if members:
        run.evaluate_members(step, [member_policy(frozen, net, args.eval_deterministic) for net in range(frozen.size)])
    else:
        run.evaluate(step, full_policy(frozen, args.eval_deterministic))


def full_policy(actor: CascadeActor, deterministic: bool) -> Policy:
    """The whole cascade: a sample of its squashed Gaussian, or with `deterministic` the squashed mean."""

    def act(x: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        sample, _, mean_action = actor.get_action(x, generator)  # as in training: an edit of get_action counts here
        return (mean_action if deterministic else sample), actor(x)[2]  # and the fallbacks, for the log

    return act


def member_policy(actor: CascadeActor, net: int, deterministic: bool) -> Policy:
    """Base net `net` (0-based) acting alone with its own mean and log-std; it has no fallbacks."""

    def act(x: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = actor.member(x, net)
        sample, _, mean_action = squashed_sample(mean, log_std, actor.action_scale, actor.action_bias, generator)
        return (mean_action if deterministic else sample), x.new_zeros(0, x.shape[0])

    return act


# ----------------------------------------------------------------------------------------------
# Fast paths: the same update with hand-written gradients, and the same acting in numpy
# (cascade_plumbing/fast_offpolicy.py; docs/performance.md, "SAC and DDPG on a GPU"), checked against `sac_update` and `explore` while the
# run trains: at each new net, then about every 2000 steps, both run on float64 copies from the same random state. Edit
# `sac_update`, `explore` and the nets above, not the fast paths: an edit they do not reproduce switches them off
# with one warning line, and the run continues exactly as --autograd runs it. On the CPU only.
# ----------------------------------------------------------------------------------------------
def make_fast_paths(args: Args, device: torch.device, run: OffPolicyRun | None = None) -> OffPolicyFastPath:
    def complete(step_in_iteration: int) -> bool:  # sac_update runs every part: the checks pick such updates
        return step_in_iteration % args.policy_frequency == 0 and step_in_iteration % args.target_network_frequency == 0

    return OffPolicyFastPath(not args.autograd and device.type == "cpu", SACFast((LOG_STD_MIN, LOG_STD_MAX)),
                             None if run is None else run.fast_path_off, complete)


# ----------------------------------------------------------------------------------------------
# Wiring to cascade_plumbing: input checks, checkpoints, --evaluate, the command line
# ----------------------------------------------------------------------------------------------
def validate(args: Args, new_run: bool = True) -> None:
    """Reject bad input with one clear line before anything is created."""
    check_common_settings(args)
    if not args.policy_lr >= 0:
        fail(f"--policy-lr must be >= 0 (got {args.policy_lr})")
    if not args.q_lr >= 0:
        fail(f"--q-lr must be >= 0 (got {args.q_lr})")
    if args.n < 1:
        fail(f"--n must be at least 1 (got {args.n})")
    if not 0.0 < args.fallback_init < 1.0:
        fail(f"--fallback-init must lie strictly between 0 and 1 (got {args.fallback_init})")
    if args.hidden_size < 1 or args.num_layers < 1:
        fail("--hidden-size and --num-layers must be at least 1")
    if args.policy_frequency < 1 or args.target_network_frequency < 1:
        fail("--policy-frequency and --target-network-frequency must be at least 1")
    if new_run and args.autotune and asked_for(args, "alpha", Args.alpha):  # (a run started before this check resumes)
        fail(f"--alpha {args.alpha} has no effect with --autotune (alpha is learned, starting at 1.0); drop one of them")
    check_replay_settings(args, bounds_needed_because="SAC squashes actions into finite bounds",
                          frequencies={"--policy-frequency": "the actor's update",
                                       "--target-network-frequency": "the target critics' update"}, new_run=new_run)


# /2: the paper's-code defaults (alpha, log-std, new-net restart, clipping); /3: checkpoints inside an iteration,
# with the replay buffer
CHECKPOINT_FORMAT = "cascade_sac/3"


def saved_nets(actor: CascadeActor, qf: QNetworks, qf_target: QNetworks, q_optimizer: torch.optim.Optimizer,
               actor_optimizer: torch.optim.Optimizer, log_alpha: torch.Tensor, a_optimizer: torch.optim.Optimizer,
               alpha: float, logged: dict) -> dict:
    """What a checkpoint holds of the algorithm: every net, target and optimizer, the temperature and the latest
    update's values (logged every 100 steps); the run's state and the replay buffer are added to it."""
    return {"actor": actor.state_dict(), "actor_size": actor.size, "qf": qf.state_dict(),
            "qf_target": qf_target.state_dict(), "q_optimizer": q_optimizer.state_dict(),
            "actor_optimizer": actor_optimizer.state_dict(), "log_alpha": log_alpha.detach().cpu(),
            "a_optimizer": a_optimizer.state_dict(), "alpha": alpha, "logged": logged}


def load_checkpoint(path: str, reader_flag: str = "") -> dict:
    """A cascade_sac checkpoint (`runs/<run>`, its latest, or a file); one line if it is missing, corrupt, another
    script's, or of an older cascade_sac.py (which it cannot resume exactly)."""
    return load_script_checkpoint(path, CHECKPOINT_FORMAT,
                                  older_note=", before checkpoints held the replay buffer", reader_flag=reader_flag)


def actor_from_checkpoint(checkpoint: dict, device: str | torch.device = "cpu") -> CascadeActor:
    saved = Args(**checkpoint["args"])
    rng = torch.get_rng_state()  # building the nets draws random inits; keep the caller's RNG untouched
    actor = CascadeActor(checkpoint["obs_dim"], checkpoint["act_dim"], saved.hidden_size, saved.num_layers,
                         saved.fallback_init, checkpoint["action_low"], checkpoint["action_high"])
    for _ in range(checkpoint["actor_size"]):
        actor.add_base_net()
    torch.set_rng_state(rng)
    actor.load_state_dict(checkpoint["actor"])
    return actor.to(device)


def evaluate_saved(args: Args) -> dict:
    """--evaluate: the saved policy on --eval-episodes fresh episodes (stochastic unless --eval-deterministic)."""

    def policies(checkpoint: dict) -> tuple[Policy, list[Policy]]:
        actor = actor_from_checkpoint(checkpoint)
        members = [member_policy(actor, net, args.eval_deterministic) for net in range(actor.size)]
        return full_policy(actor, args.eval_deterministic), members

    mode = "deterministic" if args.eval_deterministic else "stochastic"
    return evaluate_saved_policy(args, load_checkpoint, policies, mode)


def finished(args: Args, checkpoint: dict) -> bool:
    """Whether `checkpoint` ends the run: all n iterations done (resuming it has nothing to do)."""
    return checkpoint["iteration"] >= args.n and checkpoint["steps_done"] == args.k


def main() -> None:
    """The command line: train, --resume a killed run, or --evaluate a saved model."""
    run_main(Args, train, evaluate_saved, load_checkpoint, finished, description=__doc__.split("\n\n")[0])


if __name__ == "__main__":
    main()
