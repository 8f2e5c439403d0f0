"""CleanRL's conventions (issue 21): --track logs to Weights & Biases, here offline (WANDB_MODE=offline, no network),
and --capture-video records training episodes without changing training."""

import glob
import os
import shutil
import signal
import struct
import subprocess
import sys
import time

import pytest
import torch
import wandb  # noqa: F401  (pinned in requirements.txt: a broken install fails here, it does not skip the file)

import cascade_ppo_continuous as cpc
import cascade_sac as cs
import sweep
from helpers import ROOT, ctrl_c_reaches_child, error_line, read_scalars

TINY = dict(env_id="Hopper-v4", n=2, k=1024, num_steps=256, num_minibatches=4, update_epochs=1, eval_every=512,
            eval_episodes=1, eval_in_worker=False, checkpoint_every=0, quiet=True)
TINY_SAC = dict(env_id="Hopper-v4", n=2, k=400, learning_starts=200, batch_size=32, buffer_size=2000, eval_every=200,
                eval_episodes=1, quiet=True)
# Videos on InvertedPendulum: software OpenGL (llvmpipe) renders its frames ~20x faster than Hopper's (~100 ms each)
VIDEO_ENV = "InvertedPendulum-v4"
OTHERS = {  # the scripts checked with --track only (videos: the flagship and SAC)
    "ppo_baseline.py": dict(env_id="Hopper-v4", total_timesteps=512, num_steps=256, num_minibatches=4, update_epochs=1,
                            eval_every=256, eval_episodes=1, eval_in_worker=False, checkpoint_every=0, quiet=True),
    "cascade_ppo_discrete.py": dict(env_id="CartPole-v1", n=2, k=256, num_envs=2, num_steps=64, eval_every=128,
                                    eval_episodes=1, quiet=True),
    "ppo_baseline_discrete.py": dict(env_id="CartPole-v1", total_timesteps=256, num_envs=2, num_steps=64,
                                     eval_every=128, eval_episodes=1, quiet=True),
    "cascade_ddpg.py": dict(env_id="Pendulum-v1", n=2, k=300, learning_starts=100, batch_size=32, buffer_size=1000,
                            eval_every=150, eval_episodes=1, quiet=True),
}


def cli(settings: dict) -> list[str]:
    """Args fields as command-line flags."""
    flags = []
    for key, value in settings.items():
        name = key.replace("_", "-")
        flags += [f"--{name}"] if value is True else [f"--no-{name}"] if value is False else [f"--{name}", str(value)]
    return flags


def offline_env(folder, **extra) -> dict:
    """No W&B settings of this machine: offline, with its home, config and run folders in `folder`."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("WANDB_", "XDG_")) and k != "NETRC"}
    return {**env, "HOME": str(folder), "WANDB_DIR": str(folder), "WANDB_MODE": "offline", **extra}


def run(script, folder, *flags, env=None, timeout=600):
    """A script run as a user would, from `folder` (videos/ and wandb/ are made there)."""
    return subprocess.run([sys.executable, os.path.join(ROOT, script), *map(str, flags)], capture_output=True,
                          text=True, timeout=timeout, cwd=folder, env=env or offline_env(folder))


def with_gl(folder) -> dict:
    return offline_env(folder, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))


def skip_without_gl(proc):
    if proc.returncode != 0 and "cannot render" in proc.stderr:
        pytest.skip(f"no OpenGL backend here: {error_line(proc)}")
    assert proc.returncode == 0, proc.stderr[-3000:]


def offline_runs(folder) -> list[str]:
    return sorted(glob.glob(os.path.join(folder, "wandb", "offline-run-*")))


def wandb_records(offline_run: str) -> list:
    """The records of an offline W&B run, read back from its run-<id>.wandb file: wandb's protobuf `Record`s in
    LevelDB's log format (after a 7-byte file header, 32 KiB blocks of chunks, each with a 7-byte header: crc32,
    length, type 1 FULL / 2 FIRST / 3 MIDDLE / 4 LAST; a block's unused tail is zeros)."""
    from wandb.proto import wandb_internal_pb2

    data = open(glob.glob(os.path.join(offline_run, "run-*.wandb"))[0], "rb").read()
    assert data[:4] == b":W&B"
    records, pending, pos = [], b"", 7
    while pos + 7 <= len(data):
        left = 32768 - pos % 32768
        _, length, kind = struct.unpack("<IHB", data[pos:pos + 7]) if left >= 7 else (0, 0, 0)
        if kind == 0:
            pos += left
            continue
        pending += data[pos + 7:pos + 7 + length]
        pos += 7 + length
        if kind in (1, 4):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(pending)
            records.append(record)
            pending = b""
    return records


def of_type(records, kind: str) -> list:
    return [getattr(r, kind) for r in records if r.WhichOneof("record_type") == kind]


def history(records) -> list[dict]:
    import json

    return [{item.key or "/".join(item.nested_key): json.loads(item.value_json) for item in row.item}
            for row in of_type(records, "history")]


def assert_scalars_reached_wandb(run_dir, rows):
    """Every TensorBoard scalar of the run is in W&B under its own name, at its step (W&B keeps one row per step:
    the last value logged at it)."""
    for tag, points in read_scalars(run_dir).items():
        logged = {row["global_step"]: row[tag] for row in rows if tag in row}
        expected = dict(points)  # the last value per step
        assert logged.keys() == expected.keys(), tag
        assert all(logged[s] == pytest.approx(expected[s], rel=1e-6, nan_ok=True) for s in expected), tag


def final_nets(run_dir, keys=("actor", "critic")) -> dict:
    checkpoint = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)
    return {key: checkpoint[key] for key in keys} | {"wandb_run_id": checkpoint.get("wandb_run_id")}


def same_nets(a: dict, b: dict, keys=("actor", "critic")) -> bool:
    return all(a[key].keys() == b[key].keys() and all(torch.equal(a[key][k], b[key][k]) for k in a[key])
               for key in keys)


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """A short flagship run with --track, offline."""
    folder = tmp_path_factory.mktemp("tracked")
    proc = run("cascade_ppo_continuous.py", folder, *cli(TINY), "--track")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "wandb sync" in proc.stderr  # wandb says how to upload the offline run
    return folder


def test_every_scalar_reaches_wandb_under_its_name(tracked, tmp_path):
    (run_dir,) = glob.glob(os.path.join(tracked, "runs", "*"))
    (offline,) = offline_runs(tracked)
    records = wandb_records(offline)
    (info,) = of_type(records, "run")
    assert info.display_name == os.path.basename(run_dir) and info.project == "cascade"
    config = {item.key: item.value_json for item in info.config.update}
    assert config["env_id"] == '"Hopper-v4"' and config["k"] == "1024"  # all args
    rows = history(records)
    assert_scalars_reached_wandb(run_dir, rows)
    assert {"charts/episodic_return", "eval/episodic_return", "cascade/fallback/net_2", "members/return/net_2",
            "losses/approx_kl"} <= set().union(*rows)
    assert [e.exit_code for e in of_type(records, "exit")] == [0]  # wandb.finish at the end
    assert final_nets(run_dir)["wandb_run_id"] == info.run_id
    # --track changes nothing in training: the same nets as a run without it
    plain = cpc.train(cpc.Args(track_dir=str(tmp_path), **TINY))
    assert same_nets(final_nets(run_dir), final_nets(plain["run_dir"]))


def test_resume_continues_the_same_wandb_run(tracked, tmp_path):
    folder = tmp_path / "copy"
    shutil.copytree(tracked, folder)
    (run_dir,) = glob.glob(os.path.join(folder, "runs", "*"))
    shutil.copy(os.path.join(run_dir, "iteration_1.pt"), os.path.join(run_dir, "checkpoint.pt"))  # killed there
    proc = run("cascade_ppo_continuous.py", folder, "--resume", run_dir, "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    first, resumed = offline_runs(folder)  # W&B keeps one folder per process; `wandb sync` joins them by id
    first_id, resumed_id = (of_type(wandb_records(f), "run")[0].run_id for f in (first, resumed))
    assert resumed_id == first_id and resumed.endswith(first_id)
    steps = [row["global_step"] for row in history(wandb_records(resumed))]
    assert min(steps) == 1024 and max(steps) == 2048  # only what the resumed run logged: iteration 2
    assert same_nets(final_nets(run_dir), final_nets(glob.glob(os.path.join(tracked, "runs", "*"))[0]))


def test_capture_video_records_training_and_changes_nothing(tmp_path):
    """The issue's "done when" for the flagship: --track --capture-video offline gives the W&B run with our
    scalars and the videos; the nets equal those of a run without either. With --num-envs 2 the recording env
    is a forked worker (it hung when this process had rendered before the fork)."""
    settings = {**TINY, "env_id": VIDEO_ENV, "num_envs": 2}
    proc = run("cascade_ppo_continuous.py", tmp_path, *cli(settings), "--track", "--capture-video",
               env=with_gl(tmp_path))
    skip_without_gl(proc)
    (run_dir,) = glob.glob(os.path.join(tmp_path, "runs", "*"))
    videos = sorted(os.listdir(tmp_path / "videos" / os.path.basename(run_dir)),
                    key=lambda name: int(name.split("-")[-1][:-4]))
    assert videos[:3] == [f"rl-video-episode-{i}.mp4" for i in (0, 1, 8)], videos  # CleanRL's trigger
    assert all(open(tmp_path / "videos" / os.path.basename(run_dir) / v, "rb").read(12)[4:8] == b"ftyp" for v in videos)
    (offline,) = offline_runs(tmp_path)
    rows = history(wandb_records(offline))
    assert_scalars_reached_wandb(run_dir, rows)
    assert sum("videos/path" in row for row in rows) == len(videos)
    assert len(glob.glob(os.path.join(offline, "files", "media", "videos", "*.mp4"))) == len(videos)
    plain = cpc.train(cpc.Args(track_dir=str(tmp_path / "plain"), **settings))
    assert same_nets(final_nets(run_dir), final_nets(plain["run_dir"]))


def test_sac_tracked_with_videos(tmp_path):
    """The "done when" for one off-policy script: cascade_sac.py --track --capture-video, offline."""
    settings = {**TINY_SAC, "env_id": VIDEO_ENV}
    proc = run("cascade_sac.py", tmp_path, *cli(settings), "--track", "--capture-video", env=with_gl(tmp_path))
    skip_without_gl(proc)
    (run_dir,) = glob.glob(os.path.join(tmp_path, "runs", "*"))
    videos = os.listdir(tmp_path / "videos" / os.path.basename(run_dir))
    assert "rl-video-episode-8.mp4" in videos
    (offline,) = offline_runs(tmp_path)
    rows = history(wandb_records(offline))
    assert_scalars_reached_wandb(run_dir, rows)
    assert {"losses/qf_loss", "charts/episodic_return"} <= set().union(*rows)
    assert sum("videos/path" in row for row in rows) == len(videos)
    plain = cs.train(cs.Args(track_dir=str(tmp_path / "plain"), **settings))
    assert same_nets(final_nets(run_dir, ("actor", "qf")), final_nets(plain["run_dir"], ("actor", "qf")), ("actor", "qf"))


@pytest.mark.parametrize("script", sorted(OTHERS))
def test_track_in_every_other_script(script, tmp_path):
    proc = run(script, tmp_path, *cli(OTHERS[script]), "--track")
    assert proc.returncode == 0, proc.stderr[-3000:]
    (run_dir,) = glob.glob(os.path.join(tmp_path, "runs", "*"))
    (offline,) = offline_runs(tmp_path)
    records = wandb_records(offline)
    assert_scalars_reached_wandb(run_dir, history(records))
    assert torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)["wandb_run_id"] == \
        of_type(records, "run")[0].run_id


def test_a_stopped_run_finishes_its_wandb_run_as_failed(tmp_path):
    """Ctrl-C (SIGINT to the process group, wandb's own process included): wandb.finish, then the one stop line."""
    flags = [*cli({**TINY, "k": 65536, "checkpoint_every": 2048}), "--track"]
    proc = subprocess.Popen([sys.executable, os.path.join(ROOT, "cascade_ppo_continuous.py"), *flags], text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=tmp_path, env=offline_env(tmp_path),
                            start_new_session=True, preexec_fn=ctrl_c_reaches_child)
    deadline = time.time() + 120
    while time.time() < deadline and not glob.glob(os.path.join(tmp_path, "runs", "*", "checkpoint.pt")):
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-3000:]
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines[-1].startswith("stopped by SIGINT") and "Traceback" not in out + err, err[-3000:]
    (offline,) = offline_runs(tmp_path)
    assert [e.exit_code for e in of_type(wandb_records(offline), "exit")] == [1]


def test_online_without_a_login_is_one_line(tmp_path):
    """wandb would prompt for an API key (a sweep or batch job then waits forever): one line, nothing created."""
    proc = run("cascade_ppo_continuous.py", tmp_path, *cli(TINY), "--track", "--track-dir", tmp_path / "runs",
               env=offline_env(tmp_path, WANDB_MODE="online"), timeout=120)
    line = error_line(proc)
    assert "no W&B login" in line and "wandb login" in line and "WANDB_MODE=offline" in line
    assert not (tmp_path / "runs").exists() and not (tmp_path / "wandb").exists()


def test_a_server_that_does_not_answer_is_one_line_and_leaves_no_run_folder(tmp_path):
    """A W&B server that does not answer (here a closed port on this machine): one line after wandb.init's timeout,
    and no empty run folder left behind (one holding only run.lock was left)."""
    env = offline_env(tmp_path, WANDB_MODE="online", WANDB_BASE_URL="http://127.0.0.1:9", WANDB_API_KEY="a" * 40,
                      WANDB_INIT_TIMEOUT="1")
    proc = run("cascade_ppo_continuous.py", tmp_path, *cli(TINY), "--track", "--track-dir", tmp_path / "runs",
               env=env, timeout=300)
    assert proc.returncode != 0
    assert any(line.startswith("error: --track: cannot start the W&B run") for line in proc.stderr.splitlines()), \
        proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and os.listdir(tmp_path / "runs") == []


@pytest.mark.parametrize("script", ["cascade_ppo_continuous.py", "cascade_sac.py", *sorted(OTHERS)])
def test_capture_video_without_opengl_is_one_line_at_start(script, tmp_path):
    env = {k: v for k, v in offline_env(tmp_path).items()
           if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DISPLAY", "WAYLAND_DISPLAY")}
    settings = {**{"cascade_ppo_continuous.py": TINY, "cascade_sac.py": TINY_SAC, **OTHERS}[script], "env_id": "Hopper-v4"}
    proc = run(script, tmp_path, *cli(settings), "--capture-video", "--track-dir", tmp_path / "runs", env=env,
               timeout=300)
    if proc.returncode == 0:
        pytest.skip("MuJoCo renders here without MUJOCO_GL and a display")
    line = error_line(proc)
    assert "cannot render Hopper-v4 with MUJOCO_GL=(unset)" in line and "MUJOCO_GL=egl" in line
    assert not (tmp_path / "runs").exists() and not (tmp_path / "videos").exists()


def test_sweep_passes_track_in_one_group(tmp_path):
    """The runs of one sweep share a W&B group; tracking is not part of a run's identity."""
    template = "ppo_baseline.py --total-timesteps 512 --num-steps 256 --num-minibatches 4 --update-epochs 1 " \
               "--eval-every 0 --checkpoint-every 0"
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "sweep.py"), "--command", template, "--envs",
                           "InvertedPendulum-v4", "--seeds", "1", "2", "--workers", "1", "--sweep-dir",
                           tmp_path / "my_sweep", "--track"], capture_output=True, text=True, timeout=600,
                          env=offline_env(tmp_path), cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    groups = {of_type(wandb_records(f), "run")[0].run_group for f in offline_runs(tmp_path)}
    assert len(offline_runs(tmp_path)) == 2 and groups == {"my_sweep"}
    run = sweep.expand(sweep.Args(command=[template], envs=["InvertedPendulum-v4"]))[0]
    tracking = sweep.tracking_flags(sweep.Args(track=True, wandb_entity="me"), str(tmp_path / "my_sweep"))
    assert run.command("python", "runs", tracking)[-len(tracking):] == tracking == [
        "--track", "--wandb-project-name", "cascade", "--wandb-group", "my_sweep", "--wandb-entity", "me"]
    assert sorted(os.listdir(tmp_path / "my_sweep" / "done")) == sorted(
        f"{r.run_id}.json" for r in sweep.expand(sweep.Args(command=[template], envs=["InvertedPendulum-v4"],
                                                            seeds=["1", "2"])))


def test_plots_ignore_the_tracking_flags(capsys):
    """Seeds of one experiment, some tracked (or from before --track existed), are one experiment to the plots."""
    from plots import common

    base = {"n": "6", "k": "1000000", "capture_video": "False"}
    runs = [common.Run("a", "Hopper-v4", "cascade", 1, 0, {**base}),
            common.Run("b", "Hopper-v4", "cascade", 2, 0, {**base, "track": "True", "wandb_project_name": "cascade",
                                                           "wandb_entity": "me", "wandb_group": "sweep"}),
            common.Run("c", "Hopper-v4", "cascade", 3, 0, {**base, "capture_video": "True", "track": "False"})]
    common.warn_if_settings_differ(("Hopper-v4", "cascade"), runs, [])
    assert capsys.readouterr().err == ""
