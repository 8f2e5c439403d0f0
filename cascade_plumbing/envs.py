"""Environment construction and the wrappers a run needs of its envs: state save/restore, videos."""

from __future__ import annotations

import collections
import copy
import multiprocessing
import os
import pickle
import signal
import warnings
import weakref
from collections.abc import Callable

import gymnasium as gym
import numpy as np
from gymnasium.wrappers.utils import RunningMeanStd

from .errors import fail

OBS_CLIP = 10.0


REWARD_CLIP = 10.0


NORM_EPS = 1e-8  # the epsilon of gymnasium's NormalizeObservation


def makeable(env_id: str) -> bool:
    """Whether gymnasium can make `env_id` here (its package installed), for the suggestions of an unknown id."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            gym.make(env_id).close()
        return True
    except Exception:
        return False


def makeable_neighbours(env_id: str) -> list[str]:
    """Up to 3 ids close to `env_id` that can be made here: its other versions (the same version first, then the
    newest), then close spellings; not Hopper-v3, which needs the retired mujoco-py."""
    import difflib

    base = env_id.split("-v")[0].lower()
    version = env_id.rsplit("-v", 1)[-1] if "-v" in env_id else None
    versions = sorted((i for i in gym.envs.registry if i.split("-v")[0].lower() == base),  # the same version,
                      key=lambda i: (i.rsplit("-v", 1)[-1] == version, i.rsplit("-v", 1)[-1].zfill(4)),
                      reverse=True)  # then the newest first
    candidates = list(dict.fromkeys(versions + difflib.get_close_matches(env_id, list(gym.envs.registry), n=6)))
    return [i for i in candidates if i != env_id and makeable(i)][:3]


def check_env_id(env_id: str, examples: str = "Ant-v4, Hopper-v5") -> None:
    if env_id not in gym.envs.registry:
        close = makeable_neighbours(env_id)
        hint = f" Did you mean {', '.join(close)}?" if close else ""
        fail(f"unknown env id '{env_id}'.{hint} (see gymnasium's registry, e.g. {examples})")


def probe_spaces(env_id: str, examples: str = "Ant-v4, Hopper-v5") -> tuple[gym.Space, gym.Space]:
    """--env-id's (action space, observation space), from one env made and closed; one line if the id is unknown
    or the env cannot be made here (a registered env whose package is missing, e.g. Box2D for LunarLander)."""
    check_env_id(env_id, examples)
    try:
        probe = gym.make(env_id)
    except (gym.error.DependencyNotInstalled, ImportError) as exc:
        first_line = (str(exc).splitlines() or [""])[0][:200]
        close = makeable_neighbours(env_id)  # (Hopper-v3: the v4 and v5 that run here)
        fail(f"cannot make {env_id}: {first_line or type(exc).__name__}; install what it needs, or pick another "
             f"--env-id{' (' + ', '.join(close) + ' can be made here)' if close else ''}")
    spaces = probe.action_space, probe.observation_space
    probe.close()
    return spaces


def check_flat_observations(env_id: str, observation_space: gym.Space) -> None:
    """One line unless --env-id observes a flat (1-D) Box, what every script's MLPs take in: an image, a Dict (goal
    envs) or a Discrete observation (FrozenLake) would reach the nets misshapen and fail deep inside the run."""
    if isinstance(observation_space, gym.spaces.Box) and len(observation_space.shape) == 1:
        return
    what = (f"observations of shape {observation_space.shape}" if isinstance(observation_space, gym.spaces.Box)
            else f"a {type(observation_space).__name__} observation space")
    fail(f"{env_id} has {what}; these scripts' MLPs need a flat (1-D) Box of observations: pick an env that "
         "observes a vector (Hopper-v4, CartPole-v1), or flatten its observations in make_env "
         "(cascade_plumbing/envs.py)")


def check_box_env(env_id: str, discrete_script: str, examples: str = "Ant-v4, Hopper-v5") -> tuple[gym.Space, gym.Space]:
    """--env-id's (action space, observation space) for a continuous script: registered, observing a flat Box and
    acting in a Box; otherwise one line (naming `discrete_script`, the caller's discrete twin, for a discrete env)."""
    action_space, observation_space = probe_spaces(env_id, examples)
    check_flat_observations(env_id, observation_space)  # first: no script of ours runs an env that fails it
    if not isinstance(action_space, gym.spaces.Box):
        fail(f"{env_id} has a {type(action_space).__name__} action space; this script needs a Box "
             f"(continuous) one: use {discrete_script}")
    return action_space, observation_space


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
    these methods by name, so they work the same when the env lives in a worker process."""

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


def wrapper_depth(env: gym.Env) -> int:
    """Number of layers (wrappers and the env itself) below RunState."""
    depth = 1
    while isinstance(env, gym.Wrapper):
        env, depth = env.env, depth + 1
    return depth


def obs_statistics(envs: gym.vector.VectorEnv) -> tuple[np.ndarray, np.ndarray] | None:
    """Copy of the first training env's observation mean/var (None without normalization)."""
    return envs.call("obs_statistics")[0]


def normalize_obs(obs: np.ndarray, stats: tuple[np.ndarray, np.ndarray] | None, clip: float = OBS_CLIP) -> np.ndarray:
    """What the training wrappers do to a raw observation, with frozen statistics (None: no normalization),
    then clipped to +-`clip` (0: no clipping)."""
    if stats is not None:
        mean, var = stats
        obs = (obs - mean) / np.sqrt(var + NORM_EPS)
    return (np.clip(obs, -clip, clip) if clip else obs).astype(np.float32)


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


def make_env(env_id: str, index: int = 0, video: bool = False, action_wrapper: type[gym.Wrapper] | None = None,
             normalize: bool = False, gamma: float = 0.99, clip: float = 0.0) -> Callable[[], gym.Env]:
    """One env's wrapper stack, as CleanRL builds it: raw episode statistics, then `action_wrapper` (e.g.
    ClipAction), observation normalization, observations clipped to +-`clip`, reward normalization (with `gamma`),
    rewards clipped to +-`clip` (`clip` 0: no clipping), all under the outermost `RunState`; with `video`, the
    --capture-video recorder under them all."""

    def thunk() -> gym.Env:
        if multiprocessing.current_process().name != "MainProcess":  # a --num-envs worker: stops are for training
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            signal.signal(signal.SIGHUP, signal.SIG_IGN)  # (the training process ends its workers on either)
            signal.signal(signal.SIGTERM, signal.SIG_DFL)  # not the training process's handler it was forked with
        env = gym.make(env_id, render_mode="rgb_array") if video else gym.make(env_id)
        if video:
            env = TrainingVideo(env)
        env = gym.wrappers.RecordEpisodeStatistics(env)  # raw, unnormalized returns
        if action_wrapper is not None:
            env = action_wrapper(env)
        if normalize:
            env = gym.wrappers.NormalizeObservation(env)
        if clip:  # also without normalization: the paper's code clips raw values in its norm:False runs
            env = gym.wrappers.TransformObservation(env, lambda obs: np.clip(obs, -clip, clip), env.observation_space)
        if normalize:
            env = gym.wrappers.NormalizeReward(env, gamma=gamma)
        if clip:
            env = gym.wrappers.TransformReward(env, lambda r: np.clip(r, -clip, clip))
        return RunState(env, index)

    return thunk


def make_vector_env(env_fns: list[Callable[[], gym.Env]]) -> gym.vector.VectorEnv:
    """One env in this process, or several stepped in parallel worker processes.

    SAME_STEP autoreset: the obs returned on a done step is already the reset one (the real last one is in
    infos["final_obs"]), so every stored transition is real; the default NEXT_STEP mode inserts a fake step
    after each episode."""
    mode = gym.vector.AutoresetMode.SAME_STEP
    if len(env_fns) == 1:
        return gym.vector.SyncVectorEnv(env_fns, autoreset_mode=mode)
    envs = gym.vector.AsyncVectorEnv(env_fns, autoreset_mode=mode)
    WORKER_ENVS.add(envs)
    return envs


WORKER_ENVS: weakref.WeakSet = weakref.WeakSet()  # the open vector envs with worker processes


def end_env_workers() -> None:
    """After a stop (Ctrl-C, SIGTERM): terminate the --num-envs worker processes (SIGTERM, their default: they
    end silently). The stop may have interrupted the training process in the middle of a worker's reply, and the
    graceful close at exit would then fail on the half-read pipe, with tracebacks from both sides. (gymnasium's
    close(terminate=True) would first warn and read the pending reply from that pipe.)"""
    for envs in list(WORKER_ENVS):
        if envs.closed:
            continue
        for process in envs.processes:
            if process.is_alive():
                process.terminate()
        for process in envs.processes:
            process.join(timeout=10)
        for pipe in envs.parent_pipes:
            if pipe is not None:
                pipe.close()
        envs.closed = True  # nothing left for close() at exit


def write_video(frames: list[np.ndarray], path: str, fps: int) -> None:
    """An mp4 of rendered frames (imageio with imageio-ffmpeg, in requirements.txt)."""
    import imageio.v2 as imageio

    writer = imageio.get_writer(path, fps=fps)
    for frame in frames:
        writer.append_data(frame)
    writer.close()
