"""A run's life outside its algorithm: seeding and RNG state, run names, input checks every script shares,
resume, stop signals, and the command-line entry point."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import inspect
import os
import random
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
import traceback
import weakref
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
import tyro
from threadpoolctl import ThreadpoolController

from .checkpoints import CHECKPOINT_NAME, non_finite_advice, refuse_overwriting_later_work, repair_iteration_files
from .envs import end_env_workers
from .errors import check_ranges, fail, parse_command_line
from .tracking import check_wandb, finish_wandb

RESUMING: list[str] = []  # the run folder the command line's --resume continues in (run_main)
NEW_RUN_FLAGS: set[str] = set()  # the flags given on the command line of a new run (run_main), for idle checks


def check_run_dir_writable(run_dir: str) -> None:
    """A resumed run writes in its own folder: probed there (nothing left behind), one line if it cannot."""
    try:
        os.rmdir(tempfile.mkdtemp(dir=run_dir))
    except OSError as exc:
        fail(f"cannot write in the run folder {run_dir} ({exc.strerror or exc}): a resumed run goes on in its own "
             "folder; make it writable, or copy the run folder to a writable place and resume the copy there")


def check_track_dir(track_dir: str) -> None:
    """Run folders can be created under `track_dir` (probed in its nearest existing ancestor, nothing left behind)."""
    if not track_dir.strip():
        fail("--track-dir is empty; pass the folder the run folders go to (default: runs)")
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


def check_exp_name(exp_name: str) -> None:
    """The experiment name is one part of a run folder's name (`<env_id>__<exp_name>__<seed>__<time>`), which the
    plots parse: not empty, no folder separator."""
    if not exp_name.strip() or "/" in exp_name or os.sep in exp_name:
        fail(f"--exp-name {exp_name!r}: it names the run folder <env_id>__<exp_name>__<seed>__<time>; give a "
             "non-empty name without '/'")


def check_seed(seed: int) -> None:
    if not 0 <= seed < 2**32:
        fail(f"--seed must be a non-negative integer below 2**32 (got {seed}); numpy and gymnasium refuse others")


def check_threads(threads: int) -> None:
    if threads < 1:
        fail(f"--torch-threads must be at least 1 (got {threads})")


def set_threads(threads: int) -> None:
    """`threads` CPU threads for torch; one for numpy's OpenBLAS. It would otherwise take every core for a 256-wide
    product (the SAC fast path's), so one run would use two cores; and with torch's OpenMP threads beside its own,
    both spinning between calls, a 2-thread SAC run measured 15x slower (docs/performance.md, "SAC and DDPG"). Only OpenBLAS (what
    numpy's wheels carry): a BLAS that torch shares (a conda MKL) keeps torch's setting."""
    check_threads(threads)  # (training checks it with the other settings; --evaluate meets it here)
    torch.set_num_threads(threads)
    ThreadpoolController().select(internal_api="openblas").limit(limits=1)


def seed_everything(seed: int, torch_deterministic: bool) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    torch.backends.cudnn.deterministic = torch_deterministic


def run_device(cuda: bool) -> torch.device:
    """The GPU for --cuda where torch sees one, else the CPU; --cuda without a GPU says so in one line."""
    on_gpu = cuda and torch.cuda.is_available()
    if cuda and not on_gpu:
        print("warning: --cuda: torch sees no GPU here (a CPU-only torch build, or no driver); running on the CPU",
              file=sys.stderr, flush=True)
    return torch.device("cuda" if on_gpu else "cpu")


def rng_states() -> dict:
    states = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_initialized():  # a --cuda run samples its actions (and PPO its minibatches) on the GPU
        states["torch_cuda"] = torch.cuda.get_rng_state()
    return states


def set_rng_states(states: dict) -> None:
    torch.set_rng_state(states["torch"])
    np.random.set_state(states["numpy"])
    random.setstate(states["python"])
    if "torch_cuda" in states and torch.cuda.is_available():  # resumed on a CPU: that stream is not used
        # Start CUDA now: before start-up, set_rng_state is only queued, and start-up runs the queued seeding
        # (seed_everything's manual_seed) after it, which would overwrite the restored stream.
        torch.cuda.init()
        torch.cuda.set_rng_state(states["torch_cuda"])


# Settings a resumed run may change; every other flag must match the checkpoint.
RESUME_OVERRIDABLE = {"resume", "quiet", "checkpoint_every", "torch_threads", "cuda", "track", "wandb_project_name",
                      "wandb_entity", "wandb_group"}


def explicit_fields(args_type: type, argv: list[str]) -> set[str]:
    """Names of the `args_type` fields given on the command line (`--env-id X`, `--no-normalize`, ...)."""
    names = set(args_type.__dataclass_fields__)
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


def refuse_idle_flags(args: Any, given: set[str]) -> None:
    """A flag given for a new training run that it cannot affect is refused in one line (as --evaluate refuses the
    flags it ignores): the user meant something the run would not do, e.g. --deterministic for training's evaluation,
    or an ablation that a run of one net cannot show. (Not on --resume: a run started before this check goes on.)"""
    rules = [("members", "applies to --evaluate only" + (" (training's evaluation of each net: --eval-members)"
                                                          if hasattr(args, "eval_members") else "")),
             ("deterministic", "applies to --evaluate only (training evaluates the stochastic policy, as the paper)")]
    if not args.track:
        rules += [(name, "applies with --track only") for name in ("wandb_project_name", "wandb_entity", "wandb_group")]
    if getattr(args, "n", 2) == 1:
        rules += [(name, "has no effect with --n 1 (no base net is added)")
                  for name in ("keep_buffer", "reset_critic", "fallback_init", "freeze_previous", "start_full")
                  if hasattr(args, name)]
        if getattr(args, "lr_schedule", None) == "global":  # one iteration: its cycle is the whole run
            rules.append(("lr_schedule", "global is the standard cyclic schedule with --n 1 (one iteration)"))
    # (the nets alone are evaluated with the periodic evaluation only; --eval-episodes, a number, is let be: a job
    # script may turn the evaluation off by appending --eval-every 0 to its flags)
    if getattr(args, "eval_every", None) == 0:
        rules += [(name, "has no effect with --eval-every 0 (training evaluates nothing)")
                  for name in ("eval_members", "eval_deterministic", "eval_in_worker")
                  if hasattr(args, name)]
    for name, why in rules:
        # (a switch turned off, `--no-eval-members`, asks for nothing the run would not do: a job script may spell
        # out the defaults)
        if name in given and getattr(args, name) is not False:
            fail(f"--{name.replace('_', '-')} {why}; leave it out")


def script_file(args_type: type) -> str:
    """The file name of the script that defines `args_type`: cascade_sac.py, or a copy's own (my_idea.py); "" where
    there is none (a class defined in a notebook's cell or `python -c`: not checked on resume)."""
    try:
        return os.path.basename(inspect.getfile(args_type))
    except (TypeError, OSError):
        return ""


def refuse_another_scripts_checkpoint(checkpoint: dict, args_type: type, flag: str) -> None:
    """A checkpoint written by another copy of a script (`cp cascade_sac.py my_idea.py`: the same checkpoint format)
    is refused in one line: resumed or evaluated by this one it would go on with this one's code, a silently wrong
    run, or fail on the copy's own flags. (Checkpoints written before the file name was saved are not checked.)"""
    written_by = checkpoint.get("script")
    if written_by and written_by != (this := script_file(args_type)):
        fail(f"{checkpoint['path']} was written by {written_by}, not {this}: the two may differ in code and flags; "
             f"use the script that wrote it: python {written_by} --{flag} {checkpoint['path']}")


def resumed_args(args: Any, checkpoint: dict, given: set[str]) -> Any:
    """The checkpoint's settings; a conflicting flag on the command line is an error."""
    saved = type(args)(**checkpoint["args"])
    # the run continues in its folder, wherever that is now (moved off a scratch disk that is gone, say)
    saved.track_dir = os.path.dirname(os.path.dirname(os.path.abspath(checkpoint["path"])))
    for name in sorted(given - RESUME_OVERRIDABLE):
        if name == "track_dir" and os.path.realpath(args.track_dir) == os.path.realpath(saved.track_dir):
            continue  # the same folder, written another way (the relative path the run was started with)
        if getattr(args, name) != getattr(saved, name):
            fail(f"--{name.replace('_', '-')} {getattr(args, name)} differs from the checkpoint's "
                 f"{getattr(saved, name)}; a resumed run keeps its settings (drop the flag)")
    for name in given & RESUME_OVERRIDABLE:
        setattr(saved, name, getattr(args, name))
    return saved


def stop_signal(signum, frame) -> None:
    """SIGTERM, Ctrl-C and SIGHUP stop a run (the exit code tells them apart: 143, 130, 129); a SAC or DDPG run that has taken a step
    writes a checkpoint at its next one first (CHECKPOINT_ON_STOP). Once the run's final checkpoint is being
    written, a stop lets the run finish instead (its last evaluation and logs; the run is complete then).
    A stop that comes again within SAME_STOP_S of the last one is the same stop: a job scheduler signals every
    process of a job and sweep.py passes its own stop on, so a run gets two at once; as a second stop it would
    end a SAC or DDPG run before its checkpoint, or interrupt a stopping run's last line with a traceback."""
    if ENDING_BY_STOP:  # the run is ending by a stop already (its last line and exit follow): nothing to add; raised
        return  # again, it would print a traceback from wherever the ending run is (an atexit callback, say)
    now = time.monotonic()
    if LAST_STOP and now - LAST_STOP[0] < SAME_STOP_S:
        return
    LAST_STOP[:] = [now]
    if FINISHING:
        if not FINISHING[0]:  # one line, not print(): the handler may interrupt a print
            os.write(2, f"\r{signal.Signals(signum).name} after the final checkpoint: the run finishes its last "
                        "steps first\n".encode())
            FINISHING[0] = True
        return
    if CHECKPOINT_ON_STOP and not STOP_REQUESTED:  # the run writes a checkpoint at its next step, then stops
        STOP_REQUESTED.append(signum)  # (a second stop before that ends it at once, at its last checkpoint)
        return
    STOPPED_BY.append(signum)
    ENDING_BY_STOP.append(True)
    raise KeyboardInterrupt


def handle_stops() -> None:
    """SIGTERM, Ctrl-C and SIGHUP (a closed terminal or ssh session; it ended a run silently, losing the steps since
    its last checkpoint) stop the run through stop_signal; Ctrl-C and SIGHUP not where they are ignored (`cmd &`,
    nohup)."""
    signal.signal(signal.SIGTERM, stop_signal)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, stop_signal)
    if signal.getsignal(signal.SIGHUP) == signal.SIG_DFL:
        signal.signal(signal.SIGHUP, stop_signal)


def forget_stops() -> None:
    """No run of this process checkpoints on a stop, and none is asked for (at the start of a run or of --evaluate:
    what an earlier run in the same process left, a notebook's or a test's, must not defer this one's stop)."""
    drop_stop_requests()
    LAST_STOP.clear()
    ENDING_BY_STOP.clear()


def drop_stop_requests() -> None:
    """At the end of a run (finished, failed or stopped): it no longer checkpoints on a stop. What tells a repeated
    stop from a new one stays until the next run starts: the stop that ended this run may arrive twice."""
    CHECKPOINT_ON_STOP.clear()
    STOP_REQUESTED.clear()


def stop_after_checkpoint(global_step: int) -> None:
    """Called after each checkpoint of a run that checkpoints on a stop: the stop it was written for ends the run."""
    if STOP_REQUESTED and not FINISHING:
        SAVED_AT_STOP[:] = [global_step]
        STOPPED_BY.append(STOP_REQUESTED.pop())
        ENDING_BY_STOP.append(True)
        raise KeyboardInterrupt


STOPPED_BY: list[int] = []
LAST_STOP: list[float] = []  # time.monotonic() of the latest stop signal acted on
SAME_STOP_S = 1.0  # a stop's checkpoint takes well under this (SAC, Hopper, 1M rows: ~0.2 s); a person's second
# Ctrl-C after it still ends the run at once
# A run whose checkpoints are costly to lose (SAC, DDPG: tens of thousands of steps between them) sets
# CHECKPOINT_ON_STOP once it has taken a step; a stop then only asks (STOP_REQUESTED) for a checkpoint at the next
# step, after which the run stops (SAVED_AT_STOP: the step of that checkpoint).
CHECKPOINT_ON_STOP: list[bool] = []
STOP_REQUESTED: list[int] = []
SAVED_AT_STOP: list[int] = []
ENDING_BY_STOP: list[bool] = []  # a stop has ended the run (raised KeyboardInterrupt): a stop after it changes nothing
FINAL: list[Callable[[str, dict], bool]] = []  # run_main's test of whether a checkpoint is the end of the run
FINISHING: list[bool] = []  # [whether a stop was ignored] once the final checkpoint is being written


def saving(path: str, payload: dict) -> None:
    """Called by save_checkpoint before each write: from the run's final checkpoint on, a stop no longer fails
    the run (before its write, so that no stop falls between the write and this)."""
    if FINAL and not FINISHING and "args" in payload and FINAL[0](path, payload):
        FINISHING.append(False)


OPEN_WRITERS: weakref.WeakSet = weakref.WeakSet()  # the runs' TensorBoard writers (cascade_plumbing.record adds them)


def this_run_dir(checkpoint: dict | None) -> str | None:
    """The run's folder: the resumed checkpoint's, or for a new run the one it made (None if it has made none yet;
    not the newest of its name: another run of that name may have started since)."""
    if checkpoint is not None:
        return os.path.dirname(checkpoint["path"])
    return RUN_DIR[-1] if RUN_DIR else None


def remove_unresumable_run(run_dir: str) -> bool:
    """Remove a run folder that holds no checkpoint and nothing of another process (its TensorBoard writers closed
    first: their flush thread must not write into the removed folder); whether it was removed."""
    if not only_mine(run_dir):
        return False
    for writer in list(OPEN_WRITERS):
        with contextlib.suppress(Exception):  # (a full disk may fail this last flush too)
            writer.close()
    shutil.rmtree(run_dir, ignore_errors=True)
    return True


def stop_short_of(lead: str, detail: str, run_dir: str | None, to_resume: str, to_restart: str) -> None:
    """Stop a run that lacks a resource (disk, memory) in one line with advice that works: after a checkpoint,
    `to_resume` and --resume; before the first one there is nothing to resume, so the run's half-made folder is
    removed and the line says `to_restart`. `lead` says what ran out, `detail` (if any) the error itself."""
    script = os.path.basename(sys.argv[0])
    checkpoint = None if run_dir is None else os.path.join(run_dir, CHECKPOINT_NAME)
    if checkpoint is not None and os.path.exists(checkpoint):
        fail(f"{lead}{detail}; the last checkpoint {checkpoint} is intact; {to_resume} and continue with: "
             f"python {script} --resume {run_dir}")
    removed = f" (its folder {run_dir} is removed)" if run_dir is not None and remove_unresumable_run(run_dir) else ""
    fail(f"{lead} before the run's first checkpoint{detail}, so there is nothing to resume{removed}; {to_restart}")


def no_space(folder: str, run_dir: str | None) -> None:
    """Stop on a full disk in one line (stop_short_of)."""
    stop_short_of(f"no space left on {folder}", "", run_dir, "free some space", "free some space and start the run again")


def out_of_memory(exc: BaseException) -> bool:
    """Whether `exc` is an allocation that failed (Python's MemoryError, or torch's CPU allocator)."""
    return isinstance(exc, MemoryError) or (isinstance(exc, RuntimeError) and "can't allocate memory" in str(exc))


def overflowed(exc: BaseException) -> bool:
    """Whether `exc` is torch refusing a number too large for float32 (Adam's step at --learning-rate 1e300)."""
    return isinstance(exc, RuntimeError) and "cannot be converted to type float without overflow" in str(exc)


def no_memory(exc: BaseException, run_dir: str | None, args: Any) -> None:
    """Stop on a failed allocation (nets or batches too large for this machine) in one line, like a full disk
    (stop_short_of), naming the flags of this script that size the nets and batches."""
    what = str(exc).splitlines()[0].strip() if str(exc) else type(exc).__name__
    what = what.split("DefaultCPUAllocator: ")[-1].split(" Error code")[0].rstrip(". ")
    sizes = [name for name in ("hidden_size", "critic_hidden_size", "num_envs", "num_steps", "batch_size", "buffer_size")
             if hasattr(args, name)]
    advice = f"smaller nets or batches ({', '.join('--' + n.replace('_', '-') for n in sizes)}) or a machine with more"
    stop_short_of("out of memory", f" ({what})", run_dir, "free some memory", f"start again with {advice}")


def refused_write(exc: BaseException) -> OSError | None:
    """The OSError of a file the run could not write for want of permission, a read-only filesystem or a disk
    error (`exc`, or the one it was raised from; not one it was merely raised while handling), or None."""
    while exc is not None:
        if isinstance(exc, OSError) and exc.filename and exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM,
                                                                       errno.EIO):
            return exc
        exc = exc.__cause__
    return None


def changed_under_the_run(exc: BaseException, run_dir: str | None) -> OSError | None:
    """The OSError of a path inside `run_dir` that was not what the run had made (gone, or replaced by a file or a
    folder: the folder moved or deleted, replay/ replaced while it trained), or None."""
    if run_dir is None:
        return None
    folder = os.path.abspath(run_dir)
    while exc is not None:
        if isinstance(exc, OSError) and exc.filename and exc.errno in (errno.ENOENT, errno.ENOTDIR, errno.EEXIST,
                                                                       errno.EISDIR):
            path = os.path.abspath(os.fsdecode(exc.filename))
            if path == folder or path.startswith(folder + os.sep):
                return exc
        exc = exc.__cause__
    return None


def disk_full(exc: BaseException) -> bool:
    """Whether `exc` (or an exception it was raised from) is a full disk (ENOSPC, or EDQUOT: a full quota)."""
    while exc is not None:
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def quiet_writer_threads(hook: Callable = threading.excepthook) -> Callable:
    """A threading.excepthook that leaves out a TensorBoard writer thread's failed write (a full disk): the training
    thread meets the same error at its next write and reports it in one line (no second traceback)."""

    def excepthook(info) -> None:
        if type(info.thread).__name__ == "_AsyncWriterThread" and isinstance(info.exc_value, OSError):
            return
        hook(info)

    excepthook.quiet_writer_threads = True
    return excepthook


def quiet_resource_sharer(hook: Callable = sys.excepthook) -> Callable:
    """A sys.excepthook that leaves out, after a stop, the connection a --num-envs worker reset in multiprocessing's
    resource-sharer thread (which reports through sys.excepthook): the worker was ended by the same Ctrl-C, and the
    run's one stop line says all there is (a CI run saw that traceback after it)."""

    def excepthook(kind, value, tb) -> None:
        if STOPPED_BY and issubclass(kind, (ConnectionError, EOFError)) and any(
                frame.f_code.co_filename.endswith("resource_sharer.py") for frame, _ in traceback.walk_tb(tb)):
            return
        hook(kind, value, tb)

    excepthook.quiet_resource_sharer = True
    return excepthook


def stopped(checkpoint: dict | None) -> None:
    """One line on where a stopped run's last checkpoint is and how to continue; exit 130 (SIGINT) / 143 (SIGTERM).
    A new run stopped before its first checkpoint removes its folder: there is nothing in it to resume."""
    run_dir = this_run_dir(checkpoint)
    signum = STOPPED_BY[-1] if STOPPED_BY else signal.SIGINT
    name = signal.Signals(signum).name
    script = os.path.basename(sys.argv[0])
    path = None if run_dir is None else os.path.join(run_dir, CHECKPOINT_NAME)
    if path is not None and os.path.exists(path):
        saved = (f"a checkpoint was written at the stop (global_step={SAVED_AT_STOP[-1]}), {path}" if SAVED_AT_STOP
                 else f"the last checkpoint is {path}")
        where = f"{saved}; continue with: python {script} --resume {run_dir}"
    else:
        where = "no checkpoint was written yet, so there is nothing to resume"
        if checkpoint is None and run_dir is not None and remove_unresumable_run(run_dir):
            where += f" (its folder {run_dir} is removed)"
    print(f"\rstopped by {name}: {where}", file=sys.stderr, flush=True)
    sys.exit(128 + signum)


def only_mine(run_dir: str) -> bool:
    """Whether `run_dir` holds no checkpoint (no .pt file) and no TensorBoard log of another process."""
    mine = f".{socket.gethostname()}.{os.getpid()}."
    for _, _, files in os.walk(run_dir):
        for name in files:
            if name.endswith((".pt", ".pt.tmp")) or (name.startswith("events.out.tfevents.") and mine not in name):
                return False
    return True


def run_name(args: Any, stamp: int | None = None) -> str:
    """CleanRL's run name, `<env_id>__<exp_name>__<seed>__<unix time>`: the run's folder under --track-dir."""
    return f"{args.env_id}__{args.exp_name}__{args.seed}__{int(time.time()) if stamp is None else stamp}"


RUN_DIR: list[str] = []  # the folder the current run of this process trains in (for its stop line)
RUN_LOCKS: dict[str, int] = {}  # run folder -> descriptor of its run.lock, held by this process


def claim_run_dir(args: Any) -> str:
    """A new run's folder under --track-dir, made here, never one that exists: two runs of the same name started
    in the same second (a flag sweep started with `&`) would otherwise write into one folder, each overwriting the
    other's checkpoints. The second takes the next free second for its name's <unix time>."""
    os.makedirs(args.track_dir, exist_ok=True)
    stamp = int(time.time())
    while True:
        path = os.path.join(args.track_dir, run_name(args, stamp))
        try:
            os.mkdir(path)
            return path
        except FileExistsError:
            stamp += 1


def lock_run_dir(run_dir: str) -> None:
    """Hold an exclusive lock on `<run_dir>/run.lock` (which holds the pid) while this process trains there: a second
    process there (a --resume of a run that is still going, a requeued job) would overwrite its checkpoints and
    replay rows. A POSIX lock: held by this process alone (not its env workers) and ended by its exit, however it
    ends; a second lock by the same process (a resume in a notebook after a stopped train()) is its own. Refused in
    one line. A filesystem without locks is used unlocked."""
    key = os.path.realpath(run_dir)
    if key in RUN_LOCKS:
        return
    fd = os.open(os.path.join(run_dir, "run.lock"), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        if exc.errno not in (errno.EACCES, errno.EAGAIN):
            os.close(fd)  # (no locks on this filesystem)
            return
        holder = os.read(fd, 64).decode(errors="replace").strip()
        os.close(fd)
        who = f"pid {holder}" if holder.isdigit() else "another process"
        stop = f"stop it (kill {holder})" if holder.isdigit() else "stop it"
        fail(f"{run_dir} is in use: a run is training there ({who}); wait for it to end, or {stop} and resume then")
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    RUN_LOCKS[key] = fd


def unlock_run_dir(run_dir: str) -> None:
    """Release the lock of `lock_run_dir` (at the run's end)."""
    fd = RUN_LOCKS.pop(os.path.realpath(run_dir), None)
    if fd is not None:
        os.close(fd)


def script_name(file: str) -> str:
    """The default --exp-name: the script's file name without .py (CleanRL's), so a copy's runs are its own."""
    return os.path.basename(file)[: -len(".py")] if file.endswith(".py") else os.path.basename(file)


def asked_for(args: Any, name: str, default: Any) -> bool:
    """Whether a new run was asked to set `name`: on its command line (even to the default value: `--alpha 0.2`
    with --autotune asks for something the run would not do), or, called from code, to another value."""
    return name in NEW_RUN_FLAGS or getattr(args, name) != default


def check_resume_settings(args: Any) -> None:
    """The settings --resume takes anew (RESUME_OVERRIDABLE) that can be out of range: checked also when the run
    is finished and nothing else runs, so a wrong value is never accepted silently."""
    check_threads(args.torch_threads)
    if getattr(args, "checkpoint_every", 0) < 0:
        fail(f"--checkpoint-every must be >= 0 (0: only the checkpoints a run always writes; got {args.checkpoint_every})")


def check_common_settings(args: Any) -> None:
    """Settings every run shares, refused in one line each (instead of a traceback later, or a run folder left);
    first every real-valued setting: finite and in its range (errors.check_ranges)."""
    check_ranges(args)
    check_seed(args.seed)
    check_resume_settings(args)
    if RESUMING:  # its folder exists: whether the run can write there, not whether new folders can be made beside it
        check_run_dir_writable(RESUMING[0])
    else:
        check_track_dir(args.track_dir)
    check_exp_name(args.exp_name)
    if args.track:
        check_wandb()


# the flags --evaluate uses (each script has those of them it defines), and two it lets be, so that a job script may
# pass them to every command: --cuda (--evaluate runs on the CPU) and --quiet (it prints its result line only)
EVALUATE_FIELDS = {"evaluate", "eval_episodes", "seed", "capture_video", "torch_threads", "members", "deterministic",
                   "eval_deterministic"}
EVALUATE_TOLERATED = {"quiet", "cuda"}


def evaluate_only(args: Any, given: set[str], evaluate_saved: Callable[[Any], Any],
                  load_checkpoint: Callable[..., dict]) -> None:
    """--evaluate: the saved model on the env it was trained on. Flags it would ignore are refused in one line; a
    stop (Ctrl-C, SIGTERM) ends in one line too (exit 130 / 143): nothing of a run is at stake."""
    if args.resume:
        fail("--evaluate and --resume exclude each other: --evaluate runs a saved model, --resume continues its run; "
             "pass one")
    if "env_id" in given:
        fail(f"--env-id has no effect with --evaluate: the saved model is evaluated on the env it was trained on "
             f"(saved in {args.evaluate}); leave --env-id out")
    ignored = sorted(given - EVALUATE_FIELDS - EVALUATE_TOLERATED)
    if ignored:
        applying = sorted(EVALUATE_FIELDS & set(type(args).__dataclass_fields__) - {"evaluate"})
        fail(f"--{ignored[0].replace('_', '-')} has no effect with --evaluate: the saved model is evaluated with the "
             f"settings it was trained with; leave it out (with --evaluate only "
             f"{', '.join('--' + name.replace('_', '-') for name in applying)} apply)")
    check_seed(args.seed)
    forget_stops()
    refuse_another_scripts_checkpoint(load_checkpoint(args.evaluate, reader_flag="--evaluate"), type(args), "evaluate")
    handle_stops()
    try:
        evaluate_saved(args)
    except KeyboardInterrupt:
        signum = STOPPED_BY[-1] if STOPPED_BY else signal.SIGINT
        print(f"\rstopped by {signal.Signals(signum).name}: the evaluation of {args.evaluate} was stopped before it "
              "ended (nothing to resume: run it again)", file=sys.stderr, flush=True)
        sys.exit(128 + signum)


def run_main(args_type: type, train: Callable[[Any, dict | None], Any], evaluate_saved: Callable[[Any], Any],
             load_checkpoint: Callable[[str], dict], finished: Callable[[Any, dict], bool], description: str) -> None:
    """The command line of a training script: train, --resume a killed run, or --evaluate a saved model.

    A stop (Ctrl-C, SIGTERM) ends with one line saying where the last checkpoint is (exit 130 / 143); a run
    that has finished its work is not stopped any more (its checkpoint is final), and resuming a finished run
    does nothing."""
    args = parse_command_line(lambda: tyro.cli(args_type, description=description))
    for flag in ("evaluate", "resume"):  # an empty path (`--resume "$RUN"` with RUN unset) would start a new run
        if getattr(args, flag) is not None and not getattr(args, flag).strip():
            fail(f"--{flag} is empty; pass a run folder or a checkpoint file")
    given = explicit_fields(args_type, sys.argv[1:])
    if args.evaluate:
        evaluate_only(args, given, evaluate_saved, load_checkpoint)
        return
    checkpoint = None
    RESUMING.clear()
    NEW_RUN_FLAGS.clear()
    if args.resume:
        checkpoint = load_checkpoint(args.resume)
        refuse_another_scripts_checkpoint(checkpoint, args_type, "resume")
        refuse_overwriting_later_work(checkpoint, frozenset(RESUME_OVERRIDABLE))
        args = resumed_args(args, checkpoint, given)
    else:
        refuse_idle_flags(args, given)
        NEW_RUN_FLAGS.update(given)  # (the checks that need the env: discrete.resolve_env)
    if checkpoint is not None:
        check_resume_settings(args)
        if finished(args, checkpoint):
            if "iteration" in checkpoint:  # a kill while the last iteration_<i>.pt was copied: rebuild it all the same
                repair_iteration_files(os.path.dirname(checkpoint["path"]), checkpoint, at_iteration_end=True)
            print(f"{checkpoint['path']} is the end of the run (global_step={checkpoint['global_step']}); "
                  "nothing to resume")
            return
    forget_stops()
    handle_stops()
    # the checkpoint a resume would find finished (the same test): from its write on, a stop lets the run finish
    FINAL[:] = [lambda path, payload: finished(type(args)(**payload["args"]), {**payload, "path": path})]
    if not getattr(threading.excepthook, "quiet_writer_threads", False):
        threading.excepthook = quiet_writer_threads(threading.excepthook)
    if not getattr(sys.excepthook, "quiet_resource_sharer", False):
        sys.excepthook = quiet_resource_sharer(sys.excepthook)
    RUN_DIR.clear()
    SAVED_AT_STOP.clear()
    if checkpoint is not None:
        RESUMING.append(os.path.dirname(checkpoint["path"]))
    try:
        train(args, checkpoint)
    except BaseException as exc:
        FINAL.clear()  # this run's test; a later train() in the same process (a notebook, the tests) has its own
        FINISHING.clear()
        drop_stop_requests()
        finish_wandb(exit_code=1)  # an error or a stop: the W&B run ends as failed, before the last line
        if isinstance(exc, KeyboardInterrupt):
            end_env_workers()
            stopped(checkpoint)
        if not isinstance(exc, SystemExit) and disk_full(exc):  # a log write (a checkpoint's says so itself)
            end_env_workers()
            run_dir = this_run_dir(checkpoint)
            no_space(os.path.abspath(run_dir or args.track_dir), run_dir)
        if out_of_memory(exc):  # e.g. a --hidden-size that does not fit: one line, not torch's traceback
            end_env_workers()
            no_memory(exc, this_run_dir(checkpoint), args)
        if overflowed(exc):  # the non-finite guard's case, one step earlier: a float32 could not hold a value
            end_env_workers()
            run_dir = this_run_dir(checkpoint)
            rates = " / ".join(f"--{name.replace('_', '-')}" for name in ("learning_rate", "policy_lr", "q_lr")
                               if hasattr(args, name))
            kept = os.path.join(run_dir, CHECKPOINT_NAME) if run_dir else ""  # ("": no run folder yet)
            fail(f"a value overflowed float32 ({str(exc).splitlines()[0]}), e.g. a learning rate too large for it; "
                 f"{non_finite_advice(kept, rates)}")
        run_dir = None if isinstance(exc, SystemExit) else this_run_dir(checkpoint)
        changed = changed_under_the_run(exc, run_dir)
        if changed is not None:  # (a fault hunt: a 40-line traceback of TensorBoard's writer, or of replay/)
            end_env_workers()
            path = os.fsdecode(changed.filename)
            if not os.path.isdir(run_dir):
                fail(f"the run folder {run_dir} is gone ({path}: {changed.strerror}): it was moved or deleted while "
                     f"the run trained, and its checkpoints with it: continue with python "
                     f"{os.path.basename(sys.argv[0])} --resume <the folder where it is now> (if it holds a "
                     "checkpoint.pt; else start again)")
            stop_short_of(f"cannot use {path} ({changed.strerror}): the run folder was changed while the run "
                          "trained", "", run_dir, "put back what was moved or replaced there",
                          "start the run again")
        refused = None if isinstance(exc, SystemExit) else refused_write(exc)
        if refused is not None:  # a folder made read-only, a file of the run whose permissions changed, a disk error
            end_env_workers()
            verb = "write" if refused.errno == errno.EROFS else "access"  # (EACCES, EIO: reading may be what failed)
            stop_short_of(f"cannot {verb} {refused.filename} ({refused.strerror})", "", this_run_dir(checkpoint),
                          "make it writable", "make it writable and start the run again")
        raise
    finally:
        RESUMING.clear()
        NEW_RUN_FLAGS.clear()
    # The work is done and saved: a stop from here on must not turn a finished run into a failed one (at
    # interpreter exit Python resets its own handlers to the default, which would die by the signal silently).
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if signal.getsignal(signal.SIGHUP) is stop_signal:
        signal.signal(signal.SIGHUP, signal.SIG_IGN)
    FINAL.clear()
    FINISHING.clear()
    forget_stops()
