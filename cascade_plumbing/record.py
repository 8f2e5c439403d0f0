"""What a run records about itself: its folder, TensorBoard writer, W&B run, training videos, progress line,
clock and checkpoint file; and what it restores of itself when resumed. No algorithm here: a script's own
subclass adds its scalars, its evaluations and what its checkpoints hold."""

from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import asdict
from typing import Any

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn

from .checkpoints import (
    CHECKPOINT_NAME,
    atomic_copy,
    file_stamp,
    non_finite_advice,
    repair_iteration_files,
    save_checkpoint,
)
from .envs import RunState, make_render_env
from .errors import fail
from .runs import (
    OPEN_WRITERS,
    RUN_DIR,
    claim_run_dir,
    lock_run_dir,
    remove_unresumable_run,
    rng_states,
    script_file,
    set_rng_states,
    unlock_run_dir,
)
from .tracking import PROGRESS_NAME, VIDEO_ROOT, Progress, finish_wandb, finished_videos, log_new_videos, start_wandb


def wait_to_name_events_after(run_dir: str) -> None:
    """Wait (at most a second) until a new events file's name sorts after every one in `run_dir`.

    TensorBoard reads a folder's events files in name order, `events.out.tfevents.<second>.<host>.<pid>.<count>`:
    a resume within the second the killed run's file was named can sort before it (count 10 before 9), and its
    curves are then read out of order."""
    named = [name.split(".")[3] for name in os.listdir(run_dir) if name.startswith("events.out.tfevents.")]
    seconds = [int(second) for second in named if second.isdigit()]
    while seconds and time.time() < max(seconds) + 1:
        time.sleep(0.02)


class RunRecord:
    """A run's folder `<track_dir>/<run_name>` and everything written there, for a new run or a resumed one
    (`checkpoint`, whose folder it continues). `envs` are the training envs (their RunState wrappers).
    `at_iteration_end`: whether `checkpoint` was written at the end of an iteration (no default: a mid-iteration
    checkpoint taken for an iteration's end would be copied to its iteration_<i>.pt on resume); `iteration_files`:
    False for a run that keeps no iteration_<i>.pt (nothing to repair on resume); `progress_line`: False for a run
    that prints no progress line (its messages still go through `progress.message`)."""

    def __init__(self, args: Any, checkpoint: dict | None, envs: gym.vector.VectorEnv, total_steps: int, *,
                 at_iteration_end: bool, iteration_files: bool = True, progress_line: bool = True):
        from torch.utils.tensorboard import SummaryWriter

        self.args, self.envs = args, envs
        outer = envs.envs[0] if isinstance(envs, gym.vector.SyncVectorEnv) and envs.envs else None
        if not hasattr(envs, "call") or (outer is not None and not isinstance(outer, RunState)):
            # (a hunt of edited copies: a vector wrapper crashed at the first checkpoint, minutes in; one around
            # make_env's env was left out of the checkpoints, and a resumed run differed silently)
            wrapper = type(envs if not hasattr(envs, "call") else outer).__name__
            fail(f"the training envs are wrapped in {wrapper} outside make_env's RunState, whose state checkpoints "
                 "cannot keep; add the wrapper inside make_env (cascade_plumbing/envs.py), under RunState")
        if args.capture_video:  # here, once the --num-envs workers exist: forked after a render, they hang
            make_render_env(args.env_id).close()  # no OpenGL backend: one line now, not a traceback later
        if checkpoint is None:
            self.run_dir = claim_run_dir(args)
        else:
            self.run_dir = os.path.dirname(checkpoint["path"])
        lock_run_dir(self.run_dir)  # before anything in the folder changes
        stamp = checkpoint and checkpoint.get("file_stamp")
        if stamp and file_stamp(checkpoint["path"]) != stamp:
            # read before the lock was taken: the run it belongs to went on (and ended) in between (a fault hunt:
            # this resume then continued from the older state, over the newer one)
            unlock_run_dir(self.run_dir)
            fail(f"{checkpoint['path']} was replaced after it was read (the run went on there since); read it again: "
                 f"python {os.path.basename(sys.argv[0])} --resume {checkpoint['path']}")
        RUN_DIR[:] = [self.run_dir]
        if checkpoint is not None:
            # without iteration files: as a run with none finished (only an interrupted write is removed)
            repair_iteration_files(self.run_dir, checkpoint if iteration_files else {**checkpoint, "iteration": 0},
                                   at_iteration_end)
        name = os.path.basename(self.run_dir)
        # kept through an untracked resume, so that a later --track continues the same W&B run
        self.wandb_run_id = None if checkpoint is None else checkpoint.get("wandb_run_id")
        if args.track:  # before the SummaryWriter: W&B mirrors the TensorBoard logs of writers made after it
            try:
                self.wandb_run_id = start_wandb(args, name, self.run_dir, self.wandb_run_id)
            except SystemExit:  # W&B did not start (no answer from its server): a new run leaves no empty folder
                if checkpoint is None:
                    unlock_run_dir(self.run_dir)
                    remove_unresumable_run(self.run_dir)
                raise
        if checkpoint is None:
            self.writer = SummaryWriter(self.run_dir)
            self.writer.add_text(
                "hyperparameters",
                "|param|value|\n|-|-|\n" + "\n".join(f"|{key}|{value}|" for key, value in asdict(args).items()),
            )
        else:  # purge_step hides whatever the killed run logged after its last checkpoint
            wait_to_name_events_after(self.run_dir)
            self.writer = SummaryWriter(self.run_dir, purge_step=checkpoint["global_step"] + 1)
        OPEN_WRITERS.add(self.writer)
        self.video_folder = os.path.join(VIDEO_ROOT, name) if args.capture_video else None
        if self.video_folder is not None:
            envs.call("record_videos_to", self.video_folder)
        self.videos_sent = finished_videos(self.video_folder)  # a resumed run's earlier ones went to W&B already
        self.checkpoint_path = os.path.join(self.run_dir, CHECKPOINT_NAME)
        self.progress = Progress(total_steps, args.quiet, file=os.path.join(self.run_dir, PROGRESS_NAME),
                                 line=progress_line)
        self.progress_line = progress_line
        self.start_time = time.time()
        self.last_checkpoint_step = 0

    def restore_envs(self, checkpoint: dict, note: str = "") -> tuple[int, np.ndarray]:
        """Every env's saved state, the RNG streams and the clock; returns (global_step, next_obs). `note` ends
        the line that says so (e.g. " (iteration 3, empty replay buffer)")."""
        global_step = checkpoint["global_step"]
        self.start_time = time.time() - checkpoint["elapsed"]
        self.last_checkpoint_step = global_step
        self.envs.reset(seed=self.args.seed)  # sets up the vector env; then every env gets its saved state back
        self.envs.call("set_state", checkpoint["env_states"])
        set_rng_states(checkpoint["rng"])
        self.progress.message(f"resumed {checkpoint['path']} at global_step={global_step}{note}")
        return global_step, np.asarray(checkpoint["next_obs"], dtype=np.float32)

    def iteration_start(self, iteration: int, size: int, n_params: int, nets: str, global_step: int,
                        continuing: bool = False) -> None:
        """The stack at an iteration's start: its size and `n_params` (`nets`: what they count, e.g. "actor +
        critics"). `continuing`: a resume in the middle of the iteration, whose start is logged already (a second
        point would be one the uninterrupted run does not have)."""
        if not continuing:
            self.writer.add_scalar("cascade/size", size, global_step)
            self.writer.add_scalar("cascade/parameters", n_params, global_step)
        how = f"continues at global_step={global_step}" if continuing else f"{size} base net(s)"
        self.progress.message(f"iteration {iteration}/{self.args.n}: {how}, {n_params} parameters ({nets})")

    def sps(self, global_step: int) -> float:
        return global_step / max(time.time() - self.start_time, 1e-9)

    def episodes(self, infos: dict, global_step: int) -> None:
        """Raw returns and lengths of the training episodes that ended at this step."""
        if "final_info" in infos and "episode" in infos["final_info"]:
            finished = infos["final_info"]["_episode"]
            for ret, length in zip(infos["final_info"]["episode"]["r"][finished],
                                   infos["final_info"]["episode"]["l"][finished]):
                self.writer.add_scalar("charts/episodic_return", ret, global_step)
                self.writer.add_scalar("charts/episodic_length", length, global_step)

    def tick(self, global_step: int, size: int) -> None:
        """After an update: SPS, videos to W&B, the progress line (`progress_line`)."""
        sps = self.sps(global_step)
        self.writer.add_scalar("charts/SPS", int(sps), global_step)
        if self.args.track:
            log_new_videos(self.video_folder, self.videos_sent, global_step)
        self.progress.update(global_step, sps, size)  # (the line only with `progress_line`; the file always)

    def log_fallbacks(self, fallback: torch.Tensor, contribution: torch.Tensor, global_step: int) -> None:
        """The fallback metrics: means over a batch of states of each net's lambda [n-1, B] and share [n, B]."""
        mean_contribution = contribution.mean(1)
        for j, lam in enumerate(fallback.mean(1).tolist()):
            self.writer.add_scalar(f"cascade/fallback/net_{j + 2}", lam, global_step)
        for j, w in enumerate(mean_contribution.tolist()):
            self.writer.add_scalar(f"cascade/contribution/net_{j + 1}", w, global_step)
        self.writer.add_scalar("cascade/fallback_product", mean_contribution[0].item(), global_step)

    def fast_path_off(self, message: str, step: int) -> None:
        """A fast path failed its check: one line on stderr (also with --quiet), a TensorBoard text."""
        print(f"\r\033[Kwarning: {message}" if self.progress.tty else f"warning: {message}", file=sys.stderr,
              flush=True)
        self.writer.add_text("fast_paths", message, step)
        self.progress.note = " | autograd (fast path check failed)"

    def stop_if_non_finite(self, loss: torch.Tensor, modules: dict[str, nn.Module], where: str) -> None:
        """Stop before anything non-finite reaches a checkpoint, naming what became non-finite first: the loss,
        or the first parameter of `modules` (name -> module)."""
        if math.isfinite(loss.item()) and all(torch.isfinite(p).all() for m in modules.values() for p in m.parameters()):
            return
        what = "the loss"
        if math.isfinite(loss.item()):
            named = [(f"{m}.{n}", p) for m, module in modules.items() for n, p in module.named_parameters()]
            what = next(n for n, p in named if not torch.isfinite(p).all())
        self.writer.close()
        fail(f"{what} became non-finite at {where}; {non_finite_advice(self.checkpoint_path)}")

    def checkpoint_due(self, global_step: int) -> bool:
        every = getattr(self.args, "checkpoint_every", 0)
        return bool(every) and global_step - self.last_checkpoint_step >= every

    def save(self, payload: dict, global_step: int, iteration_end: int | None = None) -> None:
        """Write the checkpoint atomically, with what every run keeps (env states, RNG streams, clock, W&B run
        id); at the end of iteration i also as iteration_<i>.pt."""
        payload.update(elapsed=time.time() - self.start_time, env_states=self.envs.call("get_state"),
                       rng=rng_states(), wandb_run_id=self.wandb_run_id, global_step=global_step,
                       script=script_file(type(self.args)))  # (a copy's checkpoints resume with the copy only)
        # the logs up to this step on disk first: a resume hides what was logged after the checkpoint's step
        # (purge_step), and a SIGKILL right after the checkpoint would lose what the writer still held
        self.writer.flush()
        save_checkpoint(self.checkpoint_path, payload)
        self.progress.write_file(global_step, self.sps(global_step))  # (a stop's checkpoint: where it stopped)
        if iteration_end is not None:
            atomic_copy(self.checkpoint_path, os.path.join(self.run_dir, f"iteration_{iteration_end}.pt"))
        self.last_checkpoint_step = global_step

    def close(self, global_step: int) -> None:
        self.progress.write_file(global_step, self.sps(global_step))
        self.writer.close()
        unlock_run_dir(self.run_dir)
        if self.args.track:
            log_new_videos(self.video_folder, self.videos_sent, global_step)
            finish_wandb(exit_code=0)
