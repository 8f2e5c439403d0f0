"""Bad settings shared by every training script are refused in one line, before anything is written
(issue 18: these gave tracebacks, left run folders, or were silently accepted)."""

import importlib

import pytest

from helpers import error_line, run_script

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
