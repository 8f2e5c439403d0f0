"""Bad settings shared by every training script are refused in one line, before anything is written
(issue 18: these gave tracebacks, left run folders, or were silently accepted)."""

import importlib

import pytest

from helpers import error_line, error_line_in_process, run_script

SCRIPTS = ["cascade_ppo_continuous", "ppo_baseline", "cascade_ppo_discrete", "ppo_baseline_discrete", "cascade_sac",
           "cascade_ddpg"]
PPO = SCRIPTS[:4]
ENV = {"cascade_ppo_discrete": "CartPole-v1", "ppo_baseline_discrete": "CartPole-v1"}


def cases(script):
    rates = {"cascade_sac": [("policy_lr", "--policy-lr"), ("q_lr", "--q-lr")]}.get(script, [("learning_rate",
                                                                                                "--learning-rate")])
    out = [(dict(seed=-1), "--seed must be a non-negative integer"),
           (dict(torch_threads=0), "--torch-threads must be at least 1")]
    if script not in ("cascade_sac", "cascade_ddpg"):  # they checkpoint at iteration ends only
        out.append((dict(checkpoint_every=-1), "--checkpoint-every must be >= 0"))
    out += [({field: -1.0}, f"{flag} must be >= 0") for field, flag in rates]
    if script in PPO:
        out += [(dict(num_minibatches=0), "--num-minibatches and --update-epochs must be at least 1"),
                (dict(update_epochs=0), "--num-minibatches and --update-epochs must be at least 1")]
    return out


@pytest.mark.parametrize("script,overrides,message",
                         [(s, o, m) for s in SCRIPTS for o, m in cases(s)],
                         ids=[f"{s}-{next(iter(o))}" for s in SCRIPTS for o, _ in cases(s)])
def test_bad_setting_is_one_line_and_leaves_nothing(script, overrides, message, tmp_path):
    module = importlib.import_module(script)
    args = module.Args(env_id=ENV.get(script, "Hopper-v4"), track_dir=str(tmp_path / "runs"), **overrides)
    with pytest.raises(SystemExit) as stop:
        module.train(args)
    text = str(stop.value)
    assert text.startswith("error:") and message in text and "\n" not in text, text
    assert not (tmp_path / "runs").exists()
    assert list(tmp_path.iterdir()) == []  # the writability probe leaves nothing behind


@pytest.mark.parametrize("script", SCRIPTS)
def test_track_dir_must_be_a_writable_folder(script, tmp_path):
    module = importlib.import_module(script)
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for track_dir, message in [(a_file, "is a file, not a folder"), (a_file / "runs", "cannot create run folders")]:
        args = module.Args(env_id=ENV.get(script, "Hopper-v4"), track_dir=str(track_dir))
        with pytest.raises(SystemExit) as stop:
            module.train(args)
        assert message in str(stop.value) and "\n" not in str(stop.value), str(stop.value)


@pytest.mark.parametrize("script", SCRIPTS)
def test_evaluate_with_no_episodes_is_refused(script, tmp_path):
    module = importlib.import_module(script)
    with pytest.raises(SystemExit) as stop:
        module.evaluate_saved(module.Args(evaluate=str(tmp_path / "nope"), eval_episodes=0))
    assert "--eval-episodes must be at least 1" in str(stop.value)


def test_num_envs_that_break_the_batch_say_which_work(tmp_path):
    line = error_line(run_script("cascade_ppo_continuous.py", "--num-envs", "3", "--track-dir", tmp_path / "runs"))
    assert "2046" in line and "--num-envs 1, 2, 4, 8, 16 work" in line
    assert not (tmp_path / "runs").exists()


def range_cases(script):
    """Issue 49.5: values each script took and trained with until the non-finite guard stopped the run (inf, NaN),
    or accepted silently (a negative exploration noise)."""
    nan, inf = float("nan"), float("inf")
    rate = {"cascade_sac": "policy_lr"}.get(script, "learning_rate")
    out = [({rate: inf}, f"--{rate.replace('_', '-')} must be a finite number (got inf)"),
           (dict(gamma=nan), "--gamma must be a finite number (got nan)"),
           (dict(gamma=1.5), "--gamma must lie in [0, 1] (got 1.5)")]
    if script in PPO:
        out += [(dict(clip_coef=nan), "--clip-coef must be a finite number (got nan)"),
                (dict(clip_coef=0.0), "--clip-coef must be > 0 (got 0.0)"),
                (dict(gae_lambda=-0.1), "--gae-lambda must lie in [0, 1] (got -0.1)"),
                (dict(target_kl=-inf), "--target-kl must be a finite number (got -inf)")]
    if script == "cascade_sac":
        out += [(dict(alpha=nan), "--alpha must be a finite number (got nan)"),
                (dict(alpha=-0.2), "--alpha must be >= 0 (got -0.2)"),
                (dict(q_lr=inf), "--q-lr must be a finite number (got inf)"),
                (dict(tau=0.0), "--tau must lie in (0, 1] (got 0.0)")]
    if script == "cascade_ddpg":
        out += [(dict(exploration_noise=nan), "--exploration-noise must be a finite number (got nan)"),
                (dict(exploration_noise=-0.1), "--exploration-noise must be >= 0 (got -0.1)")]
    return out


@pytest.mark.parametrize("script,overrides,message",
                         [(s, o, m) for s in SCRIPTS for o, m in range_cases(s)],
                         ids=[f"{s}-{next(iter(o))}-{next(iter(o.values()))}" for s in SCRIPTS for o, _ in range_cases(s)])
def test_a_setting_outside_its_range_is_one_line_and_leaves_nothing(script, overrides, message, tmp_path):
    test_bad_setting_is_one_line_and_leaves_nothing(script, overrides, message, tmp_path)


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_non_finite_learning_rate_on_the_command_line_is_one_line(script, tmp_path):
    """As a user meets it: `--learning-rate inf` (SAC: `--policy-lr`), one line, exit 1, no run folder."""
    flag = "--policy-lr" if script == "cascade_sac" else "--learning-rate"
    line = error_line_in_process(f"{script}.py", "--env-id", ENV.get(script, "Hopper-v4"), flag, "inf",
                                 "--track-dir", str(tmp_path / "runs"))
    assert line == f"error: {flag} must be a finite number (got inf)"
    assert not (tmp_path / "runs").exists()
