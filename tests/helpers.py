import contextlib
import os
import shutil
import signal
import subprocess
import sys

import gymnasium as gym
import numpy as np
import torch
from filelock import FileLock
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def built_once(tmp_path_factory, name, build):
    """`build(folder)`'s result, built once per pytest session even under pytest-xdist: the first worker builds it
    in a folder all workers share (this session's temp folder) and saves it; the others wait, then load it. The
    tests must only read that folder."""
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        return build(tmp_path_factory.mktemp(name))
    shared = tmp_path_factory.getbasetemp().parent  # pytest-<n>/ of this session, above each worker's popen-gw<i>
    with FileLock(str(shared / f"{name}.lock")):
        saved = shared / f"{name}.pt"
        if saved.exists():
            return torch.load(saved, weights_only=False)
        folder = shared / name
        shutil.rmtree(folder, ignore_errors=True)  # what a worker that failed building it left
        folder.mkdir()
        result = build(folder)
        torch.save(result, saved)
        return result


def replay_batch(seed, size, obs_dim, low, high, obs_scale=1.0, reward_scale=1.0, done_every=3):
    """(obs, actions, rewards, next_obs, dones) as ReplayBuffer.sample gives them, in the default dtype: actions
    uniform in the bounds [low, high], every `done_every`-th row terminated."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(size, obs_dim, generator=g) * obs_scale
    next_obs = torch.randn(size, obs_dim, generator=g) * obs_scale
    low = torch.as_tensor(low, dtype=torch.get_default_dtype())
    high = torch.as_tensor(high, dtype=torch.get_default_dtype())
    actions = low + (high - low) * torch.rand(size, len(low), generator=g)
    rewards = torch.randn(size, generator=g) * reward_scale
    dones = (torch.arange(size) % done_every == 0).to(torch.get_default_dtype())
    return obs, actions, rewards, next_obs, dones


def perturb(module, scale, seed):
    """The module with every parameter moved off its init, in place (fallbacks then differ between nets and
    states, heads matter)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(scale * torch.randn(p.shape, generator=g))
    return module


def run_script(script, *args, timeout=600, env=None):
    """Run one of the top-level scripts as a user would; returns the CompletedProcess."""
    return subprocess.run(
        [sys.executable, os.path.join(ROOT, script), *map(str, args)],
        capture_output=True, text=True, timeout=timeout, cwd=ROOT, env={**os.environ, **(env or {})},
    )


def ctrl_c_reaches_child() -> None:
    """Popen preexec_fn: Ctrl-C interrupts the child as it would from a terminal, even when the tests were
    started with SIGINT ignored (a background job, nohup), which a child process would otherwise inherit."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def read_scalars(run_dir):
    """{tag: [(step, value), ...]} from a run folder's TensorBoard events."""
    acc = EventAccumulator(run_dir, size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def only_run_dir(track_dir):
    runs = os.listdir(track_dir)
    assert len(runs) == 1, runs
    return os.path.join(track_dir, runs[0])


def error_line(proc):
    """The single `error: ...` line a script prints on bad input, after checking it exited non-zero."""
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode != 0, proc.stdout[-2000:]
    assert len(lines) == 1 and lines[0].startswith("error:"), proc.stderr[-2000:]
    return lines[0]


@contextlib.contextmanager
def copy_checkpoint_when(module, wanted, destination):
    """While active, every checkpoint `module` saves whose payload satisfies `wanted` is also copied
    to `destination` (a checkpoint a killed run would have left behind). The save may be the script's own
    or the shared package's: every loaded module holding the package's `save_checkpoint` is patched."""
    import sys

    from cascade_plumbing.checkpoints import save_checkpoint as package_save

    def copying(save):
        def save_and_copy(path, payload):
            save(path, payload)
            if wanted(payload):
                shutil.copy(path, destination)
        return save_and_copy

    holders = {id(m): m for m in [module, *list(sys.modules.values())]
               if m is module and hasattr(m, "save_checkpoint") or getattr(m, "save_checkpoint", None) is package_save}
    originals = {key: holder.save_checkpoint for key, holder in holders.items()}
    for key, holder in holders.items():
        holder.save_checkpoint = copying(originals[key])
    try:
        yield
    finally:
        for key, holder in holders.items():
            holder.save_checkpoint = originals[key]


def resume_from(module, checkpoint_file, folder):
    """As a killed run is resumed: the checkpoint alone, in its run folder, with its saved settings."""
    os.makedirs(folder)
    shutil.copy(checkpoint_file, os.path.join(folder, "checkpoint.pt"))
    checkpoint = module.load_checkpoint(str(folder))
    return module.train(module.Args(**checkpoint["args"]), checkpoint)


def run_in_process(script, *args):
    """`python <script> <args>` run inside the test process (no interpreter start-up: ~4 s saved per call);
    returns (exit code, what SystemExit carried). The script's signal handlers are restored afterwards."""
    import importlib
    from unittest import mock

    module = importlib.import_module(os.path.splitext(os.path.basename(script))[0])
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with mock.patch.object(sys, "argv", [script, *map(str, args)]):
            module.main()
    except SystemExit as stop:
        if stop.code is None or isinstance(stop.code, int):
            return stop.code or 0, ""
        return 1, str(stop.code)
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    return 0, ""


def cli_in_process(capsys, script, *args):
    """`python <script> <args>` run in-process (`run_in_process`) with what it printed: (exit code, stdout, the
    error message it stopped with, "" if none). For checks of what a command does and prints; the tests that need a
    real interpreter (stderr, signals, the exit status, a fresh import) keep `run_script`."""
    capsys.readouterr()  # what the test printed before is not the command's
    code, message = run_in_process(script, *args)
    return code, capsys.readouterr().out, message


def error_line_in_process(script, *args):
    """The one-line `error: ...` a script stops with on bad input, run in-process (see `run_in_process`)."""
    code, message = run_in_process(script, *args)
    assert code != 0, f"{script} {args} did not fail"
    assert message.startswith("error:") and "\n" not in message, message
    return message


class RecordedEnvs:
    """The training envs, passed through, keeping what the loop is given and sends: every observation (as float32,
    the loop's cast), action, reward and episode end."""

    def __init__(self, envs):
        self.envs, self.obs, self.actions, self.rewards, self.dones = envs, [], [], [], []

    def __getattr__(self, name):
        return getattr(self.envs, name)

    def reset(self, **kwargs):
        obs, info = self.envs.reset(**kwargs)
        self.obs.append(obs.astype(np.float32))
        self.dones.append(np.zeros(len(obs), np.float32))
        return obs, info

    def step(self, actions):
        self.actions.append(np.array(actions, np.float32))
        obs, reward, terminations, truncations, info = self.envs.step(actions)
        self.obs.append(obs.astype(np.float32))
        self.rewards.append(np.asarray(reward, np.float32))
        self.dones.append(np.logical_or(terminations, truncations).astype(np.float32))
        return obs, reward, terminations, truncations, info


class ObservationLog(gym.Wrapper):
    """Keeps every raw observation the env returns (from reset and step)."""

    def __init__(self, env):
        super().__init__(env)
        self.observations = []

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.observations.append(np.array(obs))
        return obs, info

    def step(self, action):
        obs, *rest = self.env.step(action)
        self.observations.append(np.array(obs))
        return (obs, *rest)


def assert_rows_are_normalized_observations(rows, envs, mean, var):
    """Each row a policy was given is one raw observation the envs returned, as the training wrappers leave it
    (NormalizeObservation with statistics (mean, var), then clipped to +-10). Evaluation batches the running envs'
    observations in an order the test need not know: each row is looked up among all of them."""
    raw = np.concatenate([np.stack(env.observations) for env in envs])
    expected = np.clip((raw - mean) / np.sqrt(var + 1e-8), -10, 10)
    for row in rows:
        assert np.isclose(expected, row, rtol=1e-5, atol=1e-5).all(1).any(), row


class ActionLog(gym.Wrapper):
    """Keeps every action the env is stepped with."""

    def __init__(self, env):
        super().__init__(env)
        self.actions = []

    def step(self, action):
        self.actions.append(np.array(action))
        return self.env.step(action)
