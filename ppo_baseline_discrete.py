"""PPO for discrete-action tasks, the discrete baseline of the Cascade paper (single-file, CleanRL style).

Equivalent to CleanRL's `ppo.py` (same 64-64 actor and critic, same hyperparameters) on gymnasium 1.x.
Box action spaces of A dims are discretized into the 2^A corners of the box (paper Appendix I), which
gives the "discrete PPO" of the paper's Fig. 16; natively discrete envs such as CartPole-v1 are used
as they are. Discretized Box tasks get observation/reward normalization and +-10 clipping by default, as the
paper's code ran Fig. 16 (`--no-normalize`: clipping only). Extra flags shared with `ppo_baseline.py`:
`--hidden-size`, `--lr-schedule`, `--no-normalize`.
Paper: Schmöcker & Dockhorn, "Cascade - A sequential ensemble method for continuous control tasks",
RLJ 2025: discrete PPO and the discretization, Appendix I; the evaluation protocol, Appendix B.5.

Reading order: `Args`, the agent, the loss, `train`, its evaluation, and last the few lines that wire it to
`cascade_plumbing` (the env stack, run folder, checkpoints and command line every script shares).

    python ppo_baseline_discrete.py --env-id Hopper-v4 --total-timesteps 10000000
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
from cascade_plumbing.envs import obs_statistics
from cascade_plumbing.errors import fail
from cascade_plumbing.ppo import baseline_updates, check_ppo_settings
from cascade_plumbing.runs import asked_for, check_common_settings, run_device, run_main, seed_everything, set_threads

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

    # Network and schedule
    total_timesteps: int = 10_000_000
    """total environment steps of the run (paper Fig. 16: 10M)"""
    hidden_size: int = 64
    """width of the two hidden layers of the actor (the critic stays 64-64)"""
    lr_schedule: Literal["global", "cyclic", "constant"] = "global"
    """global: linear decay to 0 over the run (CleanRL); cyclic: decay restarts every --cycle-steps, with a fresh Adam at each restart (as ppo_baseline.py and the paper's code); constant: no decay"""
    cycle_steps: int = 1_000_000
    """length of one learning-rate cycle in env steps, with --lr-schedule cyclic (a cycle is cycle_steps // batch updates, as a Cascade iteration; the run is whole cycles, then the rest)"""

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
    """checkpoint every this many env steps, and at the end of the run (0: at the end only)"""
    resume: str | None = None
    """continue a killed run: `runs/<run_name>` or a checkpoint file; the saved settings are used"""
    evaluate: str | None = None
    """evaluate a saved model (`runs/<run_name>` or a checkpoint file) for --eval-episodes episodes and exit"""
    deterministic: bool = False
    """with --evaluate: act with the most probable (argmax) action instead of sampling"""
    quiet: bool = False
    """print nothing while training (errors still go to stderr); sweep.py passes it"""


# ----------------------------------------------------------------------------------------------
# The agent (CleanRL ppo.py): a 64-64 tanh actor whose outputs are the logits of a Categorical policy
# ----------------------------------------------------------------------------------------------
def layer_init(in_features: int, out_features: int, gain: float) -> nn.Linear:
    linear = nn.Linear(in_features, out_features)
    nn.init.orthogonal_(linear.weight, gain)
    nn.init.zeros_(linear.bias)
    return linear


def make_actor(obs_dim: int, num_actions: int, hidden_size: int) -> nn.Sequential:
    """Categorical policy logits, obs -> H -> H -> K (tanh); output gain 0.01 as CleanRL ppo.py."""
    return nn.Sequential(
        layer_init(obs_dim, hidden_size, math.sqrt(2)), nn.Tanh(),
        layer_init(hidden_size, hidden_size, math.sqrt(2)), nn.Tanh(),
        layer_init(hidden_size, num_actions, 0.01),
    )


def make_critic(obs_dim: int) -> nn.Sequential:
    """The PPO value net, obs -> 64 -> 64 -> 1 (tanh)."""
    return nn.Sequential(
        layer_init(obs_dim, 64, math.sqrt(2)), nn.Tanh(),
        layer_init(64, 64, math.sqrt(2)), nn.Tanh(),
        layer_init(64, 1, 1.0),
    )


def count_parameters(*modules: nn.Module) -> int:
    return sum(p.numel() for m in modules for p in m.parameters())




def make_optimizer(params: list[nn.Parameter], learning_rate: float) -> torch.optim.Adam:
    return torch.optim.Adam(params, lr=learning_rate, eps=1e-5)


# ----------------------------------------------------------------------------------------------
# The loss: PPO as CleanRL ppo.py runs it (Appendix I)
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
# Training: CleanRL ppo.py's loop (rollout, GAE, update), with the learning-rate schedules of ppo_baseline.py
# ----------------------------------------------------------------------------------------------
def train(args: Args, checkpoint: dict | None = None) -> dict:
    """Runs PPO (from scratch, or continuing `checkpoint`); returns the final actor, critic and run folder."""
    discretize, normalize = resolve(args, new_run=checkpoint is None)
    say = (lambda *_: None) if args.quiet else print
    set_threads(args.torch_threads)
    seed_everything(args.seed, args.torch_deterministic)
    device = run_device(args.cuda)

    envs = make_vector_env(args, discretize, normalize)
    obs_dim = int(np.prod(envs.single_observation_space.shape))
    num_actions = int(envs.single_action_space.n)
    batch_size = args.num_envs * args.num_steps
    total_updates = baseline_updates(args, batch_size)  # (under a cyclic LR: whole cycles, then the rest)
    updates_per_cycle = max(args.cycle_steps // batch_size, 1)
    if total_updates * batch_size != args.total_timesteps and checkpoint is None:
        cycles = f" or of --cycle-steps {args.cycle_steps}" if args.lr_schedule == "cyclic" else ""
        print(f"note: total_timesteps={args.total_timesteps} is not a multiple of the batch size {batch_size}{cycles}; "
              f"the run does {total_updates} updates = {total_updates * batch_size} steps")  # (with --quiet too)
    say(f"{args.env_id}: {num_actions} discrete actions"
        f"{' (discretized Box)' if discretize else ''}, normalization {'on' if normalize else 'off'}")
    run = DiscreteRun(args, checkpoint, envs, total_updates * batch_size)

    actor = make_actor(obs_dim, num_actions, args.hidden_size).to(device)
    critic = make_critic(obs_dim).to(device)
    optimizer = make_optimizer([*actor.parameters(), *critic.parameters()], args.learning_rate)
    params = [param for group in optimizer.param_groups for param in group["params"]]
    n_params = count_parameters(actor, critic)
    say(f"PPO: {n_params} parameters (actor + critic)")
    episodes = EvaluationEpisodes(args.env_id, args.eval_episodes, args.seed, discretize) if args.eval_every else None
    eval_calls = 0 if checkpoint is None else checkpoint["eval_calls"]

    def evaluate_and_log(step: int) -> None:
        nonlocal eval_calls
        returns = evaluate(actor, episodes, obs_statistics(envs), eval_calls)
        eval_calls += 1
        run.writer.add_scalar("eval/episodic_return", returns.mean(), step)
        run.writer.add_scalar("eval/episodic_return_std", returns.std(), step)
        run.progress.last_eval = float(returns.mean())  # for the progress file sweep.py shows
        say(f"global_step={step}, eval/episodic_return={returns.mean():.1f} ± {returns.std():.1f}")

    # Rollout storage, preallocated once
    obs = torch.zeros((args.num_steps, args.num_envs, obs_dim), device=device)
    actions = torch.zeros((args.num_steps, args.num_envs), dtype=torch.long, device=device)
    logprobs = torch.zeros((args.num_steps, args.num_envs), device=device)
    rewards = torch.zeros((args.num_steps, args.num_envs), device=device)
    dones = torch.zeros((args.num_steps, args.num_envs), device=device)
    values = torch.zeros((args.num_steps, args.num_envs), device=device)

    next_obs, next_done = run.start_envs(checkpoint, device)
    if checkpoint is None:
        global_step, start_update = 0, 1
        if episodes is not None:
            evaluate_and_log(0)
        run.writer.add_scalar("charts/parameters", n_params, global_step)
    else:
        global_step, start_update = checkpoint["global_step"], checkpoint["updates_done"] + 1
        actor.load_state_dict(checkpoint["actor"])
        critic.load_state_dict(checkpoint["critic"])
        checkpoints.load_optimizer(optimizer, checkpoint["optimizer"])

    for update in range(start_update, total_updates + 1):
        if args.lr_schedule == "global":
            frac = 1.0 - (update - 1.0) / total_updates
        elif args.lr_schedule == "cyclic":
            frac = 1.0 - ((update - 1) % updates_per_cycle) / updates_per_cycle
            if update > 1 and (update - 1) % updates_per_cycle == 0:  # a new cycle: fresh Adam moments (as ppo_baseline.py)
                optimizer = make_optimizer([*actor.parameters(), *critic.parameters()], args.learning_rate)
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
                dist = torch.distributions.Categorical(logits=actor(next_obs))
                action = dist.sample()
                logprobs[step] = dist.log_prob(action)
                values[step] = critic(next_obs).squeeze(-1)
            actions[step] = action

            next_obs_np, reward, terminations, truncations, infos = envs.step(action.cpu().numpy())
            rewards[step] = torch.as_tensor(reward, device=device)
            next_obs = torch.as_tensor(next_obs_np, dtype=torch.float32, device=device)
            next_done = torch.as_tensor(np.logical_or(terminations, truncations), dtype=torch.float32, device=device)
            run.episodes(infos, global_step)
            if episodes is not None and global_step % args.eval_every < args.num_envs:
                evaluate_and_log(global_step)

        with torch.inference_mode():
            advantages, returns = compute_gae(rewards, values, dones, critic(next_obs).squeeze(-1), next_done,
                                              args.gamma, args.gae_lambda)

        # --- PPO update ---
        batch = {"obs": obs.reshape(-1, obs_dim), "logprobs": logprobs.reshape(-1), "actions": actions.reshape(-1),
                 "advantages": advantages.reshape(-1), "returns": returns.reshape(-1), "values": values.reshape(-1)}
        loss, scalars = ppo_update(actor, critic, optimizer, batch, args)
        run.log_update(scalars, global_step, 1)  # CleanRL's names
        run.stop_if_not_finite(loss, params, global_step, f"update {update}")
        if update == total_updates and episodes is not None and global_step % args.eval_every >= args.num_envs:
            # the final policy, if the last step was not an eval step: logged before the final checkpoint, so that
            # a stop right after it loses nothing
            evaluate_and_log(global_step)
        if update == total_updates or run.checkpoint_due(global_step):
            run.save_state(CHECKPOINT_FORMAT, global_step, next_obs, next_done, eval_calls,
                           learner_state(actor, critic, optimizer, update, obs_dim, num_actions, discretize))

    run.close(global_step, episodes)
    return {"actor": actor, "critic": critic, "run_dir": run.run_dir, "global_step": global_step}


# ----------------------------------------------------------------------------------------------
# Evaluation (Appendix B.5): every --eval-every steps, --eval-episodes episodes of the frozen policy
# ----------------------------------------------------------------------------------------------
def evaluate(actor: nn.Module, episodes: EvaluationEpisodes, stats: tuple[np.ndarray, np.ndarray] | None,
             call: int = 0, deterministic: bool = False) -> np.ndarray:
    """The policy training acts with, frozen with its observation statistics `stats`, for one episode on each of
    the separate envs of `episodes`; actions are sampled from Categorical(logits) as in training (the argmax with
    `deterministic`). Returns each episode's undiscounted raw return (the paper's score is their mean)."""
    device = next(actor.parameters()).device  # the GPU in a --cuda run
    returns, _ = episodes.run(lambda x: (actor(x.to(device)), None), stats, call, deterministic)
    return returns


# ----------------------------------------------------------------------------------------------
# Wiring to cascade_plumbing: the settings, the checkpoint, the command line
# ----------------------------------------------------------------------------------------------
CHECKPOINT_FORMAT = "ppo_baseline_discrete/1"


def resolve(args: Args, new_run: bool = True) -> tuple[bool, bool]:
    """Probe the env and reject bad input with one clear line before anything is created.
    Returns (discretize, normalize) as they apply to this env."""
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
    return resolve_env(args, continuous_script="ppo_baseline.py")


def learner_state(actor: nn.Module, critic: nn.Module, optimizer: torch.optim.Optimizer, updates_done: int,
                  obs_dim: int, num_actions: int, discretize: bool) -> dict:
    """What a checkpoint holds of the learner (the run's state beside it: `DiscreteRun.save_state`)."""
    return {"obs_dim": obs_dim, "num_actions": num_actions, "discretize": discretize,
            "updates_done": updates_done, "actor": actor.state_dict(), "critic": critic.state_dict(),
            "optimizer": optimizer.state_dict()}


def load_checkpoint(path: str, reader_flag: str = "") -> dict:
    """`runs/<run>` (its latest checkpoint) or a checkpoint file of this script; one-line error otherwise."""
    return checkpoints.load_checkpoint(path, CHECKPOINT_FORMAT, reader_flag=reader_flag)


def finished(args: Args, checkpoint: dict) -> bool:
    """Whether `checkpoint` is the end of its run (resuming it has nothing left to do)."""
    # (>=: a cyclic run finished before its budget was counted in whole cycles made one update more)
    return checkpoint["updates_done"] >= baseline_updates(args, args.num_envs * args.num_steps)


def actor_from_checkpoint(checkpoint: dict, device: str | torch.device = "cpu") -> nn.Sequential:
    saved = Args(**checkpoint["args"])
    rng = torch.get_rng_state()  # building the net draws random inits; keep the caller's RNG untouched
    actor = make_actor(checkpoint["obs_dim"], checkpoint["num_actions"], saved.hidden_size)
    torch.set_rng_state(rng)
    actor.load_state_dict(checkpoint["actor"])
    return actor.to(device)


def evaluate_saved(args: Args) -> np.ndarray:
    """--evaluate: the saved policy with its saved observation statistics frozen."""

    def saved_policy(checkpoint: dict, episodes: EvaluationEpisodes) -> tuple[np.ndarray, str]:
        actor = actor_from_checkpoint(checkpoint)
        return evaluate(actor, episodes, checkpoint["obs_stats"], 0, args.deterministic), "PPO"

    return evaluate_saved_model(args, load_checkpoint, saved_policy)


def main() -> None:
    run_main(Args, train, evaluate_saved, load_checkpoint, finished, description=__doc__.split("\n\n")[0])


if __name__ == "__main__":
    main()
