"""The side experiments as the paper's own code ran them (where the paper's text, Appendix H, is silent or
differs): SAC's log-std head and alpha, DDPG's nets, clipping of raw observations and rewards, discrete
normalization, Fig. 5's one critic, Fig. 3's Adam restarts, and the sweep presets that run those figures.
(What happens when SAC/DDPG add a net: tests/test_sac_ddpg.py.)"""

import os

import gymnasium as gym
import numpy as np
import pytest
import torch
import tyro

import cascade_ddpg as cd
import cascade_ppo_continuous as cpc
import cascade_ppo_discrete as cpd
import cascade_sac as cs
import ppo_baseline as pb
import ppo_baseline_discrete as pbd
import sweep
from cascade_plumbing import offpolicy
from helpers import read_scalars, resume_from

HOPPER_OBS, HOPPER_ACT = 11, 3


def linear(d_in, d_out):
    return d_in * d_out + d_out


# ----------------------------------------------------------------------------------------------
# Nets and their parameter counts
# ----------------------------------------------------------------------------------------------
def test_paper_preset_parameter_counts_hopper():
    """Counted by hand from the paper code's configs (VanillaSAC/VanillaDDPG/Cascade net_cfg), Hopper-v4."""
    o, a = HOPPER_OBS, HOPPER_ACT
    low, high = -np.ones(a), np.ones(a)
    # Cascade-DDPG: 6 nets of 16-16 (tanh) with an A-dim output; nets 2..6 have one more output, the fallback
    ddpg_net = linear(o, 16) + linear(16, 16) + linear(16, a)
    actor = cd.CascadeActor(o, a, 16, 2, 0.5, low, high)
    for _ in range(6):
        actor.add_base_net()
    assert cd.count_parameters(actor) == 6 * ddpg_net + 5 * (16 + 1) == 3175
    ddpg_critic = linear(o + a, 64) + linear(64, 64) + linear(64, 1)
    assert cd.count_parameters(cd.QNetworks(o, a)) == ddpg_critic == 5185
    baseline = cd.CascadeActor(o, a, 64, 2, 0.5, low, high)  # --n 1 --hidden-size 64
    baseline.add_base_net()
    assert cd.count_parameters(baseline) == linear(o, 64) + linear(64, 64) + linear(64, a) == 5123
    # Cascade-SAC: 4 nets of 128-128 (ReLU) with mean and log-std heads; nets 2..4 add a fallback output
    sac_net = linear(o, 128) + linear(128, 128) + 2 * linear(128, a)
    actor = cs.CascadeActor(o, a, 128, 2, 0.5, low, high)
    for _ in range(4):
        actor.add_base_net()
    assert cs.count_parameters(actor) == 4 * sac_net + 3 * (128 + 1) == 75675
    baseline = cs.CascadeActor(o, a, 256, 2, 0.5, low, high)  # --n 1 --hidden-size 256
    baseline.add_base_net()
    assert cs.count_parameters(baseline) == linear(o, 256) + linear(256, 256) + 2 * linear(256, a) == 70406
    assert cs.count_parameters(cs.QNetworks(o, a)) == 2 * (linear(o + a, 256) + linear(256, 256) + linear(256, 1)) == 2 * 69889


def test_ddpg_default_nets_are_16_16_tanh_with_a_64_64_tanh_critic(tmp_path):
    result = cd.train(cd.Args(env_id="Pendulum-v1", n=2, k=300, learning_starts=100, batch_size=32, eval_every=0,
                              quiet=True, track_dir=str(tmp_path)))
    actor, qf = result["actor"], result["qf"]
    assert [tuple(w.shape) for w in actor.hidden_weights] == [(2, 3, 16), (2, 16, 16)]
    assert [tuple(w.shape) for w in qf.weights] == [(1, 4, 64), (1, 64, 64), (1, 64, 1)]
    assert actor.activation is torch.tanh and qf.activation is torch.tanh and actor.combine_before_tanh
    # the activation really is tanh: hidden features of a plain loop with tanh reproduce the actor's action
    obs = torch.randn(8, 3) * 3
    h = obs
    for w, b in zip(actor.hidden_weights, actor.hidden_biases):
        h = torch.tanh(h @ w[0] + b[0, 0])
    with torch.no_grad():
        torch.testing.assert_close(actor.member(obs, 0), torch.tanh(h @ actor.mu_weight[0] + actor.mu_bias[0, 0]) * 2.0)


def test_sac_log_std_head_keeps_torchs_default_init():
    """The paper's code: orthogonal 0.01 for the mean head and the fallback logit (one layer), nn.Linear's
    default init (uniform in +-1/sqrt(H)) for the log-std head."""
    torch.manual_seed(0)
    h, a = 128, 6
    actor = cs.CascadeActor(17, a, h, 2, 0.5, -np.ones(a), np.ones(a))
    actor.add_base_net()
    actor.add_base_net()
    bound = 1 / np.sqrt(h)
    for net in range(2):
        log_std_w, log_std_b = actor.head_weight[net, :, a:], actor.head_bias[net, 0, a:]
        assert log_std_w.abs().max() <= bound and log_std_b.abs().max() <= bound
        assert log_std_w.std().item() == pytest.approx(bound / np.sqrt(3), rel=0.1)  # uniform, not gain 0.01
        assert log_std_b.abs().max() > 0  # nn.Linear draws its bias too
        mean_w = actor.head_weight[net, :, :a]
        columns = mean_w if net == 0 else torch.cat([mean_w, actor.fallback_weight[0]], 1)
        gram = columns.T @ columns  # orthogonal columns of norm 0.01
        torch.testing.assert_close(gram, 1e-4 * torch.eye(columns.shape[1]), atol=1e-8, rtol=0)
        assert torch.count_nonzero(actor.head_bias[net, 0, :a]) == 0


# ----------------------------------------------------------------------------------------------
# Clipping of raw observations and rewards (the paper's code's norm:False runs)
# ----------------------------------------------------------------------------------------------
class LoudEnv(gym.Env):
    """Observations [50, -50, 3] and reward 30 on every step; 5 steps per episode."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (3,), np.float64)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.array([50.0, -50.0, 3.0]), {}

    def step(self, action):
        return np.array([50.0, -50.0, 3.0]), 30.0, False, False, {}


gym.register("CascadeTestLoud-v0", entry_point=LoudEnv, max_episode_steps=5)
CLIPPED = np.array([10.0, -10.0, 3.0])


def run_episode(env):
    obs, _ = env.reset(seed=0)
    seen, rewards = [obs], []
    for _ in range(5):
        obs, reward, _, _, info = env.step(env.action_space.sample())
        seen.append(obs)
        rewards.append(reward)
    return np.array(seen), np.array(rewards), info["episode"]["r"]


@pytest.mark.parametrize("make", [
    lambda: cpc.make_env("CascadeTestLoud-v0", 0.99, False)(),  # --no-normalize (Fig. 13)
    lambda: pb.make_env("CascadeTestLoud-v0", 0.99, False)(),
    lambda: cs.make_env("CascadeTestLoud-v0", clip=10.0)(),
    lambda: cd.make_env("CascadeTestLoud-v0", clip=10.0)(),
    lambda: cpd.make_env("CascadeTestLoud-v0", 0.99, True, False)(),  # discretized, --no-normalize
    lambda: pbd.make_env("CascadeTestLoud-v0", 0.99, True, False)(),
])
def test_raw_observations_and_rewards_are_clipped_without_normalization(make):
    obs, rewards, episode_return = run_episode(make())
    np.testing.assert_array_equal(obs, np.tile(CLIPPED, (6, 1)))
    np.testing.assert_array_equal(rewards, np.full(5, 10.0))
    assert episode_return == 150.0  # the logged return stays raw


def test_clipping_can_be_turned_off_and_is_off_for_native_discrete_envs():
    obs, rewards, _ = run_episode(cs.make_env("CascadeTestLoud-v0", clip=0.0)())
    assert obs.max() == 50.0 and rewards.max() == 30.0
    obs, rewards, _ = run_episode(cd.make_env("CascadeTestLoud-v0", clip=0.0)())
    assert obs.max() == 50.0 and rewards.max() == 30.0
    np.testing.assert_array_equal(cpd.normalize_obs(np.array([[50.0]]), None, clip=False), [[50.0]])


def test_evaluation_sees_the_observations_training_sees():
    """The frozen-policy evaluations clip as the training envs do: PPO's normalize_obs without statistics, and
    the SAC/DDPG evaluators' policy input."""
    np.testing.assert_array_equal(cpc.normalize_obs(np.array([[50.0, -50.0, 3.0]]), None), [CLIPPED])
    np.testing.assert_array_equal(pb.normalize_obs(np.array([[50.0, -50.0, 3.0]]), None), [CLIPPED])
    np.testing.assert_array_equal(cpd.normalize_obs(np.array([[50.0, -50.0, 3.0]]), None, clip=True), [CLIPPED])
    seen = []

    def policy(x, generator):
        seen.append(x.numpy().copy())
        return torch.zeros(len(x), 1), torch.zeros(0, len(x))

    offpolicy.Evaluator("CascadeTestLoud-v0", 2, seed=0, obs_clip=10.0)(policy)  # cascade_sac's and cascade_ddpg's
    assert np.array_equal(np.concatenate(seen), np.tile(CLIPPED, (10, 1)))


# ----------------------------------------------------------------------------------------------
# Discrete: normalization on by default for discretized Box tasks (Fig. 16)
# ----------------------------------------------------------------------------------------------
def test_discrete_scripts_normalize_discretized_tasks_by_default():
    assert cpd.Args().normalize and pbd.Args().normalize
    assert cpd.resolve(cpd.Args(env_id="Hopper-v4")) == (True, True)
    assert pbd.resolve(pbd.Args(env_id="Hopper-v4", discretize="on")) == (True, True)
    env = cpd.make_env("Hopper-v4", 0.99, True, True)()
    assert cpd.find_wrapper(env, gym.wrappers.NormalizeObservation) is not None
    assert cpd.find_wrapper(env, gym.wrappers.NormalizeReward) is not None
    assert cpd.resolve(cpd.Args(env_id="CartPole-v1")) == (False, False)  # natively discrete: CleanRL ppo.py


# ----------------------------------------------------------------------------------------------
# Fig. 5: --start-full keeps one critic; Fig. 3: the cyclic baseline restarts Adam every cycle
# ----------------------------------------------------------------------------------------------
TINY_PPO = dict(num_steps=256, num_minibatches=4, update_epochs=2, eval_every=0, quiet=True)


def test_start_full_keeps_one_critic_and_restarts_adam_and_the_lr_cycle(tmp_path):
    seen = []

    def record(state):
        seen.append(dict(critic=state["critic"], critic_params=[p.detach().clone() for p in state["critic"].parameters()],
                         optimizer=state["optimizer"], adam_state=len(state["optimizer"].state),
                         optimized=sum(p.numel() for g in state["optimizer"].param_groups for p in g["params"]),
                         numel=cpc.count_parameters(state["actor"], state["critic"]),
                         lr=state["optimizer"].param_groups[0]["lr"]))

    args = cpc.Args(env_id="Hopper-v4", n=3, k=512, start_full=True, track_dir=str(tmp_path / "run"), **TINY_PPO)
    result = cpc.train(args, on_iteration_start=record)
    assert result["actor"].size == 3 and result["critic"] is seen[0]["critic"]
    for prev, cur in zip(seen, seen[1:]):
        assert cur["critic"] is prev["critic"]  # one critic for the whole run, trained on
        assert any(not torch.equal(a, b) for a, b in zip(cur["critic_params"], prev["critic_params"]))
        assert cur["optimizer"] is not prev["optimizer"] and cur["adam_state"] == 0  # a fresh Adam every k
        assert cur["optimized"] == cur["numel"] and cur["lr"] == args.learning_rate
    # resuming at an iteration boundary continues with the saved critic: the very same final parameters
    resumed = resume_from(cpc, os.path.join(result["run_dir"], "iteration_1.pt"), tmp_path / "resumed")
    for name, module in (("actor", result["actor"]), ("critic", result["critic"])):
        for (key, a), b in zip(module.state_dict().items(), resumed[name].state_dict().values()):
            torch.testing.assert_close(b, a, rtol=0, atol=0, msg=f"{name}.{key}")


def test_discrete_start_full_keeps_one_critic(tmp_path):
    seen = []
    args = cpd.Args(env_id="Hopper-v4", n=2, k=512, num_envs=2, num_steps=128, start_full=True, eval_every=0,
                    quiet=True, track_dir=str(tmp_path / "run"))
    result = cpd.train(args, on_iteration_start=lambda state: seen.append((state["critic"], state["optimizer"])))
    (critic_1, optimizer_1), (critic_2, optimizer_2) = seen
    assert critic_2 is critic_1 is result["critic"] and optimizer_2 is not optimizer_1
    resumed = resume_from(cpd, os.path.join(result["run_dir"], "iteration_1.pt"), tmp_path / "resumed")
    for (key, a), b in zip(result["critic"].state_dict().items(), resumed["critic"].state_dict().values()):
        torch.testing.assert_close(b, a, rtol=0, atol=0, msg=key)


def test_cyclic_discrete_baseline_restarts_adam_every_cycle(tmp_path):
    args = pbd.Args(env_id="CartPole-v1", total_timesteps=2048, num_envs=2, num_steps=128, lr_schedule="cyclic",
                    cycle_steps=1024, eval_every=0, quiet=True, track_dir=str(tmp_path))
    result = pbd.train(args)
    checkpoint = pbd.load_checkpoint(result["run_dir"])
    # the last cycle's 4 updates x 4 epochs x 4 minibatches, not both cycles' 128, for the actor and the critic
    assert {int(s["step"]) for s in checkpoint["optimizer"]["state"].values()} == {4 * 4 * 4}
    n_tensors = len([*result["actor"].parameters(), *result["critic"].parameters()])
    assert len(checkpoint["optimizer"]["state"]) == n_tensors


@pytest.mark.parametrize("num_envs", [1, 2])
def test_cyclic_baseline_restarts_adam_every_cycle(num_envs, tmp_path):
    """The paper's code ran Fig. 3's baseline as a new PPO instance per cycle (the nets kept): Adam restarts.
    A cycle is --cycle-steps env steps over all envs (4 rollouts of 256 steps here, from 1 or 2 envs)."""
    args = pb.Args(env_id="Hopper-v4", total_timesteps=2048, num_envs=num_envs, num_steps=256 // num_envs,
                   num_minibatches=4, update_epochs=2, lr_schedule="cyclic", cycle_steps=1024, eval_every=0,
                   quiet=True, track_dir=str(tmp_path))
    result = pb.train(args)
    checkpoint = pb.load_checkpoint(result["run_dir"])
    steps = {int(s["step"]) for s in checkpoint["optimizer"]["state"].values()}
    assert steps == {4 * 2 * 4}  # the last cycle's 4 updates x 2 epochs x 4 minibatches, not both cycles' 64
    global_args = pb.Args(**{**vars(args), "lr_schedule": "global", "cycle_steps": pb.Args.cycle_steps,
                             "track_dir": str(tmp_path / "global")})
    checkpoint = pb.load_checkpoint(pb.train(global_args)["run_dir"])
    assert {int(s["step"]) for s in checkpoint["optimizer"]["state"].values()} == {8 * 2 * 4}


@pytest.mark.parametrize("module,env_id", [(pb, "Pendulum-v1"), (pbd, "CartPole-v1")])
def test_cyclic_baseline_runs_whole_cycles_only(module, env_id, tmp_path, capsys):
    """A fault hunt: 6M steps in cycles of 1M made 2929 updates of 2048 = 6 x 488 + 1, so the last update began a
    7th cycle (a fresh Adam at the full learning rate) just before the final evaluation; Cascade's 6 iterations run
    6 x 488. Here 3 cycles of 1000 steps in rollouts of 256 (3 updates each): 9 updates, not 3000 // 256 = 11."""
    args = module.Args(env_id=env_id, total_timesteps=3000, num_envs=1, num_steps=256, num_minibatches=1,
                       update_epochs=1, lr_schedule="cyclic", cycle_steps=1000, eval_every=0, quiet=True,
                       track_dir=str(tmp_path))
    result = module.train(args)
    assert "the run does 9 updates = 2304 steps" in capsys.readouterr().out
    rates = [v for _, v in read_scalars(result["run_dir"])["charts/learning_rate"]]
    np.testing.assert_allclose(rates, [args.learning_rate * f for f in (1, 2 / 3, 1 / 3)] * 3, rtol=1e-6)
    checkpoint = module.load_checkpoint(result["run_dir"])
    assert checkpoint["global_step"] == 9 * 256 and checkpoint["updates_done"] == 9
    assert {int(s["step"]) for s in checkpoint["optimizer"]["state"].values()} == {3}  # the third cycle's 3 updates
    assert module.finished(args, checkpoint) and module.finished(args, {**checkpoint, "updates_done": 10})


# ----------------------------------------------------------------------------------------------
# The sweep presets of Fig. 3, 5, 13, 14, 15, 16 run the paper's setups
# ----------------------------------------------------------------------------------------------
MODULES = {"cascade_ppo_continuous.py": cpc, "ppo_baseline.py": pb, "cascade_ppo_discrete.py": cpd,
           "ppo_baseline_discrete.py": pbd, "cascade_sac.py": cs, "cascade_ddpg.py": cd}


def preset_args(preset):
    """label -> the script's Args as the preset's command line gives them."""
    _, templates = sweep.PRESETS[preset]
    return {label: tyro.cli(MODULES[script].Args, args=flags.split()) for label, script, flags in templates}


def test_presets_run_the_papers_setups():
    runs = preset_args("sac-ddpg")  # Fig. 14, 15
    sac, sac_base, ddpg, ddpg_base = runs["cascade_sac"], runs["sac"], runs["cascade_ddpg"], runs["ddpg"]
    assert (sac.n, sac.k, sac.hidden_size, sac_base.n, sac_base.k, sac_base.hidden_size) == (
        4, 500_000, 128, 1, 2_000_000, 256)
    for a in (sac, sac_base):
        assert not a.autotune and a.alpha == 0.2 and a.restart_on_new_net and a.obs_reward_clip == 10.0
    assert (ddpg.n, ddpg.k, ddpg.hidden_size, ddpg_base.n, ddpg_base.k, ddpg_base.hidden_size) == (
        6, 1_000_000, 16, 1, 6_000_000, 64)
    for a in (ddpg, ddpg_base):
        assert (a.activation, a.critic_hidden_size, a.anneal_lr, a.combine_before_tanh, a.eval_deterministic,
                a.restart_on_new_net, a.obs_reward_clip) == ("tanh", 64, True, True, False, True, 10.0)
    runs = preset_args("discrete")  # Fig. 16
    assert runs["cascade_discrete"].normalize and runs["ppo_discrete"].normalize
    assert (runs["cascade_discrete"].n, runs["cascade_discrete"].k, runs["ppo_discrete"].total_timesteps) == (
        10, 1_000_000, 10_000_000)
    cyclic = preset_args("baselines")["ppo_h16_cyclic"]  # Fig. 3
    assert (cyclic.hidden_size, cyclic.lr_schedule, cyclic.cycle_steps, cyclic.total_timesteps) == (
        16, "cyclic", 1_000_000, 6_000_000)
    assert preset_args("start-full")["cascade_start_full"].start_full  # Fig. 5
    nonorm = preset_args("frozen")  # Fig. 13
    assert not nonorm["cascade_nonorm"].normalize and nonorm["cascade_frozen_nonorm"].freeze_previous


@pytest.mark.parametrize("mod,make", [(cpc, lambda: cpc.make_env("Hopper-v4", 0.99, False)()),
                                      (cpd, lambda: cpd.make_env("Hopper-v4", 0.99, True, False)())])
def test_resume_refuses_env_states_of_another_wrapper_stack(mod, make):
    """A checkpoint of an older version (before the clipping wrappers of --no-normalize) cannot be restored into
    this wrapper stack: one line instead of attributes set on the wrong wrappers."""
    env = make()
    env.reset(seed=0)
    state = env.get_state()
    env.set_state([state])  # the same stack: fine
    state["layers"] = state["layers"][1:]  # one wrapper fewer, as an older version had
    with pytest.raises(SystemExit, match="older version"):
        env.set_state([state])
