"""Evaluations beside training: a worker process that runs the script's own evaluation on frozen copies of
the policy, or the same inline. What is evaluated, and how, is the script's (its `Evaluator`); this is only
the transport."""

from __future__ import annotations

import multiprocessing
import signal
from collections.abc import Callable
from typing import Any

import torch

from .errors import fail


def evaluation_worker(conn, make_context: Callable[[], Any], work: Callable[[Any, int, Any], Any]) -> None:
    """Worker process: `context = make_context()` once, then `work(context, call, request)` for each request."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the training process's to handle
    torch.set_num_threads(1)
    context = make_context()
    try:
        while (message := conn.recv()) is not None:
            step, call, request = message
            conn.send((step, work(context, call, request)))
    except (EOFError, ConnectionError):  # the training process stopped: so do we, quietly
        return


class EvaluationRunner:
    """Runs `work(context, call, request)` for each submitted request, in a worker process beside training
    (`in_worker`) or inline, and hands back `(step, result)` pairs in submission order.

    `make_context` and `work` must be picklable (module-level functions, or functools.partial of them). `call`
    counts the requests over the whole run (kept in checkpoints), so that an evaluation's random streams depend
    on its position in the run only. Evaluation costs as many env steps as training under the paper's protocol,
    so on 2+ cores a worker nearly hides it."""

    def __init__(self, make_context: Callable[[], Any], work: Callable[[Any, int, Any], Any], in_worker: bool,
                 calls: int = 0):
        self.work, self.calls, self.pending, self.done = work, calls, 0, []
        self.conn = self.process = self.context = None
        if in_worker:
            ctx = multiprocessing.get_context("spawn")  # fork is unsafe with torch threads
            self.conn, child = ctx.Pipe()
            self.process = ctx.Process(target=evaluation_worker, args=(child, make_context, work), daemon=True)
            self.process.start()
        else:
            self.context = make_context()

    def submit(self, step: int, request: Any) -> None:
        if self.conn is not None:
            self.conn.send((step, self.calls, request))
            self.pending += 1
        else:
            self.done.append((step, self.work(self.context, self.calls, request)))
        self.calls += 1

    def results(self, wait: bool = False) -> list[tuple[int, Any]]:
        """Finished evaluations (all outstanding ones with `wait`)."""
        while self.pending and (wait or self.conn.poll()):
            try:
                if not self.process.is_alive() and not self.conn.poll():
                    raise EOFError
                self.done.append(self.conn.recv())
            except (EOFError, ConnectionError):  # it can also die while we wait on it
                fail("the evaluation worker process died; rerun with --no-eval-in-worker to see why")
            self.pending -= 1
        done, self.done = self.done, []
        return done

    def close(self) -> None:
        if self.conn is not None:
            self.conn.send(None)
            self.process.join(timeout=10)
        elif hasattr(self.context, "close"):
            self.context.close()
