"""Cascade trained with DDPG on continuous-action tasks (single-file, CleanRL style; paper Appendix H.2).
The defaults follow the paper's own code (github codebro634/Cascade) where its text is silent;
`--n 1 --k 6000000 --hidden-size 64` is exactly the paper's DDPG baseline (64-64 tanh actor and critic).

The actor is a Cascade of base nets `obs -> 16 -> 16 -> mu` (tanh, the paper code's Cascade default). Every
`k` env steps a new base net b_i is stacked on the ensemble C_{i-1}; besides its raw action mu_i it emits a
fallback weight lambda_i(x) in [0, 1] and the ensemble becomes (Section 3, Eq. 1; Appendix B.2)

    C_i(x) = lambda_i(x) * C_{i-1}(x) + (1 - lambda_i(x)) * mu_i(x),   action = tanh(C_n(x)) scaled to the bounds

(combined before the squash, as the paper's code; `--no-combine-before-tanh` squashes each net first). The
critic is `[obs, action] -> 64 -> 64 -> 1` (tanh). The whole stack is trained end to end by DDPG with the
learning rate annealed linearly to 0 within each iteration. When a net is added, as in the paper's code (a
new DDPG instance per net): the replay buffer is emptied, `--learning-starts` uniform-random steps without
updates follow, the critic is kept but its target is re-copied from it, the target actor becomes a copy of
the whole current cascade, and both optimizers are recreated (`--no-restart-on-new-net`: the paper's text
read literally, critic target, critic optimizer and target actor kept). `--keep-buffer` and
`--reset-critic` are the ablations. Evaluation keeps the exploration noise (the paper's code). No
observation/reward normalization; raw observations and rewards are clipped to +-10 (the paper's code).
Paper: Schmöcker & Dockhorn, "Cascade - A sequential ensemble method for continuous control tasks",
RLJ 2025, Appendix H.2 (DDPG), with the evaluation schedule of Appendix B.5.

    python cascade_ddpg.py --env-id Hopper-v4                                    # Cascade: 6 nets, a new one every 1M steps
    python cascade_ddpg.py --env-id Hopper-v4 --n 1 --k 6000000 --hidden-size 64 --exp-name ddpg_baseline
    python cascade_ddpg.py --env-id Hopper-v4 --hidden-size 256 --critic-hidden-size 256 --activation relu \
        --no-anneal-lr --adam-eps 1e-8 --eval-deterministic --obs-reward-clip 0    # Cascade on CleanRL's net sizes and settings
    tensorboard --logdir runs
"""

from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from cascade_plumbing.checkpoints import load_checkpoint as load_script_checkpoint
from cascade_plumbing.checkpoints import load_optimizer
from cascade_plumbing.envs import make_env, make_vector_env
from cascade_plumbing.errors import fail
from cascade_plumbing.fast_offpolicy import DDPGFast, OffPolicyFastPath
from cascade_plumbing.offpolicy import OffPolicyRun, Policy, check_replay_settings, evaluate_saved_policy, minimize
from cascade_plumbing.replay import ReplayBuffer, buffer_capacity
from cascade_plumbing.runs import check_common_settings, run_device, run_main, script_name, seed_everything, set_threads

# The paper used the v4 MuJoCo tasks; gymnasium warns on every make that they are out of date.
warnings.filterwarnings("ignore", message=".*is out of date.*")


@dataclass
class Args:
    exp_name: str = field(default_factory=lambda: script_name(__file__))
    """the name of this experiment (part of the run name; default: this script's file name); give the baseline its own, e.g. `ddpg_baseline`"""
    seed: int = 1
    """seed of the experiment (python, numpy, torch and the environments)"""
    torch_deterministic: bool = True
    """CleanRL's flag: `torch.backends.cudnn.deterministic` (GPU runs only; a CPU run repeats exactly on the same machine either way)"""
    torch_threads: int = 1
    """torch CPU threads (numpy's BLAS: one); 1: these nets are too small for a second thread to pay (docs/performance.md, "SAC and DDPG")"""
    autograd: bool = False
    """act with `explore` and update with `ddpg_update` (autograd) only, no fast paths (slower; the same results up to float rounding)"""
    cuda: bool = False
    """train on the GPU if torch sees one (slower for these small nets: ~0.5x one CPU core, docs/performance.md, "SAC and DDPG on a GPU"); --evaluate runs on the CPU"""
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
    n: int = 6
    """number of base nets, i.e. iterations of Cascade (the run lasts n*k steps); `--n 1 --k 6000000 --hidden-size 64` is exactly the paper's DDPG baseline"""
    k: int = 1_000_000
    """environment steps per iteration; a new base net is added every k steps (paper: 1M of 6M)"""
    hidden_size: int = 16
    """width of each hidden layer of a base net (the paper's code: 16 for Cascade, 64 for its DDPG baseline; CleanRL: 256)"""
    num_layers: int = 2
    """number of hidden layers of a base net"""
    activation: Literal["tanh", "relu"] = "tanh"
    """hidden activation of the base nets and the critic (the paper's code: tanh; CleanRL: relu)"""
    critic_hidden_size: int = 64
    """width of the critic's two hidden layers (the paper's code: 64; CleanRL: 256)"""
    combine_before_tanh: bool = True
    """combine the nets' raw outputs and squash once (the paper's code); `--no-combine-before-tanh`: squash each net, then combine"""
    fallback_init: float = 0.5
    """initial fallback weight lambda of each new base net, in (0, 1)"""
    keep_buffer: bool = False
    """ablation: keep the replay buffer when a base net is added (standard Cascade empties it)"""
    reset_critic: bool = False
    """ablation: fresh critic, target critic and critic optimizer when a base net is added (standard: the critic is kept; its target is re-copied and its optimizer recreated, see --restart-on-new-net)"""
    restart_on_new_net: bool = True
    """when a net is added, restart as the paper's code does: --learning-starts uniform-random steps without updates, target critic re-copied, target actor = copy of the whole cascade, critic optimizer recreated; `--no-restart-on-new-net`: target critic and critic optimizer kept, the target actor gets the new net with the online net's init, the current policy collects the warm-up (the paper's text); the actor optimizer is new either way"""

    # DDPG (CleanRL ddpg_continuous_action's defaults, except where the paper's code differs: docs/sac_ddpg.md)
    buffer_size: int = 1_000_000
    """the replay memory capacity (float32 numpy, preallocated; the memory it takes: docs/sac_ddpg.md, "Replay-buffer memory")"""
    gamma: float = 0.99
    """the discount factor gamma"""
    tau: float = 0.005
    """target smoothing coefficient"""
    batch_size: int = 256
    """the batch size sampled from the replay memory"""
    learning_starts: int = 25_000
    """uniform-random steps without updates at the start of each net (with `--no-restart-on-new-net`: transitions in the buffer before updates start)"""
    learning_rate: float = 3e-4
    """the initial learning rate of the actor and critic optimizers (annealed to 0 within each iteration unless --no-anneal-lr)"""
    anneal_lr: bool = True
    """anneal the learning rate linearly to 0 within each iteration (the paper's code; for n=1 over the run)"""
    adam_eps: float = 1e-5
    """Adam's epsilon (the paper's code: 1e-5; CleanRL: 1e-8)"""
    exploration_noise: float = 0.1
    """std of the Gaussian exploration noise, as a fraction of the half action range"""
    policy_frequency: int = 2
    """delayed updates: the actor and both target nets are updated every this many steps"""
    obs_reward_clip: float = 10.0
    """clip raw observations and rewards to +-this, as the paper's code does in its unnormalized runs (0: no clipping, CleanRL)"""

    # Evaluation (every 10k steps on 10 episodes, as the paper's protocol, Appendix B.5)
    eval_every: int = 10_000
    """evaluate the frozen current policy every this many env steps (0 turns evaluation off)"""
    eval_episodes: int = 10
    """episodes per evaluation (on separate envs)"""
    eval_deterministic: bool = False
    """evaluate without exploration noise; by default the training noise is kept, as the paper's code evaluates"""
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
def orthogonal_linear(in_features: int, out_features: int, gain: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Weight [in, out] (orthogonal init with `gain`) and zero bias [1, out] of one linear layer."""
    weight = torch.empty(out_features, in_features)
    nn.init.orthogonal_(weight, gain)
    return weight.T.contiguous(), torch.zeros(1, out_features)


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


ACTIVATIONS = {"tanh": torch.tanh, "relu": torch.relu}


class CascadeActor(nn.Module):
    """A stack of base nets `obs -> H -> ... -> H -> mu (+ fallback logit)` (tanh or ReLU), evaluated together.

    The base nets' weights are stacked along a leading net axis ([n, in, out]) so every layer of all nets is
    one batched matmul; the nets' outputs are then combined with the closed form of `contributions`, before
    the tanh squash (`combine_before_tanh`, the paper's code) or after it. Net 1 (the bottom) has no fallback head.
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden_size: int, num_layers: int, fallback_init: float,
                 action_low: np.ndarray, action_high: np.ndarray, activation: str = "tanh",
                 combine_before_tanh: bool = True):
        super().__init__()
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.hidden_size, self.num_layers = hidden_size, num_layers
        self.fallback_init = fallback_init
        self.activation, self.combine_before_tanh = ACTIVATIONS[activation], combine_before_tanh
        self.register_buffer("action_scale", torch.as_tensor((action_high - action_low) / 2.0, dtype=torch.float32))
        self.register_buffer("action_bias", torch.as_tensor((action_high + action_low) / 2.0, dtype=torch.float32))
        dims = [obs_dim] + [hidden_size] * num_layers
        self.hidden_weights = nn.ParameterList(
            [nn.Parameter(torch.empty(0, i, o)) for i, o in zip(dims[:-1], dims[1:])]
        )
        self.hidden_biases = nn.ParameterList([nn.Parameter(torch.empty(0, 1, o)) for o in dims[1:]])
        self.mu_weight = nn.Parameter(torch.empty(0, hidden_size, act_dim))
        self.mu_bias = nn.Parameter(torch.empty(0, 1, act_dim))
        self.fallback_weight = nn.Parameter(torch.empty(0, hidden_size, 1))
        self.fallback_bias = nn.Parameter(torch.empty(0, 1, 1))
        self._cache_parameters()

    def _cache_parameters(self) -> None:
        # Plain references for the hot path (nn.Module attribute lookups cost ~1 us each); rebuilt whenever
        # the Parameters are replaced.
        self._hidden = tuple(zip(self.hidden_weights, self.hidden_biases))
        self._heads = (self.mu_weight, self.mu_bias, self.fallback_weight, self.fallback_bias)

    @property
    def size(self) -> int:
        """number of base nets in the cascade"""
        return self.mu_weight.shape[0]

    def base_net_parameters(self) -> list[tuple[str, nn.Parameter]]:
        params = [(f"hidden_weights.{i}", p) for i, p in enumerate(self.hidden_weights)]
        params += [(f"hidden_biases.{i}", p) for i, p in enumerate(self.hidden_biases)]
        params += [("mu_weight", self.mu_weight), ("mu_bias", self.mu_bias)]
        return params + [("fallback_weight", self.fallback_weight), ("fallback_bias", self.fallback_bias)]

    def add_base_net(self, init: dict[str, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        """Stack a base net on top (new stacked Parameters: rebuild the optimizer) and return its init.
        `init` (another actor's return value) gives the target actor the online net's very weights.
        Orthogonal init (paper H, which names no gains): the paper's code's gains for its DDPG actors (its
        AgentConfigs/VanillaDDPG.py, CleanRL PPO's too): sqrt(2) hidden, 0.01 output, zero biases."""
        grown = init
        if grown is None:
            dims = [self.obs_dim] + [self.hidden_size] * self.num_layers
            grown = {}
            for i, (d_in, d_out) in enumerate(zip(dims[:-1], dims[1:])):
                grown[f"hidden_weights.{i}"], grown[f"hidden_biases.{i}"] = orthogonal_linear(d_in, d_out, math.sqrt(2))
            is_bottom = self.size == 0
            weight, bias = orthogonal_linear(self.hidden_size, self.act_dim + (0 if is_bottom else 1), 0.01)
            grown["mu_weight"], grown["mu_bias"] = weight[:, : self.act_dim], bias[:, : self.act_dim]
            if not is_bottom:
                grown["fallback_weight"] = weight[:, self.act_dim :]
                # sigmoid(logit(l0)) = l0: the new net starts by deferring a share l0 to the nets below
                grown["fallback_bias"] = torch.full((1, 1), math.log(self.fallback_init / (1 - self.fallback_init)))
        for name, param in self.base_net_parameters():
            if name in grown:
                new = torch.cat([param.data, grown[name].unsqueeze(0).to(param.device)])
                self._replace(name, nn.Parameter(new))
        self._cache_parameters()
        return grown

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

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """obs [B, obs_dim] -> action [B, A] in the bounds, fallback [n-1, B], contribution [n, B]."""
        mu_weight, mu_bias, fallback_weight, fallback_bias = self._heads
        hidden = obs.expand(len(mu_weight), *obs.shape)  # every base net reads the same observation
        for weight, bias in self._hidden:
            hidden = self.activation(torch.baddbmm(bias, hidden, weight))  # [n, B, H], all nets at once
        mu = torch.baddbmm(mu_bias, hidden, mu_weight)  # [n, B, A], each net's raw output
        fallback = torch.sigmoid(torch.baddbmm(fallback_bias, hidden[1:], fallback_weight))  # [n-1, B, 1]
        contribution = contributions(fallback)  # w_i [n, B, 1]
        if self.combine_before_tanh:  # the paper's code: C_n = sum_i w_i mu_i, squashed once
            squashed = torch.tanh((contribution * mu).sum(0))
        else:  # each net squashed into [-1, 1] first, then combined
            squashed = (contribution * torch.tanh(mu)).sum(0)
        # sum_i w_i (scale*t_i + bias) = scale * sum_i w_i t_i + bias, as the weights sum to one
        action = squashed * self.action_scale + self.action_bias
        return action, fallback.squeeze(-1), contribution.squeeze(-1)

    def member(self, obs: torch.Tensor, net: int) -> torch.Tensor:
        """Action of base net `net` (0-based) acting alone."""
        hidden = obs
        for weight, bias in zip(self.hidden_weights, self.hidden_biases):
            hidden = self.activation(torch.addmm(bias[net], hidden, weight[net]))
        return torch.tanh(torch.addmm(self.mu_bias[net], hidden, self.mu_weight[net])) * self.action_scale + self.action_bias


def add_noise(action: torch.Tensor, actor: CascadeActor, noise: float,
              generator: torch.Generator | None = None) -> torch.Tensor:
    """CleanRL's exploration: Gaussian noise of std noise * half range, clipped back into the bounds."""
    if noise:
        action = action + torch.randn(action.shape, generator=generator, device=action.device) * (
            actor.action_scale * noise)
    low, high = actor.action_bias - actor.action_scale, actor.action_bias + actor.action_scale
    return torch.maximum(torch.minimum(action, high), low)


def explore(actor: CascadeActor, obs: torch.Tensor, noise: float) -> torch.Tensor:
    """The action taken in the training env for obs [B, obs_dim]: the cascade's action plus the exploration noise."""
    action, _, _ = actor(obs)
    return add_noise(action, actor, noise)


def count_parameters(*modules: nn.Module) -> int:
    return sum(p.numel() for m in modules for p in m.parameters())


# ----------------------------------------------------------------------------------------------
# The critic: a Q-network (the paper's code's, orthogonal init), kept when a net is added (Appendix H.2)
# ----------------------------------------------------------------------------------------------
class QNetworks(nn.Module):
    """`num_q` critics Q(s, a): `[obs, action] -> H -> H -> 1` (the paper's code: H = 64, tanh; CleanRL's
    QNetwork: 256, ReLU), orthogonal init: gain sqrt(2) hidden, 1.0 output. Stacked [num_q, in, out]; DDPG uses one."""

    def __init__(self, obs_dim: int, act_dim: int, num_q: int = 1, hidden_size: int = 64, activation: str = "tanh"):
        super().__init__()
        self.activation = ACTIVATIONS[activation]
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
                x = self.activation(x)
        return x.squeeze(-1)


@torch.no_grad()
def soft_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """target <- tau * source + (1 - tau) * target, for all parameters at once."""
    torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)


# ----------------------------------------------------------------------------------------------
# The DDPG update (CleanRL's ddpg_continuous_action, the whole cascade as the actor)
# ----------------------------------------------------------------------------------------------
def make_adam(params: list[nn.Parameter], lr: float, eps: float) -> torch.optim.Adam:
    """Adam (the paper's code: eps 1e-5); the fused kernel updates all parameters at once."""
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=True)


def ddpg_update(args: Args, step_in_iteration: int, batch: tuple[torch.Tensor, ...], actor: CascadeActor,
                target_actor: CascadeActor, qf: QNetworks, qf_target: QNetworks, q_optimizer: torch.optim.Optimizer,
                actor_optimizer: torch.optim.Optimizer) -> dict:
    """One DDPG update on a replay batch (obs, actions, rewards, next_obs, dones): the critic towards the Bellman
    target of the target actor and target critic, then every `policy_frequency` steps (delayed, as CleanRL) the
    actor up the critic's gradient and the soft update of both targets. Returns what it computed for the logs:
    the critic's values and loss, and the actor's loss when the actor was updated."""
    b_obs, b_actions, b_rewards, b_next_obs, b_dones = batch
    with torch.no_grad():
        next_actions, _, _ = target_actor(b_next_obs)
        # b_dones are terminations only: truncated episodes bootstrap
        next_q_value = b_rewards + (1 - b_dones) * args.gamma * qf_target(b_next_obs, next_actions)[0]
    qf1_a_values = qf(b_obs, b_actions)[0]
    qf1_loss = F.mse_loss(qf1_a_values, next_q_value)
    minimize(q_optimizer, qf1_loss)  # zero_grad(); backward(); step(), bit for bit
    # (cascade_plumbing.offpolicy; it leaves no .grad: to clip or log gradients, write those three lines here)
    out = {"qf1_a_values": qf1_a_values, "qf1_loss": qf1_loss}

    if step_in_iteration % args.policy_frequency == 0:  # counted from 0 with each net (the paper's code)
        out["actor_loss"] = actor_loss = -qf(b_obs, actor(b_obs)[0])[0].mean()
        minimize(actor_optimizer, actor_loss)  # the actor's gradients only: dQ/da, none of the critic's weights
        soft_update(target_actor, actor, args.tau)
        soft_update(qf_target, qf, args.tau)
    return out


# ----------------------------------------------------------------------------------------------
# Training: a new base net every k steps (Algorithm 1; Appendix H.2)
# ----------------------------------------------------------------------------------------------
def train(args: Args, checkpoint: dict | None = None,
          on_iteration_start: Callable[[dict], None] | None = None) -> dict:
    """Runs Cascade-DDPG (from scratch, or continuing a `checkpoint` exactly); returns the final actor
    and target actor, critic and target, buffer and run folder. `on_iteration_start` sees each iteration's state
    (used by the tests)."""
    validate(args, new_run=checkpoint is None)
    set_threads(args.torch_threads)
    seed_everything(args.seed, args.torch_deterministic)
    device = run_device(args.cuda)
    # CleanRL's DDPG env (raw episode statistics, no normalization; `add_noise` clips the actions to the bounds),
    # plus the paper's code's clipping of raw observations and rewards to +-obs_reward_clip (0: none)
    envs = make_vector_env([make_env(args.env_id, video=args.capture_video, clip=args.obs_reward_clip)])
    run = OffPolicyRun(args, checkpoint, envs, CHECKPOINT_FORMAT, rates="--learning-rate")
    fast = make_fast_paths(args, device, run)  # the fast paths, checked against explore and ddpg_update as the run trains
    obs_dim, act_dim = run.obs_dim, run.act_dim

    actor = CascadeActor(obs_dim, act_dim, args.hidden_size, args.num_layers, args.fallback_init,
                         run.action_low, run.action_high, args.activation, args.combine_before_tanh).to(device)
    target_actor = copy.deepcopy(actor)

    def make_critic() -> QNetworks:
        return QNetworks(obs_dim, act_dim, hidden_size=args.critic_hidden_size, activation=args.activation).to(device)

    qf = make_critic()
    qf_target = copy.deepcopy(qf)
    q_optimizer = make_adam(list(qf.parameters()), args.learning_rate, args.adam_eps)
    buffer = ReplayBuffer(buffer_capacity(args.buffer_size, args.n, args.k, args.keep_buffer), obs_dim, act_dim)

    if checkpoint is None:
        global_step, start_iteration, start_step = run.start()
        if args.eval_every:
            evaluate(run, actor, args, global_step)  # step 0, before the first net: the empty cascade outputs zeros (raw)
    else:  # the saved nets, replay buffer, env state, RNG streams and position in the run
        global_step, start_iteration, start_step = run.restore(checkpoint, buffer)
        actor = actor_from_checkpoint(checkpoint, device)
        target_actor = actor_from_checkpoint(checkpoint, device, key="target_actor")
        qf.load_state_dict(checkpoint["qf"])
        qf_target.load_state_dict(checkpoint["qf_target"])
        load_optimizer(q_optimizer, checkpoint["q_optimizer"])

    for iteration in range(start_iteration, args.n + 1):
        mid_iteration = iteration == start_iteration and start_step > 0
        if not mid_iteration:  # (else: continuing the iteration a checkpoint was written in)
            # --- a new Cascade iteration: new base net, emptied buffer; the critic kept (fresh
            # with --reset-critic), its target, its optimizer and the target actor renewed (the restart) ---
            if args.restart_on_new_net:
                # the paper's code starts a new DDPG instance per net: its target actor is a copy of the whole
                # cascade, its target critic a copy of the kept critic, and the critic optimizer is new
                actor.add_base_net()
                target_actor = copy.deepcopy(actor)
            else:  # the target actor keeps its nets and gets the new one with the online net's very init
                target_actor.add_base_net(actor.add_base_net())
            if iteration > 1 and (args.reset_critic or args.restart_on_new_net):
                if args.reset_critic:  # the ablation: a fresh critic
                    qf = make_critic()
                qf_target = copy.deepcopy(qf)  # a target copied anew from the (kept or fresh) critic
                q_optimizer = make_adam(list(qf.parameters()), args.learning_rate, args.adam_eps)
            if not args.keep_buffer:
                buffer.clear()
        # a fresh actor optimizer each iteration (over all its nets); continuing one, the saved one
        actor_optimizer = make_adam(list(actor.parameters()), args.learning_rate, args.adam_eps)
        if mid_iteration:
            load_optimizer(actor_optimizer, checkpoint["actor_optimizer"])
        run.iteration_start(iteration, actor.size, count_parameters(actor, qf), "actor + critic", global_step,
                            continuing=mid_iteration)
        if on_iteration_start is not None:
            on_iteration_start({"iteration": iteration, "actor": actor, "target_actor": target_actor, "qf": qf,
                                "qf_target": qf_target, "q_optimizer": q_optimizer,
                                "actor_optimizer": actor_optimizer, "buffer": buffer, "envs": envs,
                                "next_obs": run.next_obs, "global_step": global_step})

        # the latest update's values; the actor's loss from the iteration's first actor update on
        logged: dict = checkpoint["logged"] if mid_iteration else {}
        for step_in_iteration in range(start_step if mid_iteration else 0, args.k):
            global_step += 1
            if args.anneal_lr:  # the paper's code: linearly to 0 within each iteration
                frac = 1.0 - step_in_iteration / args.k
                for group in (*q_optimizer.param_groups, *actor_optimizer.param_groups):  # each from its initial LR
                    group["lr"] = frac * group.setdefault("initial_lr", group["lr"])
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
            else:  # explore(actor, obs, noise), by the fast path when it is on: edit explore, not this line
                actions = fast.act(explore, actor, run.next_obs, args.exploration_noise, step=global_step)
            run.step(actions, buffer, global_step)

            if learning:
                batch = buffer.sample(args.batch_size, device)
                # ddpg_update(...), by the fast path when it is on: edit ddpg_update, not this line
                logged.update(fast.update(ddpg_update, args, step_in_iteration, batch, actor, target_actor, qf,
                                          qf_target, q_optimizer, actor_optimizer, step=global_step))
                if global_step % 100 == 0 and "actor_loss" in logged:
                    write = run.writer.add_scalar
                    write("losses/qf1_values", logged["qf1_a_values"].mean().item(), global_step)
                    write("losses/qf1_loss", logged["qf1_loss"].item(), global_step)
                    write("losses/actor_loss", logged["actor_loss"].item(), global_step)
                    write("charts/learning_rate", actor_optimizer.param_groups[0]["lr"], global_step)
                    # fallback metrics: means over the sampled replay batch (states of this iteration's data)
                    with torch.no_grad():
                        _, batch_fallback, batch_contribution = actor(batch[0])
                    run.log_fallbacks(batch_fallback, batch_contribution, global_step)
                    run.guard_non_finite([actor, qf], global_step, iteration,
                                           [logged["qf1_loss"].item(), logged["actor_loss"].item()])

            run.tick(global_step, actor.size)
            if args.eval_every and global_step % args.eval_every == 0:
                evaluate(run, actor, args, global_step)
            if run.checkpoint_due(global_step) and step_in_iteration + 1 < args.k:  # (the iteration's end: below)
                run.guard_non_finite([actor, qf], global_step, iteration)
                run.save_progress(iteration, step_in_iteration + 1, global_step, saved_nets(
                    actor, target_actor, qf, qf_target, q_optimizer, actor_optimizer, logged), buffer)

        # --- end of the iteration: member returns (and at the run's end the final policy's), then an atomic
        # checkpoint: a run stopped after it has nothing left to log ---
        if args.eval_every and args.eval_members:
            evaluate(run, actor, args, global_step, members=True)
        if iteration == args.n and args.eval_every and global_step % args.eval_every:
            evaluate(run, actor, args, global_step)  # the final policy, if the last step was not an eval step
        run.guard_non_finite([actor, qf], global_step, iteration)
        run.save_progress(iteration, args.k, global_step, saved_nets(
            actor, target_actor, qf, qf_target, q_optimizer, actor_optimizer, logged), buffer)

    run.close(global_step)
    return {"actor": actor, "target_actor": target_actor, "qf": qf, "qf_target": qf_target, "buffer": buffer,
            "run_dir": run.run_dir, "global_step": global_step, "fast_path": fast}


# ----------------------------------------------------------------------------------------------
# Evaluation: every --eval-every steps the frozen current actor on --eval-episodes episodes of separate envs
# with their own seeds and RNG (Appendix B.5), with the training exploration noise as the paper's code
# evaluates; each net alone at the end of each iteration
# ----------------------------------------------------------------------------------------------
def evaluate(run: OffPolicyRun, actor: CascadeActor, args: Args, step: int, members: bool = False) -> None:
    """Freeze the current actor (or, with `members`, each net acting alone) and evaluate it."""
    frozen = actor if actor.action_scale.device.type == "cpu" else copy.deepcopy(actor).cpu()
    noise = 0.0 if args.eval_deterministic else args.exploration_noise
    if members:
        run.evaluate_members(step, [member_policy(frozen, net, noise) for net in range(frozen.size)])
    else:
        run.evaluate(step, full_policy(frozen, noise))


def full_policy(actor: CascadeActor, noise: float) -> Policy:
    """The whole cascade, with exploration noise of std `noise` * half range (0: none)."""

    def act(x: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        action, fallback, _ = actor(x)
        return add_noise(action, actor, noise, generator), fallback

    return act


def member_policy(actor: CascadeActor, net: int, noise: float) -> Policy:
    """Base net `net` (0-based) acting alone, with the same noise; it has no fallbacks."""

    def act(x: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        return add_noise(actor.member(x, net), actor, noise, generator), x.new_zeros(0, x.shape[0])

    return act


# ----------------------------------------------------------------------------------------------
# Fast paths: the same update with hand-written gradients, and the same acting in numpy
# (cascade_plumbing/fast_offpolicy.py; docs/performance.md, "SAC and DDPG on a GPU"), checked against `ddpg_update` and `explore` while the
# run trains: at each new net, then about every 2000 steps, both run on float64 copies from the same random state. Edit
# `ddpg_update`, `explore` and the nets above, not the fast paths: an edit they do not reproduce switches them off
# with one warning line, and the run continues exactly as --autograd runs it. On the CPU only.
# ----------------------------------------------------------------------------------------------
def make_fast_paths(args: Args, device: torch.device, run: OffPolicyRun | None = None) -> OffPolicyFastPath:
    def complete(step_in_iteration: int) -> bool:  # ddpg_update runs every part: the checks pick such updates
        return step_in_iteration % args.policy_frequency == 0

    return OffPolicyFastPath(not args.autograd and device.type == "cpu", DDPGFast(),
                             None if run is None else run.fast_path_off, complete)


# ----------------------------------------------------------------------------------------------
# Wiring to cascade_plumbing: input checks, checkpoints, --evaluate, the command line
# ----------------------------------------------------------------------------------------------
def validate(args: Args, new_run: bool = True) -> None:
    """Reject bad input with one clear line before anything is created."""
    check_common_settings(args)
    if not args.learning_rate >= 0:
        fail(f"--learning-rate must be >= 0 (got {args.learning_rate})")
    if args.n < 1:
        fail(f"--n must be at least 1 (got {args.n})")
    if not 0.0 < args.fallback_init < 1.0:
        fail(f"--fallback-init must lie strictly between 0 and 1 (got {args.fallback_init})")
    if args.hidden_size < 1 or args.num_layers < 1 or args.critic_hidden_size < 1:
        fail("--hidden-size, --num-layers and --critic-hidden-size must be at least 1")
    if not args.adam_eps > 0:
        fail(f"--adam-eps must be > 0 (got {args.adam_eps})")
    if args.policy_frequency < 1:
        fail("--policy-frequency must be at least 1")
    check_replay_settings(args, bounds_needed_because="the actor's tanh outputs are rescaled to finite bounds",
                          frequencies={"--policy-frequency": "the actor's and the targets' update"}, new_run=new_run)


# /2: the paper's-code defaults (nets, LR, new-net restart, clipping); /3: checkpoints inside an iteration, with the
# replay buffer
CHECKPOINT_FORMAT = "cascade_ddpg/3"


def saved_nets(actor: CascadeActor, target_actor: CascadeActor, qf: QNetworks, qf_target: QNetworks,
               q_optimizer: torch.optim.Optimizer, actor_optimizer: torch.optim.Optimizer, logged: dict) -> dict:
    """What a checkpoint holds of the algorithm: every net, target and optimizer and the latest update's values
    (logged every 100 steps); the run's state and the replay buffer are added to it."""
    return {"actor": actor.state_dict(), "target_actor": target_actor.state_dict(), "actor_size": actor.size,
            "qf": qf.state_dict(), "qf_target": qf_target.state_dict(), "q_optimizer": q_optimizer.state_dict(),
            "actor_optimizer": actor_optimizer.state_dict(), "logged": logged}


def load_checkpoint(path: str, reader_flag: str = "") -> dict:
    """A cascade_ddpg checkpoint (`runs/<run>`, its latest, or a file); one line if it is missing, corrupt, another
    script's, or of an older cascade_ddpg.py (which it cannot resume exactly)."""
    return load_script_checkpoint(path, CHECKPOINT_FORMAT,
                                  older_note=", before checkpoints held the replay buffer", reader_flag=reader_flag)


def actor_from_checkpoint(checkpoint: dict, device: str | torch.device = "cpu", key: str = "actor") -> CascadeActor:
    """The saved actor (`key="target_actor"`: the target actor)."""
    saved = Args(**checkpoint["args"])
    rng = torch.get_rng_state()  # building the nets draws random inits; keep the caller's RNG untouched
    actor = CascadeActor(checkpoint["obs_dim"], checkpoint["act_dim"], saved.hidden_size, saved.num_layers,
                         saved.fallback_init, checkpoint["action_low"], checkpoint["action_high"], saved.activation,
                         saved.combine_before_tanh)
    for _ in range(checkpoint["actor_size"]):
        actor.add_base_net()
    torch.set_rng_state(rng)
    actor.load_state_dict(checkpoint[key])
    return actor.to(device)




def evaluate_saved(args: Args) -> dict:
    """--evaluate: the saved actor on --eval-episodes fresh episodes (with exploration noise unless --eval-deterministic)."""

    def policies(checkpoint: dict) -> tuple[Policy, list[Policy]]:
        actor = actor_from_checkpoint(checkpoint)
        noise = 0.0 if args.eval_deterministic else checkpoint["args"]["exploration_noise"]
        return full_policy(actor, noise), [member_policy(actor, net, noise) for net in range(actor.size)]

    mode = "noise-free" if args.eval_deterministic else "exploration-noise"
    return evaluate_saved_policy(args, load_checkpoint, policies, mode)


def finished(args: Args, checkpoint: dict) -> bool:
    """Whether `checkpoint` ends the run: all n iterations done (resuming it has nothing to do)."""
    return checkpoint["iteration"] >= args.n and checkpoint["steps_done"] == args.k


def main() -> None:
    """The command line: train, --resume a killed run, or --evaluate a saved model."""
    run_main(Args, train, evaluate_saved, load_checkpoint, finished, description=__doc__.split("\n\n")[0])


if __name__ == "__main__":
    main()
