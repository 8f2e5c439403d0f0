"""Weights & Biases (--track) the CleanRL way, mirroring the TensorBoard logs (record.RunRecord opens both for a
run folder); and the progress line.
wandb is imported only with --track."""

from __future__ import annotations

import glob
import os
import sys
import time
from dataclasses import asdict
from typing import Any

from .errors import fail

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


def start_wandb(args: Any, run_name: str, run_dir: str, run_id: str | None) -> str:
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


PROGRESS_NAME = "progress.txt"  # in the run folder: the latest progress line (sweep.py shows it)


class Progress:
    """One self-updating line on a terminal; plain lines every `interval` seconds otherwise (`line`, unless
    `quiet`). With `file`, the same line is also kept in that file, rewritten every `interval` seconds even when
    quiet: how far a run in the background is (sweep.py's progress lines read it)."""

    def __init__(self, total_steps: int, quiet: bool, interval: float = 30.0, file: str | None = None,
                 line: bool = True):
        self.total, self.quiet, self.interval, self.file, self.line = total_steps, quiet, interval, file, line
        self.tty = sys.stdout.isatty()
        self.last_print = self.last_write = 0.0
        self.last_sps, self.last_size = 0.0, 0
        self.last_eval: float | None = None
        self.note = ""  # e.g. that a fast path was switched off

    def update(self, step: int, sps: float, size: int, force: bool = False) -> None:
        now = time.time()
        self.last_sps, self.last_size = sps, size
        print_due = self.line and not self.quiet and (force or now - self.last_print >= (0.5 if self.tty else
                                                                                          self.interval))
        write_due = self.file is not None and (force or now - self.last_write >= self.interval)
        if not (print_due or write_due):
            return
        eta = (self.total - step) / max(sps, 1e-9)
        ev = "-" if self.last_eval is None else f"{self.last_eval:.1f}"
        line = (f"{step:>10,}/{self.total:,} steps ({100 * step / self.total:5.1f}%) | {sps:6.0f} SPS | "
                f"{size} net(s) | eval {ev} | ETA {duration(eta)}{self.note}")
        if print_due:
            self.last_print = now
            print(f"\r{line}" if self.tty else line, end="" if self.tty else "\n", flush=True)
        if write_due:
            self.last_write = now
            try:  # replaced whole, so a reader never sees half a line; a failed write (a full disk) is not the run's
                with open(f"{self.file}.new", "w") as f:
                    f.write(line.strip() + "\n")
                os.replace(f"{self.file}.new", self.file)
            except OSError:
                pass

    def write_file(self, step: int, sps: float) -> None:
        """At a checkpoint and at the run's end: the line as of `step` in the file (the periodic write may be up to
        `interval` old, which left a finished run at 55%, and a stopped one's resume showing a line from before
        the stop); nothing printed. (A run that never reached an update keeps what it had.)"""
        if not (self.last_print or self.last_write):
            return
        line, self.line = self.line, False
        try:
            self.update(step, sps, self.last_size, force=True)
        finally:
            self.line = line

    def message(self, text: str) -> None:
        """A normal line that does not garble the progress line."""
        if self.quiet:
            return
        print(f"\r\033[K{text}" if self.tty else text, flush=True)


def duration(seconds: float) -> str:
    """A time left as a duration, e.g. 'about 28 h 20 min left' (a clock time HH:MM:SS would wrap after 24 h)."""
    return f"about {int(seconds // 3600)} h {int(seconds % 3600 // 60):02d} min left"
