"""What the off-policy scripts (cascade_sac.py, cascade_ddpg.py) share and is not their algorithm: `minimize` (one
optimizer step, as zero_grad/backward/step with less overhead), the checks of
the settings they both have, the evaluation episodes, --evaluate of a saved model, and a run's bookkeeping
(`OffPolicyRun`, on `record.RunRecord`: env steps into the replay buffer, the logs, evaluations, the non-finite
guard, the checkpoints, with the replay buffer, and resuming from them exactly).

What is evaluated, how often and on how many episodes, like the nets, the losses and the training loop, is the
script's."""

from __future__ import annotations

import math
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn

from .checkpoints import non_finite_advice
from .envs import check_box_env
from .errors import fail
from .evaluation import EvaluationEnvs, open_saved_model, save_video_of_one_episode
from .fast import plain_fused_adam
from .record import RunRecord
from .replay import ReplayBuffer, ReplayFiles, available_memory, buffer_capacity, store_transition
from .runs import CHECKPOINT_ON_STOP, STOP_REQUESTED, drop_stop_requests, forget_stops, stop_after_checkpoint
from .tracking import log_new_videos


def minimize(optimizer: torch.optim.Optimizer, loss: torch.Tensor) -> None:
    """`optimizer.zero_grad(); loss.backward(); optimizer.step()`, with less overhead, still plain autograd:
    torch.autograd.grad computes the gradients of exactly the optimizer's parameters (no other weight gradient,
    e.g. none of the critics' in the actor loss), and `step_with_gradients` applies them. No `.grad` is left behind
    (the kernel call never sets it), so a `clip_grad_norm_` or a gradient-norm log after it sees nothing: to clip or
    log gradients, write CleanRL's three lines in the update instead."""
    params = [param for each in optimizer.param_groups for param in each["params"]]  # every group's (a hacker's)
    step_with_gradients(optimizer, params, list(torch.autograd.grad(loss, params, materialize_grads=True)))


def step_with_gradients(optimizer: torch.optim.Optimizer, params: list[torch.Tensor],
                        grads: list[torch.Tensor]) -> None:
    """`optimizer.step()` with `grads` as the gradients of `params` (all of the optimizer's, in its order): for
    torch's fused Adam, a direct call of the kernel that step() ends in (step() spends longer grouping and checking
    than the kernel takes). Any other optimizer (AdamW, amsgrad, several parameter groups...), and Adam's first
    step (it creates the state), take the plain path; the optimizer's state, and so the checkpoints, are as step()
    leaves them (tests/test_sac_ddpg_updates.py checks it bit for bit)."""
    group = optimizer.param_groups[0]
    states = [optimizer.state.get(p) for p in params]
    if all(states) and plain_fused_adam(optimizer):  # not AdamW, amsgrad, a subclass of Adam...: their step()
        steps = [state["step"] for state in states]
        torch._foreach_add_(steps, 1)  # as step() does before the kernel
        beta1, beta2 = group["betas"]
        torch._fused_adam_(params, grads, [state["exp_avg"] for state in states],
                           [state["exp_avg_sq"] for state in states], [], steps, amsgrad=False, lr=group["lr"],
                           beta1=beta1, beta2=beta2, weight_decay=group["weight_decay"], eps=group["eps"],
                           maximize=False)
        return
    for param, grad in zip(params, grads):
        param.grad = grad
    optimizer.step()
    for param in params:
        param.grad = None


def check_replay_settings(args: Any, bounds_needed_because: str, frequencies: dict[str, str],
                          new_run: bool = True) -> None:
    """The settings both off-policy scripts have, checked after the script's own: the clipping, the warm-up and the
    update `frequencies` (flag -> what it paces), the replay buffer (and its memory), the evaluation, the env (a
    bounded Box action space, flat observations). One line each, before anything is created (`RunRecord` checks the
    renderer of --capture-video)."""
    if not args.obs_reward_clip >= 0:
        fail(f"--obs-reward-clip must be >= 0 (0: no clipping; got {args.obs_reward_clip})")
    if args.batch_size < 1 or args.learning_starts < 0:
        fail("--batch-size must be at least 1 and --learning-starts at least 0")
    # an iteration updates at its steps first .. k - 1: after learning_starts + 1 stored transitions of its own
    # (CleanRL's `global_step > learning_starts`, restarted per net), or of the whole run with --no-restart-on-new-net
    first = args.learning_starts + (1 if getattr(args, "restart_on_new_net", True) else 0)
    if args.k - 1 < first:
        fail(f"--k {args.k} must exceed --learning-starts {args.learning_starts}"
             f"{' + 1' if first > args.learning_starts else ''} (the buffer is first filled with learning-starts "
             "steps before updates start, so a shorter iteration never updates)")
    for flag, paced in frequencies.items():
        value = getattr(args, flag.lstrip("-").replace("-", "_"))
        if (args.k - 1) // value * value < first:  # an update runs at the steps that are multiples of it
            fail(f"{flag} {value}: no update step of an iteration ({first:,} to {args.k - 1:,}) is a multiple of it, "
                 f"so {paced} would never run; pass one up to {args.k - first:,} (each has a multiple there)")
    if args.buffer_size < max(args.batch_size, args.learning_starts + 1):
        fail(f"--buffer-size {args.buffer_size} must hold at least --batch-size and --learning-starts + 1 rows")
    capacity = buffer_capacity(args.buffer_size, args.n, args.k, args.keep_buffer)
    if new_run and args.batch_size > capacity:  # (a run started before this check resumes)
        held = "n x k steps of the run" if args.keep_buffer else "the k steps between its emptyings at each new net"
        fail(f"--batch-size {args.batch_size} exceeds the {capacity:,} rows the replay buffer can ever hold ({held}), "
             "so every batch would repeat rows; pass a smaller --batch-size or a larger --k")
    if not 0.0 < args.tau <= 1.0:
        fail(f"--tau must lie in (0, 1] (got {args.tau})")
    if args.eval_every < 0 or args.eval_episodes < 1:  # (also with --eval-every 0: a negative count is no setting)
        fail("--eval-every must be >= 0 and --eval-episodes >= 1")
    action_space, observation_space = check_box_env(args.env_id, "cascade_ppo_discrete.py", "Hopper-v4, Ant-v5")
    if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
        fail(f"{args.env_id} has unbounded actions; {bounds_needed_because}")
    rows = buffer_capacity(args.buffer_size, args.n, args.k, args.keep_buffer)
    need = ReplayBuffer.nbytes(rows, observation_space.shape[0], int(np.prod(action_space.shape)))
    free = available_memory()
    if free is not None and need > free:
        fail(f"the replay buffer needs {need / 1e9:.2f} GB ({rows} rows) but only {free / 1e9:.2f} GB is available; "
             "lower --buffer-size")


# ----------------------------------------------------------------------------------------------
# Evaluation episodes: a frozen policy on separate envs, with their own seeds and RNG
# ----------------------------------------------------------------------------------------------
Policy = Callable[[torch.Tensor, torch.Generator], tuple[torch.Tensor, torch.Tensor]]


class Evaluator(EvaluationEnvs):
    """Runs `episodes` episodes side by side on its own envs (`EvaluationEnvs`); never touches the training envs
    or RNG. `obs_clip`: the clipping of the observations the policy sees, as in training (0: none)."""

    def __init__(self, env_id: str, episodes: int, seed: int, obs_clip: float, render: bool = False):
        super().__init__(env_id, episodes, seed, render=render)
        self.obs_clip = obs_clip

    @torch.inference_mode()
    def __call__(self, policy: Policy, call: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Runs `policy` (obs, generator -> action in bounds, fallbacks [m, B]); returns each episode's
        undiscounted return and the std of each fallback within each episode [episodes, m]. The episodes'
        seeds and the action noise depend only on (seed, call)."""
        base_seed = self.base_seed(call)
        generator = torch.Generator().manual_seed(base_seed)
        fallbacks: list[list[np.ndarray]] = [[] for _ in self.envs]

        def act(raw_obs: np.ndarray, running: list[int]) -> np.ndarray:
            seen = np.clip(raw_obs, -self.obs_clip, self.obs_clip) if self.obs_clip else raw_obs  # as in training
            action, fallback = policy(torch.as_tensor(seen, dtype=torch.float32), generator)
            for row, i in enumerate(running):
                fallbacks[i].append(fallback[:, row].numpy())
            return action.numpy()  # clipped to the bounds there: float32 rounding of scale*tanh+bias

        returns = self.run_episodes(act, base_seed)
        return returns, np.stack([np.stack(f).std(0) for f in fallbacks])


def evaluate_saved_policy(args: Any, load_checkpoint: Callable[[str], dict],
                          policies: Callable[[dict], tuple[Policy, list[Policy]]], mode: str) -> dict:
    """--evaluate: the policy of the saved model at `args.evaluate` (and with --members each net alone:
    `policies(checkpoint)` gives both) on --eval-episodes fresh episodes; prints the returns and gives them back.
    `mode` names how actions are chosen. With --capture-video, an mp4 of one more episode beside the checkpoint."""
    checkpoint = open_saved_model(args, load_checkpoint)
    saved = checkpoint["args"]
    full, members = policies(checkpoint)
    evaluator = Evaluator(saved["env_id"], args.eval_episodes, args.seed, saved["obs_reward_clip"])
    returns, _ = evaluator(full)
    print(f"{saved['env_id']}, {len(members)} base net(s), step {checkpoint['global_step']}: "
          f"return {returns.mean():.1f} ± {returns.std():.1f} over {len(returns)} {mode} episodes")
    result = {"returns": returns, "members": []}
    if args.members:
        for net, policy in enumerate(members):
            member_returns, _ = evaluator(policy)
            result["members"].append(member_returns)
            print(f"  net {net + 1} alone: {member_returns.mean():.1f} ± {member_returns.std():.1f}")
    evaluator.close()
    if args.capture_video:
        save_video_of_one_episode(checkpoint["path"], mode,
                                  Evaluator(saved["env_id"], 1, args.seed, saved["obs_reward_clip"], render=True),
                                  lambda video: video(full)[0][0])
    return result


# ----------------------------------------------------------------------------------------------
# A run's bookkeeping
# ----------------------------------------------------------------------------------------------
class OffPolicyRun(RunRecord):
    """Everything an off-policy `train` records about a run and restores when it is resumed; no algorithm here.

    Beside the run folder of `RunRecord` (TensorBoard `writer`, W&B, videos, progress, `checkpoint_path`), it
    steps the training env (`next_obs` is the observation the next action is chosen for) into the replay
    buffer, runs the evaluations the script asks for, and writes the checkpoints the script asks for (at the end of
    every iteration and every --checkpoint-every steps): with the replay buffer's rows (`ReplayFiles`, in the run
    folder's replay/), the RNG streams and the env's state, so that a resumed run continues exactly."""

    def __init__(self, args: Any, checkpoint: dict | None, envs: gym.vector.VectorEnv, checkpoint_format: str,
                 rates: str):
        """`envs`: the training env, one env with SAME_STEP autoreset; `rates`: the script's learning-rate flags,
        named by the non-finite guard."""
        # a checkpoint from the middle of an iteration is not that iteration's end: its iteration_<i>.pt is not
        # rebuilt from it (the run writes that file when it gets there)
        super().__init__(args, checkpoint, envs, total_steps=args.n * args.k,
                         at_iteration_end=checkpoint is not None and checkpoint["steps_done"] == args.k)
        self.checkpoint_format, self.rates = checkpoint_format, rates
        self.obs_dim = int(np.prod(envs.single_observation_space.shape))
        self.act_dim = int(np.prod(envs.single_action_space.shape))
        self.action_low, self.action_high = envs.single_action_space.low, envs.single_action_space.high
        self.evaluator = None
        if args.eval_every:
            self.evaluator = Evaluator(args.env_id, args.eval_episodes, args.seed, args.obs_reward_clip)
        self.eval_calls = 0
        self.next_obs: np.ndarray | None = None
        self.replay: ReplayFiles | None = None  # the replay buffer's rows on disk (made with the buffer's first save)
        forget_stops()  # (what a run before it in this process left: this one has taken no step yet)

    # --- the start of a run, or where a resumed one continues ---
    def start(self) -> tuple[int, int, int]:
        """A new run: the seeded env's first observation; returns (global_step, iteration, steps of it done) =
        (0, 1, 0)."""
        self.start_time = time.time()
        self.next_obs, _ = self.envs.reset(seed=self.args.seed)
        self.envs.single_action_space.seed(self.args.seed)  # the uniform random actions at the start of the run
        return 0, 1, 0

    def restore(self, checkpoint: dict, buffer: ReplayBuffer) -> tuple[int, int, int]:
        """The checkpoint's env state, next observation, RNG streams, evaluation count and, where the run goes on
        using it, replay buffer (the script restores its nets); returns (global_step, iteration, steps of it done)
        of where the run continues: (.., the next iteration, 0) after an iteration's end."""
        iteration, steps_done = checkpoint["iteration"], checkpoint["steps_done"]
        if steps_done == self.args.k:
            iteration, steps_done = iteration + 1, 0
        # a new iteration empties the buffer (unless --keep-buffer): its rows are not needed then
        needs_buffer = steps_done > 0 or self.args.keep_buffer
        note = f" (iteration {iteration}, step {steps_done} of it"
        global_step, self.next_obs = self.restore_envs(
            checkpoint, note=note + (f", {checkpoint['replay']['end'] - checkpoint['replay']['first']} replay rows)"
                                     if needs_buffer else ")"))
        # the uniform random warm-up actions of each new net come from the action space's own RNG
        self.envs.single_action_space.np_random.bit_generator.state = checkpoint["action_space_rng"]
        self.eval_calls = checkpoint["eval_calls"]
        self.replay = ReplayFiles(self.run_dir, buffer)
        if needs_buffer:
            self.replay.restore(checkpoint["replay"], checkpoint["path"], self.args.keep_buffer)
        else:  # the log goes on at the checkpoint's end, as in the run that was not stopped (its rows are not read)
            self.replay.skip_to(checkpoint["replay"]["end"])
        return global_step, iteration, steps_done

    # --- acting in the training env ---
    def random_actions(self) -> np.ndarray:
        """Uniform random actions (the warm-up), from the action space's own seeded RNG."""
        return np.array([self.envs.single_action_space.sample()])

    def step(self, actions: np.ndarray, buffer: ReplayBuffer, global_step: int) -> None:
        """One env step: the training episodes that end are logged (raw returns), the transition is stored."""
        obs = self.next_obs
        self.next_obs, rewards, terminations, _, infos = self.envs.step(actions)
        self.episodes(infos, global_step)
        if self.args.track and "final_info" in infos:  # a video ends with its episode
            log_new_videos(self.video_folder, self.videos_sent, global_step)
        store_transition(buffer, obs, actions, self.next_obs, rewards, terminations, infos)
        if not CHECKPOINT_ON_STOP:  # a step not yet in a checkpoint: a stop from now on writes one first
            CHECKPOINT_ON_STOP.append(True)

    def checkpoint_due(self, global_step: int) -> bool:
        """Every --checkpoint-every steps, and at the step after a stop (which then ends the run)."""
        return bool(STOP_REQUESTED) or super().checkpoint_due(global_step)

    # --- logging ---
    def tick(self, global_step: int, size: int) -> None:
        """Every 100 steps: the steps per second, and the progress line."""
        if global_step % 100 == 0:
            super().tick(global_step, size)

    def guard_non_finite(self, modules: list[nn.Module], global_step: int, iteration: int,
                         losses: list[float] | None = None) -> None:
        """The non-finite guard: stop in one line before a non-finite loss or parameter reaches a checkpoint."""
        if (losses is None or all(map(math.isfinite, losses))) and all(
            torch.isfinite(p).all() for module in modules for p in module.parameters()
        ):
            return
        self.writer.close()
        what = "parameters" if losses is None else "loss or parameters"
        fail(f"non-finite {what} at global_step={global_step} (iteration {iteration}); "
             f"{non_finite_advice(self.checkpoint_path, self.rates)}")

    # --- evaluation: the script says what is evaluated, and when ---
    def evaluate(self, step: int, policy: Policy) -> None:
        """The whole cascade's frozen policy on the evaluation envs."""
        returns, fallback_std = self.evaluator(policy, self.eval_calls)
        self.eval_calls += 1
        self.writer.add_scalar("eval/episodic_return", returns.mean(), step)
        self.writer.add_scalar("eval/episodic_return_std", returns.std(), step)
        for j, std in enumerate(fallback_std.mean(0)):
            self.writer.add_scalar(f"cascade/fallback_std/net_{j + 2}", std, step)
        self.progress.last_eval = float(returns.mean())
        self.progress.message(f"global_step={step}, eval/episodic_return={returns.mean():.1f} ± {returns.std():.1f}")

    def evaluate_members(self, step: int, policies: list[Policy]) -> None:
        """Each net acting alone (`members/return/net_i`)."""
        for net, policy in enumerate(policies, start=1):
            returns, _ = self.evaluator(policy, self.eval_calls)
            self.eval_calls += 1
            self.writer.add_scalar(f"members/return/net_{net}", returns.mean(), step)
            self.progress.message(f"global_step={step}, members/return/net_{net}={returns.mean():.1f}")

    # --- the end of an iteration, and of the run ---
    def save_progress(self, iteration: int, steps_done: int, global_step: int, nets: dict,
                      buffer: ReplayBuffer) -> None:
        """The atomic checkpoint after `steps_done` steps of `iteration` (all --k of them: its end, also kept as
        iteration_<i>.pt): the script's `nets` (its nets, optimizers and whatever else it trains and keeps), the run's
        state and the replay buffer's rows (written to replay/ first; the checkpoint records which)."""
        if self.replay is None or self.replay.buffer is not buffer:
            self.replay = ReplayFiles(self.run_dir, buffer)
        replay = self.replay.save()
        payload = {
            "format": self.checkpoint_format, "args": asdict(self.args), "obs_dim": self.obs_dim,
            "act_dim": self.act_dim, "action_low": self.action_low, "action_high": self.action_high,
            "iteration": iteration, "steps_done": steps_done, **nets, "next_obs": self.next_obs.copy(),
            "action_space_rng": self.envs.single_action_space.np_random.bit_generator.state,
            "eval_calls": self.eval_calls, "replay": replay,
        }
        end = steps_done == self.args.k
        self.save(payload, global_step, iteration_end=iteration if end else None)
        self.replay.prune(replay)
        if not (end and iteration == self.args.n):
            stop_after_checkpoint(global_step)
        elif STOP_REQUESTED:  # a stop after the last step (during the last evaluations): the run is complete now
            print(f"\r{signal.Signals(STOP_REQUESTED[-1]).name} after the run's last step: it finished instead of "
                  "stopping (its final evaluation and checkpoint are written)", file=sys.stderr, flush=True)
        if end:
            self.progress.message(f"iteration {iteration} done: global_step={global_step}, "
                                  f"SPS={int(self.sps(global_step))}")

    def close(self, global_step: int) -> None:
        drop_stop_requests()
        if self.evaluator is not None:
            self.evaluator.close()
        self.envs.close()
        super().close(global_step)
