"""What the discrete-action scripts (cascade_ppo_discrete.py, ppo_baseline_discrete.py) share and is not the
algorithm: the discretization of a Box action space into the 2^A corners of its box (the paper's Appendix I),
their env stacks, the checks of their env (their PPO settings: ppo.check_ppo_settings), their run's bookkeeping
(on record.RunRecord), and the evaluation episodes of the paper's protocol (Appendix B.5) that their evaluations
run (on evaluation.EvaluationEnvs)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from . import envs as plumbing_envs
from .checkpoints import non_finite_advice
from .envs import OBS_CLIP, check_flat_observations, obs_statistics, probe_spaces
from .errors import fail
from .evaluation import EvaluationEnvs, open_saved_model, save_video_of_one_episode
from .record import RunRecord
from .runs import NEW_RUN_FLAGS

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
# The env check both scripts make before anything is created
# ----------------------------------------------------------------------------------------------
def resolve_env(args: Any, continuous_script: str) -> tuple[bool, bool]:
    """Probe --env-id and refuse what a discrete script cannot run, in one line (`continuous_script`: the one to
    use instead for a Box task with --discretize off). Returns (discretize, normalize) as they apply to this env."""
    action_space, observation_space = probe_spaces(args.env_id, "CartPole-v1, Hopper-v4")
    check_flat_observations(args.env_id, observation_space)
    if isinstance(action_space, gym.spaces.Discrete):
        if args.discretize == "on":
            fail(f"--discretize on needs a Box action space, but {args.env_id} is already discrete "
                 f"({action_space.n} actions); leave --discretize at auto")
        if action_space.start != 0:
            fail(f"{args.env_id}'s actions start at {action_space.start}; only Discrete(n) spaces starting at 0 "
                 "are supported")
        if args.normalize and "normalize" in NEW_RUN_FLAGS:  # it would be ignored: say so rather than run
            fail(f"--normalize applies to discretized Box envs only: {args.env_id} is natively discrete and is never "
                 "normalized or clipped (as CleanRL ppo.py); leave it out")
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
# The run's bookkeeping: record.RunRecord (folder, TensorBoard, W&B, videos, checkpoint, resume)
# ----------------------------------------------------------------------------------------------
class DiscreteRun(RunRecord):
    """`<track-dir>/<run_name>` and what a discrete script's run records there (`RunRecord`: TensorBoard with
    CleanRL's names, W&B with --track, --capture-video's videos, the checkpoint; a resumed run continues its own
    folder and W&B run). No progress line: the scripts print their own messages."""

    def __init__(self, args: Any, checkpoint: dict | None, envs: gym.vector.VectorEnv, total_steps: int,
                 at_iteration_end: bool | None = None):
        """`at_iteration_end`: for a script that keeps an iteration_<i>.pt per iteration, whether `checkpoint`
        was written at the end of one (its missing or damaged iteration files are rebuilt, or named); None for a
        script without iteration files."""
        super().__init__(args, checkpoint, envs, total_steps, at_iteration_end=bool(at_iteration_end),
                         iteration_files=at_iteration_end is not None, progress_line=False)

    def start_envs(self, checkpoint: dict | None, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """The training envs as a new run starts them (reset with --seed) or as `checkpoint` left them (with the
        RNG streams and the clock: `RunRecord.restore_envs`); returns the next observations and dones."""
        if checkpoint is None:
            next_obs, _ = self.envs.reset(seed=self.args.seed)
            self.envs.action_space.seed(self.args.seed)
            return (torch.as_tensor(next_obs, dtype=torch.float32, device=device),
                    torch.zeros(self.args.num_envs, device=device))
        _, next_obs = self.restore_envs(checkpoint)
        return torch.as_tensor(next_obs, device=device), checkpoint["next_done"].to(device)

    def save_state(self, checkpoint_format: str, global_step: int, next_obs: torch.Tensor, next_done: torch.Tensor,
                   eval_calls: int, learner: dict, iteration_end: int | None = None) -> None:
        """The checkpoint: the `learner`'s state and what continues the run exactly (the settings, the envs'
        statistics and next observations, the evaluations; `RunRecord.save` adds the env states, RNG streams,
        clock and W&B run id); at the end of iteration `iteration_end` also as iteration_<i>.pt."""
        self.save({"format": checkpoint_format, "args": asdict(self.args), "obs_stats": obs_statistics(self.envs),
                   "next_obs": next_obs.cpu(), "next_done": next_done.cpu(), "eval_calls": eval_calls, **learner},
                  global_step, iteration_end)

    def log_update(self, scalars: dict[str, float], global_step: int, size: int) -> None:
        """An update's scalars, then the SPS, the progress file with the policy's `size` in base nets (sweep.py
        shows it) and (--track --capture-video) the training videos finished since."""
        for tag, value in scalars.items():
            self.writer.add_scalar(tag, value, global_step)
        self.tick(global_step, size)

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
        super().close(global_step)


# ----------------------------------------------------------------------------------------------
# Evaluation episodes (Appendix B.5): evaluation.EvaluationEnvs
# ----------------------------------------------------------------------------------------------
class EvaluationEpisodes(EvaluationEnvs):
    """`episodes` episodes run side by side on envs of their own (never the training envs or RNG), as the paper
    evaluates (Appendix B.5): the policy frozen with its observation statistics, the undiscounted raw return."""

    def __init__(self, env_id: str, episodes: int, seed: int, discretize: bool, render: bool = False):
        super().__init__(env_id, episodes, seed, render=render, wrap=DiscretizeAction if discretize else None)
        self.discretize = discretize

    @torch.inference_mode()
    def run(self, policy: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor | None]],
            stats: tuple[np.ndarray, np.ndarray] | None, call: int, deterministic: bool
            ) -> tuple[np.ndarray, list[list[np.ndarray]]]:
        """One episode per env: `policy(x)` gives the logits of the observations x (a CPU tensor) of the episodes
        still running and, per row, what to keep of that step (or None); the action is sampled from Categorical(logits) (the
        argmax with `deterministic`). Returns each episode's return and its steps' kept rows. The episodes' seeds
        and the sampled actions depend only on (seed, call): evaluation never touches training's RNG, and a
        resumed run evaluates exactly as the uninterrupted one."""
        base_seed = self.base_seed(call)
        generator = torch.Generator().manual_seed(base_seed)
        kept: list[list[np.ndarray]] = [[] for _ in self.envs]

        def act(raw_obs: np.ndarray, running: list[int]) -> list[int]:
            logits, rows = policy(torch.as_tensor(normalize_obs(raw_obs, stats, self.discretize)))
            logits = logits.cpu()  # a --cuda actor's: sampled here, by this evaluation's own CPU generator
            if rows is not None:
                rows = rows.cpu().numpy()
                for row, i in enumerate(running):
                    kept[i].append(rows[row])
            if deterministic:
                return logits.argmax(-1).tolist()
            return torch.multinomial(logits.softmax(-1), 1, generator=generator).squeeze(-1).tolist()

        return self.run_episodes(act, base_seed), kept


def evaluate_saved_model(args: Any, load_checkpoint: Callable[[str], dict],
                         evaluate: Callable[[dict, EvaluationEpisodes], tuple[np.ndarray, str]]) -> np.ndarray:
    """--evaluate: `evaluate(checkpoint, episodes)` runs the saved policy for --eval-episodes episodes and returns
    their returns and what was evaluated (e.g. "PPO"); one line says how it did. Returns the episodes' returns.
    With --capture-video, an mp4 of one more episode beside the checkpoint."""
    checkpoint = open_saved_model(args, load_checkpoint)
    env_id = checkpoint["args"]["env_id"]
    episodes = EvaluationEpisodes(env_id, args.eval_episodes, args.seed, checkpoint["discretize"])
    returns, what = evaluate(checkpoint, episodes)
    episodes.close()
    mode = "deterministic" if args.deterministic else "stochastic"
    print(f"{env_id}, {what}, step {checkpoint['global_step']}: "
          f"return {returns.mean():.1f} ± {returns.std():.1f} over {len(returns)} {mode} episodes")
    if args.capture_video:
        save_video_of_one_episode(checkpoint["path"], mode,
                                  EvaluationEpisodes(env_id, 1, args.seed, checkpoint["discretize"], render=True),
                                  lambda video: evaluate(checkpoint, video)[0][0])
    return returns
