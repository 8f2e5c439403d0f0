"""What a SAC or DDPG checkpoint costs, in time and disk: the replay rows written since the previous checkpoint
(cascade_plumbing/replay.py ReplayFiles: append, fsync, CRC of the whole buffer) and checkpoint.pt itself (nets,
targets, optimizers, run state), with the buffer at the size of a paper run.

    python benchmarks/checkpoint.py                       # Hopper-v4, a full 1M-row buffer, 50k new rows
    python benchmarks/checkpoint.py --env-id Humanoid-v4  # the largest rows

The checkpoint.pt sizes come from a short real run of each script (a few hundred steps: the nets' sizes do not
depend on the budget). Run it with nothing else on the machine: fsync times depend on the disk."""

from __future__ import annotations

import os
import sys
import tempfile
import time
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch
import tyro

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import cascade_ddpg  # noqa: E402
import cascade_sac  # noqa: E402
from cascade_plumbing.checkpoints import save_checkpoint  # noqa: E402
from cascade_plumbing.replay import ReplayBuffer, ReplayFiles  # noqa: E402


@dataclass
class Args:
    env_id: str = "Hopper-v4"
    """the env whose observation and action sizes make the rows"""
    buffer_rows: int = 1_000_000
    """rows in the buffer when the checkpoint is written (the buffer's size: --buffer-size 1M, a 1M-step iteration)"""
    new_rows: int = 50_000
    """rows added since the previous checkpoint (the scripts' default --checkpoint-every)"""
    repeats: int = 3
    """checkpoints timed (the median is reported)"""


def replay_cost(args: Args, obs_dim: int, act_dim: int, folder: str) -> tuple[float, float, int]:
    """(seconds to write the new rows and CRC the buffer, seconds of the first save of the whole buffer, bytes on
    disk) for a buffer of args.buffer_rows rows."""
    buffer = ReplayBuffer(args.buffer_rows, obs_dim, act_dim)
    buffer.data[:] = np.random.default_rng(0).standard_normal(buffer.data.shape, dtype=np.float32)
    buffer.added = buffer.size = args.buffer_rows - args.new_rows
    files = ReplayFiles(folder, buffer)
    start = time.perf_counter()
    files.prune(files.save())  # a resumed run's first checkpoint writes nothing new; a new run's writes as it goes
    first = time.perf_counter() - start
    times = []
    for _ in range(args.repeats):
        buffer.added += args.new_rows  # (the rows' values do not matter for the cost)
        buffer.size = min(buffer.size + args.new_rows, buffer.capacity)
        buffer.pos = buffer.added % buffer.capacity
        start = time.perf_counter()
        files.prune(files.save())
        times.append(time.perf_counter() - start)
    on_disk = sum(os.path.getsize(os.path.join(files.folder, f)) for f in os.listdir(files.folder))
    return float(np.median(times)), first, on_disk


def checkpoint_file(module, flags: dict, folder: str) -> tuple[int, float]:
    """(bytes, seconds to write) of the checkpoint.pt of a short real run of `module` with `flags`."""
    result = module.train(module.Args(env_id=ARGS.env_id, learning_starts=100, batch_size=32, eval_every=0,
                                      quiet=True, track_dir=folder, **flags))
    path = os.path.join(result["run_dir"], "checkpoint.pt")
    payload = torch.load(path, weights_only=False)
    start = time.perf_counter()
    for _ in range(ARGS.repeats):
        save_checkpoint(os.path.join(folder, "again.pt"), payload)
    return os.path.getsize(path), (time.perf_counter() - start) / ARGS.repeats


if __name__ == "__main__":
    ARGS = tyro.cli(Args, description=__doc__.split("\n\n")[0])
    probe = gym.make(ARGS.env_id)
    obs_dim, act_dim = probe.observation_space.shape[0], probe.action_space.shape[0]
    probe.close()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as folder:
        seconds, first, on_disk = replay_cost(ARGS, obs_dim, act_dim, folder)
        row_bytes = ReplayBuffer.row_width(obs_dim, act_dim) * 4
        print(f"{ARGS.env_id}: rows of {row_bytes} bytes; buffer of {ARGS.buffer_rows} rows = "
              f"{ARGS.buffer_rows * row_bytes / 1e6:.0f} MB")
        print(f"replay rows per checkpoint ({ARGS.new_rows} new, {ARGS.new_rows * row_bytes / 1e6:.1f} MB written, "
              f"fsync'd, CRC of the buffer): {seconds:.2f} s (median of {ARGS.repeats}); replay/ on disk: "
              f"{on_disk / 1e6:.0f} MB; a first save of the whole buffer: {first:.2f} s")
        for name, module, flags in (
            ("Cascade-SAC, 4 nets", cascade_sac, dict(n=4, k=150)),
            ("SAC baseline", cascade_sac, dict(n=1, k=300, hidden_size=256)),
            ("Cascade-DDPG, 6 nets", cascade_ddpg, dict(n=6, k=150)),
            ("DDPG baseline", cascade_ddpg, dict(n=1, k=300, hidden_size=64)),
        ):
            size, write = checkpoint_file(module, flags, os.path.join(folder, name.replace(" ", "_")))
            print(f"{name}: checkpoint.pt {size / 1e6:.2f} MB, written (fsync'd) in {write * 1000:.0f} ms")
