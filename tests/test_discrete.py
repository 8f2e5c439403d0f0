"""Cascade and PPO on discrete actions: the 2^A discretization, the logits combination, parameter
counts, short runs as a user runs them, bad input, checkpoints (exact resume, --evaluate, --resume
errors), and learning CartPole."""

import os

import gymnasium as gym
import numpy as np
import pytest
import torch

import cascade_ppo_discrete as cpd
import learning_checks
import ppo_baseline_discrete as pbd
from cascade_plumbing.discrete import EvaluationEpisodes
from helpers import (
    cli_in_process,
    copy_checkpoint_when,
    error_line,
    error_line_in_process,
    only_run_dir,
    read_scalars,
    resume_from,
    run_script,
)

TINY = dict(num_steps=128, num_minibatches=4, update_epochs=2)


class RecordingBoxEnv(gym.Env):
    """A one-step env with a given Box action space that remembers the action it received."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def __init__(self, low, high):
        self.action_space = gym.spaces.Box(np.array(low, np.float32), np.array(high, np.float32))
        self.received = None

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2, np.float32), {}

    def step(self, action):
        self.received = np.array(action)
        return np.zeros(2, np.float32), 0.0, True, False, {}


@pytest.mark.parametrize("module", [cpd, pbd])
@pytest.mark.parametrize("low,high", [([-1.0, -0.4], [1.0, 0.7]), ([-1.0, -2.0, 0.0], [0.5, 3.0, 0.25])])
def test_discretization_maps_every_action_to_its_corner(module, low, high):
    inner = RecordingBoxEnv(low, high)
    env = module.DiscretizeAction(inner)
    dims = len(low)
    assert env.action_space == gym.spaces.Discrete(2**dims)
    env.reset(seed=0)
    for i in range(2**dims):
        digits = format(i, f"0{dims}b")  # i_1 ... i_A, most significant first
        # paper Appendix I: a_j = low_j * i_j + high_j * (1 - i_j), i.e. digit "1" -> low, "0" -> high
        expected = [low[j] if digits[j] == "1" else high[j] for j in range(dims)]
        env.step(i)
        np.testing.assert_array_equal(inner.received, np.array(expected, np.float32))
        assert inner.action_space.contains(inner.received.astype(np.float32))
    # action 0 is the all-high corner, the last action the all-low one
    np.testing.assert_array_equal(env.action(0), np.array(high, np.float32))
    np.testing.assert_array_equal(env.action(2**dims - 1), np.array(low, np.float32))


@pytest.mark.parametrize("module", [cpd, pbd])
def test_discretization_refuses_too_many_dims(module):
    assert module.MAX_DISCRETIZED_DIMS == 10
    ok = module.DiscretizeAction(RecordingBoxEnv([-1.0] * 10, [1.0] * 10))
    assert ok.action_space.n == 1024
    too_big = gym.spaces.Box(-1.0, 1.0, (11,), np.float32)
    assert "2^11 = 2048" in module.discretize_problem(too_big)
    with pytest.raises(ValueError, match="at most 10 dims"):
        module.DiscretizeAction(RecordingBoxEnv([-1.0] * 11, [1.0] * 11))
    assert "infinite" in module.discretize_problem(gym.spaces.Box(-np.inf, np.inf, (2,), np.float32))


def make_actor(n, obs_dim=5, num_actions=6, hidden=7, layers=2, seed=0):
    torch.manual_seed(seed)
    actor = cpd.CascadeActor(obs_dim, num_actions, hidden, layers, 0.5)
    for _ in range(n):
        actor.add_base_net()
    with torch.no_grad():  # move away from the init so fallbacks differ between nets and states
        for p in actor.parameters():
            p.normal_(0.0, 0.7)
    return actor


def reference_logits(actor, obs):
    """Independent reference: each base net on its own, then C_i = l_i C_{i-1} + (1 - l_i) b_i, net by net."""
    combined = None
    fallbacks, members = [], []
    for i in range(actor.size):
        h = obs
        for w, b in zip(actor.hidden_weights, actor.hidden_biases):
            h = torch.tanh(h @ w[i] + b[i, 0])
        logits = h @ actor.logits_weight[i] + actor.logits_bias[i, 0]
        members.append(logits)
        if i == 0:
            combined = logits
        else:
            lam = torch.sigmoid(h @ actor.fallback_weight[i - 1] + actor.fallback_bias[i - 1, 0])
            fallbacks.append(lam.squeeze(-1))
            combined = lam * combined + (1 - lam) * logits
    return combined, fallbacks, members


@pytest.mark.parametrize("n,layers", [(1, 2), (2, 2), (3, 1), (5, 3)])
def test_logits_combination_matches_plain_loop(n, layers):
    actor = make_actor(n, layers=layers, seed=n)
    obs = torch.randn(32, 5) * 2
    with torch.no_grad():
        logits, fallback, weight = actor(obs)
        ref_logits, ref_fallbacks, ref_members = reference_logits(actor, obs)
        assert logits.shape == (32, 6) and fallback.shape == (n - 1, 32) and weight.shape == (n, 32)
        torch.testing.assert_close(logits, ref_logits, rtol=1e-5, atol=1e-5)
        if n > 1:
            torch.testing.assert_close(fallback, torch.stack(ref_fallbacks), rtol=1e-5, atol=1e-6)
            assert fallback.std() > 0.05  # the randomized nets really mix
        torch.testing.assert_close(weight.sum(0), torch.ones(32))
        for i in range(n):  # each member alone is the loop's b_i
            torch.testing.assert_close(actor.member(obs, i), ref_members[i], rtol=1e-5, atol=1e-5)


def test_new_net_starts_near_uniform_and_at_fallback_init():
    torch.manual_seed(0)
    actor = cpd.CascadeActor(11, 8, 64, 2, 0.9)
    for _ in range(3):
        actor.add_base_net()
    with torch.no_grad():
        logits, fallback, _ = actor(torch.randn(64, 11))
    assert logits.abs().max() < 0.1  # output gain 0.01: near-uniform Categorical
    assert (fallback - 0.9).abs().max() < 0.02


def test_parameter_counts_by_hand():
    # tiny: obs 3, 4 actions, one hidden layer of 5, three nets
    actor = cpd.CascadeActor(3, 4, 5, 1, 0.5)
    for _ in range(3):
        actor.add_base_net()
    per_net = (3 * 5 + 5) + (5 * 4 + 4)  # hidden layer + logits layer
    fallback_head = 5 + 1  # nets 2 and 3 only
    assert cpd.count_parameters(actor) == 3 * per_net + 2 * fallback_head == 144
    critic = (3 * 64 + 64) + (64 * 64 + 64) + (64 + 1)
    assert cpd.count_parameters(cpd.make_critic(3)) == critic == 4481
    # discretized Hopper-v4 (obs 11, 2^3 = 8 actions): two 64-64 Cascade nets, and the PPO baseline
    hopper_net = (11 * 64 + 64) + (64 * 64 + 64) + (64 * 8 + 8)
    hopper_critic = (11 * 64 + 64) + (64 * 64 + 64) + (64 + 1)
    actor = cpd.CascadeActor(11, 8, 64, 2, 0.5)
    actor.add_base_net()
    actor.add_base_net()
    assert cpd.count_parameters(actor, cpd.make_critic(11)) == 2 * hopper_net + 65 + hopper_critic == 15954
    assert pbd.count_parameters(pbd.make_actor(11, 8, 64), pbd.make_critic(11)) == hopper_net + hopper_critic == 10441


def test_normalization_and_discretization_follow_the_env():
    assert cpd.resolve(cpd.Args(env_id="CartPole-v1")) == (False, False)  # CleanRL ppo.py: no normalization
    assert cpd.resolve(cpd.Args(env_id="Hopper-v4")) == (True, True)  # the paper's code: normalized
    assert cpd.resolve(cpd.Args(env_id="Hopper-v4", normalize=False)) == (True, False)
    assert pbd.resolve(pbd.Args(env_id="CartPole-v1", discretize="off")) == (False, False)
    assert pbd.resolve(pbd.Args(env_id="Hopper-v4", discretize="on")) == (True, True)
    assert pbd.resolve(pbd.Args(env_id="Hopper-v4", discretize="on", normalize=False)) == (True, False)


def test_each_iteration_gets_fresh_critic_and_optimizer(tmp_path, capsys):
    seen = []

    def record(state):
        seen.append(dict(size=state["actor"].size, critic=state["critic"], optimizer=state["optimizer"],
                         adam_state=len(state["optimizer"].state),
                         optimized=sum(p.numel() for g in state["optimizer"].param_groups for p in g["params"]),
                         model_numel=cpd.count_parameters(state["actor"], state["critic"])))

    args = cpd.Args(env_id="CartPole-v1", n=3, k=512, eval_every=0, track_dir=str(tmp_path), quiet=True, **TINY)
    cpd.train(args, on_iteration_start=record)
    assert capsys.readouterr().out == ""  # --quiet (sweep.py passes it)
    assert [s["size"] for s in seen] == [1, 2, 3]
    for prev, cur in zip(seen, seen[1:]):
        assert cur["critic"] is not prev["critic"] and cur["optimizer"] is not prev["optimizer"]
        assert cur["adam_state"] == 0
    assert all(s["optimized"] == s["model_numel"] for s in seen)


@pytest.mark.parametrize("schedule,expected", [("cyclic", [2.5e-4, 2.5e-4, 2.5e-4]),
                                               ("global", [2.5e-4, 2.5e-4 * 2 / 3, 2.5e-4 / 3])])
def test_learning_rate_schedules(schedule, expected, tmp_path):
    """cyclic: each net's iteration restarts at the full rate; global (Fig. 12): one linear decay over the run."""
    args = cpd.Args(env_id="CartPole-v1", n=3, k=512, lr_schedule=schedule, eval_every=0, quiet=True,
                    track_dir=str(tmp_path), **TINY)  # one 512-step update per iteration
    scalars = read_scalars(cpd.train(args)["run_dir"])
    np.testing.assert_allclose([v for _, v in scalars["charts/learning_rate"]], expected, rtol=1e-5)


@pytest.mark.parametrize("module", [cpd, pbd])
def test_each_parameter_group_follows_the_schedule_from_its_own_learning_rate(module, tmp_path, monkeypatch):
    """An optimizer edited into groups with their own learning rates (here the first parameter at 4x): the schedule
    scales each group's own rate (it had set every group to --learning-rate); the log shows the first group's."""
    monkeypatch.setattr(module, "make_optimizer", lambda params, learning_rate: torch.optim.Adam(
        [{"params": params[:1], "lr": 4 * learning_rate}, {"params": params[1:]}], lr=learning_rate, eps=1e-5))
    budget = dict(n=2, k=1024) if module is cpd else dict(total_timesteps=2048, lr_schedule="global")
    result = module.train(module.Args(env_id="CartPole-v1", eval_every=0, quiet=True, track_dir=str(tmp_path),
                                      num_steps=128, num_minibatches=4, update_epochs=1, **budget))  # 512-step updates
    logged = [v for _, v in read_scalars(result["run_dir"])["charts/learning_rate"]]
    expected = [1e-3, 5e-4] * 2 if module is cpd else [1e-3, 7.5e-4, 5e-4, 2.5e-4]
    np.testing.assert_allclose(logged, expected, rtol=1e-5)


def test_cascade_discretized_hopper_run_writes_expected_scalars(tmp_path, capsys):
    code, out, error = cli_in_process(capsys, "cascade_ppo_discrete.py", "--env-id", "Hopper-v4", "--n", "3", "--k",
                                      "1024", "--update-epochs", "2", "--eval-every", "1024", "--eval-episodes", "2",
                                      "--normalize", "--track-dir", tmp_path)
    assert code == 0, error
    assert "8 discrete actions (discretized Box), normalization on" in out
    assert "15954 parameters" in out  # two nets + critic, counted by hand above
    scalars = read_scalars(only_run_dir(tmp_path))
    for tag in ["charts/episodic_return", "charts/episodic_length", "charts/SPS", "charts/learning_rate",
                "losses/value_loss", "losses/policy_loss", "losses/entropy", "losses/approx_kl", "losses/clipfrac",
                "losses/explained_variance", "eval/episodic_return", "eval/episodic_return_std", "cascade/size",
                "cascade/parameters", "cascade/fallback/net_2", "cascade/fallback/net_3", "cascade/fallback_product",
                "cascade/contribution/net_1", "cascade/contribution/net_3", "cascade/fallback_std/net_2",
                "cascade/fallback_std/net_3"]:
        assert tag in scalars, f"missing {tag}; have {sorted(scalars)}"
    assert [s for s, _ in scalars["eval/episodic_return"]] == [0, 1024, 2048, 3072]
    # 2 updates of 512 steps per iteration; the LR cycle restarts at every new base net
    np.testing.assert_allclose([v for _, v in scalars["charts/learning_rate"]], [2.5e-4, 1.25e-4] * 3, rtol=1e-5)
    assert [v for _, v in scalars["cascade/size"]][-1] == 3
    # the entropy of a near-uniform policy over 8 actions starts close to log 8
    assert abs(scalars["losses/entropy"][0][1] - np.log(8)) < 0.05
    last = {tag: scalars[tag][-1][1] for tag in scalars if tag.startswith("cascade/contribution/")}
    assert abs(sum(last.values()) - 1.0) < 1e-4
    assert abs(scalars["cascade/fallback_product"][-1][1] - last["cascade/contribution/net_1"]) < 1e-6
    assert_progress_file_says(only_run_dir(tmp_path), nets=3, last_eval=scalars["eval/episodic_return"][-1][1])


def test_baseline_discretized_hopper_run_writes_expected_scalars(tmp_path, capsys):
    code, out, error = cli_in_process(capsys, "ppo_baseline_discrete.py", "--env-id", "Hopper-v4", "--total-timesteps",
                                      "2048", "--update-epochs", "2", "--eval-every", "1024", "--eval-episodes", "2",
                                      "--track-dir", tmp_path)
    assert code == 0, error
    assert "10441 parameters" in out
    scalars = read_scalars(only_run_dir(tmp_path))
    for tag in ["charts/episodic_return", "charts/SPS", "charts/learning_rate", "charts/parameters",
                "losses/value_loss", "losses/policy_loss", "losses/entropy", "eval/episodic_return",
                "eval/episodic_return_std"]:
        assert tag in scalars, f"missing {tag}; have {sorted(scalars)}"
    assert [s for s, _ in scalars["eval/episodic_return"]] == [0, 1024, 2048]
    # CleanRL ppo.py: the LR anneals once over the whole run (4 updates of 512 steps)
    np.testing.assert_allclose([v for _, v in scalars["charts/learning_rate"]],
                               [2.5e-4 * (1 - u / 4) for u in range(4)], rtol=1e-5)
    assert_progress_file_says(only_run_dir(tmp_path), nets=1, last_eval=scalars["eval/episodic_return"][-1][1])


def assert_progress_file_says(run_dir, nets: int, last_eval: float):
    """The progress file (what sweep.py shows of a run), its last line written at the run's end: the policy's base
    nets and the latest evaluation. It said "0 net(s) | eval -" for every discrete run."""
    line = open(os.path.join(run_dir, "progress.txt")).read()
    assert f"| {nets} net(s) | eval {last_eval:.1f} |" in line, line


BAD_INPUT = [
    ("cascade_ppo_discrete.py", ["--env-id", "CartPol-v1"], "unknown env id"),
    ("cascade_ppo_discrete.py", ["--env-id", "Humanoid-v4"], "2^17"),
    ("cascade_ppo_discrete.py", ["--env-id", "CartPole-v1", "--discretize", "on"], "already discrete"),
    ("cascade_ppo_discrete.py", ["--env-id", "Hopper-v4", "--discretize", "off"], "Box action space"),
    ("cascade_ppo_discrete.py", ["--n", "0"], "--n must be at least 1"),
    ("cascade_ppo_discrete.py", ["--k", "500"], "smaller than one rollout batch"),
    ("cascade_ppo_discrete.py", ["--fallback-init", "1.0"], "--fallback-init"),
    ("cascade_ppo_discrete.py", ["--fallback-init", "0"], "--fallback-init"),
    ("ppo_baseline_discrete.py", ["--env-id", "Humanoid-v4"], "2^17"),
    ("ppo_baseline_discrete.py", ["--env-id", "CartPole-v1", "--discretize", "on"], "already discrete"),
    ("ppo_baseline_discrete.py", ["--total-timesteps", "100"], "smaller than one rollout batch"),
]


THROUGH_THE_INTERPRETER = {("cascade_ppo_discrete.py", "unknown env id"),
                           ("ppo_baseline_discrete.py", "smaller than one rollout batch")}  # one case per script


@pytest.mark.parametrize("script,extra,message", BAD_INPUT)
def test_bad_input_is_one_clear_line(tmp_path, script, extra, message):
    argv = [script, "--track-dir", tmp_path / "runs", *extra]
    if (script, message) in THROUGH_THE_INTERPRETER:  # stderr and the exit code of a real process
        line = error_line(run_script(*argv))
    else:
        line = error_line_in_process(*argv)
    assert message in line
    assert not (tmp_path / "runs").exists()


def test_help_documents_every_flag(capsys):
    code, out, _ = cli_in_process(capsys, "cascade_ppo_discrete.py", "--help")
    assert code == 0
    for flag in ["--n", "--k", "--discretize", "--freeze-previous", "--start-full", "--lr-schedule",
                 "--fallback-init", "--hidden-size", "--num-layers", "--no-normalize", "--eval-every",
                 "--eval-episodes"]:
        assert flag in out


@pytest.fixture(scope="module")
def cartpole_run(tmp_path_factory):
    """One tiny 2-net CartPole-v1 run, checkpointing after every update; keeps a copy of the checkpoint
    written after update 1 of 2 of iteration 2."""
    track = tmp_path_factory.mktemp("runs")
    args = cpd.Args(env_id="CartPole-v1", n=2, k=1024, eval_every=512, eval_episodes=2, checkpoint_every=512,
                    track_dir=str(track), quiet=True, **TINY)
    mid = str(tmp_path_factory.mktemp("mid") / "mid.pt")
    with copy_checkpoint_when(cpd, lambda c: (c["iteration"], c["updates_done"]) == (2, 1), mid):
        result = cpd.train(args)
    return {**result, "mid": mid}


def assert_same_parameters(a, b):
    a, b = a.state_dict(), b.state_dict()
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(b[key], a[key], rtol=0, atol=0)


@pytest.mark.parametrize("start", ["iteration_1.pt", "mid"])
def test_cascade_resume_gives_identical_parameters(cartpole_run, tmp_path, start):
    run_dir = cartpole_run["run_dir"]
    assert {"checkpoint.pt", "iteration_1.pt", "iteration_2.pt"} <= set(os.listdir(run_dir))
    source = os.path.join(run_dir, start) if start != "mid" else cartpole_run["mid"]
    first = cpd.load_checkpoint(source)
    expected = (1, 2, 1024, 1) if start != "mid" else (2, 1, 1536, 2)
    assert (first["iteration"], first["updates_done"], first["global_step"], first["actor_size"]) == expected
    resumed = resume_from(cpd, source, tmp_path / "resumed")
    assert_same_parameters(cartpole_run["actor"], resumed["actor"])
    assert_same_parameters(cartpole_run["critic"], resumed["critic"])
    # the resumed run evaluates exactly as the uninterrupted one did from the checkpoint on
    original = read_scalars(run_dir)["eval/episodic_return"]
    again = read_scalars(resumed["run_dir"])["eval/episodic_return"]
    assert again == [(s, v) for s, v in original if s > first["global_step"]]
    # ... and logs the net count where an iteration starts only (from iteration_1.pt: iteration 2's start, at 1024;
    # mid-iteration 2: none, it started before the checkpoint)
    starts = [step for step, _ in read_scalars(resumed["run_dir"]).get("cascade/parameters", [])]
    assert starts == ([1024] if start != "mid" else []), starts


def test_cascade_evaluate_and_resume_errors(cartpole_run, tmp_path, capsys):
    run_dir = cartpole_run["run_dir"]
    code, out, error = cli_in_process(capsys, "cascade_ppo_discrete.py", "--evaluate", run_dir, "--eval-episodes", "2",
                                      "--deterministic")
    assert code == 0, error
    assert "CartPole-v1, 2 base net(s), step 2048: return" in out
    assert " ± " in out and "over 2 deterministic episodes" in out
    for extra, message in [(["--resume", str(tmp_path / "nope")], "no checkpoint at"),
                           (["--resume", run_dir, "--env-id", "Acrobot-v1"], "--env-id Acrobot-v1 differs")]:
        assert message in error_line_in_process("cascade_ppo_discrete.py", *extra), extra


def test_baseline_checkpoint_resume_and_evaluate(tmp_path, capsys):
    """Discretized Hopper (MuJoCo state and normalization statistics restored): resuming the checkpoint
    written half way gives the uninterrupted run's parameters."""
    args = pbd.Args(env_id="Hopper-v4", total_timesteps=2048, eval_every=512, eval_episodes=2, checkpoint_every=512,
                    normalize=True, track_dir=str(tmp_path / "a"), quiet=True, **TINY)
    with copy_checkpoint_when(pbd, lambda c: c["updates_done"] == 2, tmp_path / "mid.pt"):
        full = pbd.train(args)
    checkpoint = pbd.load_checkpoint(str(tmp_path / "mid.pt"))
    assert checkpoint["global_step"] == 1024 and checkpoint["env_states"][0]["sim"] is not None
    resumed = resume_from(pbd, tmp_path / "mid.pt", tmp_path / "b")
    assert_same_parameters(full["actor"], resumed["actor"])
    assert_same_parameters(full["critic"], resumed["critic"])
    code, out, error = cli_in_process(capsys, "ppo_baseline_discrete.py", "--evaluate", full["run_dir"],
                                      "--eval-episodes", "2")
    assert code == 0 and "over 2 stochastic episodes" in out and " ± " in out, error
    assert "--hidden-size 16 differs" in error_line_in_process("ppo_baseline_discrete.py", "--resume", full["run_dir"],
                                                               "--hidden-size", "16")


@pytest.mark.parametrize("module", [cpd, pbd], ids=["cascade", "baseline"])
def test_evaluate_gives_the_saved_policy_s_returns(module, tmp_path):
    """--evaluate's returns are those of the saved actor with its saved observation statistics, evaluated directly
    (audit: only its printed wording was checked, and CartPole has no statistics to lose). Discretized Hopper-v4,
    normalized: the statistics change every observation the policy sees."""
    budget = dict(n=2, k=512) if module is cpd else dict(total_timesteps=1024)
    args = module.Args(env_id="Hopper-v4", eval_every=0, normalize=True, track_dir=str(tmp_path), quiet=True,
                       **budget, **TINY)
    checkpoint = module.load_checkpoint(module.train(args)["run_dir"])
    # a policy this young barely depends on what it sees: sharpen its logits so that the statistics show
    head = "logits_weight" if module is cpd else "4.weight"
    checkpoint["actor"][head] = checkpoint["actor"][head] * 300
    saved = str(tmp_path / "sharpened.pt")
    torch.save({key: value for key, value in checkpoint.items() if key != "path"}, saved)
    actor, stats = module.actor_from_checkpoint(checkpoint), checkpoint["obs_stats"]
    assert stats is not None

    def direct(deterministic, stats):
        episodes = EvaluationEpisodes("Hopper-v4", 3, 7, checkpoint["discretize"])
        out = module.evaluate(actor, episodes, stats, 0, deterministic)
        episodes.close()
        return out[0] if isinstance(out, tuple) else out

    for deterministic in (False, True):
        got = module.evaluate_saved(module.Args(evaluate=saved, eval_episodes=3, seed=7, deterministic=deterministic,
                                                quiet=True))
        np.testing.assert_array_equal(got, direct(deterministic, stats))
        assert not np.allclose(got, direct(deterministic, None)), "the saved statistics made no difference"
    assert not np.allclose(direct(False, stats), direct(True, stats)), "sampling and the argmax acted alike"


@pytest.mark.slow
def test_cascade_learns_cartpole(tmp_path):
    """CartPole-v1, 2 nets of 32K steps (see tests/learning_checks.py for the spread the threshold comes from)."""
    learning_checks.assert_learns("cascade_ppo_cartpole", str(tmp_path))
