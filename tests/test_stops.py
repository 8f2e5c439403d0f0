"""Stops and resumes at the edges of a run (GitHub issue 28, a soak test under injected faults): resuming a
finished run, a stop after the final checkpoint, a stop before the first one, and a stopped sweep."""

import glob
import os
import signal
import subprocess
import sys
import time

import pytest

import sweep
from helpers import ROOT, cli_in_process, ctrl_c_reaches_child, error_line, only_run_dir, read_scalars, run_script

FLAGSHIP = "cascade_ppo_continuous.py"
BASELINE = "ppo_baseline.py"
# 8 updates of 256 steps; the final step (2048) is not an eval step, so the final policy is
# evaluated once more at the end: that evaluation is what a re-run of a finished run would repeat.
FLAGS = {FLAGSHIP: ["--n", "1", "--k", "2048"], BASELINE: ["--total-timesteps", "2048"]}
COMMON = ["--num-steps", "256", "--num-minibatches", "4", "--update-epochs", "1", "--eval-every", "1000",
          "--eval-episodes", "2", "--quiet"]
ENV = ["--env-id", "InvertedPendulum-v4"]
TINY = {script: [*flags, *ENV, *COMMON] for script, flags in FLAGS.items()}
SWEEP_TINY = " ".join([FLAGSHIP, *FLAGS[FLAGSHIP], *COMMON])  # a sweep's template (the sweep adds --env-id)
SWEEP_LONG = " ".join([FLAGSHIP, "--n", "1", "--k", "1000000", *COMMON])  # stopped long before its end
EVAL_STEPS = [0, 1000, 2000, 2048]
# A stop right after a run folder appears falls while the evaluation worker is being spawned, whose traceback
# (EOFError in multiprocessing's spawn_main, the parent gone mid-handover) is another defect than these tests'
# (cascade_plumbing/evaluation.py): they stop runs there with evaluations inline.
INLINE = "--no-eval-in-worker"


def start(script, *args):
    """A script or the sweep in the background, as a user starts it (Ctrl-C reaches it)."""
    return subprocess.Popen([sys.executable, os.path.join(ROOT, script), *map(str, args)], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=ctrl_c_reaches_child)


def wait_for(pattern, proc, timeout=300):
    """The first path matching `pattern`, polled while `proc` runs."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        found = glob.glob(pattern)
        if found:
            return found[0]
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"exited {proc.returncode} before {pattern} appeared:\n{out[-2000:]}\n{err[-2000:]}")
        time.sleep(0.01)
    proc.kill()
    pytest.fail(f"no {pattern} within {timeout} s")


def finish(proc, timeout=300):
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out, err


def eval_steps(run_dir):
    return [step for step, _ in read_scalars(run_dir)["eval/episodic_return"]]


@pytest.mark.parametrize("script", [FLAGSHIP, BASELINE])
def test_resuming_a_finished_run_adds_nothing(tmp_path, script, capsys):
    """Issue 28.1: `--resume` of a finished run evaluated its final step again (0, 3000, 6000, 8192, 8192)."""
    first = run_script(script, *TINY[script], "--track-dir", tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    run_dir = only_run_dir(tmp_path)
    assert eval_steps(run_dir) == EVAL_STEPS
    files = {name: os.path.getmtime(os.path.join(run_dir, name)) for name in os.listdir(run_dir)}
    with open(os.path.join(run_dir, "checkpoint.pt"), "rb") as f:
        saved = f.read()

    code, out, error = cli_in_process(capsys, script, "--resume", run_dir, "--quiet")
    assert code == 0, error
    assert eval_steps(run_dir) == EVAL_STEPS
    assert "nothing to resume" in out, out[-2000:]
    assert {name: os.path.getmtime(os.path.join(run_dir, name)) for name in os.listdir(run_dir)} == files
    with open(os.path.join(run_dir, "checkpoint.pt"), "rb") as f:
        assert f.read() == saved


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_stop_after_the_final_checkpoint_lets_the_run_finish(tmp_path, signum):
    """Issue 28.2: a stop after the final checkpoint (during the final evaluation, the writer's and the envs'
    close) turned a finished run into a failure (exit 143), without its final evaluation."""
    proc = start(FLAGSHIP, *TINY[FLAGSHIP], "--track-dir", tmp_path)
    wait_for(str(tmp_path / "*" / "iteration_1.pt"), proc)
    proc.send_signal(signum)
    code, out, err = finish(proc)
    assert code == 0, err[-2000:]
    assert "stopped by" not in err and "Traceback" not in err, err[-2000:]
    assert f"{signal.Signals(signum).name} after the final checkpoint" in err
    assert eval_steps(only_run_dir(tmp_path)) == EVAL_STEPS  # complete: the final evaluation too


def test_a_sweep_stopped_after_its_runs_final_checkpoint_marks_it_done(tmp_path):
    """Issue 28.2 in a sweep: the run finishes (the sweep marks it done instead of running it again), and a
    run folder without a checkpoint that a killed attempt left behind is removed when the run starts again."""
    command = SWEEP_TINY
    args = ["--command", command, "--envs", "InvertedPendulum-v4", "--workers", "1", "--sweep-dir", tmp_path]
    (run,) = sweep.expand(sweep.Args(command=[command], envs=["InvertedPendulum-v4"]))
    stale = tmp_path / "runs" / run.run_id / f"InvertedPendulum-v4__{run.label}__1__1700000000"
    stale.mkdir(parents=True)
    (stale / "events.out.tfevents.1700000000.host.1.0").write_bytes(b"")
    proc = start("sweep.py", *args)
    wait_for(str(tmp_path / "runs" / "*" / "*" / "iteration_1.pt"), proc)
    proc.send_signal(signal.SIGTERM)
    code, out, err = finish(proc)
    assert code == 0, out[-2000:] + err[-2000:]  # nothing is left unfinished
    assert f"done   {run.run_id}" in out and "FAILED" not in out and "1 of 1 runs done" in out, out
    assert "removed 1 run folder(s) without a checkpoint" in out
    assert os.listdir(tmp_path / "done") == [f"{run.run_id}.json"]
    assert eval_steps(only_run_dir(tmp_path / "runs" / run.run_id)) == EVAL_STEPS
    with open(tmp_path / "logs" / f"{run.run_id}.log") as f:
        assert "SIGTERM after the final checkpoint" in f.read()


def test_a_run_stopped_before_its_first_checkpoint_removes_its_folder(tmp_path):
    """Issue 28.4a: such a run left an empty run folder behind (22 after the soak test); only its own goes."""
    older = tmp_path / "InvertedPendulum-v4__cascade_ppo_continuous__1__1700000000"  # another run's, no checkpoint
    older.mkdir()
    (older / "events.out.tfevents.1700000000.host.1.0").write_bytes(b"")
    proc = start(FLAGSHIP, "--n", "1", "--k", "1000000", "--checkpoint-every", "0", INLINE, *ENV, *COMMON,
                 "--track-dir", tmp_path)
    events = wait_for(str(tmp_path / "*" / f"events.out.tfevents.*.{proc.pid}.*"), proc)
    proc.send_signal(signal.SIGINT)
    code, out, err = finish(proc)
    assert code == 130, err[-2000:]
    lines = [line.strip("\r") for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("stopped by SIGINT: no checkpoint was written yet"), err
    assert os.path.dirname(events) in lines[0] and "is removed" in lines[0]
    assert os.listdir(tmp_path) == [older.name] and os.listdir(older) == ["events.out.tfevents.1700000000.host.1.0"]


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_stopped_sweep_says_one_line(tmp_path, signum):
    """Issue 28.3: a stopped sweep printed FAILED for each run it stopped itself, then status lines, and exited
    130 for SIGTERM too. Now: one line (the stopped runs, where each continues), exit 128 + the signal.
    SIGINT stops the run after its first checkpoint (it resumes there), SIGTERM before it (it starts over)."""
    long = f"{SWEEP_LONG} --checkpoint-every 2048" if signum == signal.SIGINT else f"{SWEEP_LONG} --checkpoint-every 0 {INLINE}"
    args = ["--command", long, f"{long} --gamma 0.98", "--envs", "InvertedPendulum-v4",
            "--workers", "1", "--status-every", "3600", "--sweep-dir", tmp_path]
    proc = start("sweep.py", *args)
    wanted = "checkpoint.pt" if signum == signal.SIGINT else "events.out.tfevents.*"
    found = wait_for(str(tmp_path / "runs" / "*" / "*" / wanted), proc)
    run_id = os.path.relpath(found, tmp_path / "runs").split(os.sep)[0]
    proc.send_signal(signum)
    code, out, err = finish(proc)
    assert code == 128 + signum, out[-2000:] + err[-2000:]
    # the start line, the first progress line (before the stop), and the stop's one line
    lines = out.splitlines()
    assert lines[0].startswith("[sweep] 2 runs in") and len(lines) == 3, out
    assert lines[1].startswith("[sweep] 0 done, ") and lines[1].endswith(" of 2 | ETA ?"), out
    assert lines[2].startswith(f"[sweep] stopped by {signal.Signals(signum).name}: stopped 1 run(s): {run_id} ("), out
    assert "1 not started" in lines[2] and "0 done, 0 failed" in lines[2]
    assert not os.path.exists(tmp_path / "done")
    with open(tmp_path / "logs" / f"{run_id}.log") as f:
        assert "stopped by SIGTERM:" in f.read()  # the sweep stops its runs with SIGTERM
    if signum == signal.SIGINT:
        folder = os.path.dirname(found)
        assert f"{run_id} (resumes from {folder})" in lines[2]
        again = run_script("sweep.py", *args, "--dry-run")  # the next call resumes that checkpoint
        assert f"--resume {folder} " in again.stdout, again.stdout
    else:
        assert f"{run_id} (starts over: no checkpoint yet)" in lines[2]
        assert os.listdir(tmp_path / "runs" / run_id) == []  # the run removed its folder itself


def start_in_own_session(script, *args):
    """A script as a job scheduler starts it: in a session (and process group) of its own, which it stops with
    SIGTERM to the whole group (`kill -TERM -<pgid>`)."""
    return subprocess.Popen([sys.executable, os.path.join(ROOT, script), *map(str, args)], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)


@pytest.mark.parametrize("script", [FLAGSHIP, BASELINE])
def test_sigterm_to_the_process_group_after_the_final_checkpoint_lets_the_run_finish(tmp_path, script):
    """Issue 49.1: SIGTERM to the run's whole process group, as job schedulers send it, killed the evaluation
    worker too; the run then failed (exit 1, "the evaluation worker process died") without its final evaluation.
    The worker is in a group of its own now: the stop reaches the training process only, which finishes."""
    proc = start_in_own_session(script, *TINY[script], "--track-dir", tmp_path)
    wait_for(str(tmp_path / "*" / "checkpoint.pt"), proc)  # the only checkpoint of these runs: the final one
    os.killpg(proc.pid, signal.SIGTERM)
    code, out, err = finish(proc)
    assert code == 0, err[-2000:]
    assert "Traceback" not in err and "worker process died" not in err, err[-2000:]
    assert eval_steps(only_run_dir(tmp_path)) == EVAL_STEPS  # complete: the final evaluation too
    again = run_script(script, "--resume", only_run_dir(tmp_path))
    assert again.returncode == 0 and "nothing to resume" in again.stdout, again.stderr[-2000:]


def test_sigterm_to_the_process_group_mid_run_stops_it_at_its_checkpoint(tmp_path):
    """The same group SIGTERM before the end: the run stops with its one line (exit 143), its worker ends with it."""
    proc = start_in_own_session(FLAGSHIP, "--n", "1", "--k", "1000000", "--checkpoint-every", "2048", *ENV, *COMMON,
                                "--track-dir", tmp_path)
    wait_for(str(tmp_path / "*" / "checkpoint.pt"), proc)
    workers = children(proc.pid)
    os.killpg(proc.pid, signal.SIGTERM)
    code, out, err = finish(proc, timeout=120)
    assert code == 128 + signal.SIGTERM, err[-2000:]
    lines = [line.strip("\r") for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("stopped by SIGTERM: the last checkpoint is"), err
    deadline = time.time() + 10
    while any(os.path.exists(f"/proc/{pid}") for pid in workers) and time.time() < deadline:
        time.sleep(0.1)
    assert workers and not any(os.path.exists(f"/proc/{pid}") for pid in workers)  # they ended with the run


def children(pid):
    """The pids of `pid`'s child processes (Linux)."""
    found = []
    for entry in os.listdir("/proc"):
        try:
            with open(f"/proc/{entry}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        if entry.isdigit() and int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            found.append(int(entry))
    return found


@pytest.mark.parametrize("script,flags", [
    (FLAGSHIP, FLAGS[FLAGSHIP] + ENV),
    (BASELINE, FLAGS[BASELINE] + ENV),
    ("cascade_ppo_discrete.py", ["--n", "1", "--k", "2048", "--env-id", "CartPole-v1"]),
    ("ppo_baseline_discrete.py", ["--total-timesteps", "2048", "--env-id", "CartPole-v1"]),
])
def test_the_final_evaluation_is_logged_before_the_final_checkpoint(tmp_path, monkeypatch, script, flags):
    """Issue 49.1: the PPO scripts evaluated the final policy after the final checkpoint, so a kill in the second
    after it lost that evaluation for good (a resume has nothing to do). SAC and DDPG evaluated it first."""
    import importlib

    from cascade_plumbing import record

    module = importlib.import_module(script[: -len(".py")])
    seen = []
    original = record.save_checkpoint

    def save_and_look(path, payload):
        original(path, payload)
        seen.append((payload["global_step"], eval_steps(os.path.dirname(path))))

    monkeypatch.setattr(record, "save_checkpoint", save_and_look)
    monkeypatch.setattr(sys, "argv", [script, *flags, *COMMON, "--no-eval-in-worker" if "baseline.py" in script or
                                      script == FLAGSHIP else "--quiet", "--track-dir", str(tmp_path)])
    module.main()
    assert seen[-1] == (2048, EVAL_STEPS)


def test_runs_of_one_name_started_in_the_same_second_get_folders_of_their_own(tmp_path, capsys):
    """A flag sweep started with `&` starts runs of one name (env, --exp-name, seed) in the same second: each gets a
    folder of its own (the next free second in its name), never one that exists. Before, the second run wrote into
    the first one's folder and the two overwrote each other's checkpoints."""
    now = int(time.time())
    taken = [tmp_path / f"InvertedPendulum-v4__cascade_ppo_continuous__1__{stamp}" for stamp in range(now, now + 4)]
    for folder in taken:  # the folders of runs started in this second and the next three
        folder.mkdir()
        (folder / "theirs.txt").write_text("another run")
    code, _, message = cli_in_process(capsys, FLAGSHIP, *TINY[FLAGSHIP], "--eval-every", "0",
                                      "--track-dir", tmp_path)
    assert code == 0, message
    new = [d for d in os.listdir(tmp_path) if tmp_path / d not in taken]
    assert len(new) == 1 and int(new[0].rsplit("__", 1)[1]) >= now + 4, new
    assert os.path.exists(tmp_path / new[0] / "checkpoint.pt")
    for folder in taken:
        assert os.listdir(folder) == ["theirs.txt"], os.listdir(folder)


def test_a_resume_of_a_run_that_is_still_training_is_refused(tmp_path):
    """`--resume` of a run folder another process still trains in (a requeued job, a second terminal) would
    overwrite that run's checkpoints and logs: it is refused in one line naming the process, and the running run's
    checkpoint is untouched. Once that run has stopped, the folder is free again."""
    proc = start(FLAGSHIP, "--n", "1", "--k", "300000", "--checkpoint-every", "2048", "--eval-every", "0", *ENV,
                 *COMMON[:-5], "--quiet", "--track-dir", tmp_path)
    try:
        checkpoint = wait_for(str(tmp_path / "*" / "checkpoint.pt"), proc)
        run_dir = os.path.dirname(checkpoint)
        resumed = run_script(FLAGSHIP, "--resume", run_dir, timeout=900)
        assert resumed.returncode != 0 and proc.poll() is None, resumed.stderr[-2000:]
        assert error_line(resumed) == (f"error: {run_dir} is in use: a run is training there (pid {proc.pid}); wait "
                                       f"for it to end, or stop it (kill {proc.pid}) and resume then")
    finally:
        proc.send_signal(signal.SIGINT)
        code, _, err = finish(proc, timeout=120)
    assert code == 128 + signal.SIGINT, err[-2000:]
    from cascade_plumbing.runs import lock_run_dir, unlock_run_dir
    lock_run_dir(run_dir)  # free: the stopped run's lock ended with it
    unlock_run_dir(run_dir)


def test_after_a_stop_a_worker_s_reset_connection_is_not_reported():
    """A fresh-clone CI run: Ctrl-C during a --num-envs 2 run printed, after the one stop line, a traceback of
    multiprocessing's resource-sharer thread (ConnectionResetError: the worker ended by the same Ctrl-C)."""
    from cascade_plumbing import runs

    code = compile("def serve():\n    raise ConnectionResetError(104, 'Connection reset by peer')\n",
                   "/usr/lib/python3/multiprocessing/resource_sharer.py", "exec")
    namespace: dict = {}
    exec(code, namespace)

    def reported(error_source, stopped):
        seen = []
        hook = runs.quiet_resource_sharer(lambda *info: seen.append(info))
        try:
            error_source()
        except Exception:
            info = sys.exc_info()
        saved = list(runs.STOPPED_BY)
        runs.STOPPED_BY[:] = [signal.SIGINT] if stopped else []
        try:
            hook(*info)
        finally:
            runs.STOPPED_BY[:] = saved
        return bool(seen)

    assert not reported(namespace["serve"], stopped=True)
    assert reported(namespace["serve"], stopped=False)  # without a stop it is a real error

    def elsewhere():
        raise ConnectionResetError(104, "Connection reset by peer")

    assert reported(elsewhere, stopped=True)  # not the resource sharer's: reported
