"""Cascade with SAC and DDPG (paper Appendix H): the combined actor, what happens at a new base net, how
transitions are stored, the buffer's memory, logged scalars, resume, bad input, and learning on a small task."""

import os

import gymnasium as gym
import numpy as np
import pytest
import torch

import cascade_ddpg as cd
import cascade_sac as cs
import learning_checks
from cascade_plumbing.offpolicy import Evaluator
from cascade_plumbing.replay import buffer_capacity, store_transition
from helpers import cli_in_process, error_line, only_run_dir, read_scalars, run_script

SCRIPTS = {"sac": cs, "ddpg": cd}
# a fast env and tiny budgets: Pendulum episodes last 200 steps and only ever truncate
TINY = dict(env_id="Pendulum-v1", n=2, k=300, learning_starts=100, batch_size=32, eval_every=0, quiet=True)


# ----------------------------------------------------------------------------------------------
# The combined actor against a plain loop over the nets
# ----------------------------------------------------------------------------------------------
def make_actor(mod, n, obs_dim=5, act_dim=3, hidden=7, seed=0, **options):
    torch.manual_seed(seed)
    low, high = np.array([-1.0, -2.0, 0.0]), np.array([1.0, 2.0, 3.0])  # asymmetric bounds: scale and bias matter
    actor = mod.CascadeActor(obs_dim, act_dim, hidden, 2, 0.5, low, high, **options)
    for _ in range(n):
        actor.add_base_net()
    with torch.no_grad():  # move away from the init so fallbacks differ between nets and states
        for p in actor.parameters():
            p.normal_(0.0, 0.7)
    return actor


def reference_nets(actor, obs, head, activation=torch.relu):
    """Each base net on its own: (raw head output, fallback or None) per net, then C_i = l_i C_{i-1} + (1-l_i) b_i."""
    outputs, fallbacks = [], []
    for i in range(actor.size):
        h = obs
        for w, b in zip(actor.hidden_weights, actor.hidden_biases):
            h = activation(h @ w[i] + b[i, 0])
        outputs.append(h @ head[0][i] + head[1][i, 0])
        if i > 0:
            fallbacks.append(torch.sigmoid(h @ actor.fallback_weight[i - 1] + actor.fallback_bias[i - 1, 0]))
    return outputs, fallbacks


def recurse(values, fallbacks):
    combined = values[0]
    for i in range(1, len(values)):
        combined = fallbacks[i - 1] * combined + (1 - fallbacks[i - 1]) * values[i]
    return combined


@pytest.mark.parametrize("n", [1, 2, 4])
def test_sac_actor_matches_plain_loop(n):
    actor = make_actor(cs, n, seed=n)
    obs = torch.randn(64, 5) * 2
    with torch.no_grad():
        mean, log_std, fallback, weight = actor(obs)
        outputs, fallbacks = reference_nets(actor, obs, (actor.head_weight, actor.head_bias))
        # the paper's code: the nets' means and raw log-stds are combined, then CleanRL's tanh bound is applied
        # to the combined log-std, before the squash
        means = [o[:, :3] for o in outputs]
        raw_log_stds = [o[:, 3:] for o in outputs]
        torch.testing.assert_close(mean, recurse(means, fallbacks), rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(log_std, -5 + 0.5 * 7 * (torch.tanh(recurse(raw_log_stds, fallbacks)) + 1),
                                   rtol=1e-5, atol=1e-5)
        assert log_std.min() >= -5 and log_std.max() <= 2
        torch.testing.assert_close(weight.sum(0), torch.ones(64))
        if n > 1:
            torch.testing.assert_close(fallback, torch.stack([f[:, 0] for f in fallbacks]), rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(weight[0], fallback.prod(0), rtol=1e-5, atol=1e-6)  # the fallback product
        # the squashed sample: tanh(mean + std * noise) rescaled to the bounds, CleanRL's log-prob
        action, log_prob, mean_action = actor.get_action(obs, torch.Generator().manual_seed(3))
        noise = torch.randn(mean.shape, generator=torch.Generator().manual_seed(3))
        x_t = mean + log_std.exp() * noise
        scale, bias = torch.tensor([1.0, 2.0, 1.5]), torch.tensor([0.0, 0.0, 1.5])
        normal = torch.distributions.Normal(mean, log_std.exp())
        ref_log_prob = (normal.log_prob(x_t) - torch.log(scale * (1 - torch.tanh(x_t) ** 2) + 1e-6)).sum(1, keepdim=True)
        torch.testing.assert_close(action, torch.tanh(x_t) * scale + bias)
        torch.testing.assert_close(log_prob, ref_log_prob, rtol=1e-4, atol=1e-4)
        torch.testing.assert_close(mean_action, torch.tanh(mean) * scale + bias)


@pytest.mark.parametrize("n", [1, 2, 4])
@pytest.mark.parametrize("activation", ["tanh", "relu"])
@pytest.mark.parametrize("combine_before_tanh", [True, False])
def test_ddpg_actor_matches_plain_loop(n, activation, combine_before_tanh):
    actor = make_actor(cd, n, seed=n, activation=activation, combine_before_tanh=combine_before_tanh)
    obs = torch.randn(64, 5) * 2
    scale, bias = torch.tensor([1.0, 2.0, 1.5]), torch.tensor([0.0, 0.0, 1.5])
    with torch.no_grad():
        action, fallback, weight = actor(obs)
        outputs, fallbacks = reference_nets(actor, obs, (actor.mu_weight, actor.mu_bias),
                                            torch.tanh if activation == "tanh" else torch.relu)
        if combine_before_tanh:  # the paper's code: raw outputs combined, squashed once
            expected = torch.tanh(recurse(outputs, fallbacks)) * scale + bias
        else:  # each net's tanh output rescaled to the bounds, combined convexly
            expected = recurse([torch.tanh(o) * scale + bias for o in outputs], fallbacks)
        torch.testing.assert_close(action, expected, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(weight.sum(0), torch.ones(64))
        for i in range(n):
            torch.testing.assert_close(actor.member(obs, i), torch.tanh(outputs[i]) * scale + bias)


def test_one_net_is_cleanrl_sac_actor():
    """--n 1 --hidden-size 256 is CleanRL's Actor: the same forward on the same weights."""
    actor = make_actor(cs, 1, hidden=256)
    fc1, fc2 = torch.nn.Linear(5, 256), torch.nn.Linear(256, 256)
    fc_mean, fc_logstd = torch.nn.Linear(256, 3), torch.nn.Linear(256, 3)
    with torch.no_grad():
        for fc, w, b in [(fc1, actor.hidden_weights[0], actor.hidden_biases[0]),
                         (fc2, actor.hidden_weights[1], actor.hidden_biases[1]),
                         (fc_mean, actor.head_weight[:, :, :3], actor.head_bias[:, :, :3]),
                         (fc_logstd, actor.head_weight[:, :, 3:], actor.head_bias[:, :, 3:])]:
            fc.weight.copy_(w[0].T)
            fc.bias.copy_(b[0, 0])
        obs = torch.randn(16, 5)
        x = torch.relu(fc2(torch.relu(fc1(obs))))
        log_std = -5 + 0.5 * (2 - -5) * (torch.tanh(fc_logstd(x)) + 1)
        mean, ours_log_std, fallback, weight = actor(obs)
    torch.testing.assert_close(mean, fc_mean(x), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(ours_log_std, log_std, rtol=1e-5, atol=1e-5)
    assert fallback.shape == (0, 16) and torch.equal(weight, torch.ones(1, 16))
    assert cs.count_parameters(actor) == 5 * 256 + 256 + 256 * 256 + 256 + 256 * 6 + 6


def test_fallback_init_and_deferring_net_acts_as_the_bottom_one():
    for mod in (cs, cd):
        actor = mod.CascadeActor(5, 3, 8, 2, 0.3, -np.ones(3), np.ones(3))
        actor.add_base_net()
        actor.add_base_net()
        with torch.no_grad():
            out = actor(torch.randn(10, 5))
            torch.testing.assert_close(out[-2], torch.full((1, 10), 0.3), atol=1e-2, rtol=0)  # lambda ~ init
            actor.fallback_weight.zero_()
            actor.fallback_bias.fill_(100.0)  # net 2 defers completely
            obs = torch.randn(10, 5)
            if mod is cs:
                mean, log_std, _, _ = actor(obs)
                torch.testing.assert_close((mean, log_std), actor.member(obs, 0))
            else:
                torch.testing.assert_close(actor(obs)[0], actor.member(obs, 0))


# ----------------------------------------------------------------------------------------------
# A new base net: the paper's code's restart (default) and the text's reading (--no-restart-on-new-net)
# ----------------------------------------------------------------------------------------------
def snapshot(module):
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def run_with_hook(mod, tmp_path, **overrides):
    seen = []

    def record(state):
        if state["iteration"] == 1:  # record when uniform random actions are taken, over the whole run
            space, buffer = state["envs"].single_action_space, state["buffer"]
            sample = space.sample

            def counted(*a, **kw):
                counts["uniform"] += 1
                counts["at_buffer_len"].append(len(buffer))
                return sample(*a, **kw)

            space.sample = counted
        seen.append({**state, "size": state["actor"].size, "buffer_len": len(state["buffer"]), "qf_state": snapshot(state["qf"]),
                     "qf_target_state": snapshot(state["qf_target"]), "next_obs": state["next_obs"].copy(),
                     "adam_state": len(state["actor_optimizer"].state), "q_adam_state": len(state["q_optimizer"].state),
                     "optimized": sum(p.numel() for g in state["actor_optimizer"].param_groups for p in g["params"]),
                     "actor_numel": mod.count_parameters(state["actor"]),
                     "target_actor_state": snapshot(state["target_actor"]) if "target_actor" in state else None,
                     "actor_state": snapshot(state["actor"]),
                     "log_alpha": state["log_alpha"].item() if "log_alpha" in state else None})

    counts = {"uniform": 0, "at_buffer_len": []}
    result = mod.train(mod.Args(track_dir=str(tmp_path), **{**TINY, **overrides}), on_iteration_start=record)
    first = mod.load_checkpoint(os.path.join(result["run_dir"], "iteration_1.pt"))
    last = mod.load_checkpoint(os.path.join(result["run_dir"], "iteration_2.pt"))
    return seen, first, last, result, counts


def adam_steps(optimizer_state):
    return {int(s["step"]) for s in optimizer_state["state"].values()}


def assert_new_net_common(mod, seen, first, result):
    """Both readings: the buffer is emptied, the critics are kept (trained), the actor optimizer is new."""
    one, two = seen
    assert (one["size"], two["size"]) == (1, 2) and two["actor"] is one["actor"]
    # the buffer: the same object, emptied at the new net, then holding this iteration's k transitions only
    assert two["buffer"] is one["buffer"] is result["buffer"]
    assert one["buffer_len"] == 0 and two["buffer_len"] == 0
    assert len(result["buffer"]) == TINY["k"]
    np.testing.assert_array_equal(result["buffer"].obs[0], two["next_obs"][0].astype(np.float32))
    # the critics: the same object, with the values iteration 1 ended with
    assert two["qf"] is one["qf"]
    for key, value in first["qf"].items():
        torch.testing.assert_close(two["qf_state"][key], value, rtol=0, atol=0)
    # the actor optimizer: new, empty, over every parameter of every actor net
    assert two["actor_optimizer"] is not one["actor_optimizer"]
    assert two["adam_state"] == 0 and two["optimized"] == two["actor_numel"]
    # the old net carries over trained, the new one is appended
    for key, value in first["actor"].items():
        if value.dim() and value.shape[0] == 1 and key != "fallback_weight":
            torch.testing.assert_close(two["actor_state"][key][:1], value, rtol=0, atol=0)


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_new_net_restarts_as_the_papers_code(algo, tmp_path):
    """Default: each net starts like a new SAC/DDPG instance of the paper's code: learning_starts uniform-random
    steps without updates, target critics copied anew from the kept critics, a new critic optimizer, and (DDPG)
    a target actor that is a copy of the whole cascade."""
    mod = SCRIPTS[algo]
    seen, first, last, result, counts = run_with_hook(mod, tmp_path)
    assert_new_net_common(mod, seen, first, result)
    one, two = seen
    # uniform random actions for the first learning_starts steps of each iteration (the buffer holds that many)
    assert counts["at_buffer_len"] == [*range(TINY["learning_starts"])] * 2
    # the targets equal the online critics at the new net, although iteration 1 ended with other target values
    for key, value in two["qf_state"].items():
        torch.testing.assert_close(two["qf_target_state"][key], value, rtol=0, atol=0)
    assert any(not torch.equal(first["qf_target"][k], v) for k, v in first["qf"].items())
    # a new critic optimizer: empty at the start, and each iteration's Adam counts only its own updates,
    # k - learning_starts - 1 of them (CleanRL's `global_step > learning_starts`, restarted per net)
    assert two["q_optimizer"] is not one["q_optimizer"] and two["q_adam_state"] == 0
    per_iteration = TINY["k"] - TINY["learning_starts"] - 1
    assert adam_steps(first["q_optimizer"]) == {per_iteration}
    assert adam_steps(last["q_optimizer"]) == {per_iteration}
    if algo == "sac":  # alpha fixed at 0.2 (the paper's code): no temperature updates
        assert first["alpha"] == last["alpha"] == 0.2 and len(first["a_optimizer"]["state"]) == 0
    else:  # the target actor: a copy of the whole current cascade, trained net 1 included
        assert two["target_actor"] is not two["actor"]
        for key, value in two["actor_state"].items():
            torch.testing.assert_close(two["target_actor_state"][key], value, rtol=0, atol=0)
        assert any(not torch.equal(first["target_actor"][k], v) for k, v in first["actor"].items())


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_new_net_without_restart_keeps_targets_and_critic_optimizer(algo, tmp_path):
    """--no-restart-on-new-net (the paper's text read literally): critics, targets and critic optimizer kept,
    the current policy collects the warm-up."""
    mod = SCRIPTS[algo]
    options = {"autotune": True} if algo == "sac" else {}
    seen, first, last, result, counts = run_with_hook(mod, tmp_path, restart_on_new_net=False, **options)
    assert_new_net_common(mod, seen, first, result)
    one, two = seen
    for name in ("qf_target", "q_optimizer"):
        assert two[name] is one[name]
    for key, value in first["qf_target"].items():
        torch.testing.assert_close(two["qf_target_state"][key], value, rtol=0, atol=0)
    # each iteration updates only after learning_starts transitions of its own; Adam's step count runs on
    per_iteration = TINY["k"] - TINY["learning_starts"] - 1
    assert adam_steps(first["q_optimizer"]) == {per_iteration}
    assert adam_steps(last["q_optimizer"]) == {2 * per_iteration}
    # uniform random actions only at the very start of the run; after the reset the policy collects
    assert counts["uniform"] == TINY["learning_starts"]
    if algo == "sac":  # with --autotune the entropy temperature and its optimizer are kept
        assert two["log_alpha"] is not None and two["a_optimizer"] is one["a_optimizer"]
        assert two["log_alpha"] == pytest.approx(first["log_alpha"].item())
    else:  # the target actor keeps its trained net 1 and gets net 2 with the online net's very init
        target_state, actor_state = two["target_actor_state"], two["actor_state"]
        for key, value in first["target_actor"].items():
            if value.dim() and value.shape[0] == 1 and key != "fallback_weight":
                torch.testing.assert_close(target_state[key][:1], value, rtol=0, atol=0)
        for key in actor_state:
            if key.startswith(("hidden", "mu")):
                torch.testing.assert_close(target_state[key][1], actor_state[key][1], rtol=0, atol=0)
        torch.testing.assert_close(target_state["fallback_bias"], actor_state["fallback_bias"], rtol=0, atol=0)


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_each_optimizer_runs_at_its_learning_rate(algo, tmp_path):
    """SAC: the actor at --policy-lr, the critics and alpha at --q-lr. DDPG: actor and critic at --learning-rate,
    both annealed linearly to 0 within each iteration: at an iteration's last step, (1 - (k - 1) / k) x the rate."""
    mod = SCRIPTS[algo]
    rates = dict(policy_lr=2e-4, q_lr=7e-4, autotune=True) if algo == "sac" else dict(learning_rate=6e-4)
    seen, _, _, _, _ = run_with_hook(mod, tmp_path, **rates)
    last = seen[-1]
    lr = {name: last[name].param_groups[0]["lr"] for name in ("actor_optimizer", "q_optimizer", "a_optimizer")
          if name in last}
    if algo == "sac":
        assert lr == {"actor_optimizer": 2e-4, "q_optimizer": 7e-4, "a_optimizer": 7e-4}
    else:
        end = pytest.approx(6e-4 * (1 - (TINY["k"] - 1) / TINY["k"]))
        assert lr == {"actor_optimizer": end, "q_optimizer": end}


def test_ddpg_anneals_each_parameter_group_from_its_own_learning_rate(tmp_path, monkeypatch):
    """Optimizers edited into groups with their own learning rates (here the first parameter at 3x): the annealing
    scales each group's own rate (it had set group 0 to --learning-rate and left the others unannealed)."""
    mod = SCRIPTS["ddpg"]
    monkeypatch.setattr(mod, "make_adam", lambda params, lr, eps: torch.optim.Adam(
        [{"params": params[:1], "lr": 3 * lr}, {"params": params[1:]}], lr=lr, eps=eps))
    seen, _, _, _, _ = run_with_hook(mod, tmp_path, learning_rate=6e-4)
    end = 6e-4 * (1 - (TINY["k"] - 1) / TINY["k"])
    for name in ("actor_optimizer", "q_optimizer"):
        rates = [group["lr"] for group in seen[-1][name].param_groups]
        assert rates == [pytest.approx(3 * end), pytest.approx(end)], (name, rates)


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_keep_buffer_and_reset_critic_ablations(algo, tmp_path):
    mod = SCRIPTS[algo]
    seen, first, _, result, _ = run_with_hook(mod, tmp_path / "keep", keep_buffer=True)
    assert seen[1]["buffer_len"] == TINY["k"] and len(result["buffer"]) == 2 * TINY["k"]
    seen, first, _, _, _ = run_with_hook(mod, tmp_path / "reset", reset_critic=True)
    one, two = seen
    assert two["qf"] is not one["qf"] and two["q_optimizer"] is not one["q_optimizer"]
    assert two["q_adam_state"] == 0
    assert any(not torch.equal(two["qf_state"][k], v) for k, v in first["qf"].items())
    # a fresh target is a copy of the fresh critic
    for key in two["qf_state"]:
        torch.testing.assert_close(two["qf_target_state"][key], two["qf_state"][key], rtol=0, atol=0)


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_nan_guard_stops_and_keeps_last_good_checkpoint(algo, tmp_path):
    mod = SCRIPTS[algo]

    def poison(state):
        if state["iteration"] == 2:
            with torch.no_grad():
                state["qf"].weights[0][0, 0, 0] = float("nan")

    with pytest.raises(SystemExit) as stop:
        mod.train(mod.Args(track_dir=str(tmp_path), **TINY), on_iteration_start=poison)
    assert "non-finite" in str(stop.value) and "iteration 2" in str(stop.value)
    checkpoint = mod.load_checkpoint(only_run_dir(tmp_path))
    assert checkpoint["iteration"] == 1 and all(torch.isfinite(v).all() for v in checkpoint["qf"].values())


def test_defaults_are_cleanrl_and_the_papers_code():
    sac, ddpg = cs.Args(), cd.Args()
    assert (sac.n, sac.k, sac.hidden_size, sac.fallback_init) == (4, 500_000, 128, 0.5)  # 2M steps
    assert (sac.buffer_size, sac.batch_size, sac.tau, sac.gamma, sac.policy_lr, sac.q_lr) == (
        1_000_000, 256, 0.005, 0.99, 3e-4, 1e-3)
    assert (sac.policy_frequency, sac.target_network_frequency, sac.learning_starts) == (2, 1, 5_000)
    # the paper's code where its text (Appendix H) is silent or differs
    assert (sac.autotune, sac.alpha, sac.restart_on_new_net, sac.obs_reward_clip) == (False, 0.2, True, 10.0)
    assert (ddpg.n, ddpg.k, ddpg.hidden_size, ddpg.activation, ddpg.critic_hidden_size) == (
        6, 1_000_000, 16, "tanh", 64)  # 6M steps
    assert (ddpg.combine_before_tanh, ddpg.anneal_lr, ddpg.adam_eps, ddpg.restart_on_new_net, ddpg.obs_reward_clip) == (
        True, True, 1e-5, True, 10.0)
    assert (ddpg.learning_rate, ddpg.exploration_noise, ddpg.learning_starts, ddpg.policy_frequency, ddpg.tau,
            ddpg.batch_size, ddpg.buffer_size) == (3e-4, 0.1, 25_000, 2, 0.005, 256, 1_000_000)
    assert not sac.eval_deterministic and not ddpg.eval_deterministic  # SAC samples, DDPG keeps its noise
    assert (sac.eval_every, sac.eval_episodes, ddpg.eval_every, ddpg.eval_episodes) == (10_000, 10, 10_000, 10)


# ----------------------------------------------------------------------------------------------
# Transitions: SAME_STEP autoreset, final_obs, bootstrapping on truncation
# ----------------------------------------------------------------------------------------------
class CounterEnv(gym.Env):
    """obs = [steps so far]; terminates when the action exceeds 0.5 (a TimeLimit truncates it)."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (1,), np.float64)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.array([0.0]), {}

    def step(self, action):
        self.t += 1
        return np.array([float(self.t)]), 1.0, bool(action[0] > 0.5), False, {}


gym.register("CascadeTestCounter-v0", entry_point=CounterEnv, max_episode_steps=3)


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_truncation_bootstraps_and_termination_does_not(algo):
    mod = SCRIPTS[algo]
    envs = mod.make_vector_env([mod.make_env("CascadeTestCounter-v0")])  # no clipping: the counter passes 10
    buffer = mod.ReplayBuffer(10, 1, 1)
    obs, _ = envs.reset(seed=0)
    for a in [0.0, 0.0, 0.0, 0.0, 1.0]:  # 3 steps to the time limit, then 2 steps ending in a termination
        actions = np.array([[a]], dtype=np.float32)
        next_obs, rewards, terminations, truncations, infos = envs.step(actions)
        store_transition(buffer, obs, actions, next_obs, rewards, terminations, infos)
        obs = next_obs
    envs.close()
    assert len(buffer) == 5
    np.testing.assert_array_equal(buffer.obs[:5, 0], [0, 1, 2, 0, 1])
    # the truncated step keeps its real last obs (3, not the reset obs 0) and is not done: it bootstraps
    np.testing.assert_array_equal(buffer.next_obs[:5, 0], [1, 2, 3, 1, 2])
    np.testing.assert_array_equal(buffer.dones[:5], [0, 0, 0, 0, 1])
    np.testing.assert_array_equal(buffer.rewards[:5], [1, 1, 1, 1, 1])
    # and the obs returned on a done step is already the next episode's first (SAME_STEP)
    assert obs[0, 0] == 0.0
    # a sampled batch keeps the columns apart
    np.random.seed(0)
    b_obs, b_actions, b_rewards, b_next_obs, b_dones = buffer.sample(64, torch.device("cpu"))
    torch.testing.assert_close(b_next_obs[:, 0], b_obs[:, 0] + 1)
    torch.testing.assert_close(b_dones, (b_actions[:, 0] > 0.5).float())


class WideBoxEnv(gym.Env):
    """Random observations; actions in [0, 10] x [-1, 1] (half ranges 5 and 1, centres 5 and 0)."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
    action_space = gym.spaces.Box(np.array([0.0, -1.0], np.float32), np.array([10.0, 1.0], np.float32))

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}


gym.register("CascadeTestWideBox-v0", entry_point=WideBoxEnv, max_episode_steps=50)


@pytest.mark.parametrize("noise", [0.1, 2.0])
def test_ddpg_explores_with_noise_scaled_to_the_bounds_and_clipped(noise, tmp_path):
    """CleanRL's exploration as the training loop applies it: the env gets the policy's action plus Gaussian noise
    of std `exploration_noise` x the half range of each action dimension, clipped into the bounds. With a learning
    rate of 0 the policy never changes, so the stored actions can be compared with the final actor's."""
    learning_starts, k = 100, 600
    result = cd.train(cd.Args(env_id="CascadeTestWideBox-v0", n=1, k=k, learning_starts=learning_starts,
                              batch_size=32, learning_rate=0.0, exploration_noise=noise, eval_every=0, quiet=True,
                              track_dir=str(tmp_path)))
    buffer = result["buffer"]
    obs, actions = buffer.obs[learning_starts:k], buffer.actions[learning_starts:k]  # the policy's steps
    with torch.no_grad():
        policy = result["actor"](torch.as_tensor(obs))[0].numpy()
    low, high = WideBoxEnv.action_space.low, WideBoxEnv.action_space.high
    assert ((actions >= low) & (actions <= high)).all()
    at_bound = (actions == low) | (actions == high)
    if noise == 0.1:  # clipping is rare (the policy acts near the centre): the noise shows as it was drawn
        assert at_bound.mean() < 0.05
        inside = ~at_bound
        for dim, half_range in enumerate((high - low) / 2):
            z = (actions[inside[:, dim], dim] - policy[inside[:, dim], dim]) / (noise * half_range)
            assert abs(z.mean()) < 0.3 and 0.8 < z.std() < 1.2, (dim, z.mean(), z.std())
    else:  # std 10 and 2 around the centres, 5 and 1 from the bounds: P(|z| > 0.5) = 62% of actions end at a bound
        assert ((0.5 < at_bound.mean(0)) & (at_bound.mean(0) < 0.75)).all(), at_bound.mean(0)


class PolicyCatcher:
    """Stands in for the run in the scripts' `evaluate`: keeps the policies it is asked to evaluate."""

    def __init__(self):
        self.policies = []

    def evaluate(self, step, policy):
        self.policies.append(policy)

    def evaluate_members(self, step, policies):
        self.policies.extend(policies)


@pytest.mark.parametrize("deterministic", [False, True], ids=["default", "eval_deterministic"])
@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_evaluations_act_as_the_papers_code_evaluates(algo, deterministic):
    """The policies `evaluate` hands to the evaluation episodes, the whole cascade's and each net's alone: by
    default SAC samples its squashed Gaussian and DDPG keeps its exploration noise (std 0.1 x half range), as the
    paper's code evaluates; with --eval-deterministic, the squashed mean and the noise-free action."""
    mod = SCRIPTS[algo]
    torch.manual_seed(0)
    actor = mod.CascadeActor(5, 3, 7, 2, 0.5, np.array([-1.0, -2.0, 0.0]), np.array([1.0, 2.0, 3.0]))
    for _ in range(2):
        actor.add_base_net()  # at its init: actions well inside the bounds, so the noise is rarely clipped
    catcher = PolicyCatcher()
    args = mod.Args(eval_deterministic=deterministic)
    mod.evaluate(catcher, actor, args, 0)
    mod.evaluate(catcher, actor, args, 0, members=True)
    assert len(catcher.policies) == 3
    obs = torch.randn(1, 5).expand(4000, 5)  # one state, 4000 draws
    generator = torch.Generator().manual_seed(1)
    scale, bias = actor.action_scale, actor.action_bias
    with torch.no_grad():
        for kind, policy in enumerate(catcher.policies):  # the cascade, then net 1 and net 2 alone
            action = policy(obs, generator)[0]
            if algo == "sac":
                mean, log_std = actor(obs)[:2] if kind == 0 else actor.member(obs, kind - 1)
                centre = torch.tanh(mean) * scale + bias
                z = (torch.atanh((action - bias) / scale) - mean) / log_std.exp()
            else:
                centre = actor(obs)[0] if kind == 0 else actor.member(obs, kind - 1)
                z = (action - centre) / (args.exploration_noise * scale)
            if deterministic:
                torch.testing.assert_close(action, centre, rtol=0, atol=1e-6)
            else:
                assert abs(z.mean()) < 0.1 and 0.9 < z.std() < 1.1, (kind, z.mean(), z.std())
            # the noise comes from the evaluation's own generator: the same draws again for the same seed, and
            # training's global RNG untouched (an evaluation never changes the run it is part of)
            training_rng = torch.get_rng_state()
            again = [policy(obs, torch.Generator().manual_seed(7))[0] for _ in range(2)]
            torch.testing.assert_close(again[0], again[1], rtol=0, atol=0)
            assert torch.equal(torch.get_rng_state(), training_rng), kind


def test_replay_buffer_wraps_and_clears():
    buffer = cs.ReplayBuffer(4, 2, 1)
    for i in range(6):
        buffer.add(np.full((1, 2), i), np.full((1, 2), i + 1), np.full((1, 1), -i), np.array([i]), np.array([0]))
    assert len(buffer) == 4
    np.testing.assert_array_equal(buffer.obs[:, 0], [4, 5, 2, 3])  # the oldest rows were overwritten
    buffer.clear()
    assert len(buffer) == 0
    buffer.add(np.full((1, 2), 9), np.full((1, 2), 9), np.zeros((1, 1)), np.array([9]), np.array([1]))
    np.random.seed(0)
    assert set(buffer.sample(32, torch.device("cpu"))[0][:, 0].tolist()) == {9.0}  # nothing from before


def test_humanoid_buffer_memory():
    """A 1e6-row buffer for Humanoid-v4 (obs 376, act 17): 1e6 * (2*376 + 17 + 2) * 4 B = 3.084 GB."""
    env = gym.make("Humanoid-v4")
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    env.close()
    assert (obs_dim, act_dim) == (376, 17)
    assert cs.ReplayBuffer.nbytes(1_000_000, obs_dim, act_dim) == 3_084_000_000
    buffer = cd.ReplayBuffer(1_000_000, obs_dim, act_dim)  # np.zeros: pages are mapped, not yet resident
    assert buffer.data.nbytes == 3_084_000_000 and buffer.data.dtype == np.float32
    buffer.pos = 999_999
    buffer.add(np.ones((1, 376)), np.ones((1, 376)), np.ones((1, 17)), np.ones(1), np.ones(1))
    assert buffer.pos == 0 and len(buffer) == 1
    del buffer
    # an emptied-every-k buffer never holds more than k rows: SAC's default k = 500k needs half of that
    def capacity(args):
        return buffer_capacity(args.buffer_size, args.n, args.k, args.keep_buffer)

    assert capacity(cs.Args(env_id="Humanoid-v4")) == 500_000
    assert capacity(cd.Args(env_id="Humanoid-v4")) == 1_000_000
    assert capacity(cd.Args(keep_buffer=True)) == 1_000_000  # capped at --buffer-size


# ----------------------------------------------------------------------------------------------
# Runs as a user starts them: scalars, checkpoints, resume, --evaluate
# ----------------------------------------------------------------------------------------------
SMOKE = ["--env-id", "Hopper-v4", "--n", "2", "--k", "400", "--learning-starts", "100", "--batch-size", "32",
         "--eval-every", "200", "--eval-episodes", "2"]
COMMON_TAGS = ["charts/episodic_return", "charts/episodic_length", "charts/SPS", "losses/qf1_values",
               "losses/qf1_loss", "losses/actor_loss", "eval/episodic_return", "eval/episodic_return_std",
               "cascade/size", "cascade/parameters", "cascade/fallback/net_2", "cascade/fallback_product",
               "cascade/contribution/net_1", "cascade/contribution/net_2", "cascade/fallback_std/net_2",
               "members/return/net_1", "members/return/net_2"]
SAC_TAGS = ["losses/qf2_values", "losses/qf2_loss", "losses/qf_loss", "losses/alpha"]  # alpha_loss: with --autotune


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_hopper_smoke_run_scalars_checkpoints_resume_and_evaluate(algo, tmp_path, capsys):
    mod, script = SCRIPTS[algo], f"cascade_{algo}.py"
    proc = run_script(script, *SMOKE, "--track-dir", tmp_path / "runs")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "iteration 2/2: 2 base net(s)" in proc.stdout and "SPS" in proc.stdout
    run_dir = only_run_dir(tmp_path / "runs")
    scalars = read_scalars(run_dir)
    for tag in COMMON_TAGS + (SAC_TAGS if algo == "sac" else []):
        assert tag in scalars, f"missing {tag}; have {sorted(scalars)}"
    assert [s for s, _ in scalars["eval/episodic_return"]] == [0, 200, 400, 600, 800]
    assert [s for s, _ in scalars["cascade/fallback_std/net_2"]] == [600, 800]
    assert [(s, v) for s, v in scalars["cascade/size"]] == [(0, 1), (400, 2)]
    assert [s for s, _ in scalars["members/return/net_2"]] == [800]
    # losses are logged every 100 steps once updates run (from step 200 in iteration 1, 600 in iteration 2)
    assert [s for s, _ in scalars["losses/qf1_loss"]] == [200, 300, 400, 600, 700, 800]
    if algo == "sac":  # fixed alpha (the paper's code)
        assert [v for _, v in scalars["losses/alpha"]] == pytest.approx([0.2] * 6) and "losses/alpha_loss" not in scalars
    else:  # the learning rate anneals linearly to 0 within each iteration: 3e-4 * (1 - step_in_iteration / k)
        lr = dict(scalars["charts/learning_rate"])
        for step in (200, 300, 600, 700):
            assert lr[step] == pytest.approx(3e-4 * (1 - ((step - 1) % 400) / 400), rel=1e-5)
    contributions = {t: v[-1][1] for t, v in scalars.items() if t.startswith("cascade/contribution/")}
    assert abs(sum(contributions.values()) - 1.0) < 1e-4
    assert abs(scalars["cascade/fallback_product"][-1][1] - contributions["cascade/contribution/net_1"]) < 1e-6
    assert {"checkpoint.pt", "iteration_1.pt", "iteration_2.pt"} <= set(os.listdir(run_dir))
    assert not [f for f in os.listdir(run_dir) if f.endswith(".tmp")]

    # resume from the iteration-boundary checkpoint: the same final nets as the uninterrupted run
    os.makedirs(tmp_path / "resumed")
    with open(os.path.join(run_dir, "iteration_1.pt"), "rb") as src, open(tmp_path / "resumed" / "checkpoint.pt",
                                                                           "wb") as dst:
        dst.write(src.read())
    checkpoint = mod.load_checkpoint(str(tmp_path / "resumed"))
    resumed = mod.train(mod.Args(**{**checkpoint["args"], "quiet": True}), checkpoint)
    final = mod.load_checkpoint(run_dir)
    for key in ("actor", "qf", "qf_target"):
        again = resumed[key].state_dict()
        for name, value in final[key].items():
            torch.testing.assert_close(again[name], value, rtol=0, atol=0, msg=f"{key}.{name}")
    again = read_scalars(resumed["run_dir"])
    assert [s for s, _ in again["eval/episodic_return"]] == [600, 800]
    assert again["eval/episodic_return"] == scalars["eval/episodic_return"][-2:]

    code, out, error = cli_in_process(capsys, script, "--evaluate", run_dir, "--eval-episodes", "2", "--members")
    assert code == 0, error
    assert "2 base net(s), step 800" in out and "net 2 alone" in out
    # its returns are the saved actor's, evaluated directly, and each net's alone in turn (audit: only the wording
    # was checked), with the exploration as evaluation during training has it, or none with --eval-deterministic
    actor = mod.actor_from_checkpoint(final)
    for deterministic in (False, True):
        got = mod.evaluate_saved(mod.Args(evaluate=run_dir, eval_episodes=3, seed=7, members=True,
                                          eval_deterministic=deterministic, quiet=True))
        explore = deterministic if algo == "sac" else 0.0 if deterministic else final["args"]["exploration_noise"]
        evaluator = Evaluator("Hopper-v4", 3, 7, final["args"]["obs_reward_clip"])
        np.testing.assert_array_equal(got["returns"], evaluator(mod.full_policy(actor, explore))[0])
        for net in range(2):
            np.testing.assert_array_equal(got["members"][net], evaluator(mod.member_policy(actor, net, explore))[0])
        evaluator.close()
        assert not np.array_equal(got["members"][0], got["members"][1])
    code, out, error = cli_in_process(capsys, script, "--resume", run_dir)
    assert code == 0 and "nothing to resume" in out, error
    # a bad value of a flag --resume takes anew is refused even though nothing would run (it said "nothing to
    # resume" and exited 0)
    for flag, value in [("--checkpoint-every", "-5"), ("--torch-threads", "0")]:
        code, out, error = cli_in_process(capsys, script, "--resume", run_dir, flag, value)
        assert code != 0 and flag in error and "nothing to resume" not in out, (out, error)


def test_help_names_the_baselines(capsys):
    for script, baseline in [("cascade_sac.py", "--n 1 --hidden-size 256 --k 2000000"),
                             ("cascade_ddpg.py", "--n 1 --k 6000000 --hidden-size 64")]:
        code, out, _ = cli_in_process(capsys, script, "--help")
        assert code == 0
        assert baseline in out and "baseline" in out
        for flag in ["--keep-buffer", "--reset-critic", "--eval-deterministic", "--fallback-init", "--resume",
                     "--evaluate", "--no-restart-on-new-net", "--obs-reward-clip"]:
            assert flag in out


# ----------------------------------------------------------------------------------------------
# Bad input: one line, non-zero exit, no run folder
# ----------------------------------------------------------------------------------------------
BAD_INPUT = [
    (dict(env_id="Hoper-v4"), "unknown env id"),
    (dict(env_id="CartPole-v1"), "Box"),
    (dict(n=0), "--n must be at least 1"),
    (dict(fallback_init=1.0), "--fallback-init"),
    (dict(fallback_init=0.0), "--fallback-init"),
    (dict(k=100, learning_starts=100), "must exceed --learning-starts 100 + 1"),
    (dict(k=101, learning_starts=100), "must exceed --learning-starts 100 + 1"),  # (no update step: it did not learn)
    # no multiple of the frequency among an iteration's update steps (101..599): the actor never trained, exit 0 (audit)
    (dict(k=600, learning_starts=100, policy_frequency=600), "--policy-frequency 600: no update step of an iteration "
                                                             "(101 to 599) is a multiple of it"),
    # a buffer emptied every 600 steps never holds 2,000 rows: every batch repeated rows, exit 0 (a new-user pass)
    (dict(env_id="Pendulum-v1", n=1, k=600, learning_starts=300, batch_size=2000), "--batch-size 2000 exceeds the "
                                                                                   "600 rows the replay buffer"),
]


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
@pytest.mark.parametrize("overrides,message", [
    *BAD_INPUT, (dict(autotune=True, alpha=0.5), "--alpha 0.5 has no effect"),
    (dict(k=600, learning_starts=100, target_network_frequency=1000), "--target-network-frequency 1000: no update")])
def test_bad_input_stops_before_anything_is_written(algo, overrides, message, tmp_path):
    mod = SCRIPTS[algo]
    if ("autotune" in overrides or "target_network_frequency" in overrides) and algo == "ddpg":
        pytest.skip("a SAC setting")
    with pytest.raises(SystemExit) as stop:
        mod.train(mod.Args(track_dir=str(tmp_path / "runs"), **overrides))
    text = str(stop.value)
    assert text.startswith("error:") and message in text and "\n" not in text
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_update_frequencies_are_refused_only_where_no_update_step_is_a_multiple(algo, tmp_path):
    """The check is exact: steps 101..599 hold a multiple of 500 (the actor updates there), of 599 too, not of 600;
    with --no-restart-on-new-net updates start one step earlier (step learning_starts, 100)."""
    mod = SCRIPTS[algo]
    for restart, frequency, refused in [(True, 500, False), (True, 599, False), (True, 600, True),
                                        (False, 100, False), (True, 100, True)]:
        args = mod.Args(env_id="Pendulum-v1", k=600 if frequency > 100 else 101, learning_starts=100, batch_size=32,
                        policy_frequency=frequency, restart_on_new_net=restart, track_dir=str(tmp_path / "runs"))
        if refused:
            with pytest.raises(SystemExit, match="is a multiple of it|must exceed --learning-starts 100 \\+ 1"):
                mod.validate(args)
        else:
            mod.validate(args)


@pytest.mark.parametrize("script", ["cascade_sac.py", "cascade_ddpg.py"])
def test_bad_input_on_the_command_line_is_one_line(script, tmp_path):
    proc = run_script(script, "--env-id", "CartPole-v1", "--track-dir", tmp_path / "runs")
    assert "Box" in error_line(proc)
    assert not (tmp_path / "runs").exists()


# ----------------------------------------------------------------------------------------------
# Learning (Pendulum-v1: about 30 s each on one core)
# ----------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("check", ["sac_pendulum", "ddpg_inverted_pendulum"])
def test_learns(check, tmp_path):
    """SAC: Pendulum-v1, 2 nets of 3K steps; DDPG: InvertedPendulum-v4, 2 nets of 4K steps (see
    tests/learning_checks.py for the spread the thresholds come from)."""
    learning_checks.assert_learns(check, str(tmp_path))


def test_sac_evaluations_act_through_get_action(monkeypatch):
    """An edit of `get_action` (another sampling of the policy) is the policy the evaluations act with too, as
    `explore` and `sac_update` do (a researcher's probe, 2026-12-05: they sampled through their own copy of it)."""
    mod = SCRIPTS["sac"]
    actor = make_actor(mod, 2)

    def edited(self, obs, generator=None):
        return torch.full((len(obs), 3), 0.25), torch.zeros(len(obs), 1), torch.full((len(obs), 3), -0.5)

    monkeypatch.setattr(mod.CascadeActor, "get_action", edited)
    obs = torch.zeros(4, 5)
    for deterministic, expected in ((False, 0.25), (True, -0.5)):
        action, fallback = mod.full_policy(actor, deterministic)(obs, torch.Generator().manual_seed(0))
        assert torch.equal(action, torch.full((4, 3), expected)) and fallback.shape == (1, 4)


@pytest.mark.parametrize("algo", ["sac", "ddpg"])
def test_a_run_started_before_the_batch_size_check_still_resumes(algo, tmp_path):
    """A review: the check that --batch-size fits the rows the buffer can hold ran on resume too, so a run started
    before it with a small --k could never be resumed (a resume may not change --batch-size). New runs only."""
    mod = SCRIPTS[algo]
    args = mod.Args(env_id="Pendulum-v1", n=1, k=600, learning_starts=300, batch_size=2000,
                    track_dir=str(tmp_path / "runs"))
    with pytest.raises(SystemExit, match="--batch-size 2000 exceeds the 600 rows"):
        mod.validate(args)
    mod.validate(args, new_run=False)
