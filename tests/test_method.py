"""The method of both continuous PPO scripts against independent references (GitHub issue 31).

Each test here fails on a one-line change of the method that the rest of the fast suite let through:
the evaluations' observation statistics (logged and `--evaluate`), GAE and the PPO loss of both
scripts against one reference written here, the CleanRL/paper defaults and initializations, the
parameter counts from the layer sizes (and Table 2), and `--freeze-previous` over a whole run.
"""

import copy
import math
import os

import gymnasium as gym
import numpy as np
import pytest
import torch

import cascade_ppo_continuous as cpc
import ppo_baseline
from helpers import ActionLog, ObservationLog, RecordedEnvs, assert_rows_are_normalized_observations, read_scalars

SCRIPTS = [cpc, ppo_baseline]
TINY = dict(num_steps=256, num_minibatches=4, update_epochs=2)
EVAL_EPISODES = 4


def close_to(logged, direct):
    """TensorBoard keeps float32: a logged mean equals the float64 one to ~1e-7 relative."""
    return abs(logged - direct) <= 1e-5 * max(1.0, abs(direct))


def clearly_apart(a, b):
    """100 times `close_to`'s tolerance: a difference the comparison must be able to see."""
    return abs(a - b) > 1e-3 * max(1.0, abs(b))


def load(module, path):
    """The script's own checkpoint loader (`load_checkpoint(path)`; `load_run(path)` where the refactor into
    cascade_plumbing moved it, leaving `load_checkpoint` the shared loader that also takes the format)."""
    return module.load_run(path) if hasattr(module, "load_run") else module.load_checkpoint(path)


def policy_for(module, actor):
    """What the script's Evaluator takes: the flagship a policy function, the baseline the actor itself."""
    return module.full_policy(actor) if hasattr(module, "full_policy") else actor


def evaluate_directly(module, env_id, seed, actor, stats, call, deterministic=False, policy=None):
    evaluator = module.Evaluator(env_id, EVAL_EPISODES, seed)
    try:
        out = evaluator(policy_for(module, actor) if policy is None else policy, stats, call, deterministic)
    finally:
        evaluator.close()
    return out[0] if isinstance(out, tuple) else out  # the flagship also returns the fallbacks' spread


# ----------------------------------------------------------------------------------------------
# 1. Logged evaluations see the training observation statistics of their step
# ----------------------------------------------------------------------------------------------
# An evaluation at a multiple of --eval-every runs inside the rollout, before that rollout's update, so it
# never sees the nets an iteration_<i>.pt holds. Two evaluations do: each net acting alone at the end of an
# iteration (`members/return/net_i`, right before the checkpoint is written), and the final policy at the end
# of the run when the last step is not a multiple of --eval-every (right after the last checkpoint). Every
# evaluation draws its episode seeds and action noise from (seed, call), where `call` counts the evaluations
# of the run; a checkpoint keeps the count (`eval_calls`) as it stood when it was written.
FLAGSHIP_RUN = dict(env_id="Hopper-v4", n=2, k=512, eval_every=384, eval_episodes=EVAL_EPISODES, seed=3,
                    eval_in_worker=False, quiet=True, **TINY)
BASELINE_RUN = dict(env_id="Hopper-v4", total_timesteps=1024, eval_every=384, eval_episodes=EVAL_EPISODES, seed=3,
                    eval_in_worker=False, quiet=True, **TINY)


@pytest.fixture(scope="module")
def flagship_run(tmp_path_factory):
    """Evaluations (calls) at steps 0 (0), 384 (1), net 1 alone at 512 (2; iteration_1.pt: eval_calls 3),
    768 (3), nets 1 and 2 alone at 1024 (4, 5), the final policy at 1024 (6; logged before iteration_2.pt is
    written, so that checkpoint holds eval_calls 7)."""
    return cpc.train(cpc.Args(track_dir=str(tmp_path_factory.mktemp("flagship")), **FLAGSHIP_RUN))


@pytest.fixture(scope="module")
def baseline_run(tmp_path_factory):
    """Evaluations at steps 0, 384, 768 and the final policy at 1024 (call 3), before the run's one checkpoint."""
    return ppo_baseline.train(ppo_baseline.Args(track_dir=str(tmp_path_factory.mktemp("baseline")), **BASELINE_RUN))


def test_flagship_evaluations_use_the_training_statistics_of_their_step(flagship_run):
    run_dir = flagship_run["run_dir"]
    scalars = read_scalars(run_dir)
    final = dict(scalars["eval/episodic_return"])
    assert sorted(final) == [0, 384, 768, 1024]
    alone = dict(scalars["members/return/net_1"])
    assert sorted(alone) == [512, 1024]
    first = load(cpc, os.path.join(run_dir, "iteration_1.pt"))
    last = load(cpc, os.path.join(run_dir, "iteration_2.pt"))
    assert (first["global_step"], last["global_step"]) == (512, 1024)
    assert (first["eval_calls"], last["eval_calls"]) == (3, 7)
    seed = FLAGSHIP_RUN["seed"]

    # the final policy, evaluated right before iteration_2.pt was written: the checkpoint counts its call
    actor, stats = cpc.actor_from_checkpoint(last), last["obs_stats"]
    assert stats is not None
    direct = evaluate_directly(cpc, "Hopper-v4", seed, actor, stats, last["eval_calls"] - 1).mean()
    assert close_to(final[1024], direct), (final[1024], direct)
    # the comparison can see wrong statistics: none at all (raw observations), or an earlier step's
    raw = evaluate_directly(cpc, "Hopper-v4", seed, actor, None, last["eval_calls"] - 1).mean()
    stale = evaluate_directly(cpc, "Hopper-v4", seed, actor, first["obs_stats"], last["eval_calls"] - 1).mean()
    assert clearly_apart(raw, direct) and clearly_apart(stale, direct), (raw, stale, direct)

    # net 1 alone at the end of iteration 1, the last evaluation before iteration_1.pt was written
    actor, stats = cpc.actor_from_checkpoint(first), first["obs_stats"]
    member = cpc.member_policy(actor, 0)
    direct = evaluate_directly(cpc, "Hopper-v4", seed, actor, stats, first["eval_calls"] - 1, policy=member).mean()
    assert close_to(alone[512], direct), (alone[512], direct)
    raw = evaluate_directly(cpc, "Hopper-v4", seed, actor, None, first["eval_calls"] - 1, policy=member).mean()
    assert clearly_apart(raw, direct), (raw, direct)


def test_baseline_final_evaluation_uses_the_training_statistics(baseline_run):
    run_dir = baseline_run["run_dir"]
    final = dict(read_scalars(run_dir)["eval/episodic_return"])
    assert sorted(final) == [0, 384, 768, 1024]
    checkpoint = load(ppo_baseline, run_dir)
    assert checkpoint["global_step"] == 1024 and checkpoint["eval_calls"] == 4
    actor, stats = ppo_baseline.actor_from_checkpoint(checkpoint), checkpoint["obs_stats"]
    assert stats is not None
    seed = BASELINE_RUN["seed"]
    direct = evaluate_directly(ppo_baseline, "Hopper-v4", seed, actor, stats, checkpoint["eval_calls"] - 1).mean()
    assert close_to(final[1024], direct), (final[1024], direct)
    raw = evaluate_directly(ppo_baseline, "Hopper-v4", seed, actor, None, checkpoint["eval_calls"] - 1).mean()
    assert clearly_apart(raw, direct), (raw, direct)


# ----------------------------------------------------------------------------------------------
# 6. --evaluate: the returns of the saved policy with its saved statistics
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("deterministic", [False, True])
@pytest.mark.parametrize("module", SCRIPTS, ids=lambda m: m.__name__)
def test_evaluate_saved_returns_equal_a_direct_evaluation(module, deterministic, flagship_run, baseline_run, capsys):
    run_dir = (flagship_run if module is cpc else baseline_run)["run_dir"]
    got = module.evaluate_saved(module.Args(evaluate=run_dir, eval_episodes=EVAL_EPISODES, seed=7,
                                            deterministic=deterministic, quiet=True))["returns"]
    printed = capsys.readouterr().out
    checkpoint = load(module, run_dir)
    actor, stats = module.actor_from_checkpoint(checkpoint), checkpoint["obs_stats"]
    # one evaluation of a saved model: the first call of an Evaluator with --seed
    direct = evaluate_directly(module, "Hopper-v4", 7, actor, stats, 0, deterministic)
    np.testing.assert_allclose(got, direct, rtol=1e-9)
    assert f"return {direct.mean():.1f} ± {direct.std():.1f} over {EVAL_EPISODES}" in printed, printed
    raw = evaluate_directly(module, "Hopper-v4", 7, actor, None, 0, deterministic)
    assert clearly_apart(raw.mean(), direct.mean()), (raw, direct)


@pytest.mark.parametrize("module", SCRIPTS, ids=lambda m: m.__name__)
def test_evaluation_samples_the_policy_unless_deterministic(module):
    """The paper evaluates the stochastic policy (Appendix B.5): evaluation episodes act with samples of
    N(mean, std), and with `deterministic` (--evaluate --deterministic) with the mean itself."""
    mean, std = 0.3, 0.2  # well inside Hopper's [-1, 1]: the evaluation's clip to the bounds rarely acts

    def policy(obs):
        out = (torch.full((len(obs), 3), mean), torch.full((len(obs), 3), math.log(std)))
        return (*out, obs.new_zeros(0, len(obs))) if module is cpc else out

    for deterministic in (False, True):
        evaluator = module.Evaluator("Hopper-v4", 3, seed=1, wrap=ActionLog)
        evaluator(policy, None, 0, deterministic)
        actions = np.concatenate([env.actions for env in evaluator.envs])
        evaluator.close()
        assert len(actions) > 30
        if deterministic:
            np.testing.assert_array_equal(actions, np.float32(mean))
        else:
            z = (actions - mean) / std
            assert abs(z.mean()) < 0.3 and 0.8 < z.std() < 1.2, (z.mean(), z.std())


@pytest.mark.parametrize("module", SCRIPTS, ids=lambda m: m.__name__)
def test_evaluation_sees_observations_as_training_does(module):
    """Evaluation normalizes each raw observation with the frozen statistics and clips it to +-10, as the
    training wrappers do (Appendix B.5): checked against the raw observations the evaluation envs returned."""
    rows = []

    def policy(obs):
        rows.extend(obs.numpy())
        out = (torch.zeros(len(obs), 3), torch.zeros(len(obs), 3))
        return (*out, obs.new_zeros(0, len(obs))) if module is cpc else out

    mean = np.linspace(-0.5, 0.5, 11)
    for var in (np.full(11, 4.0), np.full(11, 1e-4)):  # the second puts many components beyond the clip
        rows.clear()
        evaluator = module.Evaluator("Hopper-v4", 2, seed=1, wrap=ObservationLog)
        evaluator(policy, (mean, var), 0)
        evaluator.close()
        assert len(rows) > 10
        assert_rows_are_normalized_observations(rows, evaluator.envs, mean, var)
    assert np.mean(np.abs(rows) == 10) > 0.1  # the clip did act


# ----------------------------------------------------------------------------------------------
# 2. GAE and the PPO loss of both scripts against one independent reference
# ----------------------------------------------------------------------------------------------
def reference_gae(rewards, dones, values, next_value, next_done, gamma, lam):
    """Plain loops over floats. dones[t] = 1 means obs[t] began a new episode: step t-1 was the last of its
    episode, so it neither bootstraps from values[t] nor takes in advantages from t on."""
    T, E = rewards.shape
    out = np.zeros((T, E))
    for e in range(E):
        running = 0.0
        for t in reversed(range(T)):
            if t == T - 1:
                following_value, episode_ended = float(next_value[e]), bool(next_done[e])
            else:
                following_value, episode_ended = float(values[t + 1, e]), bool(dones[t + 1, e])
            if episode_ended:
                running = float(rewards[t, e]) - float(values[t, e])
            else:
                delta = float(rewards[t, e]) + gamma * following_value - float(values[t, e])
                running = delta + gamma * lam * running
            out[t, e] = running
    return out


def test_reference_gae_by_hand():
    """Three steps, one env, an episode boundary before obs[2]: checked against values worked out by hand."""
    rewards = np.array([[1.0], [2.0], [3.0]])
    values = np.array([[0.5], [0.25], [1.0]])
    dones = np.array([[0.0], [0.0], [1.0]])
    got = reference_gae(rewards, dones, values, np.array([4.0]), np.array([0.0]), 0.5, 0.5)
    a2 = 3.0 + 0.5 * 4.0 - 1.0  # bootstraps from next_value
    a1 = 2.0 - 0.25  # last step of its episode: no bootstrap, nothing from step 2
    a0 = (1.0 + 0.5 * 0.25 - 0.5) + 0.25 * a1
    np.testing.assert_allclose(got[:, 0], [a0, a1, a2])
    # next_done = 1: the rollout's last step ended its episode
    got = reference_gae(rewards, dones, values, np.array([4.0]), np.array([1.0]), 0.5, 0.5)
    assert got[2, 0] == 3.0 - 1.0


@pytest.mark.parametrize("module", SCRIPTS, ids=lambda m: m.__name__)
@pytest.mark.parametrize("num_envs,gamma,lam", [(1, 0.99, 0.95), (3, 0.99, 0.95), (2, 0.9, 0.5)])
def test_gae_matches_the_reference(module, num_envs, gamma, lam):
    rng = np.random.default_rng(num_envs)
    T = 128
    rewards = rng.normal(size=(T, num_envs)).astype(np.float32)
    dones = (rng.random((T, num_envs)) < 0.08).astype(np.float32)
    dones[T - 1] = 1.0  # an episode starting at the rollout's last observation
    values = rng.normal(size=(T, num_envs)).astype(np.float32)
    next_value = rng.normal(size=num_envs).astype(np.float32)
    next_done = (np.arange(num_envs) % 2).astype(np.float32)
    got = module.compute_gae(rewards, dones, values, next_value, next_done, gamma, lam)
    assert got.shape == (T, num_envs)
    np.testing.assert_allclose(got, reference_gae(rewards, dones, values, next_value, next_done, gamma, lam),
                               rtol=1e-5, atol=1e-5)


def reference_ppo_loss(mean, log_std, value, actions, old_logprob, advantages, returns, old_value, args):
    """CleanRL's ppo_continuous_action.py loss, the Gaussian log-density and entropy written out."""
    log2pi = math.log(2 * math.pi)
    newlogprob = (-((actions - mean) ** 2) / (2 * torch.exp(2 * log_std)) - log_std - 0.5 * log2pi).sum(1)
    ratio = torch.exp(newlogprob - old_logprob)
    if args.norm_adv:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)  # unbiased std, as torch
    pg_loss = torch.max(-advantages * ratio,
                        -advantages * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)).mean()
    if args.clip_vloss:
        v_loss_unclipped = (value - returns) ** 2
        v_clipped = old_value + torch.clamp(value - old_value, -args.clip_coef, args.clip_coef)
        v_loss = 0.5 * torch.max(v_loss_unclipped, (v_clipped - returns) ** 2).mean()
    else:
        v_loss = 0.5 * ((value - returns) ** 2).mean()
    entropy = (0.5 + 0.5 * log2pi + log_std).sum(1).mean()
    return pg_loss - args.ent_coef * entropy + v_loss * args.vf_coef, pg_loss, v_loss, entropy


LOSS_SETTINGS = [dict(), dict(norm_adv=False), dict(clip_vloss=False), dict(ent_coef=0.01),
                 dict(clip_coef=0.1, vf_coef=0.8, ent_coef=0.05)]


@pytest.mark.parametrize("module", SCRIPTS, ids=lambda m: m.__name__)
@pytest.mark.parametrize("settings", LOSS_SETTINGS, ids=lambda s: ",".join(f"{k}={v}" for k, v in s.items()) or "defaults")
def test_ppo_loss_matches_the_reference(module, settings):
    g = torch.Generator().manual_seed(0)
    B, A = 256, 3
    mean = torch.randn(B, A, generator=g, dtype=torch.float64)
    log_std = (0.4 * torch.randn(A, generator=g, dtype=torch.float64)).expand(B, A)
    actions = mean + torch.exp(log_std) * torch.randn(B, A, generator=g, dtype=torch.float64)
    # an old policy that differs: ratios spread well beyond 1 ± clip_coef on both sides
    old_logprob = torch.distributions.Normal(mean, log_std.exp()).log_prob(actions).sum(1) \
        + 0.4 * torch.randn(B, generator=g, dtype=torch.float64)
    advantages = 2.0 + 3.0 * torch.randn(B, generator=g, dtype=torch.float64)  # not normalized yet
    value = torch.randn(B, generator=g, dtype=torch.float64)
    old_value = value + 0.5 * torch.randn(B, generator=g, dtype=torch.float64)
    returns = value + torch.randn(B, generator=g, dtype=torch.float64)
    args = module.Args(**settings)
    inputs = (mean, log_std, value, actions, old_logprob, advantages, returns, old_value)
    loss, parts = module.ppo_loss(*inputs, args)
    ref_loss, ref_pg, ref_v, ref_entropy = reference_ppo_loss(*inputs, args)
    # the data reaches every branch: clipped ratios above and below, clipped values chosen by the max
    assert {"logratio", "entropy", "policy_loss", "value_loss"} <= parts.keys()  # the parts checked below, always
    ratio = torch.exp(parts["logratio"])
    assert (ratio > 1 + args.clip_coef).any() and (ratio < 1 - args.clip_coef).any()
    torch.testing.assert_close(loss, ref_loss, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(parts["policy_loss"], ref_pg, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(parts["value_loss"], ref_v, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(parts["entropy"], ref_entropy, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("autograd", [False, True], ids=["fast_paths", "autograd"])
@pytest.mark.parametrize("module", SCRIPTS, ids=lambda m: m.__name__)
def test_one_whole_update_matches_the_references(module, autograd, monkeypatch, tmp_path):
    """The last update of a real run (Cascade's: the first of its second net) against the plain references of this
    file, in float64, with one rollout, one epoch and one minibatch of the whole rollout: the rollout's actions are
    samples of the policy, and the old log-probs, values, GAE and returns built from the recorded rollout move the
    parameters by the reference loss's gradient, clipped to the global norm, times the learning rate (an
    iteration's first update runs at --learning-rate). SGD replaces Adam here: Adam's first step is about
    lr * sign(gradient) and would hide a wrong term."""
    recorded, initial = [], []
    make_vector_env, share_one_buffer = module.make_vector_env, module.share_one_buffer
    monkeypatch.setattr(module, "make_vector_env", lambda args: recorded.append(RecordedEnvs(make_vector_env(args)))
                        or recorded[-1])
    monkeypatch.setattr(module, "share_one_buffer", lambda params: initial.append(
        [p.detach().clone() for p in params]) or share_one_buffer(params))
    monkeypatch.setattr(module, "make_optimizer",
                        lambda actor, critic, flat_params, learning_rate: torch.optim.SGD([flat_params], learning_rate))
    budget = dict(n=2, k=256) if module is cpc else dict(total_timesteps=256)
    args = module.Args(env_id="Hopper-v4", num_steps=256, num_minibatches=1, update_epochs=1, learning_rate=0.5,
                       eval_every=0, checkpoint_every=0, autograd=autograd, quiet=True, track_dir=str(tmp_path),
                       **budget)
    result = module.train(args)
    envs, = recorded
    assert len(initial) == (2 if module is cpc else 1) and len(envs.actions) == 256 * len(initial)

    actor, critic = copy.deepcopy(result["actor"]).double(), copy.deepcopy(result["critic"]).double()
    params = [*actor.parameters(), *critic.parameters()]
    with torch.no_grad():
        for param, start in zip(params, initial[-1]):
            param.copy_(start)
    obs = torch.as_tensor(np.concatenate(envs.obs[-257:-1])).double()  # the last rollout
    actions = torch.as_tensor(np.concatenate(envs.actions[-256:])).double()
    mean, log_std = actor(obs)[:2]
    log_std = log_std.expand_as(mean)
    with torch.no_grad():
        # the rollout's actions: samples of the policy the update starts from, N(mean, exp(log_std)) per dimension
        z = ((actions - mean) / log_std.exp()).numpy()
        assert abs(z.mean()) < 0.2 and 0.85 < z.std() < 1.15, (z.mean(), z.std())
        values = critic(obs)[:, 0]
        next_value = critic(torch.as_tensor(envs.obs[-1]).double())[:, 0]
        rewards, dones = np.stack(envs.rewards[-256:]), np.stack(envs.dones[-257:])
        advantages = torch.as_tensor(reference_gae(rewards, dones[:-1], values.numpy()[:, None], next_value.numpy(),
                                                   dones[-1], args.gamma, args.gae_lambda)[:, 0])
        old_logprob = torch.distributions.Normal(mean, log_std.exp()).log_prob(actions).sum(1)
    loss = reference_ppo_loss(mean, log_std, critic(obs)[:, 0], actions, old_logprob, advantages,
                              advantages + values, values, args)[0]
    grads = torch.autograd.grad(loss, params)
    norm = torch.cat([g.reshape(-1) for g in grads]).norm()
    scale = min(1.0, args.max_grad_norm / (float(norm) + 1e-6))
    steps = [-args.learning_rate * scale * g for g in grads]
    moved = [(p.double() - start).detach() for p, start in
             zip([*result["actor"].parameters(), *result["critic"].parameters()], initial[-1])]
    largest = max(float(step.abs().max()) for step in steps if step.numel())
    assert largest > 1e-3  # the update moved the parameters well above float32 rounding
    for step, got in zip(steps, moved):  # measured: within 3e-7 of the largest step (float32 rounding)
        torch.testing.assert_close(got, step, rtol=0, atol=1e-4 * largest)


# ----------------------------------------------------------------------------------------------
# 3. Defaults (CleanRL's ppo_continuous_action, the paper's Cascade) and initializations
# ----------------------------------------------------------------------------------------------
CLEANRL_PPO = dict(learning_rate=3e-4, num_envs=1, gamma=0.99, gae_lambda=0.95, num_minibatches=32, update_epochs=10,
                   norm_adv=True, clip_coef=0.2, clip_vloss=True, ent_coef=0.0, vf_coef=0.5, max_grad_norm=0.5,
                   target_kl=None, normalize=True)
CASCADE = dict(n=6, k=1_000_000, hidden_size=16, num_layers=2, fallback_init=0.5, lr_schedule="cyclic",
               freeze_previous=False, start_full=False)
BASELINE = dict(hidden_size=64, lr_schedule="global")  # CleanRL's 64-64 actor and anneal_lr


@pytest.mark.parametrize("module,specific", [(cpc, CASCADE), (ppo_baseline, BASELINE)], ids=["cascade", "baseline"])
def test_defaults(module, specific, tmp_path):
    args = module.Args()
    for name, value in {**CLEANRL_PPO, **specific}.items():
        assert getattr(args, name) == value, name
    # num_steps: 2048 per rollout (written as a default of 2048 // num_envs)
    assert args.num_steps in (None, 2048)
    args = module.Args(env_id="Hopper-v4", track_dir=str(tmp_path))
    module.validate(args)
    assert args.num_steps * args.num_envs == 2048


def assert_orthogonal(weight, gain):
    """Orthogonal init with `gain` of a weight in either storage ([in, out] or [out, in]): the Gram matrix of
    its smaller side is gain^2 I."""
    w = weight.detach().double()
    gram = w.T @ w if w.shape[0] >= w.shape[1] else w @ w.T
    torch.testing.assert_close(gram, gain**2 * torch.eye(gram.shape[0], dtype=torch.float64), rtol=0,
                               atol=1e-5 * gain**2)


@pytest.mark.parametrize("fallback_init", [0.5, 0.2, 0.9])
def test_flagship_initialization(fallback_init):
    defaults = cpc.Args()
    obs_dim, act_dim, n = 11, 3, 4  # Hopper's sizes: the first layer is wider than its input
    actor = cpc.CascadeActor(obs_dim, act_dim, defaults.hidden_size, defaults.num_layers, fallback_init)
    for _ in range(n):
        actor.add_base_net()
    H = defaults.hidden_size
    assert len(actor.hidden_weights) == defaults.num_layers
    for i in range(n):
        for layer, (weight, bias) in enumerate(zip(actor.hidden_weights, actor.hidden_biases)):
            assert weight[i].shape == ((obs_dim if layer == 0 else H), H)
            assert_orthogonal(weight[i], math.sqrt(2))
            assert torch.count_nonzero(bias[i]) == 0
        assert actor.mean_weight[i].shape == (H, act_dim)
        assert_orthogonal(actor.mean_weight[i], 0.01)
        assert torch.count_nonzero(actor.mean_bias[i]) == 0
        assert torch.count_nonzero(actor.log_std[i]) == 0
    # nets 2..n: the fallback head, a column of the 0.01-gain output layer, with bias logit(fallback_init)
    assert actor.fallback_weight.shape[0] == n - 1 and actor.fallback_bias.shape[0] == n - 1
    for j in range(n - 1):
        assert math.isclose(actor.fallback_weight[j].norm().item(), 0.01, rel_tol=1e-4)
        assert math.isclose(actor.fallback_bias[j].item(), math.log(fallback_init / (1 - fallback_init)),
                            rel_tol=1e-6, abs_tol=1e-7)
    with torch.no_grad():
        fallback = actor(torch.randn(64, obs_dim))[2]
    assert (fallback - fallback_init).abs().max() < 0.02


def layers_of(mlp):
    """(weight, bias) pairs of a plain MLP in forward order, read from its parameters whatever their names."""
    params = dict(mlp.named_parameters())
    weights = [p for name, p in sorted(params.items()) if p.dim() == 2]
    biases = [p for name, p in sorted(params.items()) if p.dim() == 1]
    return list(zip(weights, biases))


@pytest.mark.parametrize("module", SCRIPTS, ids=lambda m: m.__name__)
def test_critic_initialization(module):
    obs_dim = 11
    layers = layers_of(module.make_critic(obs_dim))
    assert [sorted(w.shape) for w, _ in layers] == [sorted((obs_dim, 64)), [64, 64], [1, 64]]
    for (weight, bias), gain in zip(layers, [math.sqrt(2), math.sqrt(2), 1.0]):
        assert_orthogonal(weight, gain)
        assert torch.count_nonzero(bias) == 0


def test_baseline_actor_initialization():
    obs_dim, act_dim = 11, 3
    actor = ppo_baseline.Actor(obs_dim, act_dim, ppo_baseline.Args().hidden_size)
    log_std = [p for name, p in actor.named_parameters() if "log_std" in name]
    assert len(log_std) == 1 and torch.count_nonzero(log_std[0]) == 0 and log_std[0].numel() == act_dim
    layers = layers_of(actor.mean_net)
    assert [sorted(w.shape) for w, _ in layers] == [sorted((obs_dim, 64)), [64, 64], sorted((64, act_dim))]
    for (weight, bias), gain in zip(layers, [math.sqrt(2), math.sqrt(2), 0.01]):
        assert_orthogonal(weight, gain)
        assert torch.count_nonzero(bias) == 0


# ----------------------------------------------------------------------------------------------
# 4. Parameter counts from the layer sizes, and the paper's Table 2
# ----------------------------------------------------------------------------------------------
V4_DIMS = {"Ant-v4": (27, 8), "Hopper-v4": (11, 3), "Walker2d-v4": (17, 6), "HalfCheetah-v4": (17, 6),
           "Humanoid-v4": (376, 17)}
# Paper, Table 2 (v4 envs): actor of n=6 nets + critic, and the 64-64 PPO baseline
TABLE2_CASCADE = {"Ant-v4": 11286, "Walker2d-v4": 9470, "Hopper-v4": 8186, "Humanoid-v4": 68098,
                  "HalfCheetah-v4": 9470}
TABLE2_PPO = {"Ant-v4": 12497, "Walker2d-v4": 11085, "Hopper-v4": 10119, "Humanoid-v4": 57763,
              "HalfCheetah-v4": 11085}


def linear(d_in, d_out):
    return d_in * d_out + d_out


def critic_parameters(obs_dim):
    return linear(obs_dim, 64) + linear(64, 64) + linear(64, 1)


def cascade_parameters(obs_dim, act_dim, n, hidden=16, layers=2):
    """Actor of n base nets (each: `layers` tanh layers of width `hidden`, a mean head, a log-std vector;
    nets 2..n also a fallback head hidden -> 1) plus the 64-64 critic."""
    base_net = linear(obs_dim, hidden) + (layers - 1) * linear(hidden, hidden) + linear(hidden, act_dim) + act_dim
    return n * base_net + (n - 1) * linear(hidden, 1) + critic_parameters(obs_dim)


def ppo_parameters(obs_dim, act_dim, hidden=64):
    """The baseline's actor (hidden-hidden mean net and one log-std vector) plus the 64-64 critic."""
    return linear(obs_dim, hidden) + linear(hidden, hidden) + linear(hidden, act_dim) + act_dim \
        + critic_parameters(obs_dim)


@pytest.mark.parametrize("env_id", sorted(V4_DIMS))
def test_parameter_counts_follow_the_layer_sizes(env_id):
    env = gym.make(env_id)
    dims = (env.observation_space.shape[0], env.action_space.shape[0])
    env.close()
    assert dims == V4_DIMS[env_id]
    obs_dim, act_dim = dims
    for n, hidden, layers in [(1, 16, 2), (2, 16, 2), (6, 16, 2), (3, 8, 1), (2, 5, 3)]:
        actor = cpc.CascadeActor(obs_dim, act_dim, hidden, layers, 0.5)
        for _ in range(n):
            actor.add_base_net()
        got = cpc.count_parameters(actor, cpc.make_critic(obs_dim))
        assert got == cascade_parameters(obs_dim, act_dim, n, hidden, layers), (n, hidden, layers)
    for hidden in (64, 16):
        actor = ppo_baseline.Actor(obs_dim, act_dim, hidden)
        got = ppo_baseline.count_parameters(actor, ppo_baseline.make_critic(obs_dim))
        assert got == ppo_parameters(obs_dim, act_dim, hidden), hidden


@pytest.mark.parametrize("env_id", sorted(V4_DIMS))
def test_parameter_formula_gives_table2(env_id):
    assert cascade_parameters(*V4_DIMS[env_id], n=6) == TABLE2_CASCADE[env_id]
    assert ppo_parameters(*V4_DIMS[env_id]) == TABLE2_PPO[env_id]


# ----------------------------------------------------------------------------------------------
# 7. --freeze-previous over a whole run
# ----------------------------------------------------------------------------------------------
def net_rows(actor_state, size):
    """{net index (0-based): {parameter name: its rows}} of a CascadeActor state dict: every parameter is stacked
    over nets along its first axis, over all n nets, or over nets 2..n (the fallback head)."""
    nets = {i: {} for i in range(size)}
    for name, value in actor_state.items():
        first = size - value.shape[0]
        assert first in (0, 1), (name, value.shape)
        for row in range(value.shape[0]):
            nets[first + row][name] = value[row].detach().clone()
    return nets


def same(a, b):
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_freeze_previous_keeps_older_nets_bit_for_bit_over_a_run(tmp_path):
    starts = {}

    def record(state):
        actor = state["actor"]
        starts[state["iteration"]] = net_rows(actor.state_dict(), actor.size)

    args = cpc.Args(env_id="Hopper-v4", n=3, k=512, freeze_previous=True, eval_every=0, quiet=True,
                    track_dir=str(tmp_path), **TINY)
    result = cpc.train(args, on_iteration_start=record)
    assert result["actor"].size == 3 and sorted(starts) == [1, 2, 3]
    final = net_rows(result["actor"].state_dict(), 3)
    ends = {}
    for i in (1, 2, 3):
        checkpoint = load(cpc, os.path.join(result["run_dir"], f"iteration_{i}.pt"))
        assert checkpoint["actor_size"] == i
        ends[i] = net_rows(checkpoint["actor"], i)
    for i in (1, 2, 3):
        net = i - 1
        # net i trains in iteration i only ...
        assert not same(ends[i][net], starts[i][net]), f"net {i} did not train in iteration {i}"
        # ... and stays exactly as it was then through every later iteration, to the end of the run
        for later in range(i + 1, 4):
            assert same(starts[later][net], ends[i][net]), f"net {i} changed before iteration {later}"
            assert same(ends[later][net], ends[i][net]), f"net {i} changed in iteration {later}"
        assert same(final[net], ends[i][net])
