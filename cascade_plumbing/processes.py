"""Child processes that end with the process that started them, and that a stop sent to a whole process group does
not reach. Job schedulers stop a job with SIGTERM to its process group (`kill -TERM -<pgid>`): a worker process in
that group died by it at once, and the run then failed on the dead worker instead of stopping (or finishing) at its
checkpoint. A worker started here is in its own process group, so such a stop reaches the training process only,
which ends its workers itself; and on Linux the worker gets SIGTERM when its parent dies, even by SIGKILL
(PR_SET_PDEATHSIG), so no worker outlives its run."""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import sys
import threading

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def _find_prctl():
    """libc's prctl with its argument types, looked up once here (not in a freshly forked child), or None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    prctl.restype = ctypes.c_int
    return prctl


_PRCTL = _find_prctl()


def die_with_parent(parent: int, signum: int = signal.SIGTERM) -> None:
    """In a child process: `signum` once the thread that started it ends (Linux; elsewhere nothing). A child whose
    `parent` (its pid) has ended already ends now, before it has started any work."""
    if _PRCTL is not None:
        _PRCTL(PR_SET_PDEATHSIG, int(signum), 0, 0, 0)
    if os.getppid() != parent:
        os._exit(128 + signum)


@contextlib.contextmanager
def starting_group_workers():
    """Around the start of worker processes that call `own_group` first: SIGTERM is blocked in this thread, and so
    in the children, which inherit the signal mask (across exec too). A SIGTERM sent to the process group while a
    child starts waits in it, and `own_group` drops it; one sent to this process is handled by another thread or
    after this block. Outside the main thread (no signal handling there) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    try:
        yield
    finally:
        if signal.SIGTERM not in blocked:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})


def own_group(parent: int) -> None:
    """First thing in a worker started within `starting_group_workers`: a process group of its own, death with
    `parent` (its pid), and SIGTERM back to its default (ending the worker) without a SIGTERM that was sent to the
    parent's group while it started (that stop is the parent's to handle)."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # drops a pending SIGTERM
    with contextlib.suppress(OSError):  # (a session leader already is in a group of its own)
        os.setpgid(0, 0)
    die_with_parent(parent)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def run_dies_with_parent(parent: int):
    """A `preexec_fn` for subprocess.Popen: the child gets SIGTERM when the thread that started it ends, e.g. a
    sweep killed with SIGKILL; the child's own SIGTERM handling then stops it cleanly."""

    def preexec() -> None:
        die_with_parent(parent)

    return preexec
