"""Checkpoints: one file holds everything a run needs to continue and to act. Every write is atomic (temp file,
fsync, rename, fsync of the folder), so a kill, a power loss or a full disk never leaves a damaged checkpoint in
place of a good one."""

from __future__ import annotations

import contextlib
import errno
import glob
import io
import os
import shutil
import sys
import zipfile

import torch

from .errors import fail

CHECKPOINT_NAME = "checkpoint.pt"


def fsync_dir(folder: str) -> None:
    """Make a rename or a new file in `folder` durable: a file's own fsync does not cover its directory entry, so
    after a power loss the folder could still list the old checkpoint, or no new replay segment. Filesystems that
    cannot fsync a folder are left as they are."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def save_checkpoint(path: str, payload: dict) -> None:
    """Atomic: write a temp file, fsync, then rename over the old one (which stays intact until then).
    A failed write (a full disk, most often) removes the temp file and stops the run in one line."""
    from .runs import saving  # (runs imports this module)

    saving(path, payload)  # the run's final checkpoint: a stop from now on lets the run finish
    tmp = f"{path}.tmp"
    with write_failures(path, tmp):
        serialized = io.BytesIO()  # (torch.save into a file reports a full disk as a RuntimeError without its errno)
        torch.save(payload, serialized)
        with open(tmp, "wb") as f:
            f.write(serialized.getbuffer())
            f.flush()
            os.fsync(f.fileno())
    os.replace(tmp, path)
    fsync_dir(os.path.dirname(os.path.abspath(path)))


def atomic_copy(source: str, path: str) -> None:
    """Copy `source` to `path` as `save_checkpoint` writes: temp file, fsync, rename."""
    tmp = f"{path}.tmp"
    with write_failures(path, tmp), open(source, "rb") as src, open(tmp, "wb") as dst:
        shutil.copyfileobj(src, dst)
        dst.flush()
        os.fsync(dst.fileno())
    os.replace(tmp, path)
    fsync_dir(os.path.dirname(os.path.abspath(path)))


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
            from .runs import no_space  # (runs imports this module)

            no_space(folder, folder)  # --resume advised only where a checkpoint of the run exists
        resume = ("continue with --resume " + folder if os.path.exists(os.path.join(folder, CHECKPOINT_NAME))
                  else "start the run again (it has no checkpoint to resume)")
        fail(f"cannot write {tmp} ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}); {previous}; "
             f"fix that and {resume}")
    except BaseException:  # stopped mid-write (Ctrl-C, SIGTERM): no partial file is left behind either
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise


def non_finite_advice(checkpoint_path: str, rates: str = "--learning-rate") -> str:
    """What the non-finite guard's line says about the checkpoint it kept, and what to change (`rates`: the
    script's learning-rate flags, e.g. "--policy-lr / --q-lr")."""
    # The guard does not know the cause: an edit of the algorithm that makes NaN/inf (a mean over an empty tensor,
    # e.g. the fallbacks at n = 1; a log of 0) is as likely as divergence.
    remedy = (f"if the script was edited, check the edit for NaN/inf (e.g. a mean over an empty tensor); otherwise "
              f"start a new run with a lower {rates} (or another --seed)")
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


def load_checkpoint(path: str, checkpoint_format: str, older_note: str = "", reader_flag: str = "") -> dict:
    """Load `runs/<run>` (its latest checkpoint) or a checkpoint file; one-line error if missing, corrupt, of
    another script, or of another version of this one (`checkpoint_format` is "<script>/<version>";
    `older_note` says what changed since an older version). A caller that only reads checkpoints (an analysis)
    names in `reader_flag` the flag that takes one: a corrupt file's error then advises that flag, not --resume."""
    parent_exists = os.path.isdir(os.path.dirname(path) or ".")
    if not os.path.exists(path) and not (parent_exists and path.endswith(".pt")):  # (a mistyped run folder: its
        # parent's other runs are not named: a sibling, of another seed say, is not the run asked for)
        missing = "folder" if parent_exists else "file or folder"
        fail(f"no checkpoint at {path}: no such {missing}; pass a run folder holding {CHECKPOINT_NAME} or a "
             "checkpoint file")
    if os.path.isdir(path):
        path = os.path.join(path, CHECKPOINT_NAME)
    if not os.path.dirname(path):  # `--resume checkpoint.pt` inside the run folder: the run folder is "."
        path = os.path.join(os.curdir, path)
    if not os.path.isfile(path):
        beside = ""  # a run folder that lost its checkpoint.pt: the iteration file it can continue from
        if glob.glob(os.path.join(glob.escape(os.path.dirname(path)), "iteration_*.pt")):
            beside = intact_beside(path, reader_flag)
        else:  # a folder one level above its runs (a sweep's run_id folder, a --track-dir): name what is below
            below = sorted(glob.glob(os.path.join(glob.escape(os.path.dirname(path)), "*", CHECKPOINT_NAME)))
            if len(below) == 1:
                beside = f"; the run folder {os.path.dirname(below[0])} below it has one: pass that"
            elif below:
                beside = (f"; {len(below)} run folders below it have one (e.g. {os.path.dirname(below[-1])}): "
                          "pass one of them")
        fail(f"no checkpoint at {path}; pass a run folder holding {CHECKPOINT_NAME} or a checkpoint file{beside}")
    stamp = file_stamp(path)
    try:
        # weights_only=False: the file holds numpy statistics and the simulator state; load only your own runs
        checkpoint = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:
        fail(f"cannot read checkpoint {path} (corrupt or not a checkpoint: {type(exc).__name__}){intact_beside(path, reader_flag)}")
    script = checkpoint_format.split("/")[0]
    saved = str(checkpoint.get("format", "")) if isinstance(checkpoint, dict) else ""
    if saved.startswith(f"{script}/") and saved != checkpoint_format:
        fail(f"{path} was written by an older {script}.py ({saved}{older_note}); it cannot be resumed or evaluated "
             "exactly: start a new run")
    if saved != checkpoint_format:
        what = f"a {saved.split('/')[0]} checkpoint" if "/" in saved else "not one of ours"
        fail(f"{path} is not a {script} checkpoint (it is {what}); pass one that {script}.py wrote")
    missing = [key for key in ("args", "global_step") if key not in checkpoint]  # (every checkpoint a script writes)
    if missing:
        fail(f"{path} is an incomplete {script} checkpoint (no {', '.join(missing)}): not one that {script}.py wrote; "
             "pass a run folder or a checkpoint file it wrote")
    checkpoint["path"], checkpoint["file_stamp"] = path, stamp
    return checkpoint


def file_stamp(path: str) -> tuple | None:
    """Which version of the file at `path` this is (inode, mtime, size; a checkpoint is replaced by a rename), or
    None where there is none: `RunRecord` checks that the checkpoint it resumes was not replaced since it was read."""
    try:
        stat = os.stat(path)
    except OSError:
        return None
    return (stat.st_ino, stat.st_mtime_ns, stat.st_size)


def refuse_overwriting_later_work(checkpoint: dict, may_change: frozenset = frozenset()) -> None:
    """--resume of an earlier file of a run (an iteration_<i>.pt) continues in its folder and overwrites what the
    run did after it: refused while the folder's own checkpoint.pt is readable and further on. (Where checkpoint.pt
    is missing or corrupt, continuing from the iteration file is the way on, as the corrupt-file error advises.)"""
    path = checkpoint["path"]
    latest = os.path.join(os.path.dirname(path), CHECKPOINT_NAME)
    if os.path.basename(path) == CHECKPOINT_NAME or not os.path.isfile(latest):
        return
    try:
        later = torch.load(latest, map_location="cpu", weights_only=False)
        later_step = int(later["global_step"])
        later_run = run_of(later, may_change)
    except Exception:  # unreadable: the iteration file is what is left to continue from
        return
    this_run = run_of(checkpoint, may_change)
    if later_run != this_run:  # (a fault hunt: loose files of two runs in one folder, resumed one after the other,
        # each overwrote the other's checkpoint.pt, iteration files and logs)
        fail(f"--resume {path}: {latest} beside it is another run's ({describe_difference(later_run, this_run)}), "
             f"which continuing here would overwrite; copy {path} into a folder of its own and resume it there")
    if later_step > checkpoint["global_step"]:
        fail(f"--resume {path}: the run went on to global_step={later_step:,} ({latest}); continuing from "
             f"global_step={checkpoint['global_step']:,} would overwrite that work in the same folder. Resume "
             f"{latest} instead, or move it away first to redo the run from here")


def run_of(checkpoint: dict, may_change: frozenset) -> dict:
    """What tells one run from another in its checkpoints: its settings, but for those a resume may change
    (`may_change`) and where it logs (a run folder may move)."""
    return {name: value for name, value in (checkpoint.get("args") or {}).items()
            if name not in may_change and name != "track_dir"}


def describe_difference(other: dict, this: dict) -> str:
    """The run the settings `other` describe against this one: env, experiment and seed, or the first setting that
    differs where those are the same."""
    def who(run: dict) -> str:
        return f"{run.get('env_id')}, {run.get('exp_name')}, seed {run.get('seed')}"
    if who(other) != who(this):
        return f"{who(other)}, not {who(this)}"
    name = next(name for name in sorted({*other, *this}) if other.get(name) != this.get(name))
    return f"--{name.replace('_', '-')} {other.get(name)}, not {this.get(name)}"


def intact_beside(path: str, reader_flag: str = "") -> str:
    """For a run's unreadable checkpoint.pt: "; " and the newest intact iteration_<i>.pt beside it, with the command
    that continues the run from it (in the same folder), or "" if there is none. With `reader_flag` (a caller that
    only reads checkpoints), the advice is to pass that file with the flag instead."""
    if os.path.basename(path) != CHECKPOINT_NAME:
        return ""
    run_dir = os.path.dirname(path)
    numbered = []
    for candidate in glob.glob(os.path.join(glob.escape(run_dir), "iteration_*.pt")):
        number = os.path.basename(candidate)[len("iteration_"): -len(".pt")]
        if number.isdigit():
            numbered.append((int(number), candidate))
    for i, candidate in sorted(numbered, reverse=True):
        try:  # intact: a zip archive (what torch.save writes) whose every member matches its CRC
            with zipfile.ZipFile(candidate) as archive:
                if archive.testzip() is not None:
                    continue
        except (OSError, zipfile.BadZipFile):
            continue
        if reader_flag:  # the caller continues no run
            return (f"; the newest intact checkpoint beside it is {candidate} (the end of iteration {i}): pass that "
                    f"with {reader_flag}")
        script = os.path.basename(sys.argv[0])
        if not replay_rows_kept(run_dir, candidate):
            return (f"; the newest intact checkpoint beside it, {candidate} (the end of iteration {i}), cannot continue "
                    "the run either: the replay rows it needs (--keep-buffer) were deleted as the run moved on; "
                    f"evaluate it with: python {script} --evaluate {candidate}, or start a new run")
        return (f"; the newest intact checkpoint beside it is {candidate} (the end of iteration {i}): continue the "
                f"run from there with: python {script} --resume {candidate}")
    return "; no intact iteration_<i>.pt is beside it to continue from: start a new run"


def replay_rows_kept(run_dir: str, path: str) -> bool:
    """Whether an intact off-policy iteration_<i>.pt can continue its run: resumed at an iteration's end, it needs
    its replay rows only with --keep-buffer, and those may have been deleted since (a wrapped buffer moves its first
    row on). Always true for the PPO scripts' files, which hold no replay buffer."""
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=False)
        saved, args = checkpoint.get("replay"), checkpoint.get("args", {})
    except Exception:  # not one of ours after all: the resume that it advises says so in its own line
        return True
    if not saved or not args.get("keep_buffer") or saved["end"] == saved["first"]:
        return True
    from .replay import ReplayFiles  # (replay.py imports this module)
    return ReplayFiles.kept(run_dir, saved)


def load_optimizer(optimizer: torch.optim.Optimizer, state: dict) -> None:
    """`optimizer.load_state_dict(state)`, keeping each group's "initial_lr" (the base the scripts' LR schedules
    scale, torch's name for it) from the freshly made `optimizer` where `state` was saved before it was set, as
    in a checkpoint written before the first update of an LR cycle or by an older version of a script."""
    initial = [group.get("initial_lr", group["lr"]) for group in optimizer.param_groups]
    optimizer.load_state_dict(state)
    for group, lr in zip(optimizer.param_groups, initial):
        group.setdefault("initial_lr", lr)
