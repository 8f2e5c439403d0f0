"""Cascade trained with PPO on discrete-action tasks (single-file, CleanRL style).

Cascade grows an ensemble policy one base net at a time. Every `k` env steps a new base net b_i is
stacked on the ensemble C_{i-1}; besides its action logits it emits a fallback weight
lambda_i(x) in [0, 1] and the ensemble's logits become

    C_i(x) = lambda_i(x) * C_{i-1}(x) + (1 - lambda_i(x)) * b_i(x)        (the policy: Categorical(C_n))

Box action spaces of A dims are discretized into the 2^A corners of the box (paper Appendix I), so
the MuJoCo tasks can be compared with discrete PPO (`ppo_baseline_discrete.py`, paper Fig. 16);
natively discrete envs such as CartPole-v1 are used as they are. Discretized Box tasks get observation/reward
normalization and +-10 clipping by default, as the paper's code ran Fig. 16 (`--no-normalize`: clipping only).
PPO runs with CleanRL `ppo.py`'s hyperparameters; each iteration gets a fresh critic, a fresh Adam and a fresh
learning-rate cycle, while the normalization statistics carry over (Appendix B.3).
Paper: Schmöcker & Dockhorn, "Cascade - A sequential ensemble method for continuous control tasks",
RLJ 2025: the method, Section 3 (Eq. 1) and Algorithm 1 (Appendix A); the Cascade net, Appendix B.1-B.2; its
discrete version, Appendix I; the evaluation protocol, Appendix B.5.

Reading order: `Args`, the Cascade net, the loss, `train`, its evaluation, and last the few lines that wire it
to `cascade_plumbing` (the env stack, run folder, checkpoints and command line every script shares).

    python cascade_ppo_discrete.py --env-id Hopper-v4 --n 10 --k 1000000
    tensorboard --logdir runs
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
import torch.nn as nn

from cascade_plumbing import checkpoints
from cascade_plumbing.discrete import (  # noqa: F401 (MAX_DISCRETIZED_DIMS, DiscretizeAction, discretize_problem, make_env, normalize_obs: the tests reach them here)
    MAX_DISCRETIZED_DIMS,
    DiscreteRun,
    DiscretizeAction,
    EvaluationEpisodes,
    discretize_problem,
    evaluate_saved_model,
    make_env,
    make_vector_env,
    normalize_obs,
    resolve_env,
)
from cascade_plumbing.envs import find_wrapper, obs_statistics  # noqa: F401 (find_wrapper: for the tests)
from cascade_plumbing.errors import fail
from cascade_plumbing.ppo import check_ppo_settings
from cascade_plumbing.runs import check_common_settings, run_device, run_main, seed_everything, set_threads

# The paper used the v4 MuJoCo tasks; gymnasium warns on every make that they are out of date.
warnings.filterwarnings("ignore", message=".*is out of date.*")


@dataclass
class Args:
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment (part of the run name); default: this file's name"""
    seed: int = 1
    """seed of the experiment (python, numpy, torch and the environments)"""
    torch_deterministic: bool = True
    """CleanRL's flag: `torch.backends.cudnn.deterministic` (GPU runs only; a CPU run repeats exactly on the same machine either way)"""
    torch_threads: int = 1
    """torch CPU threads (numpy's BLAS: one); 1 is fastest for these small nets"""
    cuda: bool = False
    """train on the GPU if torch sees one (small nets are usually faster on the CPU); --evaluate runs on the CPU"""
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
    """the id of a gymnasium environment with a Discrete action space, or a Box one to discretize (e.g. Hopper-v4)"""
    discretize: Literal["auto", "on", "off"] = "auto"
    """auto: discretize a Box action space of A <= 10 dims into 2^A actions (Humanoid's 17 are refused), use a Discrete one as it is; on: require a Box space to discretize (an error on a discrete env); off: require a natively discrete env"""
    normalize: bool = True
    """observation and reward normalization of discretized Box envs, as the paper's code ran Fig. 16 (its text names CleanRL ppo.py, which has none: `--no-normalize`); their observations and rewards are clipped to ±10 either way; natively discrete envs are never normalized or clipped (CleanRL; `--normalize` is refused there)"""

    # Cascade
    n: int = 10
    """number of base nets, i.e. iterations of Cascade (the run lasts n*k steps, each k rounded down to whole rollouts; paper Fig. 16: 10)"""
    k: int = 1_000_000
    """environment steps per iteration; a new base net is added every k steps (rounded down to whole rollouts of num_envs*num_steps)"""
    hidden_size: int = 64
    """width of each hidden layer of a base net (paper, discrete actions: 64)"""
    num_layers: int = 2
    """number of hidden layers of a base net"""
    fallback_init: float = 0.5
    """initial fallback weight lambda of each new base net, in (0, 1) (the flagship's Fig. 11 ablation: 0.05, 0.5, 0.9)"""
    freeze_previous: bool = False
    """only the newest base net trains; older ones are frozen (the flagship's Fig. 4 ablation)"""
    start_full: bool = False
    """build all n base nets at the start instead of one per iteration (the flagship's Fig. 5 ablation; as the paper's code, one critic for the whole run, while Adam and the LR cycle still restart every k)"""
    lr_schedule: Literal["cyclic", "global", "constant"] = "cyclic"
    """cyclic: linear decay to 0 within each iteration (standard); global: one decay over the whole run (the flagship's Fig. 12 ablation); constant: no decay"""

    # PPO (CleanRL ppo.py defaults)
    learning_rate: float = 2.5e-4
    """initial learning rate of the optimizer"""
    num_envs: int = 4
    """training envs, stepped one after another in this process (a gymnasium SyncVectorEnv, as CleanRL ppo.py)"""
    num_steps: int = 128
    """steps per environment per rollout"""
    gamma: float = 0.99
    """discount factor"""
    gae_lambda: float = 0.95
    """lambda of generalized advantage estimation"""
    num_minibatches: int = 4
    """number of minibatches per epoch"""
    update_epochs: int = 4
    """number of epochs over each rollout"""
    norm_adv: bool = True
    """normalize advantages per minibatch"""
    clip_coef: float = 0.2
    """clip range of the surrogate objective (PPO's epsilon) and, with --clip-vloss, of the value loss"""
    clip_vloss: bool = True
    """use a clipped value loss"""
    ent_coef: float = 0.01
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

    # Checkpoints, resuming, evaluating a saved model
    checkpoint_every: int = 100_000
    """also checkpoint every this many env steps, besides the end of every iteration (0: iteration ends only)"""
    resume: str | None = None
    """continue a killed run: `runs/<run_name>` or a checkpoint file; the saved settings are used"""
    evaluate: str | None = None
    """evaluate a saved model (`runs/<run_name>` or a checkpoint file) for --eval-episodes episodes and exit"""
    deterministic: bool = False
    """with --evaluate: act with the most probable (argmax) action instead of sampling"""
    quiet: bool = False
    """print nothing while training (errors still go to stderr); sweep.py passes it"""


# ----------------------------------------------------------------------------------------------
# The Cascade net (Section 3, Eq. 1; Appendix B.1-B.2): base nets whose logits are combined convexly
# ----------------------------------------------------------------------------------------------
def orthogonal_linear(in_features: int, out_features: int, gain: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Weight [in, out] (orthogonal init with `gain`) and zero bias [1, out] of one linear layer."""
    weight = torch.empty(out_features, in_features)
    nn.init.orthogonal_(weight, gain)
    return weight.T.contiguous(), torch.zeros(1, out_features)


def contributions(fallback: torch.Tensor) -> torch.Tensor:
    """Share w_i of each base net in the ensemble output, from the fallbacks of nets 2..n.

    Unrolling C_i = l_i*C_{i-1} + (1-l_i)*b_i gives C_n = sum_i w_i*b_i with
    w_i = (1 - l_i) * prod_{j>i} l_j and l_1 := 0; w_1 = prod_{j>=2} l_j is the fallback product (Section 4.5).
    fallback: [n-1, B, 1] -> contributions [n, B, 1], summing to 1 over nets.
    """
    ones = fallback.new_ones((1, *fallback.shape[1:]))
    # later[i] = prod_{j>i} l_j: a reverse cumulative product over the nets above net i
    later = torch.cat([torch.cumprod(fallback.flip(0), 0).flip(0), ones])
    return torch.cat([ones, 1.0 - fallback]) * later


class CascadeActor(nn.Module):
    """A stack of base nets `obs -> H -> ... -> H -> logits (+ fallback logit)`, tanh, evaluated together.

    The base nets' weights are stacked along a leading net axis ([n, in, out]) so every layer of all
    nets is one batched matmul; the nets' logits are then combined with the closed form of
    `contributions`. Net 1 (the bottom) has no fallback head, so the fallback head holds nets 2..n only.
    """

    def __init__(self, obs_dim: int, num_actions: int, hidden_size: int, num_layers: int, fallback_init: float):
        super().__init__()
        self.obs_dim, self.num_actions = obs_dim, num_actions
        self.hidden_size, self.num_layers = hidden_size, num_layers
        self.fallback_init = fallback_init
        self.num_frozen = 0  # base nets 1..num_frozen get no gradient (--freeze-previous)
        dims = [obs_dim] + [hidden_size] * num_layers
        self.hidden_weights = nn.ParameterList(
            [nn.Parameter(torch.empty(0, i, o)) for i, o in zip(dims[:-1], dims[1:])]
        )
        self.hidden_biases = nn.ParameterList([nn.Parameter(torch.empty(0, 1, o)) for o in dims[1:]])
        self.logits_weight = nn.Parameter(torch.empty(0, hidden_size, num_actions))
        self.logits_bias = nn.Parameter(torch.empty(0, 1, num_actions))
        self.fallback_weight = nn.Parameter(torch.empty(0, hidden_size, 1))
        self.fallback_bias = nn.Parameter(torch.empty(0, 1, 1))

    @property
    def size(self) -> int:
        """number of base nets in the cascade"""
        return self.logits_weight.shape[0]

    def base_net_parameters(self) -> list[tuple[str, nn.Parameter, int]]:
        """(name, stacked parameter, index of the net its first row belongs to)."""
        params = [(f"hidden_weights.{i}", p, 0) for i, p in enumerate(self.hidden_weights)]
        params += [(f"hidden_biases.{i}", p, 0) for i, p in enumerate(self.hidden_biases)]
        params += [("logits_weight", self.logits_weight, 0), ("logits_bias", self.logits_bias, 0)]
        params += [("fallback_weight", self.fallback_weight, 1), ("fallback_bias", self.fallback_bias, 1)]
        return params

    def add_base_net(self) -> None:
        """Stack a freshly initialized base net on top (new stacked Parameters: rebuild the optimizer)."""
        dims = [self.obs_dim] + [self.hidden_size] * self.num_layers
        grown: dict[str, torch.Tensor] = {}
        for i, (d_in, d_out) in enumerate(zip(dims[:-1], dims[1:])):
            grown[f"hidden_weights.{i}"], grown[f"hidden_biases.{i}"] = orthogonal_linear(d_in, d_out, math.sqrt(2))
        is_bottom = self.size == 0
        # gain 0.01 as CleanRL ppo.py's actor head: the new net starts near-uniform
        weight, bias = orthogonal_linear(self.hidden_size, self.num_actions + (0 if is_bottom else 1), 0.01)
        grown["logits_weight"], grown["logits_bias"] = weight[:, : self.num_actions], bias[:, : self.num_actions]
        if not is_bottom:
            grown["fallback_weight"] = weight[:, self.num_actions :]
            # sigmoid(logit(l0)) = l0: the new net starts by deferring a share l0 to the nets below
            grown["fallback_bias"] = torch.full((1, 1), math.log(self.fallback_init / (1 - self.fallback_init)))
        for name, param, _ in self.base_net_parameters():
            if name in grown:
                new = torch.cat([param.data, grown[name].unsqueeze(0).to(param.device)])
                self._replace(name, nn.Parameter(new))
        self._register_freeze_hooks()

    def _replace(self, name: str, param: nn.Parameter) -> None:
        if "." in name:
            list_name, index = name.split(".")
            getattr(self, list_name)[int(index)] = param
        else:
            setattr(self, name, param)

    def freeze_below(self, num_frozen: int) -> None:
        """Give no gradient to base nets 1..num_frozen (the rest train)."""
        self.num_frozen = num_frozen

    def _register_freeze_hooks(self) -> None:
        for _, param, first_net in self.base_net_parameters():

            def mask(grad: torch.Tensor, first_net: int = first_net) -> torch.Tensor:
                rows = max(self.num_frozen - first_net, 0)
                if rows == 0:
                    return grad
                grad = grad.clone()
                grad[:rows] = 0.0
                return grad

            param.register_hook(mask)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """obs [B, obs_dim] -> logits [B, K], fallback [n-1, B], contribution [n, B]."""
        hidden = obs.expand(self.size, *obs.shape)  # every base net reads the same observation
        for weight, bias in zip(self.hidden_weights, self.hidden_biases):
            hidden = torch.tanh(torch.baddbmm(bias, hidden, weight))  # [n, B, H], all nets at once
        logits = torch.baddbmm(self.logits_bias, hidden, self.logits_weight)  # [n, B, K]
        fallback = torch.sigmoid(torch.baddbmm(self.fallback_bias, hidden[1:], self.fallback_weight))
        contribution = contributions(fallback)  # w_i [n, B, 1]
        return (contribution * logits).sum(0), fallback.squeeze(-1), contribution.squeeze(-1)  # C_n = sum_i w_i b_i

    def member(self, obs: torch.Tensor, net: int) -> torch.Tensor:
        """Logits of base net `net` (0-based) acting alone."""
        hidden = obs
        for weight, bias in zip(self.hidden_weights, self.hidden_biases):
            hidden = torch.tanh(torch.addmm(bias[net], hidden, weight[net]))
        return torch.addmm(self.logits_bias[net], hidden, self.logits_weight[net])


def make_critic(obs_dim: int) -> nn.Sequential:
    """The PPO value net, obs -> 64 -> 64 -> 1 (tanh), recreated at every Cascade iteration."""

    def layer(i: int, o: int, gain: float) -> nn.Linear:
        linear = nn.Linear(i, o)
        nn.init.orthogonal_(linear.weight, gain)
        nn.init.zeros_(linear.bias)
        return linear

    return nn.Sequential(
        layer(obs_dim, 64, math.sqrt(2)), nn.Tanh(), layer(64, 64, math.sqrt(2)), nn.Tanh(), layer(64, 1, 1.0)
    )


def count_parameters(*modules: nn.Module) -> int:
    return sum(p.numel() for m in modules for p in m.parameters())


def make_optimizer(params: list[nn.Parameter], learning_rate: float) -> torch.optim.Adam:
    return torch.optim.Adam(params, lr=learning_rate, eps=1e-5)


# ----------------------------------------------------------------------------------------------
# The loss: PPO as CleanRL ppo.py runs it (Appendix I), on the Cascade net as the actor
# ----------------------------------------------------------------------------------------------
def compute_gae(rewards: torch.Tensor, values: torch.Tensor, dones: torch.Tensor, next_value: torch.Tensor,
                next_done: torch.Tensor, gamma: float, gae_lambda: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalized advantage estimation over a rollout [num_steps, num_envs], as CleanRL: an episode end,
    termination or truncation, cuts the bootstrap. dones[t] = 1: the observation of step t starts a new episode;
    next_value, next_done: those of the observation after the rollout. Returns (advantages, returns)."""
    num_steps = len(rewards)
    advantages = torch.zeros_like(rewards)
    lastgaelam = 0
    for t in reversed(range(num_steps)):
        nextnonterminal = 1.0 - (next_done if t == num_steps - 1 else dones[t + 1])
        nextvalues = next_value if t == num_steps - 1 else values[t + 1]
        delta = rewards[t] + gamma * nextvalues * nextnonterminal - values[t]
        lastgaelam = delta + gamma * gae_lambda * nextnonterminal * lastgaelam
        advantages[t] = lastgaelam
    return advantages, advantages + values


def ppo_loss(logits: torch.Tensor, newvalue: torch.Tensor, mb: dict[str, torch.Tensor], args: Args
             ) -> tuple[torch.Tensor, dict[str, torch.Tensor | float]]:
    """CleanRL ppo.py's loss on a minibatch `mb` of the rollout (its actions, logprobs, advantages, returns and
    values), given the actor's `logits` and the critic's `newvalue` there: the clipped surrogate, the (clipped)
    value loss and the entropy bonus. Returns the loss and what CleanRL logs of it."""
    dist = torch.distributions.Categorical(logits=logits, validate_args=False)  # non-finite logits: the run's guard
    newlogprob = dist.log_prob(mb["actions"])
    entropy = dist.entropy()
    logratio = newlogprob - mb["logprobs"]
    ratio = logratio.exp()
    with torch.no_grad():
        old_approx_kl = (-logratio).mean()
        approx_kl = ((ratio - 1) - logratio).mean()
        clipfrac = ((ratio - 1.0).abs() > args.clip_coef).float().mean().item()

    mb_advantages = mb["advantages"]
    if args.norm_adv:
        mb_advantages = (mb_advantages - mb_advantages.mean()) / (mb_advantages.std() + 1e-8)
    pg_loss1 = -mb_advantages * ratio
    pg_loss2 = -mb_advantages * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)
    pg_loss = torch.max(pg_loss1, pg_loss2).mean()

    if args.clip_vloss:
        v_loss_unclipped = (newvalue - mb["returns"]) ** 2
        v_clipped = mb["values"] + torch.clamp(newvalue - mb["values"], -args.clip_coef, args.clip_coef)
        v_loss_clipped = (v_clipped - mb["returns"]) ** 2
        v_loss = 0.5 * torch.max(v_loss_unclipped, v_loss_clipped).mean()
    else:
        v_loss = 0.5 * ((newvalue - mb["returns"]) ** 2).mean()

    entropy_loss = entropy.mean()
    loss = pg_loss - args.ent_coef * entropy_loss + v_loss * args.vf_coef
    return loss, {"value_loss": v_loss, "policy_loss": pg_loss, "entropy": entropy_loss, "old_approx_kl": old_approx_kl,
                  "approx_kl": approx_kl, "clipfrac": clipfrac}


def ppo_update(policy: Callable[[torch.Tensor], torch.Tensor], critic: nn.Module, optimizer: torch.optim.Optimizer,
               batch: dict[str, torch.Tensor], args: Args) -> tuple[torch.Tensor, dict[str, float]]:
    """CleanRL ppo.py's update on the flat rollout `batch`: --update-epochs epochs of shuffled minibatches, one
    gradient step each (norm clipped) on everything `optimizer` holds; stops early above --target-kl. `policy`:
    observations -> logits. Returns the last minibatch's loss and the update's scalars under CleanRL's names."""
    params = [param for group in optimizer.param_groups for param in group["params"]]
    batch_size = len(batch["obs"])
    minibatch_size = batch_size // args.num_minibatches
    b_inds = np.arange(batch_size)
    clipfracs = []
    for _epoch in range(args.update_epochs):
        np.random.shuffle(b_inds)
        for start in range(0, batch_size, minibatch_size):
            mb = {key: value[b_inds[start : start + minibatch_size]] for key, value in batch.items()}
            loss, stats = ppo_loss(policy(mb["obs"]), critic(mb["obs"]).squeeze(-1), mb, args)
            clipfracs.append(stats["clipfrac"])
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(params, args.max_grad_norm)
            optimizer.step()
        if args.target_kl is not None and stats["approx_kl"] > args.target_kl:
            break

    y_pred, y_true = batch["values"].cpu().numpy(), batch["returns"].cpu().numpy()
    var_y = np.var(y_true)
    explained_var = np.nan if var_y == 0 else 1 - np.var(y_true - y_pred) / var_y
    scalars = {"charts/learning_rate": optimizer.param_groups[0]["lr"]}
    scalars |= {f"losses/{name}": stats[name].item() for name in ("value_loss", "policy_loss", "entropy",
                                                                  "old_approx_kl", "approx_kl")}
    return loss, scalars | {"losses/clipfrac": np.mean(clipfracs), "losses/explained_variance": explained_var}


# ----------------------------------------------------------------------------------------------
# Training (Algorithm 1): a new base net every k steps, with a fresh critic, Adam and LR cycle
# ----------------------------------------------------------------------------------------------
def train(args: Args, checkpoint: dict | None = None,
          on_iteration_start: Callable[[dict], None] | None = None) -> dict:
    """Runs Cascade (from scratch, or continuing `checkpoint`); returns the final actor, critic, run folder.
    `on_iteration_start` sees the fresh state of each iteration (used by the tests)."""
    discretize, normalize = resolve(args)
    say = (lambda *_: None) if args.quiet else print
    set_threads(args.torch_threads)
    seed_everything(args.seed, args.torch_deterministic)
    device = run_device(args.cuda)

    envs = make_vector_env(args, discretize, normalize)  # their normalization statistics live through all iterations
    obs_dim = int(np.prod(envs.single_observation_space.shape))
    num_actions = int(envs.single_action_space.n)
    batch_size = args.num_envs * args.num_steps
    updates_per_iteration = args.k // batch_size
    total_updates = args.n * updates_per_iteration
    if args.k % batch_size and checkpoint is None:
        print(f"note: k={args.k} is not a multiple of the batch size {batch_size}; each iteration runs "
              f"{updates_per_iteration} updates = {updates_per_iteration * batch_size} steps")  # (with --quiet too)
    say(f"{args.env_id}: {num_actions} discrete actions"
        f"{' (discretized Box)' if discretize else ''}, normalization {'on' if normalize else 'off'}")
    run = DiscreteRun(args, checkpoint, envs, total_updates * batch_size,
                      at_iteration_end=checkpoint is not None and checkpoint["updates_done"] == updates_per_iteration)
    writer = run.writer

    actor = CascadeActor(obs_dim, num_actions, args.hidden_size, args.num_layers, args.fallback_init).to(device)
    if args.start_full:
        for _ in range(args.n):
            actor.add_base_net()
    episodes = EvaluationEpisodes(args.env_id, args.eval_episodes, args.seed, discretize) if args.eval_every else None
    eval_calls = 0 if checkpoint is None else checkpoint["eval_calls"]

    def evaluate_and_log(step: int) -> None:
        nonlocal eval_calls
        returns, fallback_std = evaluate(actor, episodes, obs_statistics(envs), eval_calls)
        eval_calls += 1
        writer.add_scalar("eval/episodic_return", returns.mean(), step)
        writer.add_scalar("eval/episodic_return_std", returns.std(), step)
        for j, std in enumerate(fallback_std.mean(0)):
            writer.add_scalar(f"cascade/fallback_std/net_{j + 2}", std, step)
        run.progress.last_eval = float(returns.mean())  # for the progress file sweep.py shows
        say(f"global_step={step}, eval/episodic_return={returns.mean():.1f} ± {returns.std():.1f}")

    # Rollout storage, preallocated once
    obs = torch.zeros((args.num_steps, args.num_envs, obs_dim), device=device)
    actions = torch.zeros((args.num_steps, args.num_envs), dtype=torch.long, device=device)
    logprobs = torch.zeros((args.num_steps, args.num_envs), device=device)
    rewards = torch.zeros((args.num_steps, args.num_envs), device=device)
    dones = torch.zeros((args.num_steps, args.num_envs), device=device)
    values = torch.zeros((args.num_steps, args.num_envs), device=device)
    step_fallbacks = torch.zeros((args.num_steps, args.num_envs, args.n - 1), device=device)
    step_contributions = torch.zeros((args.num_steps, args.num_envs, args.n), device=device)

    critic: nn.Module | None = None
    optimizer: torch.optim.Optimizer | None = None

    next_obs, next_done = run.start_envs(checkpoint, device)
    if checkpoint is None:
        global_step, start_iteration, start_update = 0, 1, 1
        if episodes is not None:
            evaluate_and_log(0)
    else:
        global_step = checkpoint["global_step"]
        actor = actor_from_checkpoint(checkpoint, device)
        start_iteration, start_update = checkpoint["iteration"], checkpoint["updates_done"] + 1
        if start_update > updates_per_iteration:  # saved at the end of an iteration
            start_iteration, start_update = start_iteration + 1, 1

    if checkpoint is not None and args.start_full:
        critic = saved_critic(checkpoint, obs_dim, device)  # --start-full keeps one critic for the whole run
    for iteration in range(start_iteration, args.n + 1):
        continuing = checkpoint is not None and iteration == start_iteration and start_update > 1
        if continuing:  # resumed mid-iteration
            critic = saved_critic(checkpoint, obs_dim, device)
            optimizer = make_optimizer([*actor.parameters(), *critic.parameters()], args.learning_rate)
            checkpoints.load_optimizer(optimizer, checkpoint["optimizer"])
        else:
            # --- a new Cascade iteration: new base net, fresh critic, fresh Adam, fresh LR cycle ---
            if not args.start_full:
                actor.add_base_net()
            if args.freeze_previous:
                actor.freeze_below(actor.size - 1)
            if critic is None or not args.start_full:  # --start-full: the paper's code keeps its one critic
                critic = make_critic(obs_dim).to(device)
            optimizer = make_optimizer([*actor.parameters(), *critic.parameters()], args.learning_rate)
        size = actor.size
        params = [param for group in optimizer.param_groups for param in group["params"]]
        run.iteration_start(iteration, size, count_parameters(actor, critic), "actor + critic", global_step, continuing)
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
            for group in optimizer.param_groups:  # one group here; an edit may make more, each with its own LR
                group["lr"] = frac * group.setdefault("initial_lr", group["lr"])

            # --- rollout ---
            for step in range(args.num_steps):
                global_step += args.num_envs
                obs[step] = next_obs
                dones[step] = next_done
                with torch.inference_mode():
                    logits, fallback, contribution = actor(next_obs)
                    dist = torch.distributions.Categorical(logits=logits)
                    action = dist.sample()
                    logprobs[step] = dist.log_prob(action)
                    values[step] = critic(next_obs).squeeze(-1)
                actions[step] = action
                step_fallbacks[step, :, : size - 1] = fallback.T
                step_contributions[step, :, :size] = contribution.T

                next_obs_np, reward, terminations, truncations, infos = envs.step(action.cpu().numpy())
                rewards[step] = torch.as_tensor(reward, device=device)
                next_obs = torch.as_tensor(next_obs_np, dtype=torch.float32, device=device)
                next_done = torch.as_tensor(np.logical_or(terminations, truncations), dtype=torch.float32,
                                            device=device)
                run.episodes(infos, global_step)
                if episodes is not None and global_step % args.eval_every < args.num_envs:
                    evaluate_and_log(global_step)

            with torch.inference_mode():
                advantages, returns = compute_gae(rewards, values, dones, critic(next_obs).squeeze(-1), next_done,
                                                  args.gamma, args.gae_lambda)

            # --- PPO update of the whole stack and the critic ---
            batch = {"obs": obs.reshape(-1, obs_dim), "logprobs": logprobs.reshape(-1), "actions": actions.reshape(-1),
                     "advantages": advantages.reshape(-1), "returns": returns.reshape(-1), "values": values.reshape(-1)}
            loss, scalars = ppo_update(lambda x: actor(x)[0], critic, optimizer, batch, args)

            # --- logging: CleanRL's names, and the fallbacks of Section 4.5 (Fig. 6, Table 1) ---
            # means over the rollout batch, of the lambdas/weights the acting policy used
            mean_fallback = step_fallbacks[:, :, : size - 1].mean((0, 1))
            mean_weight = step_contributions[:, :, :size].mean((0, 1))
            for j, lam in enumerate(mean_fallback.tolist()):
                scalars[f"cascade/fallback/net_{j + 2}"] = lam
            for j, w in enumerate(mean_weight.tolist()):
                scalars[f"cascade/contribution/net_{j + 1}"] = w
            scalars["cascade/fallback_product"] = mean_weight[0].item()
            scalars["cascade/size"] = size
            run.log_update(scalars, global_step, size)
            run.stop_if_not_finite(loss, params, global_step, f"iteration {iteration}, update {update}")

            end_of_iteration = update == updates_per_iteration
            if end_of_iteration and iteration == args.n and episodes is not None and \
                    global_step % args.eval_every >= args.num_envs:
                # the final policy, if the last step was not an eval step: logged before the final checkpoint,
                # so that a stop right after it loses nothing
                evaluate_and_log(global_step)
            if end_of_iteration or run.checkpoint_due(global_step):  # at an iteration's end also iteration_<i>.pt
                run.save_state(CHECKPOINT_FORMAT, global_step, next_obs, next_done, eval_calls,
                               learner_state(actor, critic, optimizer, iteration, update, obs_dim, num_actions,
                                             discretize), iteration if end_of_iteration else None)

        say(f"iteration {iteration} done: global_step={global_step}, SPS={int(run.sps(global_step))}")

    run.close(global_step, episodes)
    return {"actor": actor, "critic": critic, "run_dir": run.run_dir, "global_step": global_step}


# ----------------------------------------------------------------------------------------------
# Evaluation (Appendix B.5): every --eval-every steps, --eval-episodes episodes of the frozen policy
# ----------------------------------------------------------------------------------------------
def evaluate(actor: CascadeActor, episodes: EvaluationEpisodes, stats: tuple[np.ndarray, np.ndarray] | None,
             call: int = 0, deterministic: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The policy training acts with, frozen with its observation statistics `stats`, for one episode on each of
    the separate envs of `episodes`; actions are sampled from Categorical(C_n(x)) as in training (the argmax with
    `deterministic`). Returns each episode's undiscounted raw return (the paper's score is their mean) and how
    much each fallback varies within it: its std over the episode's steps, [episodes, n-1]."""

    device = next(actor.parameters()).device  # the GPU in a --cuda run

    def logits_and_fallbacks(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits, fallback, _ = actor(x.to(device))
        return logits, fallback.T

    returns, fallbacks = episodes.run(logits_and_fallbacks, stats, call, deterministic)
    return returns, np.stack([np.stack(f).std(0) for f in fallbacks])


# ----------------------------------------------------------------------------------------------
# Wiring to cascade_plumbing: the settings, the checkpoint, the command line
# ----------------------------------------------------------------------------------------------
CHECKPOINT_FORMAT = "cascade_ppo_discrete/1"


def resolve(args: Args) -> tuple[bool, bool]:
    """Probe the env and reject bad input with one clear line before anything is created.
    Returns (discretize, normalize) as they apply to this env."""
    check_common_settings(args)
    batch_size = check_ppo_settings(args)
    if args.n < 1:
        fail(f"--n must be at least 1 (got {args.n})")
    if not 0.0 < args.fallback_init < 1.0:
        fail(f"--fallback-init must lie strictly between 0 and 1 (got {args.fallback_init})")
    if args.hidden_size < 1 or args.num_layers < 1:
        fail("--hidden-size and --num-layers must be at least 1")
    if args.k < batch_size:
        fail(f"--k {args.k} is smaller than one rollout batch (num_envs*num_steps = {batch_size}); raise --k")
    if args.freeze_previous and args.start_full:
        fail("--freeze-previous and --start-full cannot be combined (no such ablation in the paper)")
    return resolve_env(args, continuous_script="cascade_ppo_continuous.py")


def learner_state(actor: CascadeActor, critic: nn.Module, optimizer: torch.optim.Optimizer, iteration: int,
                  updates_done: int, obs_dim: int, num_actions: int, discretize: bool) -> dict:
    """What a checkpoint holds of the learner (the run's state beside it: `DiscreteRun.save_state`)."""
    return {"obs_dim": obs_dim, "num_actions": num_actions, "discretize": discretize,
            "iteration": iteration, "updates_done": updates_done, "actor": actor.state_dict(), "actor_size": actor.size,
            "num_frozen": actor.num_frozen, "critic": critic.state_dict(), "optimizer": optimizer.state_dict()}


def load_checkpoint(path: str, reader_flag: str = "") -> dict:
    """`runs/<run>` (its latest checkpoint) or a checkpoint file of this script; one-line error otherwise."""
    return checkpoints.load_checkpoint(path, CHECKPOINT_FORMAT, reader_flag=reader_flag)


def finished(args: Args, checkpoint: dict) -> bool:
    """Whether `checkpoint` is the end of its run (resuming it has nothing left to do)."""
    return checkpoint["iteration"] == args.n and checkpoint["updates_done"] == args.k // (args.num_envs * args.num_steps)


def actor_from_checkpoint(checkpoint: dict, device: str | torch.device = "cpu") -> CascadeActor:
    saved = Args(**checkpoint["args"])
    rng = torch.get_rng_state()  # building the nets draws random inits; keep the caller's RNG untouched
    actor = CascadeActor(checkpoint["obs_dim"], checkpoint["num_actions"], saved.hidden_size, saved.num_layers,
                         saved.fallback_init)
    for _ in range(checkpoint["actor_size"]):
        actor.add_base_net()
    torch.set_rng_state(rng)
    actor.load_state_dict(checkpoint["actor"])
    actor.num_frozen = checkpoint["num_frozen"]  # as saved: through an edited freeze_below it would change twice
    return actor.to(device)


def saved_critic(checkpoint: dict, obs_dim: int, device: torch.device) -> nn.Module:
    rng = torch.get_rng_state()  # the critic's init draws must not shift the restored RNG stream
    critic = make_critic(obs_dim).to(device)
    torch.set_rng_state(rng)
    critic.load_state_dict(checkpoint["critic"])
    return critic


def evaluate_saved(args: Args) -> np.ndarray:
    """--evaluate: the saved policy with its saved observation statistics frozen."""

    def saved_policy(checkpoint: dict, episodes: EvaluationEpisodes) -> tuple[np.ndarray, str]:
        actor = actor_from_checkpoint(checkpoint)
        returns, _ = evaluate(actor, episodes, checkpoint["obs_stats"], 0, args.deterministic)
        return returns, f"{actor.size} base net(s)"

    return evaluate_saved_model(args, load_checkpoint, saved_policy)


def main() -> None:
    run_main(Args, train, evaluate_saved, load_checkpoint, finished, description=__doc__.split("\n\n")[0])


if __name__ == "__main__":
    main()
