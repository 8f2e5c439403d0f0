"""Long runs you can trust: atomic checkpoints, exact resume, saved-model evaluation, member returns, NaN guard."""

import errno
import hashlib
import importlib
import os
import shutil
import signal
import subprocess
import sys
import time

import gymnasium as gym
import numpy as np
import pytest
import torch

import cascade_plumbing.checkpoints as checkpoints
import cascade_ppo_continuous as cpc
from cascade_plumbing.envs import find_wrapper
from helpers import (
    ROOT,
    cli_in_process,
    copy_checkpoint_when,
    ctrl_c_reaches_child,
    error_line,
    error_line_in_process,
    read_scalars,
    resume_from,
    run_script,
)

BASE = dict(env_id="Hopper-v4", n=2, k=1024, num_steps=256, num_minibatches=4, update_epochs=2,
            eval_every=512, eval_episodes=2, quiet=True)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """One short real 2-net run with mid-iteration checkpoints."""
    track = tmp_path_factory.mktemp("runs")
    result = cpc.train(cpc.Args(track_dir=str(track), checkpoint_every=512, **BASE))
    return result


def digest(folder):
    return {name: hashlib.sha256(open(os.path.join(folder, name), "rb").read()).hexdigest()
            for name in sorted(os.listdir(folder))}


def test_checkpoints_are_written_at_iteration_ends(finished_run):
    files = os.listdir(finished_run["run_dir"])
    assert {"checkpoint.pt", "iteration_1.pt", "iteration_2.pt"} <= set(files)
    first = cpc.load_checkpoint(os.path.join(finished_run["run_dir"], "iteration_1.pt"))
    assert (first["iteration"], first["updates_done"], first["global_step"], first["actor_size"]) == (1, 4, 1024, 1)
    last = cpc.load_checkpoint(finished_run["run_dir"])
    assert last["global_step"] == 2048 and last["actor_size"] == 2
    assert set(last["optimizer"]["state"])  # optimizer moments are saved
    assert last["obs_stats"] is not None and last["env_states"][0]["sim"] is not None


def test_crash_mid_write_leaves_previous_checkpoint_loadable(tmp_path, monkeypatch):
    path = str(tmp_path / "checkpoint.pt")
    checkpoints.save_checkpoint(path, {"format": "cascade_ppo_continuous/2", "global_step": 1, "args": {}})

    def crash(obj, f):  # the process dies half way through writing the new file
        f.write(b"\x80\x02partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", crash)
    with pytest.raises(KeyboardInterrupt):
        checkpoints.save_checkpoint(path, {"format": "cascade_ppo_continuous/2", "global_step": 2, "args": {}})
    monkeypatch.undo()
    assert cpc.load_checkpoint(path)["global_step"] == 1


@pytest.mark.parametrize("module_name", ["cascade_plumbing.checkpoints"])  # every script's atomic_copy
def test_iteration_copy_is_atomic(module_name, tmp_path, monkeypatch):
    """A crash while iteration_<i>.pt is being written leaves no truncated iteration_<i>.pt behind."""
    import importlib

    module = importlib.import_module(module_name)
    (tmp_path / "checkpoint.pt").write_bytes(b"x" * 10_000)

    def crash(src, dst, *args, **kwargs):  # the process dies a hundred bytes into the copy
        dst.write(src.read(100))
        raise KeyboardInterrupt

    monkeypatch.setattr(module.shutil, "copyfileobj", crash)
    with pytest.raises(KeyboardInterrupt):
        module.atomic_copy(str(tmp_path / "checkpoint.pt"), str(tmp_path / "iteration_1.pt"))
    assert not (tmp_path / "iteration_1.pt").exists()
    monkeypatch.undo()
    module.atomic_copy(str(tmp_path / "checkpoint.pt"), str(tmp_path / "iteration_1.pt"))
    assert (tmp_path / "iteration_1.pt").read_bytes() == b"x" * 10_000


def test_resume_at_iteration_boundary_gives_identical_parameters(finished_run, tmp_path):
    resumed = resume_from(cpc, os.path.join(finished_run["run_dir"], "iteration_1.pt"), tmp_path / "resumed")
    original, again = finished_run["actor"].state_dict(), resumed["actor"].state_dict()
    assert original.keys() == again.keys()
    for key in original:
        torch.testing.assert_close(again[key], original[key], rtol=0, atol=0)
    for a, b in zip(finished_run["critic"].parameters(), resumed["critic"].parameters()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    # the resumed run logged the second iteration into its own (copied) run folder
    scalars = read_scalars(resumed["run_dir"])
    assert [s for s, _ in scalars["eval/episodic_return"]] == [1536, 2048]


def test_a_run_resumed_in_its_folder_logs_every_step_and_keeps_its_clock(finished_run, tmp_path):
    """A run killed after its iteration-1 checkpoint (it had logged up to step 2048), resumed in its own folder:
    TensorBoard shows what the killed run logged up to the checkpoint's step and the resumed run's logs after
    it, the steps of an uninterrupted run. (The new net's cascade/size and cascade/parameters, logged at the
    checkpoint's step just after it was saved, appear twice there, with the same value.) The clock goes on from
    the checkpoint's elapsed time."""
    killed = tmp_path / os.path.basename(finished_run["run_dir"])
    shutil.copytree(finished_run["run_dir"], killed)
    os.remove(killed / "iteration_2.pt")
    checkpoint = torch.load(killed / "iteration_1.pt", weights_only=False)
    assert checkpoint["global_step"] == 1024
    checkpoint["elapsed"] = 1000.0  # as if the first iteration had taken 1000 s
    torch.save(checkpoint, killed / "checkpoint.pt")
    checkpoint = cpc.load_checkpoint(str(killed))
    cpc.train(cpc.Args(**checkpoint["args"]), checkpoint)
    uninterrupted, resumed = read_scalars(finished_run["run_dir"]), read_scalars(str(killed))
    assert uninterrupted.keys() == resumed.keys()
    for tag, entries in uninterrupted.items():
        assert sorted({step for step, _ in resumed[tag]}) == sorted({step for step, _ in entries}), tag
    for step, value in resumed["eval/episodic_return"]:  # the resume is exact: the same evaluations
        assert value == pytest.approx(dict(uninterrupted["eval/episodic_return"])[step], rel=1e-6)
    assert cpc.load_checkpoint(str(killed))["elapsed"] > 1000.0
    assert all(sps < 2048 / 1000 for step, sps in resumed["charts/SPS"] if step > 1024)


def test_resume_mid_iteration_gives_identical_parameters(tmp_path):
    # keep a copy of the checkpoint written after update 2 of 4 of iteration 2, resume from it
    args = cpc.Args(track_dir=str(tmp_path / "a"), checkpoint_every=256, **BASE)
    with copy_checkpoint_when(cpc, lambda c: (c["iteration"], c["updates_done"]) == (2, 2), tmp_path / "mid.pt"):
        full = cpc.train(args)
    assert cpc.load_checkpoint(str(tmp_path / "mid.pt"))["global_step"] == 1536
    resumed = resume_from(cpc, tmp_path / "mid.pt", tmp_path / "b")
    for a, b in zip(full["actor"].parameters(), resumed["actor"].parameters()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    # the iteration's start was logged before the checkpoint: the resume logs no second point of it at step 1536
    scalars = read_scalars(resumed["run_dir"])
    assert "cascade/parameters" not in scalars, scalars["cascade/parameters"]
    assert 1536 not in [step for step, _ in scalars["cascade/size"]]


@pytest.mark.parametrize("script", ["cascade_ppo_continuous", "cascade_ppo_discrete"])
def test_freeze_previous_survives_a_resume(script, tmp_path):
    """--freeze-previous: the actor a checkpoint restores keeps the older nets frozen, and a resume mid-iteration
    does not train them: both checkpoints of a 2-net run hold the frozen count of their iteration, and a run resumed
    half way through net 2 ends bit-identical to the uninterrupted one, net 1 as it was at the end of iteration 1."""
    module = importlib.import_module(script)
    env = dict(env_id="Hopper-v4", num_steps=256) if module is cpc else dict(env_id="CartPole-v1", num_envs=1,
                                                                               num_steps=256)
    args = module.Args(n=2, k=512, num_minibatches=4, update_epochs=1, freeze_previous=True, eval_every=0,
                       checkpoint_every=256, quiet=True, track_dir=str(tmp_path / "a"), **env)
    with copy_checkpoint_when(module, lambda c: c["global_step"] == 768, tmp_path / "mid.pt"):
        full = module.train(args)
    run_dir = full["run_dir"]
    for iteration, frozen in [(1, 0), (2, 1)]:
        checkpoint = module.load_checkpoint(os.path.join(run_dir, f"iteration_{iteration}.pt"))
        assert checkpoint["num_frozen"] == frozen
        assert module.actor_from_checkpoint(checkpoint).num_frozen == frozen
    assert module.load_checkpoint(str(tmp_path / "mid.pt"))["iteration"] == 2
    resumed = resume_from(module, tmp_path / "mid.pt", tmp_path / "b")["actor"]
    for a, b in zip(full["actor"].parameters(), resumed.parameters()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    first = module.load_checkpoint(os.path.join(run_dir, "iteration_1.pt"))["actor"]
    for name, param, first_net in resumed.base_net_parameters():
        if first_net == 0:  # net 1's row of every stacked parameter
            assert torch.equal(param.detach()[0], first[name][0]), name


def test_saved_model_acts_like_the_live_policy(finished_run):
    checkpoint = cpc.load_checkpoint(finished_run["run_dir"])
    saved_actor = cpc.actor_from_checkpoint(checkpoint)
    raw = np.random.default_rng(3).normal(size=(5, 11)) * 3  # raw Hopper observations
    # live: the training wrapper's own normalization with the live statistics, then the live actor
    env = cpc.make_env("Hopper-v4", 0.99, True)()
    norm = find_wrapper(env, gym.wrappers.NormalizeObservation)
    norm.obs_rms.mean, norm.obs_rms.var = finished_run["obs_stats"]
    norm.update_running_mean = False
    live_obs = np.clip(np.stack([norm.observation(o) for o in raw]), -10, 10).astype(np.float32)
    with torch.no_grad():
        live = finished_run["actor"](torch.as_tensor(live_obs))
        saved = saved_actor(torch.as_tensor(cpc.normalize_obs(raw, checkpoint["obs_stats"])))
    for a, b in zip(live, saved):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_member_evaluation_is_the_net_alone(finished_run):
    actor = cpc.actor_from_checkpoint(cpc.load_checkpoint(finished_run["run_dir"]))
    stats = finished_run["obs_stats"]
    with torch.no_grad():  # make the top net defer fully: the stack then acts exactly as net 1 alone
        actor.fallback_bias[:] = 100.0
        actor.fallback_weight[:] = 0.0
    full, _ = cpc.Evaluator("Hopper-v4", 3, seed=5)(cpc.full_policy(actor), stats)
    alone, fallback_std = cpc.Evaluator("Hopper-v4", 3, seed=5)(cpc.member_policy(actor, 0), stats)
    other, _ = cpc.Evaluator("Hopper-v4", 3, seed=5)(cpc.member_policy(actor, 1), stats)
    np.testing.assert_allclose(full, alone, rtol=1e-6)
    assert fallback_std.shape == (3, 0)
    assert not np.allclose(alone, other)
    tags = read_scalars(finished_run["run_dir"])
    assert {"members/return/net_1", "members/return/net_2"} <= set(tags)
    assert [s for s, _ in tags["members/return/net_1"]] == [1024, 2048]
    assert [s for s, _ in tags["members/return/net_2"]] == [2048]


def test_evaluate_cli_with_members(finished_run, capsys):
    code, out, error = cli_in_process(capsys, "cascade_ppo_continuous.py", "--evaluate", finished_run["run_dir"],
                                      "--eval-episodes", "2", "--members", "--deterministic")
    assert code == 0, error
    assert "over 2 deterministic episodes" in out
    assert "net 1 alone" in out and "net 2 alone" in out


def test_nan_guard_stops_and_keeps_last_good_checkpoint(tmp_path):
    def poison(state):
        if state["iteration"] == 2:
            with torch.no_grad():
                state["critic"].weights[0][0, 0] = float("nan")

    args = cpc.Args(track_dir=str(tmp_path), checkpoint_every=0, **BASE)
    with pytest.raises(SystemExit) as stop:
        cpc.train(args, on_iteration_start=poison)
    message = str(stop.value)
    assert "non-finite" in message and "iteration 2" in message and "global_step=1280" in message
    run_dir = os.path.join(tmp_path, os.listdir(tmp_path)[0])
    checkpoint = cpc.load_checkpoint(run_dir)
    assert checkpoint["global_step"] == 1024
    assert all(torch.isfinite(v).all() for v in checkpoint["critic"].values())


def test_resume_bad_input(finished_run, tmp_path):
    run_dir = finished_run["run_dir"]
    before = digest(run_dir)
    cases = [
        (["--resume", str(tmp_path / "nope")], "no checkpoint at"),
        (["--resume", run_dir, "--env-id", "Walker2d-v4"], "--env-id Walker2d-v4 differs"),
        (["--resume", run_dir, "--n", "3"], "--n 3 differs"),
        (["--evaluate", str(tmp_path / "nope.pt")], "no checkpoint at"),
    ]
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a checkpoint at all")
    cases.append((["--resume", str(corrupt)], "cannot read checkpoint"))
    # the folder above a run folder (a sweep's run_id folder, the --track-dir): the run folder below is named (a
    # fault hunt: only 'no checkpoint at')
    above = os.path.dirname(run_dir)
    cases += [(["--resume", above], f"; the run folder {run_dir} below it has one: pass that"),
              (["--evaluate", above], f"; the run folder {run_dir} below it has one: pass that")]
    # ... but a mistyped run folder (another seed's name) is not "above" its siblings: none is named (a fault hunt:
    # the run beside it was offered as "below it")
    typo = run_dir.replace("__1__", "__2__")
    assert typo != run_dir
    cases += [([flag, typo], f"no checkpoint at {typo}: no such folder; pass a run folder holding checkpoint.pt or "
                             "a checkpoint file") for flag in ("--resume", "--evaluate")]
    for i, (extra, message) in enumerate(cases):
        if i == 0:  # one case through a real interpreter: stderr and the exit code
            line = error_line(run_script("cascade_ppo_continuous.py", *extra))
        else:
            line = error_line_in_process("cascade_ppo_continuous.py", *extra)
        assert message in line, extra
        assert extra[1] != typo or line.endswith(message), line
    assert digest(run_dir) == before


def test_progress_lines_when_not_a_terminal(tmp_path, capsys):
    common = ["--env-id", "Hopper-v4", "--n", "1", "--k", "512", "--num-steps", "256", "--num-minibatches", "4",
              "--update-epochs", "1", "--eval-every", "0", "--track-dir", tmp_path]
    # captured stdout is not a terminal, as in a pipe or a log file
    loud_code, loud, _ = cli_in_process(capsys, "cascade_ppo_continuous.py", *common)
    quiet_code, quiet, _ = cli_in_process(capsys, "cascade_ppo_continuous.py", *common, "--quiet")
    assert loud_code == quiet_code == 0
    assert "SPS" in loud and "ETA" in loud and "\r" not in loud
    assert "ETA" not in quiet


def test_capture_video_writes_an_mp4_or_says_why(finished_run, tmp_path):
    run_copy = tmp_path / "run"
    shutil.copytree(finished_run["run_dir"], run_copy)
    proc = run_script("cascade_ppo_continuous.py", "--evaluate", run_copy, "--eval-episodes", "1",
                      "--capture-video", env={"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    if proc.returncode != 0:  # no GL backend on this machine: the one-line explanation is the contract
        line = error_line(proc)
        assert "cannot render" in line and "MUJOCO_GL" in line
        pytest.skip(f"no OpenGL backend here: {line}")
    video = run_copy / "checkpoint_stochastic.mp4"
    assert video.exists() and video.stat().st_size > 1000
    assert open(video, "rb").read(12)[4:8] == b"ftyp"  # an mp4 container


TINY_VIDEO_RUNS = {  # InvertedPendulum-v4 renders with MuJoCo's GL backends (the classic-control envs need pygame)
    "cascade_sac": dict(n=1, k=300, learning_starts=100, batch_size=32),
    "cascade_ddpg": dict(n=1, k=300, learning_starts=100, batch_size=32),
    "cascade_ppo_discrete": dict(n=1, k=512, num_envs=2, num_steps=128, num_minibatches=2, update_epochs=1),
}


@pytest.mark.parametrize("script", list(TINY_VIDEO_RUNS))
def test_evaluate_capture_video_writes_an_mp4_for_every_cascade_script(script, tmp_path):
    """--evaluate --capture-video wrote an mp4 in the flagship only; the discrete, SAC and DDPG scripts ran the
    episodes and silently wrote none."""
    module = importlib.import_module(script)
    result = module.train(module.Args(env_id="InvertedPendulum-v4", eval_every=0, quiet=True,
                                      track_dir=str(tmp_path), **TINY_VIDEO_RUNS[script]))
    proc = run_script(f"{script}.py", "--evaluate", result["run_dir"], "--eval-episodes", "1", "--capture-video",
                      env={"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    if proc.returncode != 0:
        line = error_line(proc)
        assert "cannot render" in line and "MUJOCO_GL" in line
        pytest.skip(f"no OpenGL backend here: {line}")
    (video,) = [name for name in os.listdir(result["run_dir"]) if name.endswith(".mp4")]
    assert proc.stdout.splitlines()[-1].endswith(os.path.join(result["run_dir"], video)), proc.stdout
    data = open(os.path.join(result["run_dir"], video), "rb").read()
    assert len(data) > 1000 and data[4:8] == b"ftyp"  # an mp4 container


@pytest.fixture
def frames_without_opengl(monkeypatch):
    """MuJoCo's renderer replaced by one that needs no OpenGL (the video tests above skip where no GL backend
    works, as on this project's CPU machines): each frame is painted with the simulation's time step, so what is
    recorded, when and where is checked, not how MuJoCo draws it. Rendering still only reads the simulation."""
    from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

    def render(self):
        return np.full((48, 64, 3), round(self.data.time / self.dt) % 256, dtype=np.uint8)

    monkeypatch.setattr(MujocoEnv, "render", render)


VIDEO_SCRIPTS = {"cascade_ppo_continuous": dict(n=1, k=1024, num_steps=256, num_minibatches=4, update_epochs=1,
                                                eval_in_worker=False), **TINY_VIDEO_RUNS}


@pytest.mark.parametrize("script", list(VIDEO_SCRIPTS))
def test_videos_are_recorded_as_cleanrl_without_opengl(script, frames_without_opengl, tmp_path, monkeypatch, capsys):
    """--capture-video in training: CleanRL's episodes 0, 1, 8, ... of the first env become
    videos/<run_name>/rl-video-episode-<i>.mp4, each one frame per step of its episode (its reset's and every
    step's), and the nets are those of a run without videos; --evaluate --capture-video writes one more episode
    beside the checkpoint."""
    import imageio.v2 as imageio

    module = importlib.import_module(script)
    monkeypatch.chdir(tmp_path)  # videos/ is made in the working directory, as CleanRL's
    settings = dict(env_id="InvertedPendulum-v4", eval_every=0, quiet=True, **VIDEO_SCRIPTS[script])
    run_dir = module.train(module.Args(capture_video=True, track_dir=str(tmp_path / "runs"), **settings))["run_dir"]
    folder = tmp_path / "videos" / os.path.basename(run_dir)
    videos = sorted(os.listdir(folder), key=lambda name: int(name.split("-")[-1][:-4]))
    assert videos[:3] == [f"rl-video-episode-{i}.mp4" for i in (0, 1, 8)], videos
    lengths = [int(length) for _, length in read_scalars(run_dir)["charts/episodic_length"]]
    if script != "cascade_ppo_discrete":  # (its four envs' episodes interleave in the log)
        for video in videos[:2]:
            episode = int(video.split("-")[-1][:-4])
            with imageio.get_reader(folder / video) as reader:
                frames = np.array([frame.mean() for frame in reader])
            assert len(frames) == lengths[episode] + 1 < 250, video
            # the reset's frame, then each step's (mp4 compresses lossily: a grey level may come back off by one)
            assert np.abs(frames - np.arange(len(frames))).max() < 2, (video, frames)
    plain = module.train(module.Args(track_dir=str(tmp_path / "plain"), **settings))
    saved, again = module.load_checkpoint(run_dir), module.load_checkpoint(plain["run_dir"])
    for name, value in saved["actor"].items():
        assert torch.equal(value, again["actor"][name]), name
    code, out, error = cli_in_process(capsys, f"{script}.py", "--evaluate", run_dir, "--eval-episodes", "1",
                                      "--capture-video")
    assert code == 0, error
    (video,) = [name for name in os.listdir(run_dir) if name.endswith(".mp4")]
    assert out.splitlines()[-1].endswith(os.path.join(run_dir, video)), out
    with imageio.get_reader(os.path.join(run_dir, video)) as reader:
        assert len([frame for frame in reader]) > 1


def test_baseline_checkpoint_resume_and_evaluate(tmp_path, capsys):
    import ppo_baseline as pb

    base = dict(env_id="Hopper-v4", total_timesteps=2048, num_steps=256, num_minibatches=4, update_epochs=2,
                eval_every=512, eval_episodes=2, quiet=True)
    with copy_checkpoint_when(pb, lambda c: c["updates_done"] == 4, tmp_path / "mid.pt"):
        full = pb.train(pb.Args(track_dir=str(tmp_path / "a"), checkpoint_every=512, **base))
    assert pb.load_checkpoint(str(tmp_path / "mid.pt"))["global_step"] == 1024
    resumed = resume_from(pb, tmp_path / "mid.pt", tmp_path / "b")
    for a, b in zip(full["actor"].parameters(), resumed["actor"].parameters()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    code, out, error = cli_in_process(capsys, "ppo_baseline.py", "--evaluate", full["run_dir"], "--eval-episodes", "2")
    assert code == 0 and "over 2 stochastic episodes" in out, error
    for extra, message in [(["--resume", full["run_dir"], "--hidden-size", "16"], "--hidden-size 16 differs"),
                           (["--evaluate", str(tmp_path / "missing")], "no checkpoint at")]:
        assert message in error_line_in_process("ppo_baseline.py", *extra), extra


@pytest.fixture
def small_disk(tmp_path):
    """A real 2.6 MB tmpfs (room for about two checkpoints of a tiny run), where the machine lets us mount one."""
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2600k", "tmpfs", str(disk)], capture_output=True,
                             text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({mounted.stderr.strip() or 'mount failed'}); needs root")
    yield disk
    subprocess.run(["umount", str(disk)], capture_output=True)


def test_full_disk_is_one_line_and_keeps_the_last_checkpoint(small_disk):
    proc = run_script("cascade_ppo_continuous.py", "--env-id", "Hopper-v4", "--n", "2", "--k", "1024", "--num-steps",
                      "256", "--num-minibatches", "4", "--update-epochs", "1", "--eval-every", "0",
                      "--checkpoint-every", "256", "--quiet", "--track-dir", small_disk)
    line = error_line(proc)
    assert line.startswith("error: no space left on") and "--resume" in line, line
    (run_dir,) = [small_disk / d for d in os.listdir(small_disk)]
    assert not [f for f in os.listdir(run_dir) if f.endswith(".tmp")]  # the partial file is gone
    assert cpc.load_checkpoint(str(run_dir))["global_step"] >= 256  # the last complete checkpoint loads


@pytest.mark.parametrize("poisoned_iteration,expected", [(1, "no checkpoint was written yet"),
                                                         (2, "resuming it repeats the same updates exactly")])
def test_nan_guard_says_what_it_kept_and_what_to_change(poisoned_iteration, expected, tmp_path):
    def poison(state):
        if state["iteration"] == poisoned_iteration:
            with torch.no_grad():
                state["critic"].weights[0][0, 0] = float("nan")

    with pytest.raises(SystemExit) as stop:
        cpc.train(cpc.Args(track_dir=str(tmp_path), checkpoint_every=0, **BASE), on_iteration_start=poison)
    message = str(stop.value)
    assert expected in message and "lower --learning-rate" in message and "\n" not in message, message


@pytest.mark.parametrize("script,extra,signum", [
    ("cascade_ppo_continuous.py", ["--n", "2", "--k", "65536", "--num-envs", "2"], signal.SIGINT),
    ("cascade_ppo_continuous.py", ["--n", "2", "--k", "65536", "--num-envs", "2"], signal.SIGTERM),
    ("ppo_baseline.py", ["--total-timesteps", "131072"], signal.SIGTERM),
    ("cascade_ppo_discrete.py", ["--n", "2", "--k", "65536"], signal.SIGINT),
    ("cascade_sac.py", ["--n", "2", "--k", "1000", "--learning-starts", "500", "--batch-size", "64"], signal.SIGTERM),
], ids=["cascade-int", "cascade-term", "ppo-term", "discrete-int", "sac-term"])
def test_stopping_a_run_is_one_line(script, extra, signum, tmp_path):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) or SIGTERM: one line on where the
    last checkpoint is and how to resume, exit 130 / 143, no traceback from any process."""
    env_id = "CartPole-v1" if "discrete" in script else "Pendulum-v1" if "sac" in script else "Hopper-v4"
    flags = ["--env-id", env_id, *extra, "--eval-every", "1000", "--eval-episodes", "2", "--track-dir", str(tmp_path)]
    if "sac" not in script:
        flags += ["--checkpoint-every", "2048", "--num-minibatches", "4", "--update-epochs", "2"]  # (a quick update)
    proc = subprocess.Popen([sys.executable, os.path.join(ROOT, script), *flags], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=ROOT, start_new_session=True, preexec_fn=ctrl_c_reaches_child)
    deadline = time.time() + 120
    while time.time() < deadline and not any(
            os.path.exists(os.path.join(tmp_path, d, "checkpoint.pt")) for d in os.listdir(tmp_path)):
        time.sleep(0.2)
    time.sleep(0.5)
    os.killpg(proc.pid, signum) if signum == signal.SIGINT else proc.send_signal(signum)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signum, err[-3000:]
    lines = [line.strip("\r") for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"stopped by {signal.Signals(signum).name}"), err[-3000:]
    assert "--resume" in lines[0] and "Traceback" not in out + err


def test_a_stop_ends_the_env_workers_quietly_even_mid_step():
    """A stop can interrupt the rollout while --num-envs workers are stepping (found when the test above stopped a
    run during its rollout: the graceful close at exit then failed on a half-read pipe, with ~80 lines of
    tracebacks from the workers). The stop path ends the workers first: nothing is printed, none is left."""
    code = """if True:
        import warnings
        import numpy as np
        from cascade_plumbing.envs import end_env_workers, make_env, make_vector_env
        warnings.filterwarnings("ignore", message=".*is out of date.*")  # (Hopper-v4, as the scripts do)
        envs = make_vector_env([make_env("Hopper-v4", i) for i in range(2)])
        envs.reset(seed=0)
        envs.step_async(np.zeros((2, 3)))  # a step in flight, as when a stop falls in the rollout
        end_env_workers()
        print(sum(process.is_alive() for process in envs.processes), envs.closed)
    """
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr[-3000:]
    assert proc.stdout.split() == ["0", "True"]


def test_resume_rebuilds_an_iteration_file_a_kill_left_truncated(finished_run, tmp_path):
    """A kill during the (old, non-atomic) copy left iteration_<i>.pt truncated or missing; resuming rebuilds the
    one the checkpoint holds the state of and names the one it cannot rebuild."""
    run_copy = tmp_path / "run"
    shutil.copytree(finished_run["run_dir"], run_copy)
    for name in ("iteration_1.pt", "iteration_2.pt"):
        data = (run_copy / name).read_bytes()
        (run_copy / name).write_bytes(data[:100])  # truncated mid-copy
    (run_copy / "iteration_2.pt.tmp").write_bytes(b"partial")
    proc = run_script("cascade_ppo_continuous.py", "--resume", run_copy)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (run_copy / "iteration_2.pt").read_bytes() == (run_copy / "checkpoint.pt").read_bytes()
    assert cpc.load_checkpoint(str(run_copy / "iteration_2.pt"))["iteration"] == 2
    assert not (run_copy / "iteration_2.pt.tmp").exists()
    assert "iteration_1.pt is missing or damaged and cannot be rebuilt" in proc.stderr, proc.stderr


def test_kill_9_during_the_iteration_copy_then_resume(tmp_path):
    """A real SIGKILL in the middle of writing iteration_1.pt (the process kills itself half way through the
    copy), then `--resume` as a user would: the iteration file is complete afterwards, no temp file is left."""
    driver = tmp_path / "driver.py"
    driver.write_text(f"""
import os, shutil, signal, sys
sys.path.insert(0, {ROOT!r})
import cascade_ppo_continuous as cpc
real = shutil.copyfileobj
def copy_then_die(src, dst, *args, **kwargs):
    dst.write(src.read(1000))
    dst.flush()
    os.kill(os.getpid(), signal.SIGKILL)
import cascade_plumbing.checkpoints
cascade_plumbing.checkpoints.shutil.copyfileobj = copy_then_die
sys.argv = ["cascade_ppo_continuous.py", *sys.argv[1:]]
cpc.main()
""")
    flags = ["--env-id", "Hopper-v4", "--n", "2", "--k", "1024", "--num-steps", "256", "--num-minibatches", "4",
             "--update-epochs", "1", "--eval-every", "0", "--checkpoint-every", "0", "--quiet",
             "--track-dir", str(tmp_path / "runs")]
    killed = subprocess.run([sys.executable, str(driver), *flags], capture_output=True, text=True, timeout=300)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    (run_dir,) = [tmp_path / "runs" / d for d in os.listdir(tmp_path / "runs")]
    assert not (run_dir / "iteration_1.pt").exists() and (run_dir / "iteration_1.pt.tmp").exists()
    resumed = run_script("cascade_ppo_continuous.py", "--resume", run_dir)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert cpc.load_checkpoint(str(run_dir / "iteration_1.pt"))["iteration"] == 1
    assert cpc.load_checkpoint(str(run_dir))["global_step"] == 2048
    assert not [f for f in os.listdir(run_dir) if f.endswith(".tmp")]


def test_a_restored_optimizer_keeps_each_groups_initial_learning_rate():
    """The LR schedules scale each group's "initial_lr": a checkpoint's optimizer state carries it; one saved without
    it (an older checkpoint, or one saved before the first update) takes it from the freshly made optimizer, not
    from the saved, already annealed rate."""
    from cascade_plumbing.checkpoints import load_optimizer

    def fresh():
        a, b = torch.nn.Parameter(torch.zeros(2)), torch.nn.Parameter(torch.zeros(3))
        return torch.optim.Adam([{"params": [a], "lr": 1e-3}, {"params": [b]}], lr=3e-4)

    saved = fresh()
    for group, rate in zip(saved.param_groups, (5e-4, 1.5e-4)):  # half way through a linear schedule
        group["lr"] = rate
    restored = fresh()
    load_optimizer(restored, saved.state_dict())
    assert [(g["lr"], g["initial_lr"]) for g in restored.param_groups] == [(5e-4, 1e-3), (1.5e-4, 3e-4)]
    for group in saved.param_groups:
        group["initial_lr"] = 2 * group["lr"]
    restored = fresh()
    load_optimizer(restored, saved.state_dict())
    assert [(g["lr"], g["initial_lr"]) for g in restored.param_groups] == [(5e-4, 1e-3), (1.5e-4, 3e-4)]
    for group in restored.param_groups:
        group["initial_lr"] = 7e-4  # the saved value wins over the fresh one
    load_optimizer(restored, saved.state_dict())
    assert [g["initial_lr"] for g in restored.param_groups] == [1e-3, 3e-4]


def test_a_corrupt_checkpoint_names_the_newest_intact_iteration_file(finished_run, tmp_path, capsys):
    """Issue 49.4: a corrupt checkpoint.pt was refused, but the intact iteration_<i>.pt beside it was not named;
    now the line names the newest intact one and the command that continues the run from it, which works."""
    run_dir = tmp_path / "run"
    shutil.copytree(finished_run["run_dir"], run_dir)
    (run_dir / "checkpoint.pt").write_bytes(b"\0" * 1000)  # a disk error, a damaged copy
    with open(run_dir / "iteration_2.pt", "r+b") as f:  # the newest iteration file damaged too (the same length)
        f.seek(os.path.getsize(run_dir / "iteration_2.pt") // 2)
        f.write(b"\xff" * 64)
    line = error_line(run_script("cascade_ppo_continuous.py", "--resume", run_dir))
    intact = run_dir / "iteration_1.pt"
    assert line.startswith(f"error: cannot read checkpoint {run_dir / 'checkpoint.pt'}"), line
    assert line.endswith(f"is {intact} (the end of iteration 1): continue the run from there with: "
                         f"python cascade_ppo_continuous.py --resume {intact}"), line
    # --evaluate continues no run: its advice is its own flag (review: it advised --resume)
    line = error_line_in_process("cascade_ppo_continuous.py", "--evaluate", str(run_dir))
    assert line.endswith(f"is {intact} (the end of iteration 1): pass that with --evaluate"), line
    code, out, message = cli_in_process(capsys, "cascade_ppo_continuous.py", "--resume", str(intact))
    assert code == 0 and message == "", message
    assert cpc.load_checkpoint(str(run_dir))["global_step"] == finished_run["global_step"]  # the run is whole again
    # a checkpoint.pt that is gone (deleted, not copied back) names the iteration file to continue from as well
    os.remove(run_dir / "checkpoint.pt")
    line = error_line_in_process("cascade_ppo_continuous.py", "--resume", str(run_dir))
    assert line.startswith(f"error: no checkpoint at {run_dir / 'checkpoint.pt'}") and line.endswith(
        f"is {run_dir / 'iteration_2.pt'} (the end of iteration 2): continue the run from there with: "
        f"python cascade_ppo_continuous.py --resume {run_dir / 'iteration_2.pt'}"), line
    (run_dir / "checkpoint.pt").write_bytes(b"\0" * 1000)
    for name in os.listdir(run_dir):
        if name.startswith("iteration_"):
            os.remove(run_dir / name)
    assert "no intact iteration_<i>.pt is beside it" in error_line_in_process("cascade_ppo_continuous.py", "--resume",
                                                                             str(run_dir))


def test_resuming_an_earlier_file_of_a_run_does_not_overwrite_its_later_work(finished_run, tmp_path, capsys):
    """Audit: `--resume <run>/iteration_1.pt` of a finished run retrained iteration 2 in the same folder, overwrote
    its checkpoint.pt and iteration_2.pt and logged the same steps twice, exit 0. Refused while the folder's
    checkpoint.pt is readable and further on; with it moved away (the user's choice), the run is redone from there."""
    run_dir = tmp_path / "run"
    shutil.copytree(finished_run["run_dir"], run_dir)
    before = digest(run_dir)
    earlier = run_dir / "iteration_1.pt"
    line = error_line_in_process("cascade_ppo_continuous.py", "--resume", str(earlier))
    assert line == (f"error: --resume {earlier}: the run went on to global_step={finished_run['global_step']:,} "
                    f"({run_dir / 'checkpoint.pt'}); continuing from global_step={torch.load(earlier, weights_only=False)['global_step']:,} "
                    f"would overwrite that work in the same folder. Resume {run_dir / 'checkpoint.pt'} instead, or "
                    "move it away first to redo the run from here"), line
    assert digest(run_dir) == before  # nothing written
    # the end of the run itself is no earlier file: it says there is nothing to resume, as checkpoint.pt does
    last = run_dir / "iteration_2.pt"
    code, out, message = cli_in_process(capsys, "cascade_ppo_continuous.py", "--resume", str(last))
    assert code == 0 and "is the end of the run" in out, (out, message)
    # another run's checkpoint kept in the folder (a fault hunt: loose files of two seeds in one folder, resumed one
    # after the other, each overwrote the other's checkpoint.pt and iteration files): refused whatever its step
    other = torch.load(run_dir / "checkpoint.pt", weights_only=False)
    other["args"]["seed"] += 1
    other["global_step"] = 0
    torch.save(other, run_dir / "checkpoint.pt")
    before = digest(run_dir)
    line = error_line_in_process("cascade_ppo_continuous.py", "--resume", str(earlier))
    seed = other["args"]["seed"]
    assert line == (f"error: --resume {earlier}: {run_dir / 'checkpoint.pt'} beside it is another run's "
                    f"(Hopper-v4, cascade_ppo_continuous, seed {seed}, not Hopper-v4, cascade_ppo_continuous, seed "
                    f"{seed - 1}), which continuing here would overwrite; copy {earlier} into a folder of its own and "
                    "resume it there"), line
    assert digest(run_dir) == before
    # ... and one of the same env, experiment and seed but other settings is another run too (review)
    other["args"]["seed"] -= 1
    other["args"]["learning_rate"] = 1e-4
    torch.save(other, run_dir / "checkpoint.pt")
    line = error_line_in_process("cascade_ppo_continuous.py", "--resume", str(earlier))
    assert "beside it is another run's (--learning-rate 0.0001, not 0.0003)" in line, line
    os.rename(run_dir / "checkpoint.pt", tmp_path / "moved_away.pt")
    code, out, message = cli_in_process(capsys, "cascade_ppo_continuous.py", "--resume", str(earlier))
    assert code == 0 and message == "", message
    assert cpc.load_checkpoint(str(run_dir))["global_step"] == finished_run["global_step"]


# A run whose TensorBoard writes fail with ENOSPC (a full disk), from the first write after its first checkpoint
# ("after") or from its 21st write on, long before its first checkpoint ("before").
FULL_DISK_DRIVER = """
import errno, glob, os, sys
from tensorboard.summary.writer import record_writer
track, mode = sys.argv[1], sys.argv[2]
original, writes = record_writer.RecordWriter.write, []
def write(self, data):
    writes.append(1)
    if glob.glob(os.path.join(track, "*", "checkpoint.pt")) if mode == "after" else len(writes) > 20:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    original(self, data)
record_writer.RecordWriter.write = write
import cascade_ppo_continuous
sys.argv = ["cascade_ppo_continuous.py", *sys.argv[3:]]
cascade_ppo_continuous.main()
"""
FULL_DISK_FLAGS = ["--env-id", "InvertedPendulum-v4", "--n", "1", "--num-steps", "256", "--num-minibatches", "4",
                   "--update-epochs", "1", "--eval-every", "0", "--quiet"]


@pytest.mark.parametrize("mode", ["after", "before"])
def test_a_full_disk_in_a_log_write_is_one_line_with_advice_that_works(mode, tmp_path):
    """Issue 49.3: ENOSPC in a TensorBoard write gave two tracebacks (58 lines: the writer thread's and the training
    thread's). Now one line: after a checkpoint, the --resume that continues the run (it does); before the first
    one, that there is nothing to resume (the half-made folder is removed) and to start again."""
    flags = [*FULL_DISK_FLAGS, "--k", "2048", "--checkpoint-every", "256"] if mode == "after" else \
        [*FULL_DISK_FLAGS, "--k", "1000000", "--checkpoint-every", "0"]
    proc = subprocess.run([sys.executable, "-c", FULL_DISK_DRIVER, str(tmp_path), mode, *flags, "--track-dir",
                           str(tmp_path)], capture_output=True, text=True, timeout=600, cwd=ROOT)
    line = error_line(proc)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    if mode == "after":
        (run_dir,) = [tmp_path / d for d in os.listdir(tmp_path)]
        assert line == (f"error: no space left on {run_dir}; the last checkpoint {run_dir / 'checkpoint.pt'} is "
                        f"intact; free some space and continue with: python cascade_ppo_continuous.py --resume "
                        f"{run_dir}"), line
        resumed = run_script("cascade_ppo_continuous.py", "--resume", run_dir)  # the advice works
        assert resumed.returncode == 0, resumed.stderr[-2000:]
        assert cpc.load_checkpoint(str(run_dir))["global_step"] == 2048
    else:
        assert line.startswith(f"error: no space left on {tmp_path}") and "--resume" not in line, line
        assert line.endswith("is removed); free some space and start the run again"), line
        assert os.listdir(tmp_path) == []  # the half-made run folder is gone (nothing in it to resume)


def test_a_full_disk_at_the_first_checkpoint_does_not_advise_resume(tmp_path, monkeypatch):
    """Issue 49.3: a full disk at the first checkpoint's write advised `--resume <folder>`, which then failed (no
    checkpoint there). Now: nothing to resume, the half-made folder removed, start again."""
    def no_space(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(torch, "save", no_space)
    with pytest.raises(SystemExit) as stop:
        cpc.train(cpc.Args(**{**BASE, "n": 1, "k": 256, "eval_every": 0}, checkpoint_every=0,
                           track_dir=str(tmp_path)))
    line = str(stop.value)
    assert line.startswith("error: no space left on") and "before the run's first checkpoint" in line, line
    assert "--resume" not in line and "is removed" in line and "\n" not in line, line
    assert os.listdir(tmp_path) == []


def test_checkpoint_writes_fsync_their_folder_after_the_rename(tmp_path, monkeypatch):
    """A file's fsync does not make its directory entry durable: after a power loss the folder could still list the
    old checkpoint (or no new replay segment). Each write fsyncs the folder once its new name is in place."""
    import stat

    from cascade_plumbing.replay import ReplayBuffer, ReplayFiles

    synced = []
    real = os.fsync

    def recording_fsync(fd):
        if stat.S_ISDIR(os.fstat(fd).st_mode):
            folder = os.readlink(f"/proc/self/fd/{fd}")
            synced.append((folder, sorted(os.listdir(folder))))
        real(fd)

    monkeypatch.setattr(os, "fsync", recording_fsync)
    checkpoints.save_checkpoint(str(tmp_path / "checkpoint.pt"), {"x": 1})
    checkpoints.atomic_copy(str(tmp_path / "checkpoint.pt"), str(tmp_path / "iteration_1.pt"))
    assert synced == [(str(tmp_path), ["checkpoint.pt"]), (str(tmp_path), ["checkpoint.pt", "iteration_1.pt"])]
    synced.clear()
    buffer = ReplayBuffer(8, 3, 1)
    buffer.add(np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 1)), np.zeros(1), np.zeros(1))
    files = ReplayFiles(str(tmp_path), buffer)
    files.save()
    assert synced and synced[-1] == (files.folder, sorted(os.listdir(files.folder))) and synced[-1][1]
