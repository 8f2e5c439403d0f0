"""Cascade trained with DDPG on continuous-action tasks (single-file, CleanRL style; paper Appendix H.2).
The defaults follow the paper's own code (github codebro634/Cascade, SPEC.md §8b) where its text is silent;
`--n 1 --k 6000000 --hidden-size 64` is exactly the paper's DDPG baseline (64-64 tanh actor and critic).

The actor is a Cascade of base nets `obs -> 16 -> 16 -> mu` (tanh, the paper code's Cascade default). Every
`k` env steps a new base net b_i is stacked on the ensemble C_{i-1}; besides its raw action mu_i it emits a
fallback weight lambda_i(x) in [0, 1] and the ensemble becomes

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
Paper: Schmöcker & Dockhorn, "Cascade - A sequential ensemble method for continuous control tasks", RLJ 2025.

    python cascade_ddpg.py --env-id Hopper-v4                                    # Cascade: 6 nets, a new one every 1M steps
    python cascade_ddpg.py --env-id Hopper-v4 --n 1 --k 6000000 --hidden-size 64 --exp-name ddpg_baseline
    python cascade_ddpg.py --env-id Hopper-v4 --hidden-size 256 --critic-hidden-size 256 --activation relu \
        --no-anneal-lr --adam-eps 1e-8 --eval-deterministic --obs-reward-clip 0    # CleanRL's DDPG nets and settings
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
import zipfile
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Literal

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro

# The paper used the v4 MuJoCo tasks; gymnasium warns on every make that they are out of date.
warnings.filterwarnings("ignore", message=".*is out of date.*")


@dataclass
class Args:
    exp_name: str = "cascade_ddpg"
    """the name of this experiment (part of the run name); give the baseline its own, e.g. `ddpg_baseline`"""
    seed: int = 1
    """seed of the experiment (python, numpy, torch and the environments)"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    torch_threads: int = 1
    """torch CPU threads"""
    cuda: bool = False
    """use CUDA if available"""
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
    """ablation: fresh critic, target critic and critic optimizer when a base net is added (standard: kept)"""
    restart_on_new_net: bool = True
    """when a net is added, restart as the paper's code does: --learning-starts uniform-random steps without updates, target critic re-copied, target actor = copy of the whole cascade, critic optimizer recreated; `--no-restart-on-new-net`: all kept, the current policy collects the warm-up (the paper's text)"""

    # DDPG (CleanRL ddpg_continuous_action defaults)
    buffer_size: int = 1_000_000
    """the replay memory capacity (float32 numpy, preallocated; see the README for the memory it takes)"""
    gamma: float = 0.99
    """the discount factor gamma"""
    tau: float = 0.005
    """target smoothing coefficient"""
    batch_size: int = 256
    """the batch size sampled from the replay memory"""
    learning_starts: int = 25_000
    """transitions collected (since the buffer was last emptied) before updates start"""
    learning_rate: float = 3e-4
    """the learning rate of the actor and critic optimizers"""
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

    # Evaluation (SPEC §6)
    eval_every: int = 10_000
    """evaluate the frozen current policy every this many env steps (0 turns evaluation off)"""
    eval_episodes: int = 10
    """episodes per evaluation (on separate envs)"""
    eval_deterministic: bool = False
    """evaluate without exploration noise; by default the training noise is kept, as the paper's code evaluates"""
    eval_members: bool = True
    """at the end of each iteration, also evaluate each base net acting alone (`members/return/net_i`)"""

    # Checkpoints, resuming, evaluating a saved model
    resume: str | None = None
    """continue a killed run from its last iteration-boundary checkpoint (`runs/<run_name>` or a .pt file); the replay buffer restarts empty"""
    evaluate: str | None = None
    """evaluate a saved model (`runs/<run_name>` or a checkpoint file) for --eval-episodes episodes and exit"""
    members: bool = False
    """with --evaluate: also report the return of each base net acting alone"""
    quiet: bool = False
    """no progress display"""


# ----------------------------------------------------------------------------------------------
# Environment plumbing
# ----------------------------------------------------------------------------------------------
def fail(message: str) -> None:
    """Stop with a one-line error and a non-zero exit code."""
    raise SystemExit(f"error: {message}")


def check_env_id(env_id: str) -> None:
    if env_id not in gym.envs.registry:
        import difflib

        close = difflib.get_close_matches(env_id, list(gym.envs.registry), n=3)
        hint = f" Did you mean {', '.join(close)}?" if close else ""
        fail(f"unknown env id '{env_id}'.{hint} (see gymnasium's registry, e.g. Hopper-v4, Ant-v5)")


def make_env(env_id: str, clip: float, index: int = 0, video: bool = False) -> Callable[[], gym.Env]:
    """CleanRL's DDPG env (raw episode statistics; actions are clipped to the bounds before stepping), plus the
    paper's code's clipping of raw observations and rewards to +-clip (0: none). Returns stay raw. With `video`,
    the --capture-video recorder under them."""

    def thunk() -> gym.Env:
        env = gym.make(env_id, render_mode="rgb_array") if video else gym.make(env_id)
        if video:
            env = TrainingVideo(env)
        env = gym.wrappers.RecordEpisodeStatistics(env)
        if clip:
            env = gym.wrappers.TransformObservation(env, lambda obs: np.clip(obs, -clip, clip), env.observation_space)
            env = gym.wrappers.TransformReward(env, lambda r: np.clip(r, -clip, clip))
        return RunState(env, index)

    return thunk


def make_vector_env(env_id: str, clip: float, video: bool = False) -> gym.vector.SyncVectorEnv:
    # SAME_STEP: on a done step the returned obs is already the reset one and infos["final_obs"] holds the
    # real last one (the default NEXT_STEP mode would insert a fake transition after each episode).
    return gym.vector.SyncVectorEnv([make_env(env_id, clip, video=video)],
                                    autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)


def find_wrapper(env: gym.Env, wrapper_type: type) -> gym.Wrapper | None:
    while isinstance(env, gym.Wrapper):
        if isinstance(env, wrapper_type):
            return env
        env = env.env
    return None


# Plain-data attributes of an env and its wrappers: step counters, episode statistics, the env's RNG.
# Saved and restored so a resumed run continues the very same trajectories (MuJoCo's MjData is saved whole).
ENV_STATE_TYPES = (bool, int, float, np.ndarray, np.generic, np.random.Generator, collections.deque)


class RunState(gym.Wrapper):
    """Outermost wrapper that reads and restores what a run needs of its env (called by name via the vector env)."""

    def __init__(self, env: gym.Env, index: int):
        super().__init__(env)
        self.index = index

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


# ----------------------------------------------------------------------------------------------
# Replay buffer
# ----------------------------------------------------------------------------------------------
class ReplayBuffer:
    """Preallocated float32 numpy rows `[obs | next_obs | action | reward | done]`, one gather per sample.

    Humanoid-v4 (obs 376, act 17) at 1e6 rows: 1e6 * (2*376 + 17 + 2) * 4 bytes = 3.08 GB. np.zeros only
    maps pages, they become resident as rows are first written, and an emptied buffer refills the same rows,
    so the footprint is min(capacity, transitions per iteration) rows (`buffer_capacity`).
    """

    def __init__(self, capacity: int, obs_dim: int, act_dim: int):
        self.capacity, self.obs_dim, self.act_dim = capacity, obs_dim, act_dim
        self.data = np.zeros((capacity, self.row_width(obs_dim, act_dim)), dtype=np.float32)
        o, a = obs_dim, act_dim
        self.obs, self.next_obs = self.data[:, :o], self.data[:, o : 2 * o]
        self.actions, self.rewards, self.dones = self.data[:, 2 * o : 2 * o + a], self.data[:, -2], self.data[:, -1]
        self.pos = self.size = 0

    @staticmethod
    def row_width(obs_dim: int, act_dim: int) -> int:
        return 2 * obs_dim + act_dim + 2

    @staticmethod
    def nbytes(capacity: int, obs_dim: int, act_dim: int) -> int:
        """Bytes of a buffer of `capacity` rows (float32)."""
        return capacity * ReplayBuffer.row_width(obs_dim, act_dim) * 4

    def __len__(self) -> int:
        return self.size

    def add(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray, reward: np.ndarray,
            done: np.ndarray) -> None:
        """Append one row per env (the oldest rows are overwritten once full)."""
        for i in range(len(obs)):
            row = self.data[self.pos]
            o, a = self.obs_dim, self.act_dim
            row[:o], row[o : 2 * o], row[2 * o : 2 * o + a] = obs[i], next_obs[i], action[i]
            row[-2], row[-1] = reward[i], done[i]
            self.pos = (self.pos + 1) % self.capacity
            self.size = min(self.size + 1, self.capacity)

    def clear(self) -> None:
        """Empty the buffer: later samples only see rows added from now on."""
        self.pos = self.size = 0

    def sample(self, batch_size: int, device: torch.device) -> tuple[torch.Tensor, ...]:
        """(obs, actions, rewards, next_obs, dones) of `batch_size` uniformly drawn rows (numpy's global RNG)."""
        rows = torch.from_numpy(self.data[np.random.randint(0, self.size, size=batch_size)]).to(device)
        o, a = self.obs_dim, self.act_dim
        return rows[:, :o], rows[:, 2 * o : 2 * o + a], rows[:, -2], rows[:, o : 2 * o], rows[:, -1]


def store_transition(buffer: ReplayBuffer, obs: np.ndarray, actions: np.ndarray, next_obs: np.ndarray,
                     rewards: np.ndarray, terminations: np.ndarray, infos: dict) -> None:
    """Store one vector-env step. Under SAME_STEP autoreset `next_obs` of a finished env is already the reset
    obs; the transition needs the real last one (`final_obs`). Only terminations are stored as done: a
    truncated (time-limit) episode is bootstrapped from its final obs."""
    real_next_obs = next_obs.copy()
    if "_final_obs" in infos:
        for i in np.flatnonzero(infos["_final_obs"]):
            real_next_obs[i] = infos["final_obs"][i]
    buffer.add(obs, real_next_obs, actions, rewards, terminations)


def available_memory() -> int | None:
    """MemAvailable of /proc/meminfo in bytes (None where there is no such file)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def buffer_capacity(args: Args) -> int:
    """Rows the buffer can ever hold: an emptied-every-k buffer never needs more than k."""
    return min(args.buffer_size, args.n * args.k if args.keep_buffer else args.k)


# ----------------------------------------------------------------------------------------------
# Nets
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
        Orthogonal init (paper H); it names no gains, so CleanRL PPO's: sqrt(2) hidden, 0.01 output, zero bias."""
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
        weight = contributions(fallback)  # [n, B, 1]
        if self.combine_before_tanh:  # the paper's code: C_n = sum_i w_i mu_i, squashed once
            squashed = torch.tanh((weight * mu).sum(0))
        else:  # each net squashed into [-1, 1] first, then combined
            squashed = (weight * torch.tanh(mu)).sum(0)
        # sum_i w_i (scale*t_i + bias) = scale * sum_i w_i t_i + bias, as the weights sum to one
        action = squashed * self.action_scale + self.action_bias
        return action, fallback.squeeze(-1), weight.squeeze(-1)

    def member(self, obs: torch.Tensor, net: int) -> torch.Tensor:
        """Action of base net `net` (0-based) acting alone."""
        hidden = obs
        for weight, bias in zip(self.hidden_weights, self.hidden_biases):
            hidden = self.activation(torch.addmm(bias[net], hidden, weight[net]))
        return torch.tanh(torch.addmm(self.mu_bias[net], hidden, self.mu_weight[net])) * self.action_scale + self.action_bias


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


def count_parameters(*modules: nn.Module) -> int:
    return sum(p.numel() for m in modules for p in m.parameters())


def make_adam(params: list[nn.Parameter], lr: float, eps: float) -> torch.optim.Adam:
    """Adam (the paper's code: eps 1e-5); the fused kernel updates all parameters at once."""
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=True)


# ----------------------------------------------------------------------------------------------
# Evaluation (SPEC §6): frozen policy, separate envs; its own seeds and RNG
# ----------------------------------------------------------------------------------------------
Policy = Callable[[torch.Tensor, torch.Generator], tuple[torch.Tensor, torch.Tensor]]


class Evaluator:
    """Runs `episodes` episodes side by side on its own envs; never touches the training envs or RNG."""

    def __init__(self, env_id: str, episodes: int, seed: int, obs_clip: float):
        self.envs = [gym.make(env_id) for _ in range(episodes)]
        self.seed, self.obs_clip = seed, obs_clip

    @torch.inference_mode()
    def __call__(self, policy: Policy, call: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Runs `policy` (obs, generator -> action in bounds, fallbacks [m, B]); returns each episode's
        undiscounted return and the std of each fallback within each episode [episodes, m]. The episodes'
        seeds and the action noise depend only on (seed, call)."""
        episodes = len(self.envs)
        base_seed = self.seed + 100_003 * (call + 1)
        generator = torch.Generator().manual_seed(base_seed)
        obs = np.stack([env.reset(seed=base_seed + i)[0] for i, env in enumerate(self.envs)])
        low, high = self.envs[0].action_space.low, self.envs[0].action_space.high
        returns = np.zeros(episodes)
        fallbacks: list[list[np.ndarray]] = [[] for _ in range(episodes)]
        active = list(range(episodes))
        while active:
            seen = np.clip(obs[active], -self.obs_clip, self.obs_clip) if self.obs_clip else obs[active]  # as in training
            action, fallback = policy(torch.as_tensor(seen, dtype=torch.float32), generator)
            action = np.clip(action.numpy(), low, high)  # float32 rounding of scale*tanh+bias
            still_active = []
            for row, i in enumerate(active):
                fallbacks[i].append(fallback[:, row].numpy())
                o, r, terminated, truncated, _ = self.envs[i].step(action[row])
                returns[i] += r
                obs[i] = o
                if not (terminated or truncated):
                    still_active.append(i)
            active = still_active
        fallback_std = np.stack([np.stack(f).std(0) for f in fallbacks])
        return returns, fallback_std

    def close(self) -> None:
        for env in self.envs:
            env.close()


def full_policy(actor: CascadeActor, deterministic: bool, exploration_noise: float) -> Policy:
    """The whole cascade; without `deterministic`, with the training exploration noise."""

    def act(x: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        action, fallback, _ = actor(x)
        return add_noise(action, actor, 0.0 if deterministic else exploration_noise, generator), fallback

    return act


def member_policy(actor: CascadeActor, net: int, deterministic: bool, exploration_noise: float) -> Policy:
    """Base net `net` (0-based) acting alone; it has no fallbacks."""

    def act(x: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        action = actor.member(x, net)
        return add_noise(action, actor, 0.0 if deterministic else exploration_noise, generator), x.new_zeros(0, x.shape[0])

    return act


def add_noise(action: torch.Tensor, actor: CascadeActor, noise: float,
              generator: torch.Generator | None = None) -> torch.Tensor:
    """CleanRL's exploration: Gaussian noise of std noise * half range, clipped back into the bounds."""
    if noise:
        action = action + torch.randn(action.shape, generator=generator, device=action.device) * (
            actor.action_scale * noise)
    low, high = actor.action_bias - actor.action_scale, actor.action_bias + actor.action_scale
    return torch.maximum(torch.minimum(action, high), low)


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
# Checkpoints: written at the end of every iteration (the replay buffer is not saved)
# ----------------------------------------------------------------------------------------------
CHECKPOINT_NAME = "checkpoint.pt"
CHECKPOINT_FORMAT = "cascade_ddpg/2"  # /2: the paper's-code defaults (nets, LR, new-net restart, clipping)


def save_checkpoint(path: str, payload: dict) -> None:
    """Atomic: write a temp file, fsync, then rename over the old one (which stays intact until then).
    A failed write (a full disk, most often) removes the temp file and stops the run in one line."""
    tmp = f"{path}.tmp"
    with write_failures(path, tmp), open(tmp, "wb") as f:
        torch.save(payload, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def atomic_copy(source: str, path: str) -> None:
    """Copy `source` to `path` as `save_checkpoint` writes: temp file, fsync, rename."""
    tmp = f"{path}.tmp"
    with write_failures(path, tmp), open(source, "rb") as src, open(tmp, "wb") as dst:
        shutil.copyfileobj(src, dst)
        dst.flush()
        os.fsync(dst.fileno())
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


def repair_iteration_files(run_dir: str, checkpoint: dict, at_iteration_end: bool) -> None:
    """On resume: every finished iteration's iteration_<i>.pt should be there and readable (plots/analyze.py reads
    them). One that a kill left missing or truncated is rebuilt from the checkpoint when that holds the same state
    (the end of that iteration); otherwise the run says in one line that it cannot be rebuilt."""
    for stale in glob.glob(os.path.join(glob.escape(run_dir), "*.pt.tmp")):
        os.remove(stale)  # a write the kill interrupted
    finished = checkpoint["iteration"] if at_iteration_end else checkpoint["iteration"] - 1
    for i in range(1, finished + 1):
        path = os.path.join(run_dir, f"iteration_{i}.pt")
        if os.path.isfile(path) and zipfile.is_zipfile(path):  # torch.save writes a zip archive: truncated ones fail
            continue
        if i == checkpoint["iteration"] and at_iteration_end:
            atomic_copy(checkpoint["path"], path)
            print(f"note: rebuilt {path} from {checkpoint['path']} (the same state: the end of iteration {i})")
        else:
            print(f"note: {path} is missing or damaged and cannot be rebuilt (the run has moved past iteration {i}); "
                  "analyses of that iteration (plots/analyze.py) are unavailable for this run", file=sys.stderr)


def load_checkpoint(path: str) -> dict:
    """Load `runs/<run>` (its latest checkpoint) or a checkpoint file; one-line error if missing or corrupt."""
    if os.path.isdir(path):
        path = os.path.join(path, CHECKPOINT_NAME)
    if not os.path.isfile(path):
        fail(f"no checkpoint at {path}; pass a run folder holding {CHECKPOINT_NAME} or a checkpoint file")
    try:
        # weights_only=False: the file holds numpy arrays and the simulator state; load only your own runs
        checkpoint = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:
        fail(f"cannot read checkpoint {path} (corrupt or not a checkpoint: {type(exc).__name__})")
    if isinstance(checkpoint, dict) and str(checkpoint.get("format", "")).startswith("cascade_ddpg/"):
        if checkpoint["format"] != CHECKPOINT_FORMAT:
            fail(f"{path} was written by an older cascade_ddpg.py ({checkpoint['format']}, before the paper's-code "
                 f"defaults of {CHECKPOINT_FORMAT}); it cannot be resumed or evaluated exactly: start a new run")
    else:
        fail(f"{path} is not a cascade_ddpg checkpoint")
    checkpoint["path"] = path
    return checkpoint


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


class Progress:
    """One self-updating line on a terminal; plain lines every `interval` seconds otherwise."""

    def __init__(self, total_steps: int, quiet: bool, interval: float = 30.0):
        self.total, self.quiet, self.interval = total_steps, quiet, interval
        self.tty = sys.stdout.isatty()
        self.last_print = 0.0
        self.last_eval: float | None = None

    def update(self, step: int, sps: float, size: int, force: bool = False) -> None:
        now = time.time()
        if self.quiet or (not force and now - self.last_print < (0.5 if self.tty else self.interval)):
            return
        self.last_print = now
        eta = (self.total - step) / max(sps, 1e-9)
        ev = "-" if self.last_eval is None else f"{self.last_eval:.1f}"
        line = (f"{step:>10,}/{self.total:,} steps ({100 * step / self.total:5.1f}%) | {sps:6.0f} SPS | "
                f"{size} net(s) | eval {ev} | ETA {time.strftime('%H:%M:%S', time.gmtime(eta))}")
        print(f"\r{line}" if self.tty else line, end="" if self.tty else "\n", flush=True)

    def message(self, text: str) -> None:
        """A normal line that does not garble the progress line."""
        if self.quiet:
            return
        print(f"\r\033[K{text}" if self.tty else text, flush=True)


# ----------------------------------------------------------------------------------------------
# Training
# ----------------------------------------------------------------------------------------------
def check_run_settings(args: Args) -> None:
    """Settings every run shares, refused in one line each (instead of a traceback later, or a run folder left)."""
    if args.seed < 0:
        fail(f"--seed must be a non-negative integer (got {args.seed}); numpy and gymnasium refuse negative seeds")
    if args.torch_threads < 1:
        fail(f"--torch-threads must be at least 1 (got {args.torch_threads})")
    if not args.learning_rate >= 0:
        fail(f"--learning-rate must be >= 0 (got {args.learning_rate})")
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


def validate(args: Args) -> None:
    """Reject bad input with one clear line before anything is created."""
    check_run_settings(args)
    if args.n < 1:
        fail(f"--n must be at least 1 (got {args.n})")
    if not 0.0 < args.fallback_init < 1.0:
        fail(f"--fallback-init must lie strictly between 0 and 1 (got {args.fallback_init})")
    if args.hidden_size < 1 or args.num_layers < 1 or args.critic_hidden_size < 1:
        fail("--hidden-size, --num-layers and --critic-hidden-size must be at least 1")
    if not args.adam_eps > 0:
        fail(f"--adam-eps must be > 0 (got {args.adam_eps})")
    if not args.obs_reward_clip >= 0:
        fail(f"--obs-reward-clip must be >= 0 (0: no clipping; got {args.obs_reward_clip})")
    if args.batch_size < 1 or args.learning_starts < 0:
        fail("--batch-size must be at least 1 and --learning-starts at least 0")
    if args.k <= args.learning_starts:
        fail(f"--k {args.k} must exceed --learning-starts {args.learning_starts} (each emptied buffer is first "
             "filled with learning-starts steps before updates resume)")
    if args.buffer_size < max(args.batch_size, args.learning_starts + 1):
        fail(f"--buffer-size {args.buffer_size} must hold at least --batch-size and --learning-starts + 1 rows")
    if args.policy_frequency < 1:
        fail("--policy-frequency must be at least 1")
    if not 0.0 < args.tau <= 1.0:
        fail(f"--tau must lie in (0, 1] (got {args.tau})")
    if args.eval_every < 0 or (args.eval_every and args.eval_episodes < 1):
        fail("--eval-every must be >= 0 and --eval-episodes >= 1")
    check_env_id(args.env_id)
    probe = gym.make(args.env_id)
    action_space, observation_space = probe.action_space, probe.observation_space
    probe.close()
    if not isinstance(action_space, gym.spaces.Box):
        fail(f"{args.env_id} has a {type(action_space).__name__} action space; this script needs a Box "
             "(continuous) one: use cascade_ppo_discrete.py")
    if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
        fail(f"{args.env_id} has unbounded actions; the actor's tanh outputs are rescaled to finite bounds")
    if not isinstance(observation_space, gym.spaces.Box) or len(observation_space.shape) != 1:
        fail(f"{args.env_id} needs a flat Box observation space (got {observation_space})")
    if args.capture_video:
        make_render_env(args.env_id).close()  # no renderer (OpenGL backend, pygame): one line now, not a traceback later
    rows = buffer_capacity(args)
    need = ReplayBuffer.nbytes(rows, observation_space.shape[0], int(np.prod(action_space.shape)))
    free = available_memory()
    if free is not None and need > free:
        fail(f"the replay buffer needs {need / 1e9:.2f} GB ({rows} rows) but only {free / 1e9:.2f} GB is available; "
             "lower --buffer-size")


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


def train(args: Args, checkpoint: dict | None = None,
          on_iteration_start: Callable[[dict], None] | None = None) -> dict:
    """Runs Cascade-DDPG (from scratch, or continuing an iteration-boundary `checkpoint`); returns the final
    nets, buffer and run folder. `on_iteration_start` sees the state of each iteration (used by the tests)."""
    validate(args)
    torch.set_num_threads(args.torch_threads)
    seed_everything(args.seed, args.torch_deterministic)
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")

    envs = make_vector_env(args.env_id, args.obs_reward_clip, args.capture_video)
    obs_dim = int(np.prod(envs.single_observation_space.shape))
    act_dim = int(np.prod(envs.single_action_space.shape))
    action_low, action_high = envs.single_action_space.low, envs.single_action_space.high

    from torch.utils.tensorboard import SummaryWriter

    if checkpoint is None:
        run_dir = os.path.join(args.track_dir, f"{args.env_id}__{args.exp_name}__{args.seed}__{int(time.time())}")
    else:
        run_dir = os.path.dirname(checkpoint["path"])
        repair_iteration_files(run_dir, checkpoint, at_iteration_end=True)
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

    actor = CascadeActor(obs_dim, act_dim, args.hidden_size, args.num_layers, args.fallback_init,
                         action_low, action_high, args.activation, args.combine_before_tanh).to(device)
    target_actor = copy.deepcopy(actor)

    def make_critic() -> QNetworks:
        return QNetworks(obs_dim, act_dim, hidden_size=args.critic_hidden_size, activation=args.activation).to(device)

    qf = make_critic()
    qf_target = copy.deepcopy(qf)
    q_optimizer = make_adam(list(qf.parameters()), args.learning_rate, args.adam_eps)
    buffer = ReplayBuffer(buffer_capacity(args), obs_dim, act_dim)
    evaluator = Evaluator(args.env_id, args.eval_episodes, args.seed, args.obs_reward_clip) if args.eval_every else None
    eval_calls = 0
    progress = Progress(args.n * args.k, args.quiet)

    def evaluate(step: int, members: bool = False) -> None:
        """Freeze the current policy and evaluate it on the evaluator's own envs (SPEC §6)."""
        nonlocal eval_calls
        frozen = actor if device.type == "cpu" else copy.deepcopy(actor).cpu()
        kinds = range(1, frozen.size + 1) if members else [0]
        for kind in kinds:
            policy = (full_policy(frozen, args.eval_deterministic, args.exploration_noise) if kind == 0
                      else member_policy(frozen, kind - 1, args.eval_deterministic, args.exploration_noise))
            returns, fallback_std = evaluator(policy, eval_calls)
            eval_calls += 1
            if kind == 0:
                writer.add_scalar("eval/episodic_return", returns.mean(), step)
                writer.add_scalar("eval/episodic_return_std", returns.std(), step)
                for j, std in enumerate(fallback_std.mean(0)):
                    writer.add_scalar(f"cascade/fallback_std/net_{j + 2}", std, step)
                progress.last_eval = float(returns.mean())
                progress.message(f"global_step={step}, eval/episodic_return={returns.mean():.1f} ± {returns.std():.1f}")
            else:
                writer.add_scalar(f"members/return/net_{kind}", returns.mean(), step)
                progress.message(f"global_step={step}, members/return/net_{kind}={returns.mean():.1f}")

    def make_checkpoint(iteration: int) -> dict:
        return {
            "format": CHECKPOINT_FORMAT, "args": asdict(args), "obs_dim": obs_dim, "act_dim": act_dim,
            "action_low": action_low, "action_high": action_high,
            "iteration": iteration, "global_step": global_step, "elapsed": time.time() - start_time,
            "actor": actor.state_dict(), "target_actor": target_actor.state_dict(), "actor_size": actor.size,
            "qf": qf.state_dict(), "qf_target": qf_target.state_dict(), "q_optimizer": q_optimizer.state_dict(),
            "env_states": envs.call("get_state"), "next_obs": next_obs.copy(), "rng": rng_states(),
            # the uniform random warm-up actions of each new net come from the action space's own RNG
            "action_space_rng": envs.single_action_space.np_random.bit_generator.state,
            "eval_calls": eval_calls, "wandb_run_id": wandb_run_id,
        }

    if checkpoint is None:
        global_step, start_iteration = 0, 1
        start_time = time.time()
        next_obs, _ = envs.reset(seed=args.seed)
        envs.single_action_space.seed(args.seed)  # the uniform random actions at the start of the run
        if evaluator is not None:
            evaluate(0)
    else:
        global_step, start_iteration = checkpoint["global_step"], checkpoint["iteration"] + 1
        start_time = time.time() - checkpoint["elapsed"]
        envs.reset(seed=args.seed)  # sets up the vector env; then the env gets its saved state back
        envs.call("set_state", checkpoint["env_states"])
        envs.single_action_space.np_random.bit_generator.state = checkpoint["action_space_rng"]
        next_obs = checkpoint["next_obs"]
        actor = actor_from_checkpoint(checkpoint, device)
        target_actor = actor_from_checkpoint(checkpoint, device, key="target_actor")
        qf.load_state_dict(checkpoint["qf"])
        qf_target.load_state_dict(checkpoint["qf_target"])
        q_optimizer.load_state_dict(checkpoint["q_optimizer"])
        eval_calls = checkpoint["eval_calls"]
        set_rng_states(checkpoint["rng"])
        progress.message(f"resumed {checkpoint['path']} at global_step={global_step} (iteration "
                         f"{start_iteration}, empty replay buffer)")

    for iteration in range(start_iteration, args.n + 1):
        # --- a new Cascade iteration: new base net, emptied buffer, kept critic, fresh actor optimizer ---
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
        actor_optimizer = make_adam(list(actor.parameters()), args.learning_rate, args.adam_eps)
        size = actor.size
        n_params = count_parameters(actor, qf)
        writer.add_scalar("cascade/size", size, global_step)
        writer.add_scalar("cascade/parameters", n_params, global_step)
        progress.message(f"iteration {iteration}/{args.n}: {size} base net(s), {n_params} parameters (actor + critic)")
        if on_iteration_start is not None:
            on_iteration_start({"iteration": iteration, "actor": actor, "target_actor": target_actor, "qf": qf,
                                "qf_target": qf_target, "q_optimizer": q_optimizer,
                                "actor_optimizer": actor_optimizer, "buffer": buffer, "envs": envs,
                                "next_obs": next_obs, "global_step": global_step})

        actor_loss = None  # set by the first actor update of the iteration
        for step_in_iteration in range(args.k):
            global_step += 1
            if args.anneal_lr:  # the paper's code: linearly to 0 within each iteration
                lr_now = (1.0 - step_in_iteration / args.k) * args.learning_rate
                q_optimizer.param_groups[0]["lr"] = actor_optimizer.param_groups[0]["lr"] = lr_now
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
                actions = np.array([envs.single_action_space.sample()])
            else:
                with torch.no_grad():
                    actions, _, _ = actor(torch.as_tensor(next_obs, dtype=torch.float32, device=device))
                    actions = add_noise(actions, actor, args.exploration_noise)
                actions = actions.cpu().numpy()
            obs = next_obs
            next_obs, rewards, terminations, truncations, infos = envs.step(actions)
            if "final_info" in infos and "episode" in infos["final_info"]:
                finished = infos["final_info"]["_episode"]
                for ret, length in zip(infos["final_info"]["episode"]["r"][finished],
                                       infos["final_info"]["episode"]["l"][finished]):
                    writer.add_scalar("charts/episodic_return", ret, global_step)
                    writer.add_scalar("charts/episodic_length", length, global_step)
                if args.track:  # a video ends with its episode
                    log_new_videos(video_folder, videos_sent, global_step)
            store_transition(buffer, obs, actions, next_obs, rewards, terminations, infos)

            if learning:
                b_obs, b_actions, b_rewards, b_next_obs, b_dones = buffer.sample(args.batch_size, device)
                with torch.no_grad():
                    next_actions, _, _ = target_actor(b_next_obs)
                    # b_dones are terminations only: truncated episodes bootstrap
                    next_q_value = b_rewards + (1 - b_dones) * args.gamma * qf_target(b_next_obs, next_actions)[0]
                qf1_a_values = qf(b_obs, b_actions)[0]
                qf1_loss = F.mse_loss(qf1_a_values, next_q_value)
                q_optimizer.zero_grad()
                qf1_loss.backward()
                q_optimizer.step()

                if step_in_iteration % args.policy_frequency == 0:  # counted from 0 with each net (the paper's code)
                    qf.requires_grad_(False)  # the actor loss needs dQ/da only; skip the critic's weight gradients
                    actor_loss = -qf(b_obs, actor(b_obs)[0])[0].mean()
                    actor_optimizer.zero_grad()
                    actor_loss.backward()
                    actor_optimizer.step()
                    qf.requires_grad_(True)
                    soft_update(target_actor, actor, args.tau)
                    soft_update(qf_target, qf, args.tau)

                if global_step % 100 == 0 and actor_loss is not None:
                    writer.add_scalar("losses/qf1_values", qf1_a_values.mean().item(), global_step)
                    writer.add_scalar("losses/qf1_loss", qf1_loss.item(), global_step)
                    writer.add_scalar("losses/actor_loss", actor_loss.item(), global_step)
                    writer.add_scalar("charts/learning_rate", actor_optimizer.param_groups[0]["lr"], global_step)
                    # fallback metrics: means over the sampled replay batch (states of this iteration's data)
                    with torch.no_grad():
                        _, batch_fallback, batch_contribution = actor(b_obs)
                    mean_weight = batch_contribution.mean(1)
                    for j, lam in enumerate(batch_fallback.mean(1).tolist()):
                        writer.add_scalar(f"cascade/fallback/net_{j + 2}", lam, global_step)
                    for j, w in enumerate(mean_weight.tolist()):
                        writer.add_scalar(f"cascade/contribution/net_{j + 1}", w, global_step)
                    writer.add_scalar("cascade/fallback_product", mean_weight[0].item(), global_step)
                    # --- non-finite guard: stop before anything bad reaches a checkpoint ---
                    if not all(map(math.isfinite, [qf1_loss.item(), actor_loss.item()])) or not all(
                        torch.isfinite(p).all() for p in [*actor.parameters(), *qf.parameters()]
                    ):
                        writer.close()
                        fail(f"non-finite loss or parameters at global_step={global_step} (iteration {iteration}); "
                             f"{non_finite_advice(checkpoint_path)}")

            if global_step % 100 == 0:
                sps = global_step / (time.time() - start_time)
                writer.add_scalar("charts/SPS", int(sps), global_step)
                progress.update(global_step, sps, size)
            if evaluator is not None and global_step % args.eval_every == 0:
                evaluate(global_step)

        # --- end of the iteration: member returns, then an atomic checkpoint ---
        if evaluator is not None and args.eval_members:
            evaluate(global_step, members=True)
        if not all(torch.isfinite(p).all() for p in [*actor.parameters(), *qf.parameters()]):
            writer.close()
            fail(f"non-finite parameters at global_step={global_step} (iteration {iteration}); "
                 f"{non_finite_advice(checkpoint_path)}")
        save_checkpoint(checkpoint_path, make_checkpoint(iteration))
        atomic_copy(checkpoint_path, os.path.join(run_dir, f"iteration_{iteration}.pt"))
        progress.message(f"iteration {iteration} done: global_step={global_step}, "
                         f"SPS={int(global_step / (time.time() - start_time))}")

    if evaluator is not None:
        if global_step % args.eval_every:
            evaluate(global_step)  # the final policy, if the last step was not an eval step
        evaluator.close()
    envs.close()
    writer.close()
    if args.track:
        log_new_videos(video_folder, videos_sent, global_step)
        finish_wandb(exit_code=0)
    return {"actor": actor, "target_actor": target_actor, "qf": qf, "qf_target": qf_target, "buffer": buffer,
            "run_dir": run_dir, "global_step": global_step}


# ----------------------------------------------------------------------------------------------
# Command line: train, resume, or evaluate a saved model
# ----------------------------------------------------------------------------------------------
# Settings a resumed run may change; every other flag must match the checkpoint.
RESUME_OVERRIDABLE = {"resume", "quiet", "torch_threads", "cuda", "track", "wandb_project_name", "wandb_entity",
                      "wandb_group"}


def explicit_fields(argv: list[str]) -> set[str]:
    """Names of the Args fields given on the command line (`--env-id X`, `--no-eval-members`, ...)."""
    names = set(Args.__dataclass_fields__)
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


def evaluate_saved(args: Args) -> dict:
    """--evaluate: the saved actor on --eval-episodes fresh episodes (with exploration noise unless --eval-deterministic)."""
    if args.eval_episodes < 1:
        fail(f"--eval-episodes must be at least 1 (got {args.eval_episodes})")
    checkpoint = load_checkpoint(args.evaluate)
    saved = Args(**checkpoint["args"])
    torch.set_num_threads(args.torch_threads)
    actor = actor_from_checkpoint(checkpoint)
    evaluator = Evaluator(saved.env_id, args.eval_episodes, args.seed, saved.obs_reward_clip)
    returns, _ = evaluator(full_policy(actor, args.eval_deterministic, saved.exploration_noise))
    mode = "noise-free" if args.eval_deterministic else "exploration-noise"
    print(f"{saved.env_id}, {actor.size} base net(s), step {checkpoint['global_step']}: "
          f"return {returns.mean():.1f} ± {returns.std():.1f} over {len(returns)} {mode} episodes")
    result = {"returns": returns, "members": []}
    if args.members:
        for net in range(actor.size):
            member_returns, _ = evaluator(member_policy(actor, net, args.eval_deterministic, saved.exploration_noise))
            result["members"].append(member_returns)
            print(f"  net {net + 1} alone: {member_returns.mean():.1f} ± {member_returns.std():.1f}")
    evaluator.close()
    return result


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
        if checkpoint["iteration"] >= args.n:
            print(f"{checkpoint['path']} is the end of the run (iteration {checkpoint['iteration']} of {args.n}); "
                  "nothing to resume")
            return
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
