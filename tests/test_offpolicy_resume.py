"""SAC and DDPG runs lose nothing when killed: a checkpoint every --checkpoint-every steps holds the nets, targets,
optimizers, RNG streams, env state and the replay buffer (its rows in the run folder's replay/), and a run killed at
any step and resumed ends bit-identical to the uninterrupted one (GitHub issue 48)."""

import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

import cascade_ddpg as cd
import cascade_sac as cs
from cascade_plumbing import offpolicy, record, runs
from cascade_plumbing.replay import ReplayBuffer, ReplayFiles
from helpers import ROOT, cli_in_process, only_run_dir, read_scalars

SCRIPTS = {"sac": cs, "ddpg": cd}
# Pendulum (200-step episodes that only truncate), 2 iterations of 300 steps, a checkpoint every 70 steps, evaluations
# at 100-step multiples: kills fall in the warm-up, between checkpoints, right after one, in the second iteration
TINY = dict(env_id="Pendulum-v1", n=2, k=300, learning_starts=100, batch_size=32, eval_every=100, eval_episodes=2,
            checkpoint_every=70, quiet=True)
CHECKPOINT_STEPS = [70, 140, 210, 280, 300, 370, 440, 510, 580, 600]  # every 70 steps since the last, and iteration ends
NETS = {"sac": ("actor", "qf", "qf_target"), "ddpg": ("actor", "target_actor", "qf", "qf_target")}


class Killed(BaseException):
    """What the test raises inside a run, as a SIGKILL would stop it: nothing after it runs (not an Exception, so no
    handler in the run can catch it)."""


def kill_at(monkeypatch, step):
    """Stop the next run right after env step `step` (before its update, evaluation or checkpoint)."""
    original = offpolicy.OffPolicyRun.step

    def step_then_die(self, actions, buffer, global_step):
        original(self, actions, buffer, global_step)
        if global_step == step:
            raise Killed

    monkeypatch.setattr(offpolicy.OffPolicyRun, "step", step_then_die)


def train_killed_at(monkeypatch, mod, step, args, checkpoint=None):
    """`mod.train(args, checkpoint)` killed right after env step `step` (`kill_at`), as a SIGKILL would stop it."""
    with monkeypatch.context() as patch:
        kill_at(patch, step)
        with pytest.raises(Killed):
            mod.train(args, checkpoint)
    KILLED_WRITERS.extend(record.OPEN_WRITERS)  # (the killed run's writer: a real kill leaves it behind too)
    record.OPEN_WRITERS.clear()


KILLED_WRITERS = []  # the writers of in-process kills: their flush thread goes on writing into the run folder


def close_killed_writers():
    """Before a killed run's folder is removed or moved: its writers' flush thread (every 120 s) appends to the
    events file by its path, which made it again while rmtree emptied the folder ("Directory not empty", a CI run)."""
    while KILLED_WRITERS:
        KILLED_WRITERS.pop().close()


def final_state(result, algo):
    return {name: {k: v.clone() for k, v in result[name].state_dict().items()} for name in NETS[algo]}


def assert_identical(a, b):
    for name, state in a.items():
        for key, value in state.items():
            torch.testing.assert_close(b[name][key], value, rtol=0, atol=0, msg=f"{name}.{key}")


def assert_same_saved_nets(algo, run_a, run_b):
    """The nets the checkpoints of two run folders hold are bit-identical."""
    a, b = SCRIPTS[algo].load_checkpoint(run_a), SCRIPTS[algo].load_checkpoint(run_b)
    assert_identical({name: a[name] for name in NETS[algo]}, b)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The uninterrupted runs, per (algo, keep_buffer)."""
    cache = {}

    def get(algo, keep_buffer):
        if (algo, keep_buffer) not in cache:
            mod = SCRIPTS[algo]
            folder = tmp_path_factory.mktemp(f"{algo}_{keep_buffer}")
            result = mod.train(mod.Args(**TINY, keep_buffer=keep_buffer, buffer_size=250, track_dir=str(folder)))
            cache[algo, keep_buffer] = (final_state(result, algo), read_scalars(result["run_dir"]),
                                        mod.load_checkpoint(result["run_dir"])["replay"])
        return cache[algo, keep_buffer]

    return get


def resume(mod, run_dir):
    checkpoint = mod.load_checkpoint(run_dir)
    return mod.train(mod.Args(**checkpoint["args"]), checkpoint)


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
@pytest.mark.parametrize("keep_buffer", [False, True], ids=["standard", "keep-buffer"])
# after the warm-up's checkpoint (70), right after a checkpoint (141: its step 140 written), before the iteration's
# end (299), in iteration 2's warm-up (351) and its learning steps (563)
@pytest.mark.parametrize("kill_step", [99, 141, 299, 351, 563])
def test_a_run_killed_at_any_step_resumes_bit_identical(algo, keep_buffer, kill_step, uninterrupted, tmp_path,
                                                       monkeypatch):
    mod = SCRIPTS[algo]
    # small segments (and a 250-row buffer, with --keep-buffer one that wraps): the rows span several files, and old
    # ones are deleted as the run goes
    monkeypatch.setattr(ReplayFiles, "SEGMENT_ROWS", 16)
    expected, expected_scalars, expected_replay = uninterrupted(algo, keep_buffer)
    args = mod.Args(**TINY, keep_buffer=keep_buffer, buffer_size=250, track_dir=str(tmp_path))
    train_killed_at(monkeypatch, mod, kill_step, args)
    run_dir = only_run_dir(tmp_path)
    assert mod.load_checkpoint(run_dir)["global_step"] == max(s for s in CHECKPOINT_STEPS if s < kill_step)
    resumed = resume(mod, run_dir)
    assert_identical(expected, final_state(resumed, algo))
    scalars = read_scalars(run_dir)
    for tag in ("eval/episodic_return", "losses/qf1_loss", "losses/actor_loss", "members/return/net_2"):
        assert scalars[tag] == expected_scalars[tag], tag
    # the net count at each iteration's start only (a fault hunt: a resume mid-iteration logged it again, at its own
    # step); a resume at an iteration's end may log the next one's start twice, at one step (the killed run logged it
    # after the checkpoint, and may not have flushed it)
    for tag in ("cascade/size", "cascade/parameters"):
        assert sorted(set(scalars[tag])) == expected_scalars[tag], tag
    # the replay log goes on where the uninterrupted run's is (a resume at an iteration's end, which needs no rows,
    # numbered the rows from 0 again and rewrote the files of rows written before)
    saved = mod.load_checkpoint(run_dir)["replay"]
    assert saved == expected_replay
    # replay/ keeps only what the latest checkpoint needs: the rows of the buffer at its step
    segments = sorted(int(f[5:-4]) for f in os.listdir(os.path.join(run_dir, "replay")))
    assert segments and segments[0] == saved["first"] // 16, (segments, saved)


def stop_at(monkeypatch, step, signum=signal.SIGTERM):
    """A stop signal (SIGTERM, Ctrl-C) arriving right after env step `step` of the next run, through the scripts'
    own handler: in-process, as run_main installs it."""
    original = offpolicy.OffPolicyRun.step

    def step_then_signal(self, actions, buffer, global_step):
        original(self, actions, buffer, global_step)
        if global_step == step:
            runs.stop_signal(signum, None)

    monkeypatch.setattr(offpolicy.OffPolicyRun, "step", step_then_signal)


# in the warm-up (99), between periodic checkpoints (163), at the last step of iteration 1 (its end's checkpoint:
# 300), in iteration 2 (563); DDPG at one of them (the stop is the shared OffPolicyRun's; what a DDPG checkpoint
# holds is checked by the kills above)
@pytest.mark.parametrize("algo,stop_step", [("sac", 99), ("sac", 163), ("sac", 300), ("sac", 563), ("ddpg", 163)])
def test_a_stop_writes_a_checkpoint_at_the_next_step_and_resumes_bit_identical(algo, stop_step, uninterrupted,
                                                                              tmp_path, monkeypatch):
    """SIGTERM or Ctrl-C loses nothing: the run writes a checkpoint at the step after the signal (not only at its
    last periodic one, up to --checkpoint-every steps back), then stops; resumed, it ends as if never stopped."""
    mod = SCRIPTS[algo]
    expected, expected_scalars, _ = uninterrupted(algo, False)
    with monkeypatch.context() as patch:
        stop_at(patch, stop_step)
        with pytest.raises(KeyboardInterrupt):
            mod.train(mod.Args(**TINY, buffer_size=250, track_dir=str(tmp_path)))
    record.OPEN_WRITERS.clear()
    run_dir = only_run_dir(tmp_path)
    assert mod.load_checkpoint(run_dir)["global_step"] == stop_step == runs.SAVED_AT_STOP[-1]
    assert runs.STOPPED_BY == [signal.SIGTERM] and not runs.STOP_REQUESTED
    # the progress file (sweep.py shows it) says where the run stopped (a fault hunt: it kept a line up to 30 s old,
    # shown for the resumed run too)
    if stop_step > TINY["learning_starts"]:  # (a line is first written at the first update)
        progress = open(os.path.join(run_dir, "progress.txt")).read()
        assert progress.startswith(f"{stop_step:,}/600 steps"), progress
    runs.CHECKPOINT_ON_STOP.clear()  # (run_main's cleanup after a stop)
    resumed = resume(mod, run_dir)
    assert_identical(expected, final_state(resumed, algo))
    scalars = read_scalars(run_dir)
    for tag in ("eval/episodic_return", "losses/qf1_loss", "members/return/net_2"):
        assert scalars[tag] == expected_scalars[tag], tag


def test_a_stop_at_the_last_step_lets_the_run_finish(uninterrupted, tmp_path, monkeypatch, capsys):
    """A stop at the run's last step (during its last evaluations): its checkpoint is the final one, the run ends
    complete and says so (it did not stop), and leaves no stop behind for a later run in the process."""
    expected = uninterrupted("sac", False)[0]
    with monkeypatch.context() as patch:
        stop_at(patch, 600)
        result = cs.train(cs.Args(**TINY, buffer_size=250, track_dir=str(tmp_path)))
    assert_identical(expected, final_state(result, "sac"))
    assert not runs.STOPPED_BY and not runs.CHECKPOINT_ON_STOP and not runs.STOP_REQUESTED
    assert "SIGTERM after the run's last step: it finished instead of stopping" in capsys.readouterr().err


def test_a_stop_left_pending_by_an_earlier_run_does_not_defer_the_next_ones(tmp_path, monkeypatch,
                                                                          capsys):
    """A run of the same process killed mid-way (a notebook, a test) left a run registered to checkpoint on a stop:
    the next run's stops, even a PPO run's or --evaluate's, which never checkpoint on one, were only recorded and
    never acted on. Each run (and --evaluate) starts with none registered."""
    with monkeypatch.context() as patch:
        kill_at(patch, 50)
        with pytest.raises(Killed):
            cs.train(cs.Args(**TINY, track_dir=str(tmp_path)))
    record.OPEN_WRITERS.clear()
    assert runs.CHECKPOINT_ON_STOP  # left behind by the killed run
    runs.STOP_REQUESTED.append(signal.SIGTERM)
    code, _, err = cli_in_process(capsys, "cascade_sac.py", "--evaluate", str(tmp_path / "missing"))
    assert code != 0 and not runs.CHECKPOINT_ON_STOP and not runs.STOP_REQUESTED
    with pytest.raises(KeyboardInterrupt):  # a stop now acts at once
        runs.stop_signal(signal.SIGTERM, None)
    # ... and a run started next in the same process (a notebook's next cell) runs through, not stopped at its step 1
    runs.CHECKPOINT_ON_STOP.append(True)
    runs.STOP_REQUESTED.append(signal.SIGTERM)
    try:
        result = cs.train(cs.Args(**{**TINY, "n": 1, "k": 150}, track_dir=str(tmp_path / "next")))
    except KeyboardInterrupt:  # (not pytest's own stop)
        pytest.fail("the next run was stopped by the stop an earlier run left pending")
    assert result["global_step"] == 150 and not runs.STOP_REQUESTED


def test_a_stop_before_the_first_step_or_a_second_stop_ends_the_run_at_once():
    """Before its first step a run has nothing to keep, and a second stop means now: both stop at once."""
    def a_second_later():
        runs.LAST_STOP[0] -= runs.SAME_STOP_S

    with pytest.raises(KeyboardInterrupt):  # no step taken yet
        runs.stop_signal(signal.SIGINT, None)
    runs.STOPPED_BY.clear()
    runs.forget_stops()  # (the next run)
    runs.CHECKPOINT_ON_STOP.append(True)
    assert runs.stop_signal(signal.SIGINT, None) is None and runs.STOP_REQUESTED == [signal.SIGINT]
    with pytest.raises(KeyboardInterrupt):
        a_second_later()
        runs.stop_signal(signal.SIGTERM, None)
    assert runs.STOPPED_BY == [signal.SIGTERM]


def test_the_same_stop_delivered_twice_is_one_stop():
    """A job scheduler signals every process of a job, and sweep.py passes its own stop on: a run gets the stop
    twice within milliseconds. Taken as a second stop, it ended a SAC or DDPG run before its checkpoint (and a
    third one interrupted its last line with a traceback); within runs.SAME_STOP_S it is the same stop."""
    runs.CHECKPOINT_ON_STOP.append(True)
    for signum in (signal.SIGTERM, signal.SIGTERM, signal.SIGINT):
        try:
            runs.stop_signal(signum, None)
        except KeyboardInterrupt:  # (not pytest's own stop)
            pytest.fail("the repeated stop ended the run before its checkpoint")
    assert runs.STOP_REQUESTED == [signal.SIGTERM] and not runs.STOPPED_BY
    runs.forget_stops()
    with pytest.raises(KeyboardInterrupt):  # a run that stops at once (PPO): the repeat does not interrupt its stop
        runs.stop_signal(signal.SIGTERM, None)
    try:
        runs.stop_signal(signal.SIGTERM, None)
    except KeyboardInterrupt:
        pytest.fail("the repeated stop interrupted the stopping run")
    assert runs.STOPPED_BY == [signal.SIGTERM]


@pytest.mark.parametrize("deferred", [False, True], ids=["at-once", "after-its-checkpoint"])
def test_a_stop_that_comes_while_a_stopped_run_ends_changes_nothing(deferred):
    """The stop's repeat may come after the stopped run's end had cleared its stop bookkeeping (a small SAC run
    writes its checkpoint at the stop and ends within the 10 ms between a scheduler's two signals), or a person's
    second Ctrl-C a few seconds into the ending: raised again, it printed a traceback from an atexit callback after
    the stop's line (a fresh-clone CI run saw it)."""
    if deferred:
        runs.CHECKPOINT_ON_STOP.append(True)
        runs.stop_signal(signal.SIGTERM, None)
        with pytest.raises(KeyboardInterrupt):
            runs.stop_after_checkpoint(614)
    else:
        with pytest.raises(KeyboardInterrupt):
            runs.stop_signal(signal.SIGTERM, None)
    runs.drop_stop_requests()  # the run's end: offpolicy's close, run_main's except
    runs.LAST_STOP[0] -= 10 * runs.SAME_STOP_S  # (and seconds later)
    for signum in (signal.SIGTERM, signal.SIGINT):
        try:
            runs.stop_signal(signum, None)
        except KeyboardInterrupt:  # (not pytest's own stop)
            pytest.fail("a stop during the stopped run's end raised again")
    assert runs.STOPPED_BY == [signal.SIGTERM]
    runs.forget_stops()  # a run started next acts on a stop again
    with pytest.raises(KeyboardInterrupt):
        runs.stop_signal(signal.SIGINT, None)


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_a_kill_between_the_rows_and_the_checkpoint_loses_nothing(algo, uninterrupted, tmp_path, monkeypatch):
    """Killed after the replay rows of a checkpoint were written but before the checkpoint itself: the files hold
    rows the previous checkpoint does not record, which the resumed run writes again, the same."""
    mod = SCRIPTS[algo]
    expected = uninterrupted(algo, False)[0]
    original = record.save_checkpoint

    def die_at_210(path, payload):
        if payload["global_step"] == 210:
            raise Killed
        original(path, payload)

    with monkeypatch.context() as patch:
        patch.setattr(record, "save_checkpoint", die_at_210)
        with pytest.raises(Killed):
            mod.train(mod.Args(**TINY, buffer_size=250, track_dir=str(tmp_path)))
    record.OPEN_WRITERS.clear()
    run_dir = only_run_dir(tmp_path)
    assert mod.load_checkpoint(run_dir)["global_step"] == 140
    assert_identical(expected, final_state(resume(mod, run_dir), algo))


@pytest.mark.parametrize("damage", ["folder deleted", "segment cut short"])
def test_replay_files_lost_while_the_run_trains_are_written_again(damage, uninterrupted, tmp_path, monkeypatch):
    """A fault hunt: replay/ deleted (or a segment cut short) while a run trained, the next checkpoint wrote only the
    rows added since the previous one and recorded rows that were gone, so the run could never be resumed (all its
    work lost). Every row is still in memory: the next checkpoint writes them again, and a kill after it resumes
    bit-identical."""
    mod = SCRIPTS["sac"]
    monkeypatch.setattr(ReplayFiles, "SEGMENT_ROWS", 16)
    expected = uninterrupted("sac", False)[0]
    original = offpolicy.OffPolicyRun.step

    def damage_then_die(self, actions, buffer, global_step):
        original(self, actions, buffer, global_step)
        replay = os.path.join(self.run_dir, "replay")
        if global_step == 150 and damage == "folder deleted":
            shutil.rmtree(replay)
        elif global_step == 150:
            segment = os.path.join(replay, sorted(os.listdir(replay))[-2])  # a whole one, of rows the buffer holds
            os.truncate(segment, os.path.getsize(segment) // 2)
        if global_step == 230:
            raise Killed

    with monkeypatch.context() as patch:
        patch.setattr(offpolicy.OffPolicyRun, "step", damage_then_die)
        with pytest.raises(Killed):
            mod.train(mod.Args(**TINY, buffer_size=250, track_dir=str(tmp_path)))
    KILLED_WRITERS.extend(record.OPEN_WRITERS)
    record.OPEN_WRITERS.clear()
    run_dir = only_run_dir(tmp_path)
    assert mod.load_checkpoint(run_dir)["global_step"] == 210
    assert_identical(expected, final_state(resume(mod, run_dir), "sac"))


@pytest.mark.parametrize("change", ["folder moved", "replay/ replaced by a file"])
def test_a_run_folder_changed_while_the_run_trains_is_one_line(change, tmp_path, monkeypatch, capsys):
    """A fault hunt: a run folder moved away mid-run (`mv runs/x archive/`), or its replay/ replaced by a file, ended
    in a traceback of 12-40 lines (TensorBoard's writer, the replay files). Now one line that says what happened and
    how to continue; the moved folder resumes where it is now."""
    original = offpolicy.OffPolicyRun.step

    def change_at_150(self, actions, buffer, global_step):
        original(self, actions, buffer, global_step)
        if global_step == 150 and change == "folder moved":
            os.rename(self.run_dir, tmp_path / "moved")
        elif global_step == 150:
            shutil.rmtree(os.path.join(self.run_dir, "replay"))
            open(os.path.join(self.run_dir, "replay"), "w").close()

    monkeypatch.setattr(offpolicy.OffPolicyRun, "step", change_at_150)
    flags = ["--env-id", "Pendulum-v1", "--n", "2", "--k", "300", "--learning-starts", "100", "--batch-size", "32",
             "--eval-every", "100", "--eval-episodes", "1", "--checkpoint-every", "70", "--quiet",
             "--track-dir", str(tmp_path / "runs")]
    code, _, error = cli_in_process(capsys, "cascade_sac.py", *flags)
    record.OPEN_WRITERS.clear()  # (the failed run's writer: its events file is gone, as in a real process's end)
    assert code == 1 and error.startswith("error: ") and "\n" not in error, error
    if change == "folder moved":
        assert "was moved or deleted while the run trained" in error and "--resume <the folder where it is now>" in error
        assert not os.listdir(tmp_path / "runs"), "nothing written at the old place"
        monkeypatch.setattr(offpolicy.OffPolicyRun, "step", original)
        code, _, error = cli_in_process(capsys, "cascade_sac.py", "--resume", str(tmp_path / "moved"))
        assert code == 0 and cs.load_checkpoint(str(tmp_path / "moved"))["global_step"] == 600, error
    else:
        assert "the run folder was changed while the run trained" in error and "checkpoint" in error, error
        assert "put back what was moved or replaced there and continue with: python cascade_sac.py --resume" in error


def test_only_a_path_of_the_run_folder_is_a_change_under_the_run(tmp_path):
    """The one line for a run folder changed mid-run is for its own paths (and the folder itself) only: an unrelated
    missing file (an edit's open() of a typo) stays the error it is."""
    import errno

    run_dir = str(tmp_path / "run")
    gone = OSError(errno.ENOENT, "No such file or directory", os.path.join(run_dir, "replay", "rows_000000.f32"))
    assert runs.changed_under_the_run(gone, run_dir) is gone
    folder = FileNotFoundError(errno.ENOENT, "No such file or directory", run_dir)
    assert runs.changed_under_the_run(folder, run_dir) is folder
    tensorboard = FileNotFoundError(errno.ENOENT, "No such file", os.fsencode(os.path.join(run_dir, "events.out")))
    assert runs.changed_under_the_run(tensorboard, run_dir) is tensorboard
    for elsewhere in (os.path.join(str(tmp_path), "data.csv"), run_dir + "2/checkpoint.pt"):
        assert runs.changed_under_the_run(OSError(errno.ENOENT, "No such file", elsewhere), run_dir) is None
    assert runs.changed_under_the_run(OSError(errno.EACCES, "Permission denied", run_dir), run_dir) is None
    assert runs.changed_under_the_run(gone, None) is None


def test_a_checkpoint_replaced_between_its_read_and_the_lock_is_not_resumed(tmp_path, monkeypatch):
    """A fault hunt: a resume reads the checkpoint before it takes the run folder's lock; a run still training there
    that wrote a newer checkpoint (and ended) in between was then continued from the older state, over the newer.
    Now the resume stops in one line, and resumed again, continues from the newer one."""
    mod = SCRIPTS["sac"]
    train_killed_at(monkeypatch, mod, 150, mod.Args(**TINY, buffer_size=250, track_dir=str(tmp_path)))
    close_killed_writers()
    run_dir = only_run_dir(tmp_path)
    read = mod.load_checkpoint(run_dir)
    newer = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)
    torch.save(newer, os.path.join(run_dir, "checkpoint.new"))  # (what the other process's next checkpoint does)
    os.replace(os.path.join(run_dir, "checkpoint.new"), os.path.join(run_dir, "checkpoint.pt"))
    before = {name: os.path.getmtime(os.path.join(run_dir, name)) for name in os.listdir(run_dir)}
    with pytest.raises(SystemExit) as stop:
        mod.train(mod.Args(**read["args"]), read)
    assert f"{read['path']} was replaced after it was read (the run went on there since)" in str(stop.value)
    assert f"--resume {read['path']}" in str(stop.value) and "\n" not in str(stop.value), stop.value
    assert {name: os.path.getmtime(os.path.join(run_dir, name)) for name in os.listdir(run_dir)} == before
    record.OPEN_WRITERS.clear()
    assert resume(mod, run_dir)["global_step"] == 600


def test_a_resume_named_in_the_same_second_is_read_after_the_killed_run(uninterrupted, tmp_path, monkeypatch):
    """TensorBoard reads a run folder's events files in name order (`...tfevents.<second>.<host>.<pid>.<count>`):
    a resume named within the second of the killed run's file could sort before it (count 10 before 9, or another
    host), and its curves were read out of order. Here the killed run's file is renamed to sort after anything
    named now; the resumed run's file must still come last."""
    expected, expected_scalars, _ = uninterrupted("sac", False)
    train_killed_at(monkeypatch, cs, 141, cs.Args(**TINY, buffer_size=250, track_dir=str(tmp_path)))
    run_dir = only_run_dir(tmp_path)
    [killed] = [name for name in os.listdir(run_dir) if name.startswith("events.out.tfevents.")]
    os.rename(os.path.join(run_dir, killed),
              os.path.join(run_dir, f"events.out.tfevents.{int(time.time()) + 1:010d}.zzzz.1.9"))
    assert_identical(expected, final_state(resume(cs, run_dir), "sac"))
    scalars = read_scalars(run_dir)
    for tag in ("eval/episodic_return", "losses/qf1_loss"):
        assert scalars[tag] == expected_scalars[tag], tag


@pytest.mark.parametrize("keep_buffer", [False, True], ids=["standard", "keep-buffer"])
def test_a_corrupt_checkpoint_names_an_iteration_file_only_if_it_can_continue(keep_buffer, uninterrupted, tmp_path,
                                                                             monkeypatch, capsys):
    """A corrupt checkpoint.pt names the newest intact iteration_<i>.pt to continue from. Resumed at an iteration's
    end, a --keep-buffer run needs that file's replay rows, which the run deleted as its wrapped buffer moved on:
    the line then says the file cannot continue the run (naming --evaluate), instead of sending the user on to a
    second error. Without --keep-buffer the named file continues the run, to the uninterrupted end."""
    monkeypatch.setattr(ReplayFiles, "SEGMENT_ROWS", 16)
    args = cs.Args(**TINY, keep_buffer=keep_buffer, buffer_size=250, track_dir=str(tmp_path))
    train_killed_at(monkeypatch, cs, 563, args)  # checkpoint.pt at 510: its buffer starts at row 260
    run_dir = only_run_dir(tmp_path)
    with open(os.path.join(run_dir, "checkpoint.pt"), "wb") as f:
        f.write(b"\0" * 1000)  # a disk error
    iteration_1 = os.path.join(run_dir, "iteration_1.pt")
    code, _, error = cli_in_process(capsys, "cascade_sac.py", "--resume", run_dir)
    assert code == 1 and error.startswith("error: cannot read checkpoint") and "\n" not in error, error
    if keep_buffer:  # iteration 1's buffer, rows 50..299, was in segments 3..18, deleted up to segment 15
        assert error.endswith(f"{iteration_1} (the end of iteration 1), cannot continue the run either: the replay "
                              "rows it needs (--keep-buffer) were deleted as the run moved on; evaluate it with: "
                              f"python cascade_sac.py --evaluate {iteration_1}, or start a new run"), error
        code, _, error = cli_in_process(capsys, "cascade_sac.py", "--resume", iteration_1)
        assert code == 1 and "resume the run folder itself" in error, error  # what the line spares the user
    else:
        assert error.endswith(f"continue the run from there with: python cascade_sac.py --resume {iteration_1}")
        code, _, error = cli_in_process(capsys, "cascade_sac.py", "--resume", iteration_1)
        assert code == 0 and error == "", error
        expected = uninterrupted("sac", False)[0]
        final = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)
        assert final["global_step"] == 600
        assert_identical({name: expected[name] for name in ("actor", "qf")},
                         {"actor": final["actor"], "qf": final["qf"]})


def test_replay_files_round_trip_a_wrapped_buffer(tmp_path):
    """The rows on disk give back the very buffer: its rows in their ring positions, its position and size, and the
    same samples; after a clear, only rows added since."""
    rng = np.random.default_rng(0)
    buffer = ReplayBuffer(50, 3, 2)
    files = ReplayFiles(str(tmp_path), buffer)
    files.SEGMENT_ROWS = 16

    def add(rows):
        for _ in range(rows):
            buffer.add(rng.normal(size=(1, 3)), rng.normal(size=(1, 3)), rng.normal(size=(1, 2)), rng.normal(size=1),
                       rng.integers(0, 2, size=1))

    for rows in (30, 45, 2, 60):  # the buffer wraps; checkpoints at 30, 75, 77, 137 rows
        add(rows)
        saved = files.save()
        files.prune(saved)
    buffer.clear()
    add(20)
    saved = files.save()
    files.prune(saved)
    for _case in ("after a clear", "full"):
        again = ReplayBuffer(50, 3, 2)
        twin = ReplayFiles(str(tmp_path), again)
        twin.SEGMENT_ROWS = 16
        twin.restore(saved)
        assert (again.pos, again.size, again.added, again.start) == (buffer.pos, buffer.size, buffer.added, buffer.start)
        np.testing.assert_array_equal(again.data[: again.size], buffer.data[: buffer.size])
        np.random.seed(3)
        one = buffer.sample(8, torch.device("cpu"))
        np.random.seed(3)
        two = again.sample(8, torch.device("cpu"))
        for a, b in zip(one, two):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
        add(70)  # then a full, wrapped buffer
        saved = files.save()
        files.prune(saved)
    assert sorted(os.listdir(tmp_path / "replay"))[0] == f"rows_{saved['first'] // 16:06d}.f32"


def test_missing_or_changed_replay_rows_are_one_line(tmp_path, capsys):
    """A mid-iteration checkpoint whose replay rows are gone (copied out of its folder) or changed (another run's)
    is refused in one line that says what to do."""
    args = cs.Args(**{**TINY, "n": 1}, track_dir=str(tmp_path / "runs"))
    cs.train(args)
    run_dir = only_run_dir(tmp_path / "runs")
    # a copy of the last mid-iteration checkpoint alone, without replay/
    checkpoint = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)
    checkpoint["steps_done"], checkpoint["iteration"] = 280, 1
    os.makedirs(tmp_path / "copy")
    torch.save(checkpoint, tmp_path / "copy" / "checkpoint.pt")
    code, _, error = cli_in_process(capsys, "cascade_sac.py", "--resume", str(tmp_path / "copy"))
    assert code == 1 and "replay buffer" in error and "is not in" in error and "\n" not in error, error
    assert "copied out of its run folder without them; resume the original run folder" in error, error
    shutil.copytree(os.path.join(run_dir, "replay"), tmp_path / "copy" / "replay")
    path = tmp_path / "copy" / "replay" / sorted(os.listdir(tmp_path / "copy" / "replay"))[-1]
    raw = bytearray(path.read_bytes())
    raw[5] ^= 1
    path.write_bytes(bytes(raw))
    code, _, error = cli_in_process(capsys, "cascade_sac.py", "--resume", str(tmp_path / "copy"))
    assert code == 1 and "differ" in error and "\n" not in error, error
    # the run folder's own checkpoint.pt whose replay/ lost files: not told to resume what it just resumed
    for name in os.listdir(os.path.join(run_dir, "replay")):
        os.remove(os.path.join(run_dir, "replay", name))
    torch.save(checkpoint, os.path.join(run_dir, "checkpoint.pt"))
    code, _, error = cli_in_process(capsys, "cascade_sac.py", "--resume", run_dir)
    assert code == 1 and "files of replay/ were deleted or moved since the checkpoint was written" in error, error


def test_lost_replay_rows_name_the_iteration_file_that_needs_none(uninterrupted, tmp_path, monkeypatch, capsys):
    """A fault hunt: a checkpoint.pt whose replay rows were lost said to start a new run, though the end of the
    previous iteration (iteration_<i>.pt: a new iteration empties the buffer) needs no rows. The line names it and
    how; followed, the run ends as the uninterrupted one."""
    expected = uninterrupted("sac", False)[0]
    train_killed_at(monkeypatch, cs, 563, cs.Args(**TINY, buffer_size=250, track_dir=str(tmp_path / "runs")))
    close_killed_writers()
    run_dir = only_run_dir(tmp_path / "runs")
    shutil.rmtree(os.path.join(run_dir, "replay"))
    code, _, error = cli_in_process(capsys, "cascade_sac.py", "--resume", run_dir)
    latest, iteration = os.path.join(run_dir, "checkpoint.pt"), os.path.join(run_dir, "iteration_1.pt")
    assert code == 1 and error.endswith(f"; or continue from the end of iteration 1, which needs no rows: move "
                                        f"{latest} aside, then --resume {iteration}"), error
    os.rename(latest, tmp_path / "aside.pt")
    assert_identical(expected, final_state(resume(cs, iteration), "sac"))


def test_the_final_evaluation_is_logged_before_the_final_checkpoint(tmp_path, monkeypatch):
    """The final checkpoint is written after the last evaluation is logged and on disk: a run killed right after it
    has lost nothing (--resume then has nothing to do)."""
    seen = []
    original = record.save_checkpoint

    def save_and_look(path, payload):
        original(path, payload)
        seen.append((payload["global_step"], [s for s, _ in read_scalars(os.path.dirname(path))
                                              .get("eval/episodic_return", [])]))

    monkeypatch.setattr(record, "save_checkpoint", save_and_look)
    cs.train(cs.Args(**{**TINY, "k": 260, "checkpoint_every": 0}, track_dir=str(tmp_path)))
    # at the final checkpoint (step 520, not an eval step) the final policy's evaluation is in the event file
    assert seen[-1] == (520, [0, 100, 200, 300, 400, 500, 520])


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_sigkill_then_resume_on_the_command_line(algo, tmp_path):
    """As a user meets it: a real SIGKILL of a running run, `--resume` of its folder, the same final nets as a run
    never killed."""
    script = f"cascade_{algo}.py"
    flags = ["--env-id", "Pendulum-v1", "--n", "2", "--k", "600", "--learning-starts", "100", "--batch-size", "32",
             "--eval-every", "0", "--checkpoint-every", "50", "--quiet"]
    whole = subprocess.run([sys.executable, os.path.join(ROOT, script), *flags, "--track-dir", str(tmp_path / "a")],
                           capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert whole.returncode == 0, whole.stderr[-2000:]
    proc = subprocess.Popen([sys.executable, os.path.join(ROOT, script), *flags, "--track-dir", str(tmp_path / "b")],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=ROOT)
    # kill once the run is past its first few checkpoints and still running
    deadline = 600
    while deadline:
        found = list((tmp_path / "b").glob("*/checkpoint.pt"))
        if found and torch.load(found[0], weights_only=False)["global_step"] >= 400:
            break
        if proc.poll() is not None:
            pytest.fail(f"the run ended before it was killed: {proc.stderr.read()[-2000:]}")
        subprocess.run(["sleep", "0.2"])
        deadline -= 1
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    run_dir = only_run_dir(tmp_path / "b")
    assert not cs.finished(cs.Args(n=2, k=600), torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False))
    again = subprocess.run([sys.executable, os.path.join(ROOT, script), "--resume", run_dir],
                           capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert again.returncode == 0, again.stderr[-2000:]
    assert_same_saved_nets(algo, only_run_dir(tmp_path / "a"), run_dir)


@pytest.mark.parametrize("algo,signals,signum", [("sac", 1, signal.SIGTERM), ("sac", 2, signal.SIGTERM),
                                                 ("sac", 1, signal.SIGHUP)], ids=["sac", "sac-twice", "sac-sighup"])
def test_sigterm_then_resume_on_the_command_line(algo, signals, signum, tmp_path):
    """As a cluster's preemption or a sweep's stop meets a run: SIGTERM in the middle of an iteration, with no
    periodic checkpoint since its start (--checkpoint-every 0). The run writes one at the stop, says so in one line
    (exit 143), and `--resume` ends with the same nets as a run never stopped. Twice at once (a scheduler's SIGTERM
    to every process of the job, and a sweep passing on its own): the same. SIGHUP (the terminal or ssh session of a
    run started without nohup closed): the same, exit 129 (a fault hunt: it ended the run silently, losing the
    steps since its last checkpoint)."""
    script = f"cascade_{algo}.py"
    flags = ["--env-id", "Pendulum-v1", "--n", "2", "--k", "600", "--learning-starts", "100", "--batch-size", "32",
             "--eval-every", "0", "--checkpoint-every", "0", "--quiet"]
    whole = subprocess.run([sys.executable, os.path.join(ROOT, script), *flags, "--track-dir", str(tmp_path / "a")],
                           capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert whole.returncode == 0, whole.stderr[-2000:]
    proc = subprocess.Popen([sys.executable, os.path.join(ROOT, script), *flags, "--track-dir", str(tmp_path / "b")],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL))  # (not nohup's)
    deadline = time.time() + 600
    while not list((tmp_path / "b").glob("*/iteration_1.pt")):  # the end of iteration 1 (step 600)
        if proc.poll() is not None or time.time() > deadline:
            proc.kill()
            pytest.fail(f"the run ended before it was stopped: {proc.stderr.read()[-2000:]}")
        time.sleep(0.05)
    for _ in range(signals):  # the second one 10 ms later: as the same signal, one pending, the kernel merges them
        proc.send_signal(signum)
        time.sleep(0.01)
    err = proc.communicate(timeout=120)[1]
    assert proc.returncode == 128 + signum, err[-2000:]
    lines = [line.strip("\r") for line in err.splitlines() if line.strip()]
    name = signal.Signals(signum).name
    assert len(lines) == 1 and lines[0].startswith(f"stopped by {name}: a checkpoint was written at the stop"), err
    run_dir = only_run_dir(tmp_path / "b")
    step = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)["global_step"]
    # (600: the stop came while the checkpoint of iteration 1's end was written, after its iteration_1.pt: that one
    # is the checkpoint at the stop, as a loaded host showed)
    assert 600 <= step < 1200 and f"global_step={step}" in lines[0] and f"--resume {run_dir}" in lines[0]
    again = subprocess.run([sys.executable, os.path.join(ROOT, script), "--resume", run_dir],
                           capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert again.returncode == 0, again.stderr[-2000:]
    assert_same_saved_nets(algo, only_run_dir(tmp_path / "a"), run_dir)


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_a_resume_from_the_middle_of_an_iteration_writes_no_iteration_file_for_it(algo, tmp_path, monkeypatch,
                                                                                  capsys):
    """iteration_<i>.pt is the state at the end of iteration i (plots/analyze.py reads it as that). A run killed in
    the middle of iteration 2 and resumed must not "rebuild" iteration_2.pt from its mid-iteration checkpoint
    (before the fix, every off-policy resume did, naming a state of step 440 the end of iteration 2); a run killed
    right after an iteration's end, its iteration file lost, does get it back from the checkpoint."""
    mod = SCRIPTS[algo]
    args = mod.Args(**TINY, buffer_size=250, track_dir=str(tmp_path))
    train_killed_at(monkeypatch, mod, 450, args)
    run_dir = only_run_dir(tmp_path)
    first = open(os.path.join(run_dir, "iteration_1.pt"), "rb").read()
    checkpoint = mod.load_checkpoint(run_dir)
    assert (checkpoint["global_step"], checkpoint["iteration"], checkpoint["steps_done"]) == (440, 2, 140)
    # the resume is stopped again right after its first step
    train_killed_at(monkeypatch, mod, 441, mod.Args(**checkpoint["args"]), checkpoint)
    assert not os.path.exists(os.path.join(run_dir, "iteration_2.pt"))
    assert open(os.path.join(run_dir, "iteration_1.pt"), "rb").read() == first  # the end of iteration 1, untouched
    assert "rebuilt" not in capsys.readouterr().out

    # killed right after the end of iteration 1, and its iteration_1.pt lost: rebuilt from the checkpoint
    close_killed_writers()
    shutil.rmtree(run_dir)
    train_killed_at(monkeypatch, mod, 301, args)
    run_dir = only_run_dir(tmp_path)
    os.remove(os.path.join(run_dir, "iteration_1.pt"))
    checkpoint = mod.load_checkpoint(run_dir)
    assert (checkpoint["iteration"], checkpoint["steps_done"]) == (1, 300)
    train_killed_at(monkeypatch, mod, 301, mod.Args(**checkpoint["args"]), checkpoint)
    assert mod.load_checkpoint(os.path.join(run_dir, "iteration_1.pt"))["global_step"] == 300
    assert "rebuilt" in capsys.readouterr().out


def test_a_run_moved_to_another_folder_resumes_there(tmp_path, monkeypatch, capsys):
    """A killed run whose folder was moved (off a scratch disk that is gone now) resumes in its new place: the saved
    --track-dir is where the run was, not where it must be."""
    scratch = tmp_path / "scratch"
    train_killed_at(monkeypatch, cs, 150, cs.Args(**TINY, buffer_size=250, track_dir=str(scratch)))
    moved = tmp_path / "home" / os.path.basename(only_run_dir(scratch))
    os.makedirs(moved.parent)
    close_killed_writers()
    shutil.move(only_run_dir(scratch), moved)
    shutil.rmtree(scratch)
    scratch.write_text("the scratch disk is gone")  # nothing can be made under the old --track-dir
    code, _, message = cli_in_process(capsys, "cascade_sac.py", "--resume", moved)
    assert code == 0, message
    final = cs.load_checkpoint(str(moved))
    assert final["global_step"] == 600 and final["args"]["track_dir"] == str(moved.parent)
    assert os.listdir(tmp_path / "home") == [moved.name]


def test_a_resume_may_repeat_the_relative_track_dir_it_was_started_with(tmp_path, monkeypatch, capsys):
    """Audit of issue 48: a job script that re-runs its original command with --resume added (`--track-dir r1`,
    relative) was refused: "--track-dir r1 differs from the checkpoint's /abs/r1", the same folder."""
    monkeypatch.chdir(tmp_path)
    train_killed_at(monkeypatch, cd, 141, cd.Args(**TINY, buffer_size=250, track_dir="r1"))
    run_dir = os.path.relpath(only_run_dir("r1"))
    code, _, error = cli_in_process(capsys, "cascade_ddpg.py", "--resume", run_dir, "--track-dir", "r1")
    assert code == 0 and error == "", error
    assert cd.load_checkpoint(run_dir)["global_step"] == 600
    code, _, error = cli_in_process(capsys, "cascade_ddpg.py", "--resume", run_dir, "--track-dir", "r2")
    assert code == 1 and "--track-dir r2 differs from the checkpoint's" in error, error


@pytest.fixture
def small_disk(tmp_path):
    """A real 4 MB tmpfs (room for one checkpoint of a small SAC run, not two), where the machine lets us mount one;
    unmounted at the end, with whatever a test bind-mounted inside it."""
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(disk)], capture_output=True,
                             text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({mounted.stderr.strip() or 'mount failed'}); needs root")
    yield disk
    subprocess.run(["umount", "-R", str(disk)], capture_output=True)


def stopped_sac_run(track_dir, monkeypatch) -> str:
    """A small SAC run killed after its checkpoint at step 200 (in-process, as a SIGKILL would stop it)."""
    args = cs.Args(env_id="Pendulum-v1", n=2, k=1000, learning_starts=100, batch_size=32, eval_every=0,
                   checkpoint_every=200, quiet=True, track_dir=str(track_dir))
    train_killed_at(monkeypatch, cs, 250, args)
    close_killed_writers()
    run_dir = only_run_dir(track_dir)
    runs.unlock_run_dir(run_dir)  # (what a killed process's exit does)
    return run_dir


def error_line_of(*argv) -> str:
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "cascade_sac.py"), *map(str, argv)],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 1 and len(lines) == 1 and lines[0].startswith("error: "), proc.stderr[-2000:]
    return lines[0]


def test_a_full_disk_at_a_checkpoint_is_named_as_one(small_disk):
    """A new-user pass: a SAC checkpoint that did not fit said "cannot write ...checkpoint.pt.tmp (RuntimeError:
    [enforce fail at inline_container.cc:672] . unexpected pos ...); ... fix that": torch.save into a file loses
    the full disk's errno, and after the partial file was removed more than the 1 MB the fallback test wanted was
    free. The checkpoint is serialized first and written whole, so the disk's own error names it."""
    line = error_line_of("--env-id", "Pendulum-v1", "--n", "2", "--k", "1000", "--learning-starts", "300",
                         "--batch-size", "32", "--eval-every", "0", "--checkpoint-every", "200", "--quiet",
                         "--track-dir", small_disk)
    run_dir = only_run_dir(small_disk)
    assert line == (f"error: no space left on {run_dir}; the last checkpoint {run_dir}/checkpoint.pt is intact; free "
                    f"some space and continue with: python cascade_sac.py --resume {run_dir}"), line
    assert not [f for f in os.listdir(run_dir) if f.endswith(".tmp")]
    assert cs.load_checkpoint(run_dir)["global_step"] >= 200  # the last that fitted


@pytest.mark.parametrize("read_only", ["run folder", "replay"])
def test_a_read_only_run_folder_is_one_line_on_resume(read_only, small_disk, monkeypatch):
    """A new-user pass: a run folder made read-only (a results share, a quota), then --resume, ended in a traceback
    from run.lock; with only replay/ read-only, the run trained to its next checkpoint and ended in a traceback
    there. Now one line each, with advice that applies to a resume (the run folder, not --track-dir)."""
    subprocess.run(["mount", "-o", "remount,size=64m", str(small_disk)], check=True)
    run_dir = stopped_sac_run(small_disk, monkeypatch)
    target = small_disk if read_only == "run folder" else os.path.join(run_dir, "replay")
    if read_only == "replay":
        subprocess.run(["mount", "--bind", target, target], check=True)
    remounted = subprocess.run(["mount", "-o", "remount,bind,ro" if read_only == "replay" else "remount,ro",
                                str(target)], capture_output=True, text=True)
    if remounted.returncode != 0:
        pytest.skip(f"cannot remount read-only here ({remounted.stderr.strip()})")
    line = error_line_of("--resume", run_dir)
    if read_only == "run folder":
        assert line == (f"error: cannot write in the run folder {run_dir} (Read-only file system): a resumed run goes "
                        "on in its own folder; make it writable, or copy the run folder to a writable place and "
                        "resume the copy there"), line
    else:
        assert line == (f"error: cannot write {run_dir}/replay/rows_000000.f32 (Read-only file system); the last "
                        f"checkpoint {run_dir}/checkpoint.pt is intact; make it writable and continue with: python "
                        f"cascade_sac.py --resume {run_dir}"), line
    subprocess.run(["mount", "-o", "remount,rw" if read_only == "run folder" else "remount,bind,rw", str(target)],
                   check=True)
    assert cs.load_checkpoint(run_dir)["global_step"] == 200  # untouched, and the advice works once writable
    resumed = subprocess.run([sys.executable, os.path.join(ROOT, "cascade_sac.py"), "--resume", run_dir],
                             capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert resumed.returncode == 0, resumed.stderr[-2000:]


def test_evaluate_capture_video_of_a_read_only_run_folder_is_one_line(small_disk, monkeypatch):
    """A new-user pass: `--evaluate <a read-only results folder> --capture-video` ran its episode, then ended in a
    BrokenPipeError traceback from ffmpeg. The folder the video goes to is probed first, one line."""
    subprocess.run(["mount", "-o", "remount,size=64m", str(small_disk)], check=True)
    run_dir = stopped_sac_run(small_disk, monkeypatch)
    remounted = subprocess.run(["mount", "-o", "remount,ro", str(small_disk)], capture_output=True, text=True)
    if remounted.returncode != 0:
        pytest.skip(f"cannot remount read-only here ({remounted.stderr.strip()})")
    line = error_line_of("--evaluate", run_dir, "--capture-video")
    assert line == (f"error: --capture-video writes its video beside the checkpoint, and {run_dir} is not writable "
                    "(Read-only file system); copy the run folder somewhere writable and evaluate the copy, or leave "
                    "out --capture-video"), line


@pytest.mark.parametrize("where", ["around the vector env", "around make_env's env"])
def test_envs_wrapped_outside_run_state_are_one_line_before_training(where, tmp_path, monkeypatch):
    """A hunt of edited copies: a vector wrapper (gymnasium's vector NormalizeReward) crashed with a traceback at the
    first checkpoint, the steps before it lost; a wrapper around make_env's env kept its state out of the checkpoints,
    so a resumed run differed silently. Both are refused in one line before any step."""
    import gymnasium as gym

    original = cs.make_vector_env
    if where == "around the vector env":
        monkeypatch.setattr(cs, "make_vector_env", lambda fns: gym.wrappers.vector.NormalizeReward(original(fns)))
    else:
        monkeypatch.setattr(cs, "make_vector_env",
                            lambda fns: original([lambda fn=fn: gym.wrappers.NormalizeReward(fn()) for fn in fns]))
    with pytest.raises(SystemExit) as stop:
        cs.train(cs.Args(**TINY, track_dir=str(tmp_path)))
    assert "wrapped in NormalizeReward outside make_env's RunState" in str(stop.value), stop.value
    assert "\n" not in str(stop.value) and not os.listdir(tmp_path)
