"""What the discrete-action scripts (cascade_ppo_discrete.py, ppo_baseline_discrete.py) share and is not the
algorithm: the discretization of a Box action space into the 2^A corners of its box (the paper's Appendix I),
their env stacks, the checks of their settings and env, their run folder (TensorBoard, W&B, videos, checkpoint,
resume), and the evaluation episodes of the paper's protocol (Appendix B.5) that their evaluations run."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from . import envs as plumbing_envs
from .checkpoints import CHECKPOINT_NAME, non_finite_advice, repair_iteration_files
from .envs import OBS_CLIP, check_env_id, make_render_env, obs_statistics
from .errors import fail
from .runs import check_common_settings, rng_states, run_name
from .tracking import finish_wandb, log_new_videos, log_training_episodes, open_run_log

MAX_DISCRETIZED_DIMS = 10  # 2^10 = 1024 actions; Humanoid's 17 dims (131072 actions) are out of scope


# ----------------------------------------------------------------------------------------------
# The discretization (Appendix I) and the env stacks
# ----------------------------------------------------------------------------------------------
def discretize_problem(space: gym.spaces.Box) -> str | None:
    """Why `space` cannot be discretized into its 2^A corners, or None if it can."""
    dims = int(np.prod(space.shape))
    if dims > MAX_DISCRETIZED_DIMS:
        return (f"a Box action space of {dims} dims would become 2^{dims} = {2**dims} discrete actions; "
                f"at most {MAX_DISCRETIZED_DIMS} dims ({2**MAX_DISCRETIZED_DIMS} actions) are supported")
    if not (np.all(np.isfinite(space.low)) and np.all(np.isfinite(space.high))):
        return "a Box action space with infinite bounds has no corners to discretize into"
    return None


class DiscretizeAction(gym.ActionWrapper):
    """Box action space of A dims -> Discrete(2^A), the discretization of the paper's Appendix I.

    Action i, with binary digits i_1 ... i_A (i_1 the most significant), is the box corner
    a_j = low_j * i_j + high_j * (1 - i_j): digit 1 picks the lower bound, digit 0 the upper one.
    """

    def __init__(self, env: gym.Env):
        super().__init__(env)
        space = env.action_space
        problem = discretize_problem(space)
        if problem is not None:
            raise ValueError(problem)
        low, high = space.low.reshape(-1), space.high.reshape(-1)
        dims = low.size
        # bits[i, j] = i_{j+1}: shift the most significant digit down first
        bits = (np.arange(2**dims)[:, None] >> np.arange(dims - 1, -1, -1)) & 1
        self.corners = (low * bits + high * (1 - bits)).astype(space.dtype).reshape(-1, *space.shape)
        self.action_space = gym.spaces.Discrete(2**dims)

    def action(self, action: int) -> np.ndarray:
        return self.corners[int(action)].copy()


def make_env(env_id: str, gamma: float, discretize: bool, normalize: bool, index: int = 0,
             video: bool = False) -> Callable[[], gym.Env]:
    """One training env of a discrete script (`envs.make_env`'s stack). A discretized Box task, as the paper's code
    ran Fig. 16: raw episode statistics, the 2^A discretization (its corners lie inside the box: no ClipAction),
    with `normalize` the observation/reward normalization of the continuous scripts, and observations and rewards
    clipped to +-10 either way. A natively discrete env, as CleanRL ppo.py: raw episode statistics only.
    `normalize` is already resolved (`resolve_env`)."""
    if not discretize:
        return plumbing_envs.make_env(env_id, index, video)
    return plumbing_envs.make_env(env_id, index, video, DiscretizeAction, normalize, gamma, OBS_CLIP)


def make_vector_env(args: Any, discretize: bool, normalize: bool) -> gym.vector.SyncVectorEnv:
    """--num-envs training envs stepped in this process (cheap envs, as CleanRL ppo.py); SAME_STEP autoreset
    as `envs.make_vector_env`: every stored transition is real."""
    return gym.vector.SyncVectorEnv(
        [make_env(args.env_id, args.gamma, discretize, normalize, i, video=args.capture_video and i == 0)
         for i in range(args.num_envs)],
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
    )


def normalize_obs(obs: np.ndarray, stats: tuple[np.ndarray, np.ndarray] | None, clip: bool) -> np.ndarray:
    """What the training wrappers do to a raw observation, with frozen statistics (None: no normalization;
    `clip`: a discretized Box task, whose raw observations are clipped too)."""
    return plumbing_envs.normalize_obs(obs, stats, OBS_CLIP if clip or stats is not None else 0)


# ----------------------------------------------------------------------------------------------
# The checks both scripts make before anything is created
# ----------------------------------------------------------------------------------------------
def check_ppo_settings(args: Any) -> int:
    """The settings both discrete PPO scripts share, refused in one line each; returns the rollout batch size."""
    check_common_settings(args)
    if not args.learning_rate >= 0:
        fail(f"--learning-rate must be >= 0 (got {args.learning_rate})")
    if args.num_minibatches < 1 or args.update_epochs < 1:
        fail(f"--num-minibatches and --update-epochs must be at least 1 (got {args.num_minibatches}, {args.update_epochs})")
    if args.num_envs < 1 or args.num_steps < 1:
        fail("--num-envs and --num-steps must be at least 1")
    batch_size = args.num_envs * args.num_steps
    if batch_size % args.num_minibatches:
        fail(f"the batch size {batch_size} is not divisible by --num-minibatches {args.num_minibatches}")
    if args.eval_every < 0 or (args.eval_every and args.eval_episodes < 1):
        fail("--eval-every must be >= 0 and --eval-episodes >= 1")
    return batch_size


def resolve_env(args: Any, continuous_script: str) -> tuple[bool, bool]:
    """Probe --env-id and refuse what a discrete script cannot run, in one line (`continuous_script`: the one to
    use instead for a Box task with --discretize off). Returns (discretize, normalize) as they apply to this env."""
    check_env_id(args.env_id, "CartPole-v1, Hopper-v4")
    probe = gym.make(args.env_id)
    action_space, observation_space = probe.action_space, probe.observation_space
    probe.close()
    if not isinstance(observation_space, gym.spaces.Box):
        fail(f"{args.env_id} has a {type(observation_space).__name__} observation space; this script needs a Box one")
    if args.capture_video:
        make_render_env(args.env_id).close()  # no renderer (OpenGL backend, pygame): one line now, not a traceback later
    if isinstance(action_space, gym.spaces.Discrete):
        if args.discretize == "on":
            fail(f"--discretize on needs a Box action space, but {args.env_id} is already discrete "
                 f"({action_space.n} actions); leave --discretize at auto")
        if action_space.start != 0:
            fail(f"{args.env_id}'s actions start at {action_space.start}; only Discrete(n) spaces starting at 0 "
                 "are supported")
        return False, False  # as CleanRL ppo.py: natively discrete envs get no normalization or clipping
    if isinstance(action_space, gym.spaces.Box):
        if args.discretize == "off":
            fail(f"{args.env_id} has a Box action space: with --discretize off this script needs a discrete env "
                 f"(use --discretize auto, or {continuous_script})")
        problem = discretize_problem(action_space)
        if problem is not None:
            fail(f"cannot discretize {args.env_id}: {problem}")
        return True, args.normalize
    fail(f"{args.env_id} has a {type(action_space).__name__} action space; this script needs a Discrete or Box one")


# ----------------------------------------------------------------------------------------------
# The run folder: TensorBoard, W&B, videos, the checkpoint and resume
# ----------------------------------------------------------------------------------------------
class RunFolder:
    """`<track-dir>/<run_name>` and what a run records there: TensorBoard (CleanRL's names; W&B mirrors it with
    --track), --capture-video's videos, the checkpoint. A resumed run continues its own folder (and W&B run)."""

    def __init__(self, args: Any, checkpoint: dict | None, envs: gym.vector.VectorEnv,
                 at_iteration_end: bool | None = None):
        """`at_iteration_end`: for a script that keeps an iteration_<i>.pt per iteration, whether `checkpoint`
        was written at the end of one (its missing or damaged iteration files are rebuilt, or named)."""
        self.args, self.envs = args, envs
        if checkpoint is None:
            self.run_dir = os.path.join(args.track_dir, run_name(args))
        else:
            self.run_dir = os.path.dirname(checkpoint["path"])
            if at_iteration_end is not None:
                repair_iteration_files(self.run_dir, checkpoint, at_iteration_end)
        self.writer, self.wandb_run_id, self.video_folder, self.videos_sent = open_run_log(args, checkpoint,
                                                                                           self.run_dir, envs)
        self.checkpoint_path = os.path.join(self.run_dir, CHECKPOINT_NAME)
        self.start_time = time.time() if checkpoint is None else time.time() - checkpoint["elapsed"]

    def start_envs(self, checkpoint: dict | None, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """The training envs as a new run starts them (reset with --seed) or as `checkpoint` left them; returns
        the next observations and dones."""
        if checkpoint is None:
            next_obs, _ = self.envs.reset(seed=self.args.seed)
            self.envs.action_space.seed(self.args.seed)
            return (torch.as_tensor(next_obs, dtype=torch.float32, device=device),
                    torch.zeros(self.args.num_envs, device=device))
        self.envs.reset(seed=self.args.seed)  # sets up the vector env; then every env gets its saved state back
        self.envs.call("set_state", checkpoint["env_states"])
        return checkpoint["next_obs"].to(device), checkpoint["next_done"].to(device)

    def state(self, checkpoint_format: str, global_step: int, next_obs: torch.Tensor, next_done: torch.Tensor,
              eval_calls: int) -> dict:
        """What a checkpoint holds besides the learner's own state: where the envs, the RNG streams and the
        evaluations are, to continue exactly."""
        return {
            "format": checkpoint_format, "args": asdict(self.args), "global_step": global_step,
            "elapsed": time.time() - self.start_time, "obs_stats": obs_statistics(self.envs),
            "env_states": self.envs.call("get_state"), "next_obs": next_obs.cpu(), "next_done": next_done.cpu(),
            "rng": rng_states(), "eval_calls": eval_calls, "wandb_run_id": self.wandb_run_id,
        }

    def sps(self, global_step: int) -> int:
        return int(global_step / (time.time() - self.start_time))

    def log_episodes(self, infos: dict, global_step: int) -> None:
        log_training_episodes(self.writer, infos, global_step)

    def log_update(self, scalars: dict[str, float], global_step: int) -> None:
        """An update's scalars, the SPS, and (--track --capture-video) the training videos finished since."""
        for tag, value in scalars.items():
            self.writer.add_scalar(tag, value, global_step)
        self.writer.add_scalar("charts/SPS", self.sps(global_step), global_step)
        if self.args.track:
            log_new_videos(self.video_folder, self.videos_sent, global_step)

    def stop_if_not_finite(self, loss: torch.Tensor, params: list[torch.Tensor], global_step: int, where: str) -> None:
        """The non-finite guard: stop before anything bad is written to the checkpoint."""
        if not math.isfinite(loss.item()) or not all(torch.isfinite(p).all() for p in params):
            self.writer.close()
            fail(f"non-finite loss or parameters at global_step={global_step} ({where}); "
                 f"{non_finite_advice(self.checkpoint_path)}")

    def close(self, global_step: int, episodes: EvaluationEpisodes | None = None) -> None:
        """The end of training: the training envs, the evaluation `episodes`' envs and the log closed, the last
        videos sent, the W&B run finished."""
        if episodes is not None:
            episodes.close()
        self.envs.close()
        self.writer.close()
        if self.args.track:
            log_new_videos(self.video_folder, self.videos_sent, global_step)
            finish_wandb(exit_code=0)


# ----------------------------------------------------------------------------------------------
# Evaluation episodes (Appendix B.5)
# ----------------------------------------------------------------------------------------------
class EvaluationEpisodes:
    """`episodes` episodes run side by side on envs of their own (never the training envs or RNG), as the paper
    evaluates (Appendix B.5): the policy frozen with its observation statistics, the undiscounted raw return."""

    def __init__(self, env_id: str, episodes: int, seed: int, discretize: bool):
        self.envs = [DiscretizeAction(gym.make(env_id)) if discretize else gym.make(env_id) for _ in range(episodes)]
        self.seed, self.discretize = seed, discretize

    @torch.inference_mode()
    def run(self, policy: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor | None]],
            stats: tuple[np.ndarray, np.ndarray] | None, call: int, deterministic: bool
            ) -> tuple[np.ndarray, list[list[np.ndarray]]]:
        """One episode per env: `policy(x)` gives the logits of the observations x of the episodes still running
        and, per row, what to keep of that step (or None); the action is sampled from Categorical(logits) (the
        argmax with `deterministic`). Returns each episode's return and its steps' kept rows. The episodes' seeds
        and the sampled actions depend only on (seed, call): evaluation never touches training's RNG, and a
        resumed run evaluates exactly as the uninterrupted one."""
        episodes = len(self.envs)
        base_seed = self.seed + 100_003 * (call + 1)
        generator = torch.Generator().manual_seed(base_seed)
        obs = np.stack([env.reset(seed=base_seed + i)[0] for i, env in enumerate(self.envs)])
        returns = np.zeros(episodes)
        kept: list[list[np.ndarray]] = [[] for _ in range(episodes)]
        active = list(range(episodes))
        while active:
            logits, rows = policy(torch.as_tensor(normalize_obs(obs[active], stats, self.discretize)))
            if deterministic:
                action = logits.argmax(-1).numpy()
            else:
                action = torch.multinomial(logits.softmax(-1), 1, generator=generator).squeeze(-1).numpy()
            still_active = []
            for row, i in enumerate(active):
                if rows is not None:
                    kept[i].append(rows[row].numpy())
                o, r, terminated, truncated, _ = self.envs[i].step(int(action[row]))
                returns[i] += r
                obs[i] = o
                if not (terminated or truncated):
                    still_active.append(i)
            active = still_active
        return returns, kept

    def close(self) -> None:
        for env in self.envs:
            env.close()



def evaluate_saved_model(args: Any, load_checkpoint: Callable[[str], dict],
                         evaluate: Callable[[dict, EvaluationEpisodes], tuple[np.ndarray, str]]) -> np.ndarray:
    """--evaluate: `evaluate(checkpoint, episodes)` runs the saved policy for --eval-episodes episodes and returns
    their returns and what was evaluated (e.g. "PPO"); one line says how it did. Returns the episodes' returns."""
    if args.eval_episodes < 1:
        fail(f"--eval-episodes must be at least 1 (got {args.eval_episodes})")
    checkpoint = load_checkpoint(args.evaluate)
    torch.set_num_threads(args.torch_threads)
    env_id = checkpoint["args"]["env_id"]
    episodes = EvaluationEpisodes(env_id, args.eval_episodes, args.seed, checkpoint["discretize"])
    returns, what = evaluate(checkpoint, episodes)
    episodes.close()
    mode = "deterministic" if args.deterministic else "stochastic"
    print(f"{env_id}, {what}, step {checkpoint['global_step']}: "
          f"return {returns.mean():.1f} ± {returns.std():.1f} over {len(returns)} {mode} episodes")
    return returns
