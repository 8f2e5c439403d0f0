"""Evaluations beside training: a worker process that runs the script's own evaluation on frozen copies of
the policy, or the same inline; the envs of evaluation episodes, stepped side by side; the start of --evaluate.
What is evaluated, and how it acts, is the script's (its `Evaluator`); this is only the transport and the envs."""

from __future__ import annotations

import atexit
import contextlib
import multiprocessing
import os
import signal
import tempfile
import traceback
from collections.abc import Callable, Iterator
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from .envs import make_render_env, write_video
from .errors import fail
from .processes import own_group, starting_group_workers
from .runs import set_threads


def evaluation_worker(conn, make_context: Callable[[], Any], work: Callable[[Any, int, Any], Any],
                      parent: int) -> None:
    """Worker process: `context = make_context()` once, then `work(context, call, request)` for each request.
    In a process group of its own (a scheduler's SIGTERM to the run's group is the training process's to handle:
    it stops at its checkpoint, or finishes after the final one), ending with the training process (`parent`)."""
    own_group(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the training process's to handle
    signal.signal(signal.SIGHUP, signal.SIG_IGN)  # (so is a closed terminal's SIGHUP)
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
            self.process = ctx.Process(target=evaluation_worker, args=(child, make_context, work, os.getpid()),
                                       daemon=True)
            with starting_group_workers():
                self.process.start()
            # at any exit (a stop, an error): a worker still starting has SIGTERM blocked, so multiprocessing's
            # own end of daemon workers (SIGTERM, then an unbounded join) could wait on it forever
            atexit.register(self.end)
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
            self.end()
        elif hasattr(self.context, "close"):
            self.context.close()

    def end(self) -> None:
        """The worker ended now if it has not (it holds nothing to keep)."""
        if self.process is not None and self.process.is_alive():
            self.process.kill()
            self.process.join(timeout=10)


class EvaluationEnvs:
    """`episodes` envs of `env_id` for evaluation episodes, run side by side (with `render`, the first one's frames
    are kept in `frames`, for a video; `wrap`, e.g. an action wrapper, wraps each env); a script's `Evaluator`
    subclasses it and says how its policy acts. `seed`: the evaluation's seed, from which each call's episode
    seeds (`base_seed`) and the script's action noise derive."""

    def __init__(self, env_id: str, episodes: int, seed: int, render: bool = False,
                 wrap: Callable[[gym.Env], gym.Env] | None = None):
        self.envs = [make_render_env(env_id) if render else gym.make(env_id) for _ in range(episodes)]
        if wrap is not None:
            self.envs = [wrap(env) for env in self.envs]
        self.seed = seed
        self.frames: list[np.ndarray] | None = [] if render else None

    def base_seed(self, call: int) -> int:
        """The seed of episode 0 of the run's evaluation number `call` (episode i: this + i)."""
        return self.seed + 100_003 * (call + 1)

    def run_episodes(self, act: Callable[[np.ndarray, list[int]], np.ndarray], base_seed: int) -> np.ndarray:
        """One episode on every env (env i reset with seed `base_seed + i`), until all have ended; `act(obs,
        running)` maps the raw observations [m, obs_dim] of the m envs still running (their indices: `running`) to
        their actions, which are clipped to a Box action space. Returns each episode's undiscounted return."""
        obs = np.stack([env.reset(seed=base_seed + i)[0] for i, env in enumerate(self.envs)])
        if self.frames is not None:
            self.frames.append(self.envs[0].render())
        space = self.envs[0].action_space
        box = isinstance(space, gym.spaces.Box)
        returns = np.zeros(len(self.envs))
        active = list(range(len(self.envs)))
        while active:
            action = act(obs[active], active)
            if box:
                action = np.clip(action, space.low, space.high)
            still_active = []
            for row, i in enumerate(active):
                o, r, terminated, truncated, _ = self.envs[i].step(action[row])
                if self.frames is not None and i == 0:
                    self.frames.append(self.envs[0].render())
                returns[i] += r
                obs[i] = o
                if not (terminated or truncated):
                    still_active.append(i)
            active = still_active
        return returns

    def write_video(self, path: str) -> None:
        """The kept frames (`render`) as an mp4."""
        write_video(self.frames, path, self.envs[0].metadata.get("render_fps", 30))

    def close(self) -> None:
        for env in self.envs:
            env.close()


def save_video_of_one_episode(checkpoint_path: str, mode: str, video: EvaluationEnvs,
                              run: Callable[[EvaluationEnvs], float]) -> None:
    """--evaluate --capture-video: one more episode, `run(video)` on `video` (made with render=True; it returns the
    episode's return), written as <checkpoint>_<mode>.mp4 beside the checkpoint; one line says where."""
    path = os.path.splitext(checkpoint_path)[0] + f"_{mode}.mp4"
    episode_return = run(video)
    video.write_video(path)
    video.close()
    print(f"video of one episode (return {episode_return:.1f}): {path}")


def open_saved_model(args: Any, load_checkpoint: Callable[..., dict]) -> dict:
    """The start of --evaluate: --eval-episodes checked, the checkpoint `args.evaluate` loaded, with
    --capture-video its env's renderer tried (one line now, before any episode is run), torch's threads set."""
    if args.eval_episodes < 1:
        fail(f"--eval-episodes must be at least 1 (got {args.eval_episodes})")
    checkpoint = load_checkpoint(args.evaluate, reader_flag="--evaluate")  # (a corrupt file's advice: --evaluate)
    if args.capture_video:
        folder = os.path.dirname(os.path.abspath(checkpoint["path"]))
        try:  # the video goes beside the checkpoint: a read-only results share ended in a BrokenPipeError traceback
            probe, probe_path = tempfile.mkstemp(dir=folder, suffix=".mp4")
            os.close(probe)
            os.remove(probe_path)
        except OSError as exc:
            fail(f"--capture-video writes its video beside the checkpoint, and {folder} is not writable "
                 f"({exc.strerror or exc}); copy the run folder somewhere writable and evaluate the copy, or leave out "
                 "--capture-video")
        make_render_env(checkpoint["args"]["env_id"]).close()
    set_threads(args.torch_threads)
    return checkpoint


@contextlib.contextmanager
def mean_action_defined(deterministic: bool) -> Iterator[None]:
    """--evaluate --deterministic acts with the mean of the policy's distribution (`action_distribution(...).mean`):
    a distribution with no closed-form mean (torch's TransformedDistribution, e.g. a tanh-squashed Gaussian) raises
    NotImplementedError there, which ends in one line saying so and what to do, not in a traceback."""
    try:
        yield
    except NotImplementedError as exc:
        frames = traceback.extract_tb(exc.__traceback__)
        if not deterministic or not frames or frames[-1].name != "mean":
            raise
        fail(f"--deterministic acts with the mean of the policy's distribution, and this one has none in closed form "
             f"(NotImplementedError{': ' + str(exc) if str(exc) else ''} from its .mean, in {frames[-1].filename}); "
             "evaluate without --deterministic (sampled actions), or define the mean in section 1 (e.g. a subclass of "
             "the distribution with a `mean` property, such as tanh of the Gaussian's mean)")
