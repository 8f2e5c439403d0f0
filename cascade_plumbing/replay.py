"""The replay buffer of the off-policy scripts (cascade_sac.py, cascade_ddpg.py), and the memory it takes."""

from __future__ import annotations

import numpy as np
import torch


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
        # np.take: the same rows as data[indices], gathered in about half the time
        rows = torch.from_numpy(np.take(self.data, np.random.randint(0, self.size, size=batch_size), axis=0)).to(device)
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


def buffer_capacity(buffer_size: int, n: int, k: int, keep_buffer: bool) -> int:
    """Rows the buffer of a run of `n` iterations of `k` steps can ever hold: at most `buffer_size`, and a buffer
    emptied every k steps (unless `keep_buffer`) never needs more than k."""
    return min(buffer_size, n * k if keep_buffer else k)
