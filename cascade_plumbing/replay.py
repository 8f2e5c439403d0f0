"""The replay buffer of the off-policy scripts (cascade_sac.py, cascade_ddpg.py), the memory it takes, and its
rows on disk (`ReplayFiles`), so that a checkpoint holds the buffer without rewriting it."""

from __future__ import annotations

import contextlib
import glob
import os
import zlib

import numpy as np
import torch

from .checkpoints import fsync_dir
from .errors import fail


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
        # The buffer as a window on the log of every row ever added: `added` rows so far, the latest `clear` at log
        # row `start`; log row r sits at ring position (r - start) % capacity. ReplayFiles writes the log to disk.
        self.added = self.start = 0

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
            self.added += 1

    def clear(self) -> None:
        """Empty the buffer: later samples only see rows added from now on."""
        self.pos = self.size = 0
        self.start = self.added

    def log_slices(self, first: int, end: int) -> list[np.ndarray]:
        """The rows of log rows [first, end) (all inside the buffer), in log order: at most two ring slices."""
        if first >= end:
            return []
        lo, hi = (first - self.start) % self.capacity, (end - self.start) % self.capacity
        if lo < hi:
            return [self.data[lo:hi]]
        return [self.data[lo:], self.data[:hi]] if hi else [self.data[lo:]]

    def sample(self, batch_size: int, device: torch.device) -> tuple[torch.Tensor, ...]:
        """(obs, actions, rewards, next_obs, dones) of `batch_size` uniformly drawn rows (numpy's global RNG)."""
        # np.take: the same rows as data[indices], gathered in about half the time
        rows = torch.from_numpy(np.take(self.data, np.random.randint(0, self.size, size=batch_size), axis=0)).to(device)
        o, a = self.obs_dim, self.act_dim
        return rows[:, :o], rows[:, 2 * o : 2 * o + a], rows[:, -2], rows[:, o : 2 * o], rows[:, -1]


class ReplayFiles:
    """The replay buffer's rows on disk, in the run folder's `replay/`, so that a checkpoint can hold the buffer at
    the cost of the rows added since the previous one.

    The files hold the buffer's log (`ReplayBuffer.added`): log row r is row r % SEGMENT_ROWS of
    `rows_<r // SEGMENT_ROWS>.f32`. A log row is written once and never changed, so a checkpoint that records
    "the buffer is log rows [first, end)" stays valid whatever the run writes after it; rows no checkpoint can need
    any more (before the latest checkpoint's first row) are deleted with their segment. Each checkpoint records the
    CRC-32 of its rows, checked on resume."""

    SEGMENT_ROWS = 1 << 16

    def __init__(self, run_dir: str, buffer: ReplayBuffer):
        self.folder, self.buffer = os.path.join(run_dir, "replay"), buffer
        self.row_bytes = buffer.data.shape[1] * buffer.data.itemsize
        self.flushed = 0  # log rows before this one are on disk

    def segment(self, index: int) -> str:
        return os.path.join(self.folder, segment_name(index))

    @classmethod
    def kept(cls, run_dir: str, saved: dict) -> bool:
        """Whether the segment files of a checkpoint's rows (`saved`, its "replay") are still in `run_dir`/replay:
        rows before the latest checkpoint's first are deleted as the run moves on, so an older checkpoint's may
        be gone (whether the files are whole is checked by `restore`)."""
        first, end = saved["first"], saved["end"]
        folder = os.path.join(run_dir, "replay")
        return all(os.path.isfile(os.path.join(folder, segment_name(index)))
                   for index in range(first // cls.SEGMENT_ROWS, (end - 1) // cls.SEGMENT_ROWS + 1))

    def save(self) -> dict:
        """Write the rows added since the last save (fsync'd), before the checkpoint that records them; returns
        what the checkpoint holds of the buffer."""
        buffer = self.buffer
        first, end = buffer.added - buffer.size, buffer.added
        with contextlib.suppress(FileExistsError):  # (not makedirs: a run folder moved away is not made again here)
            os.mkdir(self.folder)
        row = max(self.flushed, first)
        if row > first and not self.on_disk(first, row):
            # files of replay/ were deleted or cut short since the last save (a fault hunt: the next checkpoint
            # recorded rows that were gone, and could never be resumed); every row is still in memory: write them again
            row = first
        for part in buffer.log_slices(row, end):
            while len(part):
                index, offset = divmod(row, self.SEGMENT_ROWS)
                count = min(len(part), self.SEGMENT_ROWS - offset)
                fd = os.open(self.segment(index), os.O_WRONLY | os.O_CREAT, 0o644)
                try:
                    os.pwrite(fd, part[:count].tobytes(), offset * self.row_bytes)
                    os.fsync(fd)
                finally:
                    os.close(fd)
                part, row = part[count:], row + count
        if end > self.flushed or row < end:
            fsync_dir(self.folder)  # a new segment's name, durable before the checkpoint that needs it
        self.flushed = end
        return {"first": first, "end": end, "start": buffer.start, "crc32": self.crc32(first, end)}

    def on_disk(self, first: int, end: int) -> bool:
        """Whether the segment files that hold log rows [first, end) are there and long enough (a stat each)."""
        for index in range(first // self.SEGMENT_ROWS, (end - 1) // self.SEGMENT_ROWS + 1):
            rows = min(end - index * self.SEGMENT_ROWS, self.SEGMENT_ROWS)
            try:
                if os.path.getsize(self.segment(index)) < rows * self.row_bytes:
                    return False
            except OSError:
                return False
        return True

    def crc32(self, first: int, end: int) -> int:
        """CRC-32 of the buffer's log rows [first, end), in log order."""
        crc = 0
        for part in self.buffer.log_slices(first, end):
            crc = zlib.crc32(memoryview(np.ascontiguousarray(part)).cast("B"), crc)
        return crc

    def prune(self, saved: dict) -> None:
        """After the checkpoint of `saved` is written: delete the segments that hold only rows before its first."""
        for path in glob.glob(os.path.join(glob.escape(self.folder), "rows_*.f32")):
            index = int(os.path.basename(path)[5:-4])
            if (index + 1) * self.SEGMENT_ROWS <= saved["first"]:
                os.remove(path)

    def restore(self, saved: dict, source: str = "", keep_buffer: bool = False) -> None:
        """Refill the (new, empty) buffer with the rows a checkpoint recorded (`saved`, of the checkpoint file
        `source`, of a run with `keep_buffer` or not); one line if they are gone or differ."""
        buffer, first, end = self.buffer, saved["first"], saved["end"]
        buffer.added, buffer.start = end, saved["start"]
        buffer.size, buffer.pos = end - first, (end - buffer.start) % buffer.capacity
        row = first
        for part in buffer.log_slices(first, end):
            filled = 0
            while filled < len(part):
                index, offset = divmod(row, self.SEGMENT_ROWS)
                count = min(len(part) - filled, self.SEGMENT_ROWS - offset)
                try:
                    with open(self.segment(index), "rb") as f:
                        f.seek(offset * self.row_bytes)
                        raw = f.read(count * self.row_bytes)
                except OSError:
                    raw = b""
                if len(raw) != count * self.row_bytes:
                    self.missing(first, end, source, keep_buffer)
                part[filled : filled + count] = np.frombuffer(raw, dtype=part.dtype).reshape(count, -1)
                filled, row = filled + count, row + count
        if self.crc32(first, end) != saved["crc32"]:
            fail(f"the replay rows in {self.folder} differ from what the checkpoint recorded (CRC mismatch); they "
                 f"were changed or belong to another run: resume the run from its own folder's checkpoint.pt"
                 f"{row_free_iteration(source, keep_buffer)}")
        self.flushed = end

    def skip_to(self, end: int) -> None:
        """An empty buffer whose log goes on at row `end` (a run resumed at an iteration's end, which empties the
        buffer): the rows before it are not needed, and the next ones get new log rows, not those of old files."""
        self.buffer.added = self.buffer.start = self.flushed = end

    def missing(self, first: int, end: int, source: str, keep_buffer: bool = False) -> None:
        rows = f"the checkpoint's replay buffer (log rows {first}..{end - 1}) is not in {self.folder}"
        if os.path.basename(source) == "checkpoint.pt":
            # a run folder's latest checkpoint: its rows were beside it when it was written
            fail(f"{rows}: files of replay/ were deleted or moved since the checkpoint was written, or the checkpoint "
                 "was copied out of its run folder without them; resume the original run folder, put the files back, "
                 f"or start a new run{row_free_iteration(source, keep_buffer)}")
        fail(f"{rows}: a checkpoint resumes with its run folder's replay/ files, which keep only what the latest "
             "checkpoint needs; resume the run folder itself (its checkpoint.pt), or start a new run")


def row_free_iteration(source: str, keep_buffer: bool) -> str:
    """For a run folder's checkpoint.pt whose replay rows are lost: "; or ..." naming the newest iteration_<i>.pt beside
    it, whose resume needs no rows (a new iteration empties the buffer; not with `keep_buffer`), or ""."""
    if keep_buffer or os.path.basename(source) != "checkpoint.pt":
        return ""
    folder = os.path.dirname(source)
    numbered = []
    for path in glob.glob(os.path.join(glob.escape(folder), "iteration_*.pt")):
        with contextlib.suppress(ValueError):
            numbered.append((int(os.path.basename(path)[len("iteration_"):-3]), path))
    if not numbered:
        return ""
    index, path = max(numbered)
    return (f"; or continue from the end of iteration {index}, which needs no rows: move {source} aside, then "
            f"--resume {path}")


def segment_name(index: int) -> str:
    return f"rows_{index:06d}.f32"


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
