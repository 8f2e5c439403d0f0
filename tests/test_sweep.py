"""sweep.py: grid expansion, a local sweep with a failure, skipping finished runs, a real Ray head."""

import json
import os
import shlex
import socket
import subprocess
import sys
import tempfile
from unittest import mock

import pytest

import sweep
from helpers import ROOT, error_line, read_scalars, run_script

TINY = ("cascade_ppo_continuous.py --n 1 --k 2048 --num-steps 512 --num-minibatches 4 --update-epochs 1 "
        "--eval-every 0 --checkpoint-every 0")


@pytest.mark.parametrize("preset", sorted(sweep.PRESETS))
def test_every_preset_expands_to_the_papers_grid(preset):
    # (at 0.01 the 16 nets of "tiny" get --k 4096, 18% off 5000: refused, test_scale_keeps_budgets_equal...)
    runs = sweep.expand(sweep.Args(preset=[preset], envs=["Hopper-v4", "Walker2d-v4"], seeds=["1", "2", "3"],
                                   scale=0.02))
    entries = sweep.PRESETS[preset][1]
    assert len(runs) == len(entries) * 2 * 3
    assert {r.label for r in runs} == {label for label, _, _ in entries}
    assert {(r.env_id, r.seed) for r in runs} == {(e, s) for e in ("Hopper-v4", "Walker2d-v4") for s in (1, 2, 3)}
    for run in runs:
        assert os.path.isfile(os.path.join(ROOT, run.script))
        command = run.command(sys.executable, "/tmp/none")
        assert command[command.index("--exp-name") + 1] == run.label
        for flag in ("--k", "--total-timesteps", "--cycle-steps"):  # the budgets in env steps (Fig. 3's cycle too)
            if flag in run.flags:  # budgets scaled by 0.02 (the runs a figure compares keep equal budgets), a PPO
                # script's in the nearest whole rollouts (which it would round down to)
                original = dict(zip(*[iter(dict((lab, f) for lab, _, f in entries)[run.label].split())] * 2))
                expected = round(int(original[flag]) * 0.02)
                rollout = sweep.rollout_steps(run.script, run.flags)
                if rollout:
                    expected = max(round(expected / rollout), 1) * rollout
                if flag == "--total-timesteps" and original.get("--lr-schedule") == "cyclic":  # whole LR cycles
                    cycles = int(original[flag]) // int(original["--cycle-steps"])
                    expected = cycles * int(sweep.flag_value(run.flags, "--cycle-steps"))
                assert int(run.flags[run.flags.index(flag) + 1]) == expected
        # the evaluation cadence too (the presets' 50000, the scripts' default 10000), not below 1000 steps
        assert sweep.flag_value(run.flags, "--eval-every") == "1000"
        # and a checkpoint cadence scaled with them (the PPO scripts' default 100000: one rollout)
        assert run.cadence == ["--checkpoint-every", "2048"]


def test_scale_scales_the_checkpoint_cadence():
    """Issue 28.4b: with --scale 0.01 a PPO run kept --checkpoint-every 100000, so it wrote no checkpoint before its
    end and restarted from zero after every kill. The cadence scales with the budget (never below one rollout);
    the script's default, scaled, is passed where the template leaves it. It is not part of a run's identity."""
    def one(template, scale):
        (run,) = sweep.expand(sweep.Args(command=[template], scale=scale))
        return run

    for script in ("cascade_ppo_continuous.py", "ppo_baseline.py", "cascade_ppo_discrete.py", "ppo_baseline_discrete.py"):
        assert sweep.script_default(script, "checkpoint_every") == 100_000, script
    for script in ("cascade_sac.py", "cascade_ddpg.py"):
        assert sweep.script_default(script, "checkpoint_every") == 50_000, script
        assert one(f"{script} --n 2 --k 1000000", 0.01).cadence == ["--checkpoint-every", "2048"]
    run = one("cascade_ppo_continuous.py --n 6 --k 1000000", 0.01)
    assert run.flags == ["--n", "6", "--k", "10240", "--eval-every", "1000"]  # 10,000 in whole rollouts of 2,048
    assert run.cadence == ["--checkpoint-every", "2048"]
    command = run.command(sys.executable, "/tmp/none")
    assert command[command.index("--checkpoint-every") + 1] == "2048"
    assert run.setup_hash == sweep.Run(run.label, run.script, run.flags, run.env_id, run.seed).setup_hash
    assert one("cascade_ppo_continuous.py --n 6 --k 1000000", 0.1).cadence == ["--checkpoint-every", "10000"]
    full = one("cascade_ppo_continuous.py --n 6 --k 1000000", 1)  # unscaled: the command as before
    assert full.cadence == [] and "--checkpoint-every" not in full.command(sys.executable, "/tmp/none")
    # a cadence in the template scales in place; 0 (checkpoints at iteration ends only) stays 0
    assert one("ppo_baseline.py --total-timesteps 6000000 --checkpoint-every 50000", 0.1).flags[2:4] == \
        ["--checkpoint-every", "5000"]
    spelled = one("ppo_baseline.py --total-timesteps 6000000 --checkpoint-every=50000", 0.01)
    assert spelled.flags[2:4] == ["--checkpoint-every", "2048"] and spelled.written[2] == "--checkpoint-every=2048"
    explicit = one("ppo_baseline.py --total-timesteps 6000000 --checkpoint-every 0", 0.01)
    assert explicit.flags[2:4] == ["--checkpoint-every", "0"] and explicit.cadence == []
    off = one("ppo_baseline.py --total-timesteps=6000000 --eval-every 0", 0.01)  # evaluation off stays off
    assert off.flags == ["--total-timesteps", "59392", "--eval-every", "0"]
    assert off.written == ["--total-timesteps=59392", "--eval-every", "0"]
    # Fig. 3's LR cycle shrinks with the run it divides (6 cycles either way)
    # (not without the cyclic schedule: there --cycle-steps is refused by the script)
    assert one("ppo_baseline.py --total-timesteps 6000000 --cycle-steps 1000000 --eval-every 0", 0.01).flags == \
        ["--total-timesteps", "59392", "--cycle-steps", "10240", "--eval-every", "0"]
    # ... and the budget stays 6 whole cycles, as the Cascade it is compared with (6 x --k 10240): rounded on their
    # own the total was 59,392 steps, the last cycle cut short
    for lr in (["--lr-schedule", "cyclic"], ["--lr-schedule=cyclic"]):
        flags = one(shlex.join(["ppo_baseline.py", "--total-timesteps=6000000", "--cycle-steps", "1000000", *lr]),
                    0.01).written
        assert flags[:3] == ["--total-timesteps=61440", "--cycle-steps", "10240"], flags
    assert sweep.flag_value(one("ppo_baseline.py --lr-schedule cyclic --eval-every 0", 0.01).flags,
                            "--total-timesteps") == str(6 * 10240)  # the defaults: 6M steps, cycles of 1M
    # a total that is no whole number of cycles is rounded on its own
    assert one("ppo_baseline.py --total-timesteps 5500000 --lr-schedule cyclic", 0.01).flags[:2] == \
        ["--total-timesteps", "55296"]
    # ... also where the template leaves the cycle at its default (it stayed 1M: a 60k-step run that never cycled);
    # without the cyclic schedule no --cycle-steps is added (the script refuses one there)
    for template in ("ppo_baseline.py --lr-schedule cyclic --eval-every 0",
                     "ppo_baseline.py --lr-schedule=cyclic --eval-every 0"):
        assert sweep.flag_value(one(template, 0.01).flags, "--cycle-steps") == "10240", template
    assert sweep.flag_value(one("ppo_baseline.py --eval-every 0", 0.01).flags, "--cycle-steps") is None
    assert run_script("sweep.py", "--command", "ppo_baseline.py --lr-schedule cyclic", "--envs", "Pendulum-v1",
                      "--scale", "0.01", "--dry-run").returncode == 0


def test_scale_keeps_budgets_equal_and_scales_the_defaults():
    """Audit of issue 48: the floor of one rollout raised every budget and cadence to 2048 even at --scale 1, and
    broke the equal budgets a figure compares when scaling down (4 x 2048 Cascade-SAC steps against 2048 of SAC);
    a budget the template left at the script's default was not scaled at all (a "quick check" of 2M steps), nor
    was --eval-every (a curve of two points)."""
    def one(template, scale):
        (run,) = sweep.expand(sweep.Args(command=[template], scale=scale))
        return run

    # at scale 1 the command is the one written, small values included
    small = "cascade_sac.py --n 2 --k 300 --learning-starts 100 --checkpoint-every 100"
    assert one(small, 1).flags == small.split()[1:] and one(small, 1).cadence == []
    # scaled down, the Cascade and its baseline keep the same total budget, counted in the steps the scripts run:
    # a PPO script rounds a budget down to whole rollouts (at 0.001 discrete Cascade's 10 x --k 1000 were 10 x 512
    # steps against its baseline's 9,728), so the sweep gives whole rollouts
    for preset, labels, scale in (("sac", ("cascade_sac", "sac"), 0.001), ("ddpg", ("cascade_ddpg", "ddpg"), 0.001),
                                  ("discrete", ("cascade_discrete", "ppo_discrete"), 0.001),
                                  ("standard", ("cascade", "ppo"), 0.01)):
        runs = {run.label: run for run in sweep.expand(sweep.Args(preset=[preset], scale=scale))}
        totals = []
        for label in labels:
            flags = runs[label].flags
            budget = int(sweep.flag_value(flags, "--k") or sweep.flag_value(flags, "--total-timesteps"))
            rollout = sweep.rollout_steps(runs[label].script, flags)
            if rollout:
                assert budget % rollout == 0, (preset, label, budget)
            totals.append(budget * int(sweep.flag_value(flags, "--n") or 1))
        assert abs(totals[0] / totals[1] - 1) < 0.05, (preset, totals)
    # a budget, warm-up and evaluation cadence left at the script's default are scaled too
    flags = one("cascade_sac.py", 0.01).flags
    assert [sweep.flag_value(flags, f) for f in ("--k", "--learning-starts", "--eval-every")] == ["5000", "50", "1000"]
    assert sweep.flag_value(one("ppo_baseline_discrete.py", 0.01).flags, "--total-timesteps") == "99840"  # x 512
    # a PPO budget below one rollout, or one that rounding to whole rollouts moves by more than 10% (a Cascade's
    # budget against its baseline's), is refused in one line naming a scale that works for every template (the
    # largest need, rounded up: 0.002 was named, and refused in turn)
    for preset, scale, problem, works in (("standard", "0.001", "less than one PPO rollout", "0.0021"),
                                          ("k-sweep", "0.0005", "less than one PPO rollout", "0.014"),
                                          ("standard", "0.005", "--k 4096 (whole PPO rollouts) instead of 5000, 18% off",
                                           "0.0057"),
                                          # each within 10%, but one up, one down: 12% apart (a review)
                                          ("standard", "0.0056", "--k 6144 and 'ppo_baseline.py --total-timesteps "
                                           "6000000' --total-timesteps 32768 (+10% and -2% of", "0.0057"),
                                          ("discrete", "0.0007", "--k 512 (whole PPO rollouts) instead of 700, 27% off",
                                           "0.00095")):
        error = error_line(run_script("sweep.py", "--preset", preset, "--scale", scale, "--dry-run"))
        assert problem in error and f"; use --scale {works} (the " in error, error
        assert run_script("sweep.py", "--preset", preset, "--scale", works, "--dry-run").returncode == 0
    assert int(sweep.flag_value(one("cascade_ppo_discrete.py --k 1000000", 0.001).flags, "--k")) == 1024
    # the floors never raise a cadence above the template's own
    assert sweep.flag_value(one("cascade_sac.py --eval-every 500 --checkpoint-every 700", 0.5).flags,
                            "--eval-every") == "500"
    assert one("cascade_sac.py --eval-every 500 --checkpoint-every 700", 0.5).flags[3] == "700"
    # tyro's other spelling (--total_timesteps) is the same flag: scaled, not overridden by a scaled default
    run = one("ppo_baseline.py --total_timesteps 2000000", 0.01)
    assert run.flags[:2] == ["--total-timesteps", "20480"]  # (the identity: one spelling)
    flags = run.written  # (the identity a sweep folder of an earlier version gave it: as written)
    assert flags[:2] == ["--total_timesteps", "20480"] and sweep.flag_value(flags, "--total-timesteps") == "20480"
    assert "--total-timesteps" not in flags
    # --exp-name=NAME is the label too (it took the next flag as the label)
    assert one("cascade_sac.py --exp-name=mine --k 1000", 1).label == "mine"
    assert one("cascade_sac.py --exp-name=mine --k 1000", 1).flags == ["--k", "1000"]
    # a --num-envs the script will refuse is left to the script (no traceback here)
    assert one("ppo_baseline.py --num-envs 0", 0.5).flags[:2] == ["--num-envs", "0"]


def test_bad_templates_and_scales_are_one_line():
    """Audit of issue 48: --env-id or --seed in a template was silently overridden by the sweep's (the run trained
    Hopper-v4 in a folder hashed from "Ant-v4"); a budget such as 1e6 and --scale inf ended in tracebacks."""
    cases = [(["--command", "cascade_sac.py --env-id Ant-v4 --k 1000"], "sets --env-id, which the sweep sets"),
             (["--command", "cascade_sac.py --seed=5"], "sets --seed, which the sweep sets"),
             (["--command", "cascade_sac.py --env_id Ant-v4"], "sets --env-id, which the sweep sets"),
             (["--command", "ppo_baseline.py --resume runs/x"], "sets --resume"),
             (["--command", "cascade_sac.py --k 1e6", "--scale", "0.5"], "--k 1e6 in 'cascade_sac.py --k 1e6' is not"),
             (["--command", "cascade_sac.py --k=abc", "--scale", "0.5"], "is not a whole number"),
             (["--preset", "sac", "--scale", "inf"], "--scale must be positive (got inf)"),
             (["--preset", "sac", "--scale", "nan"], "--scale must be positive (got nan)"),
             # checked up front, not one failed run per seed and template later
             (["--preset", "sac", "--envs", "CartPole-v1"], "--envs CartPole-v1 has a Discrete action space, and "
              "cascade_sac.py needs a Box (continuous) one"),
             (["--command", "cascade_ddpg.py", "--envs", "CartPole-v1"], "cascade_ddpg.py needs a Box"),
             (["--preset", "discrete", "--envs", "Hopper-v4", "Hoper-v4"], "unknown env id 'Hoper-v4'"),
             # (a fresh-user hunt: the sweep's --quiet, put after the template, overrode its --no-quiet silently)
             (["--command", "cascade_sac.py --no-quiet"], "sets --no-quiet: the sweep runs every script with --quiet"),
             (["--command", "ppo_baseline.py -h"], "asks for --help, which runs nothing: read the flags with "
              "`python ppo_baseline.py --help`"),
             # (a fault hunt: an interpreter that cannot run the scripts was accepted, each run failing with "exit 1")
             (["--preset", "sac", "--python", "/bin/false"], "--python /bin/false cannot run the scripts (importing "
              "torch, gymnasium and tyro: exit 1)")]
    for extra, message in cases:
        assert message in error_line(run_script("sweep.py", *extra, "--dry-run")), extra


def test_each_template_is_checked_by_its_script_before_any_run(tmp_path):
    """Audit: a flag the script does not have, a value it refuses, a template it cannot read, a script that is not a
    training script, a bad --python or seed: each passed --dry-run and the sweep's start, then failed one run per
    seed and template (the summary naming tyro's box border), or was a traceback. Now one line up front, each."""
    sweep_dir = ["--sweep-dir", str(tmp_path / "sweep")]
    cases = [(["--command", "cascade_sac.py --bogus 3"], "cascade_sac.py does not accept it: Unrecognized options: "
              "--bogus, 3"),
             (["--command", "cascade_sac.py --k abc"], "does not accept it: Error parsing --k: invalid literal"),
             (["--command", "cascade_sac.py --k"], "does not accept it: Missing value for argument '--k'"),
             (["--command", "cascade_sac.py --n 0"], "'cascade_sac.py --n 0' on Hopper-v4: --n must be at least 1"),
             (["--command", "cascade_sac.py --k 600 --learning-starts 100 --policy-frequency 1000"],
              "--policy-frequency 1000: no update step of an iteration (101 to 599) is a multiple of it"),
             (["--preset", "sac", "--scale", "0.000001"], "makes a budget of 'cascade_sac.py --n 4 --k 500000 "
              "--eval-every 50000' less than one --batch-size of steps; use --scale 0.00052 (the smallest that works"),
             (["--command", "cascade_sac.py --n 1 --keep-buffer"], "--keep-buffer has no effect with --n 1"),
             (["--command", "ppo_baseline_discrete.py --normalize", "--envs", "CartPole-v1"],
              "on CartPole-v1: --normalize applies to discretized Box envs only"),
             # (checked with the env ids now, alike for every script: 2026-12-08)
             (["--preset", "discrete", "--envs", "FrozenLake-v1"], "FrozenLake-v1 has a Discrete observation space; "
              "these scripts' MLPs need a flat (1-D) Box"),
             (["--command", "cascade_sac.py --exp-name"], "--exp-name in 'cascade_sac.py --exp-name' has no value"),
             (["--command", "cascade_sac.py --exp-name 'x"], "cannot be read as a command line (No closing quotation)"),
             (["--command", "./cascade_sac.py"], "without a folder (e.g. cascade_sac.py)"),
             (["--command", "plots/analyze.py"], "without a folder (e.g. cascade_ppo_continuous.py)"),
             (["--command", "sweep.py"], "sweep.py is not one of the training scripts"),
             (["--preset", "sac", "--seeds", "-1"], "--seeds -1: a seed must be a non-negative integer"),
             (["--preset", "sac", "--seeds"], "nothing to run: --seeds is given with no value"),
             (["--preset", "sac", "--envs"], "nothing to run: --envs is given with no value"),
             (["--preset", "sac", "--status-every", "0"], "--status-every must be a positive number"),
             (["--preset", "sac", "--backend", "ray", "--cpus-per-run", "-1"], "--cpus-per-run must be >= 0"),
             (["--preset", "sac", "--ray-address", "10.0.0.1:6379"], "applies to --backend ray only"),
             # (a fault hunt: these were ignored)
             (["--preset", "sac", "--ray-address", "auto"], "--ray-address auto applies to --backend ray only"),
             (["--preset", "sac", "--cpus-per-run", "3"], "--cpus-per-run 3.0 applies to --backend ray only"),
             (["--preset", "sac", "--backend", "ray", "--workers", "3"], "--workers 3 applies to --backend local "
              "only (Ray places runs by --cpus-per-run); use --cpus-per-run, or leave it out"),
             (["--preset", "sac", "--wandb-group", "g"], "--wandb-group g applies with --track only; add --track"),
             (["--preset", "sac", "--python", str(tmp_path / "nope")], "is not an executable (a path, or a name"),
             (["--preset", "sac", "--python", "no-such-python3"], "is not an executable (a path, or a name"),
             (["--preset", "sac", "--sweep-dir", os.path.join(__file__, "sub")], f"{__file__} is a file, not a folder")]
    for extra, message in cases:  # in process (each a subprocess: ~4 s of imports each)
        flags = extra if "--sweep-dir" in extra else [*extra, *sweep_dir]
        with mock.patch.object(sys, "argv", ["sweep.py", *flags, "--dry-run"]), pytest.raises(SystemExit) as stop:
            sweep.sweep()
        assert str(stop.value).startswith("error: ") and "\n" not in str(stop.value), (extra, stop.value)
        assert message in str(stop.value), (extra, stop.value)
    assert not (tmp_path / "sweep").exists()
    # the checks see each run as it will run: scaled, with the sweep's own flags (a good grid passes)
    proc = run_script("sweep.py", "--preset", "sac", "--scale", "0.01", *sweep_dir, "--dry-run")
    assert proc.returncode == 0 and "# 2 runs to do" in proc.stdout, proc.stderr
    # ... with the tracking flags the sweep adds (review: --wandb-entity in a template was refused without them),
    # a --python found on PATH, and a template's own --quiet (the check had cut the command there)
    proc = run_script("sweep.py", "--command", "cascade_sac.py --quiet --n 0", *sweep_dir, "--dry-run")
    assert "--n must be at least 1" in error_line(proc)
    on_path = {**os.environ, "WANDB_MODE": "offline",  # (the venv's interpreter by name: one that can run the scripts)
               "PATH": os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", "")}
    proc = run_script("sweep.py", "--command", "cascade_sac.py --wandb-entity team", "--track", "--python",
                      os.path.basename(sys.executable), "--scale", "0.01", *sweep_dir, "--dry-run", env=on_path)
    assert proc.returncode == 0 and "--wandb-entity team" in proc.stdout, proc.stderr


def test_scale_works_for_sac_and_ddpg(tmp_path):
    """Issue 48: `--scale` failed for both off-policy scripts ("--k 5000 must exceed --learning-starts 5000"): the
    warm-up now scales with the budget (part of the run's identity: it changes what the run computes), in a
    template or from the script's default, and a scaled sweep runs and finishes."""
    runs = {run.label: run for run in sweep.expand(sweep.Args(preset=["sac-ddpg"], scale=0.01))}
    assert runs["cascade_sac"].flags == ["--n", "4", "--k", "5000", "--learning-starts", "50", "--eval-every", "1000"]
    assert runs["ddpg"].flags == ["--n", "1", "--k", "60000", "--hidden-size", "64", "--learning-starts", "250",
                                  "--eval-every", "1000"]
    assert runs["sac"].cadence == ["--checkpoint-every", "2048"]
    (run,) = sweep.expand(sweep.Args(command=["cascade_ddpg.py --k 100000 --learning-starts 1000 --eval-every 0"],
                                     scale=0.1))
    assert run.flags == ["--k", "10000", "--learning-starts", "100", "--eval-every", "0"]
    (run,) = sweep.expand(sweep.Args(command=["cascade_sac.py --k 100000"], scale=1))
    assert run.flags == ["--k", "100000"]  # unscaled: the command as written
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "sweep.py"), "--command",
                           "cascade_sac.py --n 2 --k 40000 --batch-size 32 --eval-every 0", "--envs", "Pendulum-v1",
                           "--scale", "0.01", "--sweep-dir", str(tmp_path), "--workers", "1"],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert len(os.listdir(tmp_path / "done")) == 1
    # a scale too small for a batch names one that works (a fault hunt: it failed in the script's own line, "pass a
    # smaller --batch-size or a larger --k", naming no scale), and that one passes every script's checks
    for template, works in (("cascade_sac.py --n 4 --k 500000", 0.00052),
                            ("cascade_sac.py --n 4 --k 500000 --keep-buffer", 0.00013),
                            ("cascade_ddpg.py --n 6 --k 1000000 --batch-size 100", 0.0001)):
        with mock.patch.object(sys, "argv", ["sweep.py", "--command", template, "--scale", str(works / 2),
                                             "--sweep-dir", str(tmp_path / "s"), "--dry-run"]):
            with pytest.raises(SystemExit) as stop:
                sweep.sweep()
        assert f"less than one --batch-size of steps; use --scale {works:.2g} (the smallest" in str(stop.value)
        with mock.patch.object(sys, "argv", ["sweep.py", "--command", template, "--scale", str(works),
                                             "--sweep-dir", str(tmp_path / "s"), "--dry-run"]):
            sweep.sweep()


def test_one_setup_spelled_two_ways_is_one_run_in_one_or_two_sweeps(tmp_path, capsys):
    """A run's identity is its command: `--k=300` and `--k 300` (or `--learning_starts`) were two setups, so a second
    sweep into the same folder trained the same runs again. Flags are read in one spelling now; a folder made before
    that (runs under the template's own spelling) is still found, finished or half-way."""
    def dry_run(*templates):
        argv = ["sweep.py", "--envs", "Pendulum-v1", "--sweep-dir", str(tmp_path), "--dry-run", "--command", *templates]
        with mock.patch.object(sys, "argv", argv):
            sweep.sweep()
        return capsys.readouterr().out

    spellings = ("cascade_sac.py --k 300 --learning-starts 100 --exp-name t",
                 "cascade_sac.py --k=300 --learning_starts=100 --exp-name t")
    both = dry_run(*spellings)
    assert "# 1 runs to do, 0 already finished" in both, both
    ids = [line.split()[1].rstrip(":") for line in both.splitlines() if line.startswith("# Pendulum")]
    assert len(ids) == 1 and " --k 300 --learning-starts 100 " in both, both
    os.makedirs(tmp_path / "done")
    open(tmp_path / "done" / f"{ids[0]}.json", "w").close()
    for template in spellings:  # a later sweep in either spelling finds the run finished
        assert "# 0 runs to do, 1 already finished" in dry_run(template)
    # a folder of an earlier version: its runs were named after the command as written
    earlier = sweep.Run("t", "cascade_sac.py", shlex.split(spellings[1])[1:-2], "Pendulum-v1", 1)
    assert earlier.run_id != ids[0]
    os.rename(tmp_path / "done" / f"{ids[0]}.json", tmp_path / "done" / f"{earlier.run_id}.json")
    assert "# 0 runs to do, 1 already finished" in dry_run(spellings[1])
    assert "# 1 runs to do, 0 already finished" in dry_run(spellings[0])  # (as that version did)
    os.remove(tmp_path / "done" / f"{earlier.run_id}.json")
    os.makedirs(tmp_path / "runs" / earlier.run_id / "Pendulum-v1__t__1__1")
    half_way = dry_run(spellings[1])
    assert f"# {earlier.run_id}:" in half_way and "--k=300" in half_way, half_way  # its folder, its command


def test_paper_settings_in_presets():
    k_sweep = sweep.expand(sweep.Args(preset=["k-sweep"]))
    assert sorted(int(r.flags[1]) for r in k_sweep) == list(range(2, 9))
    assert all(int(r.flags[1]) * int(r.flags[3]) <= 6_000_000 for r in k_sweep)
    merged = sweep.expand(sweep.Args(preset=["standard", "frozen", "global-lr"]))
    assert sum(r.label == "cascade" for r in merged) == 1  # shared runs are run once


def test_unfinished_run_resumes_from_its_own_checkpoint_only(tmp_path):
    run = sweep.Run("cascade", "cascade_ppo_continuous.py", ["--n", "2"], "Hopper-v4", 3,
                    cadence=["--checkpoint-every", "2048"])
    tracking = ["--track", "--wandb-project-name", "cascade"]
    assert "--resume" not in run.command("python", str(tmp_path))
    # another setup's checkpoint (other flags, same env/label/seed) is never picked up
    other = sweep.Run("cascade", "cascade_ppo_continuous.py", ["--n", "3"], "Hopper-v4", 3)
    assert other.run_id != run.run_id and other.run_id.startswith("Hopper-v4__cascade__3__")
    foreign = tmp_path / other.run_id / "Hopper-v4__cascade__3__1790000000"
    foreign.mkdir(parents=True)
    (foreign / "checkpoint.pt").write_bytes(b"x")
    assert "--resume" not in run.command("python", str(tmp_path))
    own = tmp_path / run.run_id / "Hopper-v4__cascade__3__1790000001"
    own.mkdir(parents=True)
    (own / "checkpoint.pt").write_bytes(b"x")
    command = run.command("python", str(tmp_path), tracking)
    assert command[2:4] == ["--resume", str(own)]
    # the resume repeats every flag, so the script itself refuses a checkpoint saved with other settings; the
    # checkpoint cadence and the tracking go on as they were (only --track-dir goes: the run keeps its folder)
    assert command[4:] == ["--n", "2", "--env-id", "Hopper-v4", "--seed", "3", "--exp-name", "cascade", "--quiet",
                           "--checkpoint-every", "2048", *tracking]
    # a folder whose checkpoint.pt is gone but whose iteration files are there is the run too (a fault hunt: the
    # sweep started a new run beside it, its finished iterations unused); the script then names the file to resume
    later = tmp_path / run.run_id / "Hopper-v4__cascade__3__1790000002"
    later.mkdir()
    (later / "iteration_1.pt").write_bytes(b"x")
    assert run.command("python", str(tmp_path))[2:4] == ["--resume", str(later)]
    assert sweep.how_far(run.command("python", str(tmp_path))) == (
        f"cannot resume {later} by itself: its checkpoint.pt is gone; the run will stop naming the iteration_<i>.pt "
        "beside it to continue from")


def test_rerun_with_other_budget_starts_a_new_run(tmp_path):
    """Issue 18: a re-run into the same sweep folder with another --scale used to resume the first run's
    checkpoint and mark the new setup done after 2048 of ~4096 steps."""
    common = ["--command", "ppo_baseline.py --total-timesteps 20480000 --eval-every 0 --checkpoint-every 0",
              "--envs", "InvertedPendulum-v4", "--workers", "1", "--sweep-dir", tmp_path]
    first = run_script("sweep.py", *common, "--scale", "0.0001")
    assert first.returncode == 0, first.stdout + first.stderr
    second = run_script("sweep.py", *common, "--scale", "0.0002")
    assert second.returncode == 0, second.stdout + second.stderr
    assert "0 already finished, 1 to run" in second.stdout
    markers = sorted(os.listdir(tmp_path / "done"))
    assert len(markers) == 2
    logs = {m: open(tmp_path / "logs" / m.replace(".json", ".log")).read() for m in markers}
    assert not any("--resume" in log for log in logs.values()), logs
    updates = {}
    for marker in markers:  # each setup has its own run folder, trained for the budget it asked for
        budget = int(json.load(open(tmp_path / "done" / marker))["flags"][1])
        folders = os.listdir(tmp_path / "runs" / marker[:-5])
        assert len(folders) == 1
        updates[budget] = len(read_scalars(str(tmp_path / "runs" / marker[:-5] / folders[0]))["charts/learning_rate"])
    assert updates == {2048: 1, 4096: 2}


def test_local_sweep_reports_failure_and_skips_finished_runs(tmp_path):
    args = ["--command", TINY + " --exp-name good_a", TINY + " --gamma 0.98 --exp-name good_b",
            TINY + " --learning-rate 1e30 --exp-name broken",  # (fails as it trains: past the sweep's checks)
            "--envs", "Hopper-v4", "--seeds", "1", "--workers", "2", "--sweep-dir", tmp_path]
    first = run_script("sweep.py", *args)
    assert first.returncode == 1, first.stdout + first.stderr
    assert "2 of 3 runs done" in first.stdout and "1 failed" in first.stdout
    assert "FAILED Hopper-v4__broken__1__" in first.stdout and str(tmp_path / "logs") in first.stdout
    # the summary carries the run's one-line error, so a grid's failures read without opening each log
    [failed] = [line for line in first.stdout.splitlines() if line.startswith("  FAILED")]
    assert "(exit 1): error: the loss became non-finite" in failed, failed
    broken_logs = [f for f in os.listdir(tmp_path / "logs") if "broken" in f]
    assert len(broken_logs) == 1
    assert "the loss became non-finite" in open(tmp_path / "logs" / broken_logs[0]).read()
    assert len(os.listdir(tmp_path / "done")) == 2
    assert sorted(d.split("__")[1] for d in os.listdir(tmp_path / "runs")) == ["broken", "good_a", "good_b"]
    for setup in os.listdir(tmp_path / "runs"):  # one run folder inside each setup's folder
        assert len(os.listdir(tmp_path / "runs" / setup)) == 1

    again = run_script("sweep.py", *args)
    assert again.returncode == 1
    assert "2 already finished, 1 to run" in again.stdout
    assert all(len(os.listdir(tmp_path / "runs" / setup)) == 1 for setup in os.listdir(tmp_path / "runs"))


def test_bad_input(tmp_path):
    cases = [(["--command", TINY, "--scale", "0"], "--scale must be positive"),
             (["--command", TINY, "--scale", "-1"], "--scale must be positive"),
             (["--command", TINY, "--workers", "0"], "--workers must be at least 1"),
             (["--preset", "nope"], "unknown preset 'nope'"),
             (["--command", "train.py --n 2"], "unknown script"),
             (["--preset", "standard", "--seeds", "1", "two"], "--seeds must be integers"),
             ([], "nothing to run"),
             # tyro keeps a repeated list flag's last values only: a grid smaller than asked for
             (["--preset", "sac", "--preset", "ddpg", "--dry-run"], "--preset is given 2 times, and only its last values"),
             (["--command", TINY, "--command", TINY, "--dry-run"], "--command is given 2 times"),
             (["--preset", "sac", "--seeds", "1", "--seeds=2", "--dry-run"], "--seeds is given 2 times"),
             (["--preset", "sac", "--envs", "Hopper-v4", "--envs", "Walker2d-v4", "--dry-run"], "--envs is given 2 times")]
    for extra, message in cases:
        proc = run_script("sweep.py", *extra, "--sweep-dir", tmp_path)
        assert proc.returncode != 0 and message in proc.stderr, (extra, proc.stderr)
    proc = run_script("sweep.py", "--command", TINY, "--sweep-dir", "", "--dry-run")
    assert proc.returncode != 0 and "--sweep-dir is empty" in proc.stderr, proc.stderr
    # a folder that cannot be made: one line about --sweep-dir (it named each run's --track-dir, never given)
    line = error_line(run_script("sweep.py", "--command", TINY, "--sweep-dir", "/proc/x", "--dry-run"))
    assert line.startswith("error: --sweep-dir /proc/x cannot be made or written"), line
    with socket.socket() as s:  # a port with nothing listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    # a hang would raise subprocess.TimeoutExpired (the script gives up after 5 s; the bound is generous)
    proc = run_script("sweep.py", "--command", TINY, "--backend", "ray", "--ray-address", f"127.0.0.1:{port}",
                      "--sweep-dir", tmp_path, timeout=120)
    assert proc.returncode != 0 and "no Ray head answers" in proc.stderr


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_port_range(size: int) -> int:
    """The first port of `size` consecutive ports that are free now (for Ray's worker ports)."""
    for low in range(20000, 60000, size):
        try:
            sockets = []
            for p in range(low, low + size):
                s = socket.socket()
                sockets.append(s)
                s.bind(("127.0.0.1", p))
            return low
        except OSError:
            continue
        finally:
            for s in sockets:
                s.close()
    pytest.skip("no range of free ports for Ray's workers on this machine")


def test_ray_sweep_on_a_real_local_head(tmp_path):
    ray_bin = os.path.join(os.path.dirname(sys.executable), "ray")
    port = free_port()
    # Ray's socket paths must stay short (a deep $TMPDIR can exceed the 107-byte limit of a Unix socket path)
    temp_dir = tempfile.mkdtemp(prefix="ray", dir="/tmp" if os.path.isdir("/tmp") else None)
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    # every port Ray opens is a free one of this machine, not a default that another process may hold
    ports = ["--node-manager-port", "--object-manager-port", "--ray-client-server-port", "--metrics-export-port",
             "--dashboard-agent-listen-port", "--dashboard-agent-grpc-port", "--runtime-env-agent-port"]
    port_flags = [item for flag in ports for item in (flag, str(free_port()))]
    low = free_port_range(64)
    start = subprocess.run([ray_bin, "start", "--head", "--node-ip-address", "127.0.0.1", "--port", str(port),
                            "--num-cpus", "2", "--include-dashboard=false", "--disable-usage-stats",
                            "--object-store-memory", "100000000", "--temp-dir", temp_dir, *port_flags,
                            "--min-worker-port", str(low), "--max-worker-port", str(low + 63)],
                           capture_output=True, text=True, env=env, timeout=120)
    assert start.returncode == 0, start.stderr[-2000:]
    try:
        proc = run_script("sweep.py", "--command", TINY, "--envs", "Hopper-v4", "--seeds", "1", "2",
                          "--backend", "ray", "--ray-address", f"127.0.0.1:{port}", "--sweep-dir", tmp_path,
                          env={"RAY_USAGE_STATS_ENABLED": "0"})
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
        assert "2 of 2 runs done" in proc.stdout
        assert len(os.listdir(tmp_path / "done")) == 2 and len(os.listdir(tmp_path / "runs")) == 2
    finally:
        subprocess.run([ray_bin, "stop", "--force"], capture_output=True, env=env, timeout=120)


def test_progress_eta_is_a_duration_that_can_pass_a_day(capsys):
    tracker = sweep.Tracker(total=5, parallel=1, every=0)
    run = sweep.expand(sweep.Args(preset=["reproduce"], envs=["Hopper-v4"], seeds=["1"]))[0]
    tracker.started(run)
    tracker.finished(run, 0, "log", seconds=7 * 3600 + 5 * 60)  # 4 runs left at 7 h 05 min each: 28 h 20 min
    assert "ETA about 28 h 20 min left" in capsys.readouterr().out


LONG = ("cascade_ppo_continuous.py --n 1 --k 1000000 --num-steps 256 --num-minibatches 4 --update-epochs 1 "
        "--eval-every 0 --checkpoint-every 256 --quiet")


def test_a_sweep_folder_has_one_sweep_and_a_killed_sweeps_runs_stop(tmp_path):
    """Issue 49.2: a sweep killed with SIGKILL left its runs running, and a second sweep on the same folder then
    trained the same run beside it (or removed the folder of a run not yet checkpointed). Now the folder is locked
    for a sweep's lifetime (and its runs'), and the runs of a killed sweep get SIGTERM and stop at their checkpoint."""
    import glob
    import time

    args = [sys.executable, os.path.join(ROOT, "sweep.py"), "--command", LONG, "--envs", "InvertedPendulum-v4",
            "--workers", "1", "--status-every", "3600", "--sweep-dir", str(tmp_path)]
    first = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 300
        while not glob.glob(str(tmp_path / "runs" / "*" / "*" / "checkpoint.pt")):
            assert first.poll() is None and time.time() < deadline, "the first sweep's run wrote no checkpoint"
            time.sleep(0.1)
        (events,) = glob.glob(str(tmp_path / "runs" / "*" / "*" / "events.out.tfevents.*"))
        run_pid = int(os.path.basename(events).split(".")[-2])
        second = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            out, err = second.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            second.kill()
            second.communicate()
            pytest.fail("a second sweep on the same folder ran beside the first")
        lines = [line for line in err.splitlines() if line.strip()]
        assert second.returncode == 1 and len(lines) == 1, err
        assert lines[0] == (f"error: another sweep (pid {first.pid}) is using {tmp_path}; wait for it to end, or "
                            f"stop it (kill {first.pid}) and run this again"), lines[0]
        assert out == ""  # it changed nothing (no start line: nothing removed, no run started)
        first.kill()  # SIGKILL: no handler of the sweep runs
        first.wait()
        deadline = time.time() + 120
        while os.path.exists(f"/proc/{run_pid}") and not open(f"/proc/{run_pid}/stat").read().split()[2] == "Z":
            assert time.time() < deadline, "the killed sweep's run is still running"
            time.sleep(0.1)
    finally:
        if first.poll() is None:
            first.kill()
    (log,) = glob.glob(str(tmp_path / "logs" / "*.log"))
    with open(log) as f:
        assert "stopped by SIGTERM: the last checkpoint is" in f.read()  # it stopped cleanly, at its checkpoint
    # the folder is free again once the run's own children (its evaluation worker, which inherited the lock too and
    # dies with the run) have exited: under load that can take a moment after the run itself
    deadline = time.time() + 120
    while True:
        try:
            os.close(sweep.lock_sweep_dir(str(tmp_path)))
            break
        except SystemExit as refused:
            assert "are still stopping" in str(refused) and time.time() < deadline, str(refused)
            time.sleep(0.1)
    assert not os.path.exists(tmp_path / "done")


def test_a_failed_runs_summary_line_is_the_reason_inside_a_parse_errors_box(tmp_path, capsys):
    """Audit: a run stopped by tyro's parse error (a resumed run's flags, which the up-front check does not see)
    was summarized by the box's bottom border line."""
    import contextlib
    import io

    import tyro

    import cascade_sac

    box = io.StringIO()
    with contextlib.redirect_stderr(box), pytest.raises(SystemExit):
        tyro.cli(cascade_sac.Args, args=["--bogus"])
    log = tmp_path / "run.log"
    log.write_text("global_step=0, eval/episodic_return=36.1\n" + box.getvalue())
    assert sweep.last_line(str(log)) == "Unrecognized options: --bogus"
    # as tyro draws it on a terminal (a box, its title in the top border)
    log.write_text("global_step=0\n\u256d\u2500 Value error \u2500\u2500\u2500\u256e\n"
                   "\u2502 Error parsing --k: invalid literal for int() with base 10: 'abc' \u2502\n"
                   "\u2502 \u2500\u2500\u2500\u2500\u2500\u2500 \u2502\n\u2502 Argument helptext: \u2502\n"
                   "\u2502 \u2500\u2500\u2500\u2500\u2500\u2500 \u2502\n"
                   "\u2502 For full helptext, see cascade_sac.py --help \u2502\n"
                   "\u2570\u2500\u2500\u2500\u2500\u2500\u2500\u256f\n")
    assert sweep.last_line(str(log)) == "Error parsing --k: invalid literal for int() with base 10: 'abc'"
    log.write_text("error: --n must be at least 1 (got 0)\n")
    assert sweep.last_line(str(log)) == "error: --n must be at least 1 (got 0)"


def test_each_running_runs_progress_shows_in_the_sweeps_progress_lines(tmp_path, capsys):
    """A sweep of runs that take hours said "ETA ?" until the first one ended. Each run now keeps its progress line
    in its folder (also with --quiet, as the sweep runs it), and the sweep's progress lines show it per running
    run."""
    from cascade_plumbing.tracking import PROGRESS_NAME, Progress

    progress_file = tmp_path / "progress.txt"
    progress = Progress(2_000_000, quiet=True, file=str(progress_file))
    progress.update(500_000, 100.0, 2)
    assert capsys.readouterr().out == ""  # quiet: nothing printed, the file written all the same
    assert progress_file.read_text().startswith("500,000/2,000,000 steps ( 25.0%) |    100 SPS | 2 net(s)")
    assert "ETA about 4 h 10 min left" in progress_file.read_text()

    (run,) = sweep.expand(sweep.Args(command=["cascade_sac.py --n 2"], envs=["Hopper-v4"]))
    run_folder = tmp_path / "runs" / run.run_id / "Hopper-v4__cascade_sac_1__1__1700000000"
    run_folder.mkdir(parents=True)
    (run_folder / PROGRESS_NAME).write_text(progress_file.read_text())
    tracker = sweep.Tracker(1, 1, every=30.0)
    tracker.runs_dir = str(tmp_path / "runs")
    tracker.started(run)
    tracker.report(force=True)
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("[sweep] 0 done, 1 running") and lines[1].startswith(
        f"  {run.run_id}: 500,000/2,000,000 steps ( 25.0%)"), lines


def test_a_quiet_run_keeps_its_progress_line_in_its_folder(tmp_path):
    import cascade_ppo_continuous as cpc

    run_dir = cpc.train(cpc.Args(env_id="Hopper-v4", n=1, k=512, num_steps=256, num_minibatches=4, update_epochs=1,
                                 eval_every=0, quiet=True, track_dir=str(tmp_path)))["run_dir"]
    line = open(os.path.join(run_dir, "progress.txt")).read()
    # the finished run's last line (a periodic write alone left it at the first update's, "256/512 steps")
    assert line.startswith("512/512 steps (100.0%) |") and "SPS" in line and "| 1 net(s) |" in line, line


def test_a_second_stop_of_the_sweep_passes_on_to_its_runs(monkeypatch):
    """A first stop ends the sweep's wait (its runs get SIGTERM from it: a SAC or DDPG run then writes a checkpoint
    at its next step); a second one, while the sweep waits for them, was ignored and could not hurry them: it now
    sends each running run SIGTERM again, which stops it at once."""
    import signal

    sent = []

    class Run:
        def send_signal(self, signum):
            sent.append(signum)

    monkeypatch.setattr(sweep, "STOP", [])
    monkeypatch.setattr(sweep, "RUNNING", {Run()})
    with pytest.raises(KeyboardInterrupt):
        sweep.interrupt(signal.SIGINT, None)
    assert sent == [] and sweep.STOP == [signal.SIGINT]
    sweep.interrupt(signal.SIGINT, None)
    assert sent == [signal.SIGTERM]


def test_a_dry_run_says_how_far_each_run_is(tmp_path):
    """A sweep of hours-long runs stopped and started across days: --dry-run said which runs resume, not how far
    they are (the TensorBoard files had to be read for that). Now each run's line says it: a new run, a stopped one
    with the step it resumes at (its checkpoint's), or one training now with the progress line it keeps (or, from
    a run without one, its last checkpoint's step); a new run training towards its first checkpoint was a "new run"."""
    import torch

    from cascade_plumbing.tracking import PROGRESS_NAME

    sweep_dir = tmp_path / "sweep"
    runs = sweep.expand(sweep.Args(preset=["sac"], envs=["Hopper-v4"], seeds=["1", "2", "3"]))
    cascade_1, baseline_1, cascade_2, baseline_3 = (r for r in runs if (r.label, r.seed) not in (("sac", 2),
                                                                                              ("cascade_sac", 3)))
    folders = {}
    for run in (cascade_1, baseline_1, cascade_2, baseline_3):
        folders[run.run_id] = sweep_dir / "runs" / run.run_id / f"Hopper-v4__{run.label}__{run.seed}__1790000000"
        folders[run.run_id].mkdir(parents=True)
    torch.save({"global_step": 650_000, "args": {"n": 4, "k": 500_000}},
               folders[cascade_1.run_id] / "checkpoint.pt")
    torch.save({"global_step": 50_000, "args": {"n": 1, "k": 2_000_000}}, folders[baseline_1.run_id] / "checkpoint.pt")
    torch.save({"global_step": 100_000, "args": {"n": 4, "k": 500_000}}, folders[cascade_2.run_id] / "checkpoint.pt")
    (folders[baseline_1.run_id] / PROGRESS_NAME).write_text("steps 61,000/2,000,000 | SPS 95 | ETA 5.7h\n")
    # three runs training now: each holds its folder's lock, as a run does (one keeps a progress line, one does not,
    # one has written no checkpoint yet)
    holders = []
    for run in (baseline_1, cascade_2, baseline_3):
        lock = folders[run.run_id] / "run.lock"
        holders.append(subprocess.Popen([sys.executable, "-c", f"""if True:
            import fcntl, os, sys, time
            fd = os.open({str(lock)!r}, os.O_RDWR | os.O_CREAT)
            fcntl.lockf(fd, fcntl.LOCK_EX)
            os.write(fd, f"{{os.getpid()}}\\n".encode())
            print("locked", flush=True)
            time.sleep(120)"""], stdout=subprocess.PIPE, text=True))
    try:
        for holder in holders:
            assert holder.stdout.readline().strip() == "locked"
        proc = run_script("sweep.py", "--preset", "sac", "--envs", "Hopper-v4", "--seeds", "1", "2", "3",
                          "--sweep-dir", sweep_dir, "--dry-run")
    finally:
        for holder in holders:
            holder.kill()
    assert proc.returncode == 0, proc.stderr[-2000:]
    said = {line.split(": ", 1)[0][2:]: line.split(": ", 1)[1] for line in proc.stdout.splitlines()
            if line.startswith("# ") and "__" in line.split(": ", 1)[0]}
    assert said[cascade_1.run_id].startswith("stopped; resumes at global_step 650,000 of 2,000,000 (its checkpoint of ")
    assert said[baseline_1.run_id] == f"training now (pid {holders[0].pid}): steps 61,000/2,000,000 | SPS 95 | ETA 5.7h"
    assert said[cascade_2.run_id].startswith(f"training now (pid {holders[1].pid}); its last checkpoint is at "
                                             "global_step 100,000 of 2,000,000")
    assert said[baseline_3.run_id] == f"training now (pid {holders[2].pid}), before its first checkpoint"
    for new in (r for r in runs if (r.label, r.seed) in (("sac", 2), ("cascade_sac", 3))):
        assert said[new.run_id] == "new run"
