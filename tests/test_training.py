"""The training loops as a user runs them: iterations, logging, bad input, learning."""


import os

import gymnasium as gym
import numpy as np
import pytest
import torch

import cascade_ppo_continuous as cpc
import learning_checks
from cascade_plumbing.envs import OBS_CLIP, find_wrapper
from helpers import cli_in_process, error_line, error_line_in_process, only_run_dir, read_scalars, run_script

TINY = dict(num_steps=256, num_minibatches=4, update_epochs=2)


def test_each_iteration_gets_fresh_critic_and_optimizer_and_keeps_normalization(tmp_path):
    seen = []

    def record(state):
        norm = find_wrapper(state["envs"].envs[0], gym.wrappers.NormalizeObservation)
        rew = find_wrapper(state["envs"].envs[0], gym.wrappers.NormalizeReward)
        seen.append(dict(
            iteration=state["iteration"], size=state["actor"].size, critic=state["critic"],
            critic_params=[p.detach().clone() for p in state["critic"].parameters()],
            optimizer=state["optimizer"], adam_state=len(state["optimizer"].state),
            optimized=sum(p.numel() for g in state["optimizer"].param_groups for p in g["params"]),
            model_numel=cpc.count_parameters(state["actor"], state["critic"]),
            norm=norm, obs_count=float(norm.obs_rms.count), obs_mean=norm.obs_rms.mean.copy(),
            rew_count=float(rew.return_rms.count), lr=state["optimizer"].param_groups[0]["lr"],
        ))

    args = cpc.Args(env_id="Hopper-v4", n=3, k=512, eval_every=0, track_dir=str(tmp_path), **TINY)
    cpc.train(args, on_iteration_start=record)
    assert [s["size"] for s in seen] == [1, 2, 3]
    for prev, cur in zip(seen, seen[1:]):
        assert cur["critic"] is not prev["critic"]
        assert cur["optimizer"] is not prev["optimizer"]
        assert cur["adam_state"] == 0  # fresh Adam: no moments carried over
        # the fresh critic is a new random init, not the trained one
        assert any(not torch.equal(a, b) for a, b in zip(cur["critic_params"], prev["critic_params"]))
        # normalization: same wrapper, statistics accumulated over the previous iteration, not reset
        assert cur["norm"] is prev["norm"]
        assert cur["obs_count"] >= prev["obs_count"] + 512
        assert cur["rew_count"] >= prev["rew_count"] + 512
        assert not np.allclose(cur["obs_mean"], prev["obs_mean"])
    # the optimizer covers every parameter of every base net (all trainable) and of the new critic
    assert all(s["optimized"] == s["model_numel"] for s in seen)


def test_cascade_run_writes_expected_scalars_and_cycles_the_lr(tmp_path, capsys):
    code, out, error = cli_in_process(capsys, "cascade_ppo_continuous.py", "--env-id", "Hopper-v4", "--n", "3",
                                      "--k", "1024", "--num-steps", "256", "--num-minibatches", "4", "--update-epochs",
                                      "2", "--eval-every", "1024", "--eval-episodes", "2", "--track-dir", tmp_path)
    assert code == 0, error
    from test_method import cascade_parameters  # from the layer sizes; Hopper-v4: obs 11, action 3

    for size in (1, 2, 3):  # the parameter count (actor + critic) is printed per iteration
        assert f"{cascade_parameters(11, 3, size)} parameters" in out, out[-2000:]
    scalars = read_scalars(only_run_dir(tmp_path))
    for tag in ["charts/episodic_return", "charts/SPS", "charts/learning_rate", "losses/value_loss",
                "losses/policy_loss", "losses/entropy", "losses/approx_kl", "eval/episodic_return",
                "eval/episodic_return_std", "cascade/size", "cascade/parameters", "cascade/fallback/net_2",
                "cascade/fallback/net_3", "cascade/fallback_product", "cascade/contribution/net_1",
                "cascade/contribution/net_3", "cascade/fallback_std/net_2", "cascade/fallback_std/net_3"]:
        assert tag in scalars, f"missing {tag}; have {sorted(scalars)}"
    # evaluation at step 0 and every 1024 steps, 4 updates per iteration of 1024 steps
    assert [s for s, _ in scalars["eval/episodic_return"]] == [0, 1024, 2048, 3072]
    lrs = [v for _, v in scalars["charts/learning_rate"]]
    assert len(lrs) == 12
    expected = [3e-4 * (1 - u / 4) for u in range(4)] * 3  # restarts at every new base net
    np.testing.assert_allclose(lrs, expected, rtol=1e-5)
    assert [v for _, v in scalars["cascade/size"]][-1] == 3
    # contributions of the logged nets sum to one at each update of the 3-net stack
    last = {tag: scalars[tag][-1][1] for tag in scalars if tag.startswith("cascade/contribution/")}
    assert abs(sum(last.values()) - 1.0) < 1e-4
    assert abs(scalars["cascade/fallback_product"][-1][1] - last["cascade/contribution/net_1"]) < 1e-6


def test_parameter_count_is_logged_per_iteration(tmp_path):
    args = cpc.Args(env_id="Hopper-v4", n=6, k=256, eval_every=0, track_dir=str(tmp_path), **TINY)
    cpc.train(args)
    scalars = read_scalars(only_run_dir(tmp_path))
    counts = [v for _, v in scalars["cascade/parameters"]]
    assert counts[-1] == 8186  # Table 2, Hopper-v4
    assert counts == sorted(counts) and len(set(counts)) == 6


def test_baseline_run_writes_expected_scalars(tmp_path, capsys):
    code, out, error = cli_in_process(capsys, "ppo_baseline.py", "--env-id", "Hopper-v4", "--total-timesteps", "2048",
                                      "--num-steps", "512", "--num-minibatches", "4", "--update-epochs", "2",
                                      "--lr-schedule", "cyclic", "--cycle-steps", "1024",
                                      "--eval-every", "1024", "--eval-episodes", "2", "--track-dir", tmp_path)
    assert code == 0, error
    assert "10119 parameters" in out  # Table 2, Hopper-v4 PPO
    scalars = read_scalars(only_run_dir(tmp_path))
    for tag in ["charts/episodic_return", "charts/SPS", "charts/learning_rate", "losses/value_loss",
                "eval/episodic_return", "eval/episodic_return_std"]:
        assert tag in scalars
    np.testing.assert_allclose([v for _, v in scalars["charts/learning_rate"]],
                               [3e-4, 1.5e-4, 3e-4, 1.5e-4], rtol=1e-5)


def test_frozen_eval_normalization_equals_the_training_wrapper():
    env = cpc.make_env("Hopper-v4", 0.99, True)()
    env.reset(seed=0)
    for _ in range(50):
        raw_next, *_ = env.unwrapped.step(env.action_space.sample())  # advance the sim, bypassing wrappers
        wrapped, *_ = env.step(env.action_space.sample())
    norm = find_wrapper(env, gym.wrappers.NormalizeObservation)
    norm.update_running_mean = False
    stats = (norm.obs_rms.mean.copy(), norm.obs_rms.var.copy())
    raw = np.random.default_rng(0).normal(size=env.observation_space.shape) * 5
    through_wrappers = np.clip(norm.observation(raw), -OBS_CLIP, OBS_CLIP)
    np.testing.assert_allclose(cpc.normalize_obs(raw[None], stats)[0], through_wrappers, rtol=1e-6, atol=1e-6)


BAD_INPUT = [
    (["--env-id", "Hoper-v4"], "unknown env id"),
    (["--env-id", "CartPole-v1"], "cascade_ppo_discrete.py"),
    (["--n", "0"], "--n must be at least 1"),
    (["--k", "1000"], "smaller than one rollout batch"),
    (["--fallback-init", "1.0"], "--fallback-init"),
    (["--fallback-init", "0"], "--fallback-init"),
]


@pytest.mark.parametrize("extra,message", BAD_INPUT)
def test_bad_input_is_one_clear_line(tmp_path, extra, message):
    assert message in error_line_in_process("cascade_ppo_continuous.py", "--track-dir", tmp_path / "runs", *extra)
    assert not (tmp_path / "runs").exists()


def test_bad_input_on_the_command_line_is_one_line_and_exits_nonzero(tmp_path):
    """One case through a real interpreter: the line on stderr, the exit code, nothing written."""
    assert "unknown env id" in error_line(run_script("cascade_ppo_continuous.py", "--track-dir", tmp_path / "runs",
                                                     "--env-id", "Hoper-v4"))
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("extra,message", [(["--env-id", "Pendulum-v9"], "unknown env id"),
                                          (["--env-id", "Acrobot-v1"], "Box"),
                                          (["--total-timesteps", "100"], "smaller than one rollout batch")])
def test_baseline_bad_input(tmp_path, extra, message):
    argv = ["ppo_baseline.py", "--track-dir", tmp_path / "runs", *extra]
    if extra[1] == "Pendulum-v9":  # one case through a real interpreter: stderr and the exit code
        line = error_line(run_script(*argv))
    else:
        line = error_line_in_process(*argv)
    assert message in line
    assert not (tmp_path / "runs").exists()


def test_help_documents_every_flag(capsys):
    code, out, _ = cli_in_process(capsys, "cascade_ppo_continuous.py", "--help")
    assert code == 0
    for flag in ["--n", "--k", "--freeze-previous", "--start-full", "--lr-schedule", "--fallback-init",
                 "--hidden-size", "--num-layers", "--no-normalize", "--eval-every", "--eval-episodes"]:
        assert flag in out


@pytest.mark.parametrize("overrides", [dict(freeze_previous=True), dict(start_full=True),
                                       dict(lr_schedule="global"),
                                       dict(normalize=False, hidden_size=1, num_layers=1)])
def test_ablations_run(tmp_path, overrides):
    args = cpc.Args(env_id="Hopper-v4", n=2, k=256, eval_every=0, track_dir=str(tmp_path), **TINY, **overrides)
    result = cpc.train(args)
    actor, run_dir = result["actor"], result["run_dir"]
    assert actor.size == 2
    scalars = read_scalars(run_dir)
    lrs = [v for _, v in scalars["charts/learning_rate"]]
    np.testing.assert_allclose(lrs, [3e-4, 1.5e-4] if args.lr_schedule == "global" else [3e-4, 3e-4], rtol=1e-5)
    # each ablation does what it says: the net's shape, the stack's size from the start, net 1 kept, no statistics
    hidden = [(11, args.hidden_size)] + [(args.hidden_size, args.hidden_size)] * (args.num_layers - 1)
    assert [tuple(w.shape) for w in actor.hidden_weights] == [(2, *shape) for shape in hidden]
    assert scalars["cascade/size"][0][1] == (2 if args.start_full else 1)
    checkpoint = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)
    assert (checkpoint["obs_stats"] is None) == (not args.normalize)
    first = torch.load(os.path.join(run_dir, "iteration_1.pt"), weights_only=False)["actor"]
    net_1_kept = [torch.equal(param.detach()[0], first[name][0])
                  for name, param, first_net in actor.base_net_parameters() if first_net == 0]
    assert all(net_1_kept) if args.freeze_previous else not any(net_1_kept)


@pytest.mark.slow
@pytest.mark.parametrize("check", ["cascade_ppo_inverted_pendulum", "ppo_inverted_pendulum"])
def test_learns_inverted_pendulum(check, tmp_path):
    """InvertedPendulum-v4, 32K steps (see tests/learning_checks.py for the spread the threshold comes from)."""
    learning_checks.assert_learns(check, str(tmp_path))


def test_evaluation_in_worker_process_matches_inline(tmp_path):
    curves = {}
    for in_worker in (True, False):
        args = cpc.Args(env_id="Hopper-v4", n=2, k=512, eval_every=256, eval_episodes=3, eval_in_worker=in_worker,
                        track_dir=str(tmp_path / str(in_worker)), **TINY)
        scalars = read_scalars(cpc.train(args)["run_dir"])
        curves[in_worker] = {tag: scalars[tag] for tag in scalars
                             if tag.startswith(("eval/", "members/", "cascade/fallback_std"))}
    assert [s for s, _ in curves[True]["eval/episodic_return"]] == [0, 256, 512, 768, 1024]
    assert curves[True] == curves[False]


def test_parallel_envs_keep_the_batch_size(tmp_path):
    args = cpc.Args(env_id="Hopper-v4", n=1, k=2048, num_envs=2, num_minibatches=4, update_epochs=1,
                    eval_every=0, track_dir=str(tmp_path))
    result = cpc.train(args)
    assert args.num_steps == 1024 and result["global_step"] == 2048
    envs = cpc.make_vector_env(args)
    assert isinstance(envs, gym.vector.AsyncVectorEnv)
    envs.reset(seed=0)
    states = envs.call("get_state")
    assert len(states) == 2 and states[0]["sim"] is not None
    envs.close()
