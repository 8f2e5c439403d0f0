"""PPO for discrete-action tasks, the discrete baseline of the Cascade paper (single-file, CleanRL style).

Equivalent to CleanRL's `ppo.py` (same 64-64 actor and critic, same hyperparameters) on gymnasium 1.x.
Box action spaces of A dims are discretized into the 2^A corners of the box (paper Appendix I), which
gives the "discrete PPO" of the paper's Fig. 16; natively discrete envs such as CartPole-v1 are used
as they are. Discretized Box tasks get observation/reward normalization and +-10 clipping by default, as the
paper's code ran Fig. 16 (`--no-normalize`: clipping only). Extra flags shared with `ppo_baseline.py`:
`--hidden-size`, `--lr-schedule`, `--no-normalize`.

    python ppo_baseline_discrete.py --env-id Hopper-v4 --total-timesteps 10000000
    tensorboard --logdir runs
"""

from __future__ import annotations

import collections
import contextlib
import copy
import errno
import glob
import math
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

# The paper used the v4 MuJoCo tasks; gymnasium warns on every make that they are out of date.
warnings.filterwarnings("ignore", message=".*is out of date.*")


@dataclass
class Args:
    exp_name: str = "ppo_baseline_discrete"
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
    """mp4s of training episodes 0, 1, 8, 27, ..., 1000, 2000, ... of the first env in videos/<run_name>/ (to W&B with --track). MuJoCo needs MUJOCO_GL=egl or osmesa"""

    # Environment
    env_id: str = "Hopper-v4"
    """the id of a gymnasium environment with a Discrete action space, or a Box one to discretize (e.g. Hopper-v4)"""
    discretize: Literal["auto", "on", "off"] = "auto"
    """auto: discretize a Box action space of A <= 10 dims into 2^A actions (Humanoid's 17 are refused), use a Discrete one as it is; on: require a Box space to discretize (an error on a discrete env); off: require a natively discrete env"""
    normalize: bool = True
    """observation and reward normalization of discretized Box envs, as the paper's code ran Fig. 16 (its text names CleanRL ppo.py, which has none: `--no-normalize`); their observations and rewards are clipped to ±10 either way; natively discrete envs are never normalized or clipped (CleanRL)"""

    # Network and schedule
    total_timesteps: int = 10_000_000
    """total environment steps of the run (paper Fig. 16: 10M)"""
    hidden_size: int = 64
    """width of the two hidden layers of the actor (the critic stays 64-64)"""
    lr_schedule: Literal["global", "cyclic", "constant"] = "global"
    """global: linear decay to 0 over the run (CleanRL); cyclic: decay restarts every --cycle-steps, with a fresh Adam at each restart (as ppo_baseline.py and the paper's code)"""
    cycle_steps: int = 1_000_000
    """length of one learning-rate cycle in env steps, with --lr-schedule cyclic"""

    # PPO (CleanRL ppo.py defaults)
    learning_rate: float = 2.5e-4
    """initial learning rate of the optimizer"""
    num_envs: int = 4
    """number of parallel training environments"""
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
    """surrogate clipping coefficient"""
    clip_vloss: bool = True
    """use a clipped value loss"""
    ent_coef: float = 0.01
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
# Environment plumbing
# ----------------------------------------------------------------------------------------------
OBS_CLIP = 10.0
REWARD_CLIP = 10.0
NORM_EPS = 1e-8  # the epsilon of gymnasium's NormalizeObservation
MAX_DISCRETIZED_DIMS = 10  # 2^10 = 1024 actions; Humanoid's 17 dims (131072 actions) are out of scope


def fail(message: str) -> None:
    """Stop with a one-line error and a non-zero exit code."""
    raise SystemExit(f"error: {message}")


def check_env_id(env_id: str) -> None:
    if env_id not in gym.envs.registry:
        import difflib

        close = difflib.get_close_matches(env_id, list(gym.envs.registry), n=3)
        hint = f" Did you mean {', '.join(close)}?" if close else ""
        fail(f"unknown env id '{env_id}'.{hint} (see gymnasium's registry, e.g. CartPole-v1, Hopper-v4)")


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
    """Per env: raw episode stats and, for discretized Box tasks, the 2^A discretization, the obs/reward
    normalization of the continuous scripts (the paper's code's default) and the clipping to +-10, under the
    outermost `RunState` (and with `video`, the --capture-video recorder under them all). `normalize` is already
    resolved (see `resolve`)."""

    def thunk() -> gym.Env:
        env = gym.make(env_id, render_mode="rgb_array") if video else gym.make(env_id)
        if video:
            env = TrainingVideo(env)
        env = gym.wrappers.RecordEpisodeStatistics(env)  # raw, unnormalized returns
        if discretize:  # a MuJoCo-like Box task, wrapped as the paper's code wraps it
            env = DiscretizeAction(env)  # corners lie inside the box: no ClipAction needed
            if normalize:
                env = gym.wrappers.NormalizeObservation(env)
            # clipped to +-10 with or without normalization (the paper's code clips raw values in norm:False runs)
            env = gym.wrappers.TransformObservation(
                env, lambda obs: np.clip(obs, -OBS_CLIP, OBS_CLIP), env.observation_space
            )
            if normalize:
                env = gym.wrappers.NormalizeReward(env, gamma=gamma)
            env = gym.wrappers.TransformReward(env, lambda r: np.clip(r, -REWARD_CLIP, REWARD_CLIP))
        return RunState(env, index)

    return thunk


def make_vector_env(args: Args, discretize: bool, normalize: bool) -> gym.vector.SyncVectorEnv:
    # SAME_STEP: the obs returned on a done step is already the reset one, so every stored
    # transition is real (the default NEXT_STEP mode inserts a fake step after each episode).
    return gym.vector.SyncVectorEnv(
        [make_env(args.env_id, args.gamma, discretize, normalize, i, video=args.capture_video and i == 0)
         for i in range(args.num_envs)],
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
    )


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
    these methods by name (`envs.call`)."""

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


def wrapper_depth(env: gym.Env) -> int:
    """Number of layers (wrappers and the env itself) below RunState."""
    depth = 1
    while isinstance(env, gym.Wrapper):
        env, depth = env.env, depth + 1
    return depth


def obs_statistics(envs: gym.vector.VectorEnv) -> tuple[np.ndarray, np.ndarray] | None:
    """Copy of the first training env's observation mean/var (None without normalization)."""
    return envs.call("obs_statistics")[0]


def normalize_obs(obs: np.ndarray, stats: tuple[np.ndarray, np.ndarray] | None, clip: bool) -> np.ndarray:
    """What the training wrappers do to a raw observation, with frozen statistics (None: no normalization;
    `clip`: a discretized Box task, whose raw observations are clipped too)."""
    if stats is None:
        return (np.clip(obs, -OBS_CLIP, OBS_CLIP) if clip else obs).astype(np.float32)
    mean, var = stats
    return np.clip((obs - mean) / np.sqrt(var + NORM_EPS), -OBS_CLIP, OBS_CLIP).astype(np.float32)


# ----------------------------------------------------------------------------------------------
# The agent (CleanRL ppo.py)
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


# ----------------------------------------------------------------------------------------------
# Evaluation (SPEC §6): frozen policy, frozen obs statistics, separate envs, stochastic actions
# ----------------------------------------------------------------------------------------------
class Evaluator:
    """Runs `episodes` episodes side by side on its own envs; never touches the training envs."""

    def __init__(self, env_id: str, episodes: int, seed: int, discretize: bool):
        self.envs = [DiscretizeAction(gym.make(env_id)) if discretize else gym.make(env_id) for _ in range(episodes)]
        self.seed, self.discretize = seed, discretize

    @torch.inference_mode()
    def __call__(
        self,
        actor: nn.Module,
        stats: tuple[np.ndarray, np.ndarray] | None,
        call: int = 0,
        deterministic: bool = False,
    ) -> np.ndarray:
        """Returns each episode's undiscounted raw return. The episodes' seeds and the sampled actions depend
        only on (seed, call): evaluation never touches training's RNG, and a resumed run evaluates exactly as
        the uninterrupted one."""
        episodes = len(self.envs)
        base_seed = self.seed + 100_003 * (call + 1)
        generator = torch.Generator().manual_seed(base_seed)
        obs = np.stack([env.reset(seed=base_seed + i)[0] for i, env in enumerate(self.envs)])
        returns = np.zeros(episodes)
        active = list(range(episodes))
        while active:
            logits = actor(torch.as_tensor(normalize_obs(obs[active], stats, self.discretize)))
            if deterministic:
                action = logits.argmax(-1).numpy()
            else:
                action = torch.multinomial(logits.softmax(-1), 1, generator=generator).squeeze(-1).numpy()
            still_active = []
            for row, i in enumerate(active):
                o, r, terminated, truncated, _ = self.envs[i].step(int(action[row]))
                returns[i] += r
                obs[i] = o
                if not (terminated or truncated):
                    still_active.append(i)
            active = still_active
        return returns

    def close(self) -> None:
        for env in self.envs:
            env.close()


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
# Checkpoints: one file with everything needed to continue and to act
# ----------------------------------------------------------------------------------------------
CHECKPOINT_NAME = "checkpoint.pt"
CHECKPOINT_FORMAT = "ppo_baseline_discrete/1"


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
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != CHECKPOINT_FORMAT:
        fail(f"{path} is not a ppo_baseline_discrete checkpoint")
    checkpoint["path"] = path
    return checkpoint


def actor_from_checkpoint(checkpoint: dict, device: str | torch.device = "cpu") -> nn.Sequential:
    saved = Args(**checkpoint["args"])
    rng = torch.get_rng_state()  # building the net draws random inits; keep the caller's RNG untouched
    actor = make_actor(checkpoint["obs_dim"], checkpoint["num_actions"], saved.hidden_size)
    torch.set_rng_state(rng)
    actor.load_state_dict(checkpoint["actor"])
    return actor.to(device)


# ----------------------------------------------------------------------------------------------
# Training
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


def resolve(args: Args) -> tuple[bool, bool]:
    """Probe the env and reject bad input with one clear line before anything is created.
    Returns (discretize, normalize) as they apply to this env."""
    check_run_settings(args)
    if args.hidden_size < 1:
        fail(f"--hidden-size must be at least 1 (got {args.hidden_size})")
    if args.num_envs < 1 or args.num_steps < 1:
        fail("--num-envs and --num-steps must be at least 1")
    batch_size = args.num_envs * args.num_steps
    if args.total_timesteps < batch_size:
        fail(f"--total-timesteps {args.total_timesteps} is smaller than one rollout batch "
             f"(num_envs*num_steps = {batch_size}); raise it")
    if args.lr_schedule == "cyclic" and args.cycle_steps < batch_size:
        fail(f"--cycle-steps {args.cycle_steps} is smaller than one rollout batch ({batch_size})")
    if batch_size % args.num_minibatches:
        fail(f"the batch size {batch_size} is not divisible by --num-minibatches {args.num_minibatches}")
    if args.eval_every < 0 or (args.eval_every and args.eval_episodes < 1):
        fail("--eval-every must be >= 0 and --eval-episodes >= 1")
    check_env_id(args.env_id)
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
                 "(use --discretize auto, or ppo_baseline.py)")
        problem = discretize_problem(action_space)
        if problem is not None:
            fail(f"cannot discretize {args.env_id}: {problem}")
        return True, args.normalize
    fail(f"{args.env_id} has a {type(action_space).__name__} action space; this script needs a Discrete or Box one")


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


def train(args: Args, checkpoint: dict | None = None) -> dict:
    """Runs PPO (from scratch, or continuing `checkpoint`); returns the final actor, critic and run folder."""
    discretize, normalize = resolve(args)
    say = (lambda *_: None) if args.quiet else print
    torch.set_num_threads(args.torch_threads)
    seed_everything(args.seed, args.torch_deterministic)
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")

    envs = make_vector_env(args, discretize, normalize)
    obs_dim = int(np.prod(envs.single_observation_space.shape))
    num_actions = int(envs.single_action_space.n)

    batch_size = args.num_envs * args.num_steps
    minibatch_size = batch_size // args.num_minibatches
    total_updates = args.total_timesteps // batch_size
    updates_per_cycle = max(args.cycle_steps // batch_size, 1)
    if args.total_timesteps % batch_size and checkpoint is None:
        say(f"note: total_timesteps={args.total_timesteps} is not a multiple of the batch size {batch_size}; "
              f"the run does {total_updates} updates = {total_updates * batch_size} steps")
    say(f"{args.env_id}: {num_actions} discrete actions"
          f"{' (discretized Box)' if discretize else ''}, normalization {'on' if normalize else 'off'}")

    from torch.utils.tensorboard import SummaryWriter

    if checkpoint is None:
        run_dir = os.path.join(args.track_dir, f"{args.env_id}__{args.exp_name}__{args.seed}__{int(time.time())}")
    else:
        run_dir = os.path.dirname(checkpoint["path"])
    run_name = os.path.basename(run_dir)
    # kept through an untracked resume, so that a later --track continues the same W&B run
    wandb_run_id = None if checkpoint is None else checkpoint.get("wandb_run_id")
    if args.track:  # before the SummaryWriter: W&B mirrors the TensorBoard logs of writers made after it
        wandb_run_id = start_wandb(args, run_name, run_dir, wandb_run_id)
    if checkpoint is None:
        writer = SummaryWriter(run_dir)
        writer.add_text(
            "hyperparameters",
            "|param|value|\n|-|-|\n" + "\n".join(f"|{key}|{value}|" for key, value in asdict(args).items()),
        )
    else:  # purge_step hides whatever the killed run logged after its last checkpoint
        writer = SummaryWriter(run_dir, purge_step=checkpoint["global_step"] + 1)
    checkpoint_path = os.path.join(run_dir, CHECKPOINT_NAME)
    video_folder = os.path.join(VIDEO_ROOT, run_name) if args.capture_video else None
    if video_folder is not None:
        envs.call("record_videos_to", video_folder)
    videos_sent = finished_videos(video_folder)  # a resumed run's earlier ones went to W&B already

    actor = make_actor(obs_dim, num_actions, args.hidden_size).to(device)
    critic = make_critic(obs_dim).to(device)
    optimizer = torch.optim.Adam([*actor.parameters(), *critic.parameters()], lr=args.learning_rate, eps=1e-5)
    params = optimizer.param_groups[0]["params"]
    n_params = count_parameters(actor, critic)
    say(f"PPO: {n_params} parameters (actor + critic)")
    evaluator = Evaluator(args.env_id, args.eval_episodes, args.seed, discretize) if args.eval_every else None
    eval_calls = 0 if checkpoint is None else checkpoint["eval_calls"]

    def evaluate_and_log(step: int) -> None:
        nonlocal eval_calls
        returns = evaluator(actor, obs_statistics(envs), eval_calls)
        eval_calls += 1
        writer.add_scalar("eval/episodic_return", returns.mean(), step)
        writer.add_scalar("eval/episodic_return_std", returns.std(), step)
        say(f"global_step={step}, eval/episodic_return={returns.mean():.1f} ± {returns.std():.1f}")

    # Rollout storage, preallocated once
    obs = torch.zeros((args.num_steps, args.num_envs, obs_dim), device=device)
    actions = torch.zeros((args.num_steps, args.num_envs), dtype=torch.long, device=device)
    logprobs = torch.zeros((args.num_steps, args.num_envs), device=device)
    rewards = torch.zeros((args.num_steps, args.num_envs), device=device)
    dones = torch.zeros((args.num_steps, args.num_envs), device=device)
    values = torch.zeros((args.num_steps, args.num_envs), device=device)

    def make_checkpoint(updates_done: int) -> dict:
        return {
            "format": CHECKPOINT_FORMAT, "args": asdict(args), "obs_dim": obs_dim, "num_actions": num_actions,
            "discretize": discretize, "updates_done": updates_done, "global_step": global_step,
            "elapsed": time.time() - start_time,
            "actor": actor.state_dict(), "critic": critic.state_dict(), "optimizer": optimizer.state_dict(),
            "obs_stats": obs_statistics(envs), "env_states": envs.call("get_state"),
            "next_obs": next_obs.cpu(), "next_done": next_done.cpu(), "rng": rng_states(), "eval_calls": eval_calls,
            "wandb_run_id": wandb_run_id,
        }

    if checkpoint is None:
        global_step, start_update = 0, 1
        start_time = time.time()
        next_obs_np, _ = envs.reset(seed=args.seed)
        envs.action_space.seed(args.seed)
        next_obs = torch.as_tensor(next_obs_np, dtype=torch.float32, device=device)
        next_done = torch.zeros(args.num_envs, device=device)
        if evaluator is not None:
            evaluate_and_log(0)
        writer.add_scalar("charts/parameters", n_params, global_step)
    else:
        global_step, start_update = checkpoint["global_step"], checkpoint["updates_done"] + 1
        start_time = time.time() - checkpoint["elapsed"]
        envs.reset(seed=args.seed)  # sets up the vector env; then every env gets its saved state back
        envs.call("set_state", checkpoint["env_states"])
        next_obs = checkpoint["next_obs"].to(device)
        next_done = checkpoint["next_done"].to(device)
        actor.load_state_dict(checkpoint["actor"])
        critic.load_state_dict(checkpoint["critic"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        set_rng_states(checkpoint["rng"])
        say(f"resumed {checkpoint['path']} at global_step={global_step}")
    last_checkpoint_step = global_step

    for update in range(start_update, total_updates + 1):
        if args.lr_schedule == "global":
            frac = 1.0 - (update - 1.0) / total_updates
        elif args.lr_schedule == "cyclic":
            frac = 1.0 - ((update - 1) % updates_per_cycle) / updates_per_cycle
            if update > 1 and (update - 1) % updates_per_cycle == 0:  # a new cycle: fresh Adam moments (as ppo_baseline.py)
                optimizer = torch.optim.Adam([*actor.parameters(), *critic.parameters()], lr=args.learning_rate, eps=1e-5)
        else:
            frac = 1.0
        optimizer.param_groups[0]["lr"] = frac * args.learning_rate

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
            next_done = torch.as_tensor(np.logical_or(terminations, truncations), dtype=torch.float32,
                                        device=device)
            if "final_info" in infos and "episode" in infos["final_info"]:
                finished = infos["final_info"]["_episode"]
                for ret, length in zip(infos["final_info"]["episode"]["r"][finished],
                                       infos["final_info"]["episode"]["l"][finished]):
                    writer.add_scalar("charts/episodic_return", ret, global_step)
                    writer.add_scalar("charts/episodic_length", length, global_step)
            if evaluator is not None and global_step % args.eval_every < args.num_envs:
                evaluate_and_log(global_step)

        # --- GAE (CleanRL: an episode end, termination or truncation, cuts the bootstrap) ---
        with torch.inference_mode():
            next_value = critic(next_obs).squeeze(-1)
            advantages = torch.zeros_like(rewards)
            lastgaelam = 0
            for t in reversed(range(args.num_steps)):
                nextnonterminal = 1.0 - (next_done if t == args.num_steps - 1 else dones[t + 1])
                nextvalues = next_value if t == args.num_steps - 1 else values[t + 1]
                delta = rewards[t] + args.gamma * nextvalues * nextnonterminal - values[t]
                lastgaelam = delta + args.gamma * args.gae_lambda * nextnonterminal * lastgaelam
                advantages[t] = lastgaelam
            returns = advantages + values

        b_obs = obs.reshape(-1, obs_dim)
        b_logprobs = logprobs.reshape(-1)
        b_actions = actions.reshape(-1)
        b_advantages = advantages.reshape(-1)
        b_returns = returns.reshape(-1)
        b_values = values.reshape(-1)

        # --- PPO update ---
        b_inds = np.arange(batch_size)
        clipfracs = []
        for _epoch in range(args.update_epochs):
            np.random.shuffle(b_inds)
            for start in range(0, batch_size, minibatch_size):
                mb_inds = b_inds[start : start + minibatch_size]
                dist = torch.distributions.Categorical(logits=actor(b_obs[mb_inds]))
                newlogprob = dist.log_prob(b_actions[mb_inds])
                entropy = dist.entropy()
                newvalue = critic(b_obs[mb_inds]).squeeze(-1)
                logratio = newlogprob - b_logprobs[mb_inds]
                ratio = logratio.exp()
                with torch.no_grad():
                    old_approx_kl = (-logratio).mean()
                    approx_kl = ((ratio - 1) - logratio).mean()
                    clipfracs.append(((ratio - 1.0).abs() > args.clip_coef).float().mean().item())

                mb_advantages = b_advantages[mb_inds]
                if args.norm_adv:
                    mb_advantages = (mb_advantages - mb_advantages.mean()) / (mb_advantages.std() + 1e-8)
                pg_loss1 = -mb_advantages * ratio
                pg_loss2 = -mb_advantages * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)
                pg_loss = torch.max(pg_loss1, pg_loss2).mean()

                if args.clip_vloss:
                    v_loss_unclipped = (newvalue - b_returns[mb_inds]) ** 2
                    v_clipped = b_values[mb_inds] + torch.clamp(
                        newvalue - b_values[mb_inds], -args.clip_coef, args.clip_coef
                    )
                    v_loss_clipped = (v_clipped - b_returns[mb_inds]) ** 2
                    v_loss = 0.5 * torch.max(v_loss_unclipped, v_loss_clipped).mean()
                else:
                    v_loss = 0.5 * ((newvalue - b_returns[mb_inds]) ** 2).mean()

                entropy_loss = entropy.mean()
                loss = pg_loss - args.ent_coef * entropy_loss + v_loss * args.vf_coef

                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(params, args.max_grad_norm)
                optimizer.step()

            if args.target_kl is not None and approx_kl > args.target_kl:
                break

        y_pred, y_true = b_values.cpu().numpy(), b_returns.cpu().numpy()
        var_y = np.var(y_true)
        explained_var = np.nan if var_y == 0 else 1 - np.var(y_true - y_pred) / var_y

        # --- logging (CleanRL names) ---
        writer.add_scalar("charts/learning_rate", optimizer.param_groups[0]["lr"], global_step)
        writer.add_scalar("losses/value_loss", v_loss.item(), global_step)
        writer.add_scalar("losses/policy_loss", pg_loss.item(), global_step)
        writer.add_scalar("losses/entropy", entropy_loss.item(), global_step)
        writer.add_scalar("losses/old_approx_kl", old_approx_kl.item(), global_step)
        writer.add_scalar("losses/approx_kl", approx_kl.item(), global_step)
        writer.add_scalar("losses/clipfrac", np.mean(clipfracs), global_step)
        writer.add_scalar("losses/explained_variance", explained_var, global_step)
        sps = int(global_step / (time.time() - start_time))
        writer.add_scalar("charts/SPS", sps, global_step)
        if args.track:
            log_new_videos(video_folder, videos_sent, global_step)

        # --- non-finite guard: stop before anything bad is written to the checkpoint ---
        if not math.isfinite(loss.item()) or not all(torch.isfinite(p).all() for p in params):
            writer.close()
            fail(f"non-finite loss or parameters at global_step={global_step} (update {update}); "
                 f"{non_finite_advice(checkpoint_path)}")
        if update == total_updates or (
                args.checkpoint_every and global_step - last_checkpoint_step >= args.checkpoint_every):
            save_checkpoint(checkpoint_path, make_checkpoint(update))
            last_checkpoint_step = global_step

    if evaluator is not None and global_step % args.eval_every >= args.num_envs:
        evaluate_and_log(global_step)  # the final policy, if the last step was not an eval step
    if evaluator is not None:
        evaluator.close()
    envs.close()
    writer.close()
    if args.track:
        log_new_videos(video_folder, videos_sent, global_step)
        finish_wandb(exit_code=0)
    return {"actor": actor, "critic": critic, "run_dir": run_dir, "global_step": global_step}


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


def evaluate_saved(args: Args) -> np.ndarray:
    """--evaluate: the saved policy with its saved observation statistics frozen."""
    if args.eval_episodes < 1:
        fail(f"--eval-episodes must be at least 1 (got {args.eval_episodes})")
    checkpoint = load_checkpoint(args.evaluate)
    saved = Args(**checkpoint["args"])
    torch.set_num_threads(args.torch_threads)
    actor = actor_from_checkpoint(checkpoint)
    evaluator = Evaluator(saved.env_id, args.eval_episodes, args.seed, checkpoint["discretize"])
    returns = evaluator(actor, checkpoint["obs_stats"], 0, args.deterministic)
    evaluator.close()
    mode = "deterministic" if args.deterministic else "stochastic"
    print(f"{saved.env_id}, PPO, step {checkpoint['global_step']}: "
          f"return {returns.mean():.1f} ± {returns.std():.1f} over {len(returns)} {mode} episodes")
    return returns


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
