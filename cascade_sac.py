"""Cascade trained with SAC on continuous-action tasks (single-file, CleanRL style; paper Appendix H.1).
`--n 1 --hidden-size 256 --k 2000000` is exactly the paper's SAC baseline (its code: CleanRL
sac_continuous_action with orthogonal init and alpha fixed at 0.2).

The actor is a Cascade of base nets `obs -> 128 -> 128 -> (mean, log-std)` (ReLU). Every `k` env steps a
new base net b_i is stacked on the ensemble C_{i-1}; besides its mean and state-dependent log-std it emits
a fallback weight lambda_i(x) in [0, 1] and the ensemble becomes

    C_i(x) = lambda_i(x) * C_{i-1}(x) + (1 - lambda_i(x)) * b_i(x)     (mean and log-std, before the tanh squash)

The whole stack is trained end to end by SAC. When a net is added, as in the paper's code (a new SAC
instance per net): the replay buffer is emptied, `--learning-starts` uniform-random steps without updates
follow, the twin critics are kept but their targets are re-copied from them and their optimizer is
recreated, and the actor optimizer is recreated over all actor nets (`--no-restart-on-new-net`: the
paper's text read literally, targets and critic optimizer kept, the current policy collects the warm-up).
`--keep-buffer` and `--reset-critic` are the ablations. Alpha is fixed at 0.2 (the paper's code;
`--autotune` is CleanRL's default). No observation/reward normalization; raw observations and rewards are
clipped to +-10 (the paper's code, `--obs-reward-clip 0` turns that off).
Paper: Schmöcker & Dockhorn, "Cascade - A sequential ensemble method for continuous control tasks",
RLJ 2025; SPEC.md §8.

    python cascade_sac.py --env-id Hopper-v4                                              # Cascade: 4 nets, a new one every 500k steps
    python cascade_sac.py --env-id Hopper-v4 --n 1 --hidden-size 256 --k 2000000 --exp-name sac_baseline
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
    exp_name: str = "cascade_sac"
    """the name of this experiment (part of the run name); give the baseline its own, e.g. `sac_baseline`"""
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
    """ablation: fresh critics, targets and critic optimizer when a base net is added (standard: kept)"""
    restart_on_new_net: bool = True
    """when a net is added, restart as the paper's code does: --learning-starts uniform-random steps without updates, target critics re-copied, critic optimizer recreated; `--no-restart-on-new-net`: targets and optimizer kept, the current policy collects the warm-up (the paper's text)"""

    # SAC (CleanRL sac_continuous_action defaults)
    buffer_size: int = 1_000_000
    """the replay memory capacity (float32 numpy, preallocated; see the README for the memory it takes)"""
    gamma: float = 0.99
    """the discount factor gamma"""
    tau: float = 0.005
    """target smoothing coefficient"""
    batch_size: int = 256
    """the batch size sampled from the replay memory"""
    learning_starts: int = 5_000
    """transitions collected (since the buffer was last emptied) before updates start"""
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

    # Evaluation (SPEC §6)
    eval_every: int = 10_000
    """evaluate the frozen current policy every this many env steps (0 turns evaluation off)"""
    eval_episodes: int = 10
    """episodes per evaluation (on separate envs)"""
    eval_deterministic: bool = False
    """evaluate with the squashed mean action instead of sampling (default: stochastic policy, SPEC §6)"""
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
    """CleanRL's SAC env (raw episode statistics; no action clipping: actions are squashed into bounds), plus
    the paper's code's clipping of raw observations and rewards to +-clip (0: none). Returns stay raw. With `video`,
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
        weight = contributions(fallback)  # [n, B, 1]
        combined = (weight * out).sum(0)  # C_n = sum_i w_i b_i, for mean and raw log-std at once
        # the paper's code bounds the combined raw log-std (SAC's get_action), not each net's
        return combined[:, : self.act_dim], bounded_log_std(combined[:, self.act_dim :]), fallback.squeeze(-1), \
            weight.squeeze(-1)

    def get_action(self, obs: torch.Tensor, generator: torch.Generator | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(sampled action in the env's bounds, its log-prob [B, 1], squashed mean action) of the whole cascade."""
        mean, log_std, _, _ = self(obs)
        return squashed_sample(mean, log_std, self.action_scale, self.action_bias, generator)

    def member(self, obs: torch.Tensor, net: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std of base net `net` (0-based) acting alone."""
        hidden = obs
        for weight, bias in zip(self.hidden_weights, self.hidden_biases):
            hidden = torch.relu(torch.addmm(bias[net], hidden, weight[net]))
        out = torch.addmm(self.head_bias[net], hidden, self.head_weight[net])
        return out[:, : self.act_dim], bounded_log_std(out[:, self.act_dim :])


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


def count_parameters(*modules: nn.Module) -> int:
    return sum(p.numel() for m in modules for p in m.parameters())


def make_adam(params: list[nn.Parameter], lr: float) -> torch.optim.Adam:
    """CleanRL's Adam (default eps); the fused kernel updates all parameters at once."""
    return torch.optim.Adam(params, lr=lr, fused=True)


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


def full_policy(actor: CascadeActor, deterministic: bool) -> Policy:
    def act(x: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std, fallback, _ = actor(x)
        sample, _, mean_action = squashed_sample(mean, log_std, actor.action_scale, actor.action_bias, generator)
        return (mean_action if deterministic else sample), fallback

    return act


def member_policy(actor: CascadeActor, net: int, deterministic: bool) -> Policy:
    """Base net `net` (0-based) acting alone with its own mean and log-std; it has no fallbacks."""

    def act(x: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = actor.member(x, net)
        sample, _, mean_action = squashed_sample(mean, log_std, actor.action_scale, actor.action_bias, generator)
        return (mean_action if deterministic else sample), x.new_zeros(0, x.shape[0])

    return act


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
CHECKPOINT_FORMAT = "cascade_sac/2"  # /2: the paper's-code defaults (alpha, log-std, new-net restart, clipping)


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
    remedy = "start a new run with a lower --policy-lr / --q-lr (or another --seed)"
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
    if isinstance(checkpoint, dict) and str(checkpoint.get("format", "")).startswith("cascade_sac/"):
        if checkpoint["format"] != CHECKPOINT_FORMAT:
            fail(f"{path} was written by an older cascade_sac.py ({checkpoint['format']}, before the paper's-code "
                 f"defaults of {CHECKPOINT_FORMAT}); it cannot be resumed or evaluated exactly: start a new run")
    else:
        fail(f"{path} is not a cascade_sac checkpoint")
    checkpoint["path"] = path
    return checkpoint


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
    if not args.policy_lr >= 0:
        fail(f"--policy-lr must be >= 0 (got {args.policy_lr})")
    if not args.q_lr >= 0:
        fail(f"--q-lr must be >= 0 (got {args.q_lr})")
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
    if args.hidden_size < 1 or args.num_layers < 1:
        fail("--hidden-size and --num-layers must be at least 1")
    if not args.obs_reward_clip >= 0:
        fail(f"--obs-reward-clip must be >= 0 (0: no clipping; got {args.obs_reward_clip})")
    if args.batch_size < 1 or args.learning_starts < 0:
        fail("--batch-size must be at least 1 and --learning-starts at least 0")
    if args.k <= args.learning_starts:
        fail(f"--k {args.k} must exceed --learning-starts {args.learning_starts} (each emptied buffer is first "
             "filled with learning-starts steps before updates resume)")
    if args.buffer_size < max(args.batch_size, args.learning_starts + 1):
        fail(f"--buffer-size {args.buffer_size} must hold at least --batch-size and --learning-starts + 1 rows")
    if args.policy_frequency < 1 or args.target_network_frequency < 1:
        fail("--policy-frequency and --target-network-frequency must be at least 1")
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
        fail(f"{args.env_id} has unbounded actions; SAC squashes actions into finite bounds")
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
    """Runs Cascade-SAC (from scratch, or continuing an iteration-boundary `checkpoint`); returns the final
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
                         action_low, action_high).to(device)
    qf = QNetworks(obs_dim, act_dim).to(device)
    qf_target = copy.deepcopy(qf)
    q_optimizer = make_adam(list(qf.parameters()), args.q_lr)
    target_entropy = -float(act_dim)
    log_alpha = torch.zeros(1, requires_grad=True, device=device)
    a_optimizer = make_adam([log_alpha], args.q_lr)
    alpha = log_alpha.exp().item() if args.autotune else args.alpha
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
            policy = (full_policy(frozen, args.eval_deterministic) if kind == 0
                      else member_policy(frozen, kind - 1, args.eval_deterministic))
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
            "actor": actor.state_dict(), "actor_size": actor.size,
            "qf": qf.state_dict(), "qf_target": qf_target.state_dict(), "q_optimizer": q_optimizer.state_dict(),
            "log_alpha": log_alpha.detach().cpu(), "a_optimizer": a_optimizer.state_dict(), "alpha": alpha,
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
        qf.load_state_dict(checkpoint["qf"])
        qf_target.load_state_dict(checkpoint["qf_target"])
        q_optimizer.load_state_dict(checkpoint["q_optimizer"])
        with torch.no_grad():
            log_alpha.copy_(checkpoint["log_alpha"])
        a_optimizer.load_state_dict(checkpoint["a_optimizer"])
        alpha, eval_calls = checkpoint["alpha"], checkpoint["eval_calls"]
        set_rng_states(checkpoint["rng"])
        progress.message(f"resumed {checkpoint['path']} at global_step={global_step} (iteration "
                         f"{start_iteration}, empty replay buffer)")

    for iteration in range(start_iteration, args.n + 1):
        # --- a new Cascade iteration: new base net, emptied buffer, kept critics, fresh actor optimizer ---
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
        actor_optimizer = make_adam(list(actor.parameters()), args.policy_lr)
        size = actor.size
        n_params = count_parameters(actor, qf)
        writer.add_scalar("cascade/size", size, global_step)
        writer.add_scalar("cascade/parameters", n_params, global_step)
        progress.message(f"iteration {iteration}/{args.n}: {size} base net(s), {n_params} parameters (actor + critics)")
        if on_iteration_start is not None:
            on_iteration_start({"iteration": iteration, "actor": actor, "qf": qf, "qf_target": qf_target,
                                "q_optimizer": q_optimizer, "actor_optimizer": actor_optimizer,
                                "log_alpha": log_alpha, "a_optimizer": a_optimizer, "buffer": buffer,
                                "envs": envs, "next_obs": next_obs, "global_step": global_step})

        actor_loss = alpha_loss = None  # set by the first actor update of the iteration
        for step_in_iteration in range(args.k):
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
                actions = np.array([envs.single_action_space.sample()])
            else:
                with torch.no_grad():
                    actions, _, _ = actor.get_action(torch.as_tensor(next_obs, dtype=torch.float32, device=device))
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
                    next_actions, next_log_pi, _ = actor.get_action(b_next_obs)
                    min_qf_next = qf_target(b_next_obs, next_actions).min(0).values - alpha * next_log_pi.view(-1)
                    # b_dones are terminations only: truncated episodes bootstrap
                    next_q_value = b_rewards + (1 - b_dones) * args.gamma * min_qf_next
                qf_a_values = qf(b_obs, b_actions)  # [2, B]
                qf1_loss = F.mse_loss(qf_a_values[0], next_q_value)
                qf2_loss = F.mse_loss(qf_a_values[1], next_q_value)
                qf_loss = qf1_loss + qf2_loss
                q_optimizer.zero_grad()
                qf_loss.backward()
                q_optimizer.step()

                # TD3-style delay, compensated by as many updates; counted from 0 with each net, as the paper's
                # code (a new instance per net) and CleanRL (a 0-based step) count it
                if step_in_iteration % args.policy_frequency == 0:
                    qf.requires_grad_(False)  # the actor loss needs dQ/da only; skip the critics' weight gradients
                    for _ in range(args.policy_frequency):
                        pi, log_pi, _ = actor.get_action(b_obs)
                        min_qf_pi = qf(b_obs, pi).min(0).values
                        actor_loss = (alpha * log_pi.view(-1) - min_qf_pi).mean()
                        actor_optimizer.zero_grad()
                        actor_loss.backward()
                        actor_optimizer.step()
                        if args.autotune:
                            with torch.no_grad():
                                _, log_pi, _ = actor.get_action(b_obs)
                            alpha_loss = (-log_alpha.exp() * (log_pi + target_entropy)).mean()
                            a_optimizer.zero_grad()
                            alpha_loss.backward()
                            a_optimizer.step()
                            alpha = log_alpha.exp().item()
                    qf.requires_grad_(True)

                if step_in_iteration % args.target_network_frequency == 0:
                    soft_update(qf_target, qf, args.tau)

                if global_step % 100 == 0 and actor_loss is not None:
                    writer.add_scalar("losses/qf1_values", qf_a_values[0].mean().item(), global_step)
                    writer.add_scalar("losses/qf2_values", qf_a_values[1].mean().item(), global_step)
                    writer.add_scalar("losses/qf1_loss", qf1_loss.item(), global_step)
                    writer.add_scalar("losses/qf2_loss", qf2_loss.item(), global_step)
                    writer.add_scalar("losses/qf_loss", qf_loss.item() / 2.0, global_step)
                    writer.add_scalar("losses/actor_loss", actor_loss.item(), global_step)
                    writer.add_scalar("losses/alpha", alpha, global_step)
                    if args.autotune:
                        writer.add_scalar("losses/alpha_loss", alpha_loss.item(), global_step)
                    # fallback metrics: means over the sampled replay batch (states of this iteration's data)
                    with torch.no_grad():
                        _, _, batch_fallback, batch_contribution = actor(b_obs)
                    mean_weight = batch_contribution.mean(1)
                    for j, lam in enumerate(batch_fallback.mean(1).tolist()):
                        writer.add_scalar(f"cascade/fallback/net_{j + 2}", lam, global_step)
                    for j, w in enumerate(mean_weight.tolist()):
                        writer.add_scalar(f"cascade/contribution/net_{j + 1}", w, global_step)
                    writer.add_scalar("cascade/fallback_product", mean_weight[0].item(), global_step)
                    # --- non-finite guard: stop before anything bad reaches a checkpoint ---
                    losses = [qf_loss.item(), actor_loss.item(), alpha]
                    if not all(map(math.isfinite, losses)) or not all(
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
    return {"actor": actor, "qf": qf, "qf_target": qf_target, "buffer": buffer, "run_dir": run_dir,
            "global_step": global_step, "alpha": alpha}


# ----------------------------------------------------------------------------------------------
# Command line: train, resume, or evaluate a saved model
# ----------------------------------------------------------------------------------------------
# Settings a resumed run may change; every other flag must match the checkpoint.
RESUME_OVERRIDABLE = {"resume", "quiet", "torch_threads", "cuda", "track", "wandb_project_name", "wandb_entity",
                      "wandb_group"}


def explicit_fields(argv: list[str]) -> set[str]:
    """Names of the Args fields given on the command line (`--env-id X`, `--autotune`, ...)."""
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
    """--evaluate: the saved policy on --eval-episodes fresh episodes (stochastic unless --eval-deterministic)."""
    if args.eval_episodes < 1:
        fail(f"--eval-episodes must be at least 1 (got {args.eval_episodes})")
    checkpoint = load_checkpoint(args.evaluate)
    saved = Args(**checkpoint["args"])
    torch.set_num_threads(args.torch_threads)
    actor = actor_from_checkpoint(checkpoint)
    evaluator = Evaluator(saved.env_id, args.eval_episodes, args.seed, saved.obs_reward_clip)
    returns, _ = evaluator(full_policy(actor, args.eval_deterministic))
    mode = "deterministic" if args.eval_deterministic else "stochastic"
    print(f"{saved.env_id}, {actor.size} base net(s), step {checkpoint['global_step']}: "
          f"return {returns.mean():.1f} ± {returns.std():.1f} over {len(returns)} {mode} episodes")
    result = {"returns": returns, "members": []}
    if args.members:
        for net in range(actor.size):
            member_returns, _ = evaluator(member_policy(actor, net, args.eval_deterministic))
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
