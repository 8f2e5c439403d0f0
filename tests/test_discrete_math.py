"""The method of the discrete scripts against plain references written here: GAE, the PPO loss and its gradient,
one PPO update, the whole Cascade stack training (Section 3: older base nets stay trainable), and the
normalization statistics of a discretized Box task carried across Cascade iterations (Appendix B.3) and used by
the evaluations (Appendix B.5)."""

import copy
import dataclasses

import gymnasium as gym
import numpy as np
import pytest
import torch

import cascade_ppo_discrete as cpd
import ppo_baseline_discrete as pbd
from cascade_plumbing.discrete import EvaluationEpisodes
from cascade_plumbing.envs import find_wrapper
from helpers import ActionLog, ObservationLog, RecordedEnvs, assert_rows_are_normalized_observations

SCRIPTS = [cpd, pbd]


# ----------------------------------------------------------------------------------------------
# GAE
# ----------------------------------------------------------------------------------------------
def reference_gae(rewards, values, dones, next_value, next_done, gamma, lam):
    """A_t = sum_l (gamma*lam)^l delta_{t+l}, summed forward until the episode of step t ends, with
    delta_t = r_t + gamma * V(s_{t+1}) * [no episode end after step t] - V(s_t). dones[t] marks an observation that
    starts a new episode, so an episode ends after step t when dones[t + 1] (next_done after the last step)."""
    rewards, values, dones = (np.asarray(x, np.float64) for x in (rewards, values, dones))
    steps, envs = rewards.shape
    ended = np.concatenate([dones[1:], np.asarray(next_done, np.float64)[None]])  # ended[t]: an episode end after t
    following = np.concatenate([values[1:], np.asarray(next_value, np.float64)[None]])
    advantages = np.zeros((steps, envs))
    for e in range(envs):
        delta = [rewards[t, e] + gamma * following[t, e] * (1 - ended[t, e]) - values[t, e] for t in range(steps)]
        for t in range(steps):
            total, weight = 0.0, 1.0
            for u in range(t, steps):
                total += weight * delta[u]
                if ended[u, e]:
                    break
                weight *= gamma * lam
            advantages[t, e] = total
    return advantages, advantages + values


def test_reference_gae_by_hand():
    """The reference on a case worked out by hand: gamma = lambda = 0.5, so each step looks 0.25 ahead."""
    rewards, values = [[1.0], [1.0], [1.0]], [[0.0], [0.0], [0.0]]
    advantages, _ = reference_gae(rewards, values, [[0], [0], [0]], [0.0], [0.0], 0.5, 0.5)
    np.testing.assert_allclose(advantages[:, 0], [1 + 0.25 * (1 + 0.25), 1 + 0.25, 1])
    advantages, _ = reference_gae(rewards, values, [[0], [1], [0]], [4.0], [0.0], 0.5, 0.5)  # episode ends after step 0
    np.testing.assert_allclose(advantages[:, 0], [1, 1 + 0.25 * (1 + 0.5 * 4), 1 + 0.5 * 4])


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda m: m.__name__)
@pytest.mark.parametrize("next_done", [0.0, 1.0])
def test_gae_matches_the_reference(script, next_done):
    rng = np.random.default_rng(3)
    steps, envs = 40, 3
    rewards = rng.normal(size=(steps, envs))
    values = rng.normal(size=(steps, envs))
    dones = (rng.random((steps, envs)) < 0.15).astype(np.float64)  # several episode ends per env
    next_value, next_dones = rng.normal(size=envs), np.full(envs, next_done)
    as_torch = [torch.tensor(x, dtype=torch.float64) for x in (rewards, values, dones, next_value, next_dones)]
    advantages, returns = script.compute_gae(*as_torch, 0.97, 0.9)
    expected_advantages, expected_returns = reference_gae(rewards, values, dones, next_value, next_dones, 0.97, 0.9)
    np.testing.assert_allclose(advantages.numpy(), expected_advantages, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(returns.numpy(), expected_returns, rtol=1e-12, atol=1e-12)


# ----------------------------------------------------------------------------------------------
# The PPO loss and one update
# ----------------------------------------------------------------------------------------------
def reference_ppo_loss(logits, newvalue, mb, args):
    """CleanRL ppo.py's loss written out: log-softmax by hand, the clipped surrogate as a min of objectives, the
    value loss as a max of squared errors, the entropy -sum p log p."""
    log_p = logits - torch.logsumexp(logits, -1, keepdim=True)
    new_logprob = log_p.gather(-1, mb["actions"][:, None])[:, 0]
    ratio = torch.exp(new_logprob - mb["logprobs"])
    adv = mb["advantages"]
    if args.norm_adv:
        adv = (adv - adv.mean()) / (adv.std(unbiased=True) + 1e-8)
    objective = torch.minimum(ratio * adv, torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef) * adv)
    policy_loss = -objective.mean()
    error = (newvalue - mb["returns"]) ** 2
    if args.clip_vloss:
        clipped = mb["values"] + torch.clamp(newvalue - mb["values"], -args.clip_coef, args.clip_coef)
        error = torch.maximum(error, (clipped - mb["returns"]) ** 2)
    value_loss = 0.5 * error.mean()
    entropy = -(log_p.exp() * log_p).sum(-1).mean()
    return policy_loss + args.vf_coef * value_loss - args.ent_coef * entropy, policy_loss, value_loss, entropy


def minibatch(rng, size=64, actions=8):
    """A minibatch whose old log-probabilities put the ratios on both sides of the clipping range."""
    logits = torch.tensor(rng.normal(size=(size, actions)), dtype=torch.float64, requires_grad=True)
    newvalue = torch.tensor(rng.normal(size=size), dtype=torch.float64, requires_grad=True)
    action = torch.tensor(rng.integers(actions, size=size))
    with torch.no_grad():
        logprob = torch.log_softmax(logits, -1).gather(-1, action[:, None])[:, 0]
    mb = {"actions": action, "logprobs": logprob + torch.tensor(rng.normal(scale=0.4, size=size)),
          "advantages": torch.tensor(rng.normal(size=size) * 3 + 1), "returns": torch.tensor(rng.normal(size=size)),
          "values": newvalue.detach() + torch.tensor(rng.normal(scale=0.5, size=size))}
    return logits, newvalue, mb


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda m: m.__name__)
@pytest.mark.parametrize("norm_adv,clip_vloss", [(True, True), (False, False), (True, False)])
def test_ppo_loss_and_its_gradient_match_the_reference(script, norm_adv, clip_vloss):
    args = script.Args(norm_adv=norm_adv, clip_vloss=clip_vloss, clip_coef=0.2, ent_coef=0.03, vf_coef=0.7)
    logits, newvalue, mb = minibatch(np.random.default_rng(7))
    ratio = torch.exp(torch.log_softmax(logits, -1).gather(-1, mb["actions"][:, None])[:, 0] - mb["logprobs"])
    assert ((ratio > 1.2).sum() > 5 and (ratio < 0.8).sum() > 5), "the minibatch should exercise the clipping"

    loss, stats = script.ppo_loss(logits, newvalue, mb, args)
    got = torch.autograd.grad(loss, [logits, newvalue])
    expected, policy_loss, value_loss, entropy = reference_ppo_loss(logits, newvalue, mb, args)
    want = torch.autograd.grad(expected, [logits, newvalue])
    torch.testing.assert_close(loss, expected, rtol=1e-10, atol=1e-12)
    for name, value in [("policy_loss", policy_loss), ("value_loss", value_loss), ("entropy", entropy)]:
        torch.testing.assert_close(stats[name], value.detach(), rtol=1e-10, atol=1e-12, msg=name)
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w, rtol=1e-9, atol=1e-12)
    assert stats["clipfrac"] == pytest.approx(((ratio - 1).abs() > 0.2).double().mean().item())


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda m: m.__name__)
def test_one_ppo_update_matches_a_plain_loop(script):
    """ppo_update's epochs of shuffled minibatches, gradient-norm clipping and Adam steps, against a loop written
    here with the reference loss (both draw the shuffles from numpy's global RNG, seeded alike)."""
    args = script.Args(update_epochs=3, num_minibatches=4, max_grad_norm=0.5, learning_rate=3e-3)
    rng = np.random.default_rng(11)
    size, obs_dim, actions = 64, 5, 4
    batch = {"obs": torch.tensor(rng.normal(size=(size, obs_dim))), "actions": torch.tensor(rng.integers(actions, size=size)),
             "logprobs": torch.tensor(rng.normal(-1.4, 0.3, size=size)), "advantages": torch.tensor(rng.normal(size=size)),
             "returns": torch.tensor(rng.normal(size=size)), "values": torch.tensor(rng.normal(size=size))}
    torch.manual_seed(0)  # float64 throughout: Adam turns float32 rounding of near-zero gradients into whole steps
    nets = [torch.nn.Linear(obs_dim, actions).double(), torch.nn.Linear(obs_dim, 1).double()]
    twins = [torch.nn.Linear(obs_dim, actions).double(), torch.nn.Linear(obs_dim, 1).double()]
    for net, twin in zip(nets, twins):
        twin.load_state_dict(net.state_dict())
    initial = [p.detach().clone() for net in nets for p in net.parameters()]

    def adam(pair):
        return torch.optim.Adam([p for net in pair for p in net.parameters()], lr=args.learning_rate, eps=1e-5)

    np.random.seed(5)
    script.ppo_update(nets[0], nets[1], adam(nets), batch, args)

    np.random.seed(5)
    optimizer = adam(twins)
    params = [p for net in twins for p in net.parameters()]
    order = np.arange(size)
    for _ in range(args.update_epochs):
        np.random.shuffle(order)
        for chunk in np.split(order, args.num_minibatches):
            mb = {key: value[chunk] for key, value in batch.items()}
            loss = reference_ppo_loss(twins[0](mb["obs"]), twins[1](mb["obs"])[:, 0], mb, args)[0]
            optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, args.max_grad_norm)
            optimizer.step()
    for net, twin in zip(nets, twins):
        for p, q in zip(net.parameters(), twin.parameters()):
            torch.testing.assert_close(p, q, rtol=1e-9, atol=1e-10)
    assert all(not torch.equal(p, p0) for p, p0 in zip(params, initial))  # the update did move everything


# ----------------------------------------------------------------------------------------------
# How the policy acts: samples of Categorical(logits) in rollouts and evaluations, the argmax only on request
# ----------------------------------------------------------------------------------------------
def test_rollouts_sample_the_policy(monkeypatch, tmp_path):
    """A run's first rollout acts with samples of the initial, near-uniform policy (logits head gain 0.01): about
    half of the actions are not its most probable one (a greedy rollout: none)."""
    recorded, initial = [], []
    make_vector_env = cpd.make_vector_env
    monkeypatch.setattr(cpd, "make_vector_env", lambda *a: recorded.append(RecordedEnvs(make_vector_env(*a)))
                        or recorded[-1])
    args = cpd.Args(env_id="CartPole-v1", n=1, k=512, num_envs=1, num_steps=512, num_minibatches=4, update_epochs=1,
                    eval_every=0, quiet=True, track_dir=str(tmp_path))
    cpd.train(args, on_iteration_start=lambda state: initial.append(copy.deepcopy(state["actor"])))
    envs, = recorded
    with torch.no_grad():
        logits = initial[0](torch.as_tensor(np.concatenate(envs.obs[:512])))[0]
    greedy = (np.concatenate(envs.actions) == logits.argmax(-1).numpy()).mean()
    assert 0.35 < greedy < 0.65, greedy


def test_evaluations_sample_the_policy_unless_deterministic():
    """The paper evaluates the stochastic policy (Appendix B.5): evaluation episodes sample Categorical(logits),
    and take the argmax only with `deterministic` (--evaluate --deterministic). Both discrete scripts use this."""
    episodes = EvaluationEpisodes("CartPole-v1", 16, seed=1, discretize=False)
    episodes.envs = [ActionLog(env) for env in episodes.envs]

    def policy(obs):  # action 1 with probability 3/4 (the argmax), whatever the observation and batch size
        return obs.new_tensor([0.0, np.log(3.0)]).expand(len(obs), 2), None

    for deterministic in (False, True):
        for env in episodes.envs:
            env.actions.clear()
        episodes.run(policy, None, 0, deterministic)
        actions = np.concatenate([env.actions for env in episodes.envs])
        assert len(actions) > 100
        # sampled: about 3/4 (0.72-0.84 over 20 seeds; a softmax over the batch axis samples 1/2)
        assert (actions == 1).all() if deterministic else 0.6 < actions.mean() < 0.92, actions.mean()
    episodes.close()


def test_evaluations_see_observations_as_training_does():
    """Evaluation episodes normalize each raw observation with the frozen statistics and clip it to +-10, as the
    training wrappers do: checked against the raw observations the evaluation envs returned."""
    rows = []

    def policy(obs):
        rows.extend(obs.numpy())
        return obs.new_zeros(len(obs), 2), None

    mean = np.array([0.1, -0.2, 0.05, 0.3])
    for var in (np.full(4, 4.0), np.full(4, 1e-4)):  # the second puts many components beyond the clip
        rows.clear()
        episodes = EvaluationEpisodes("CartPole-v1", 4, seed=1, discretize=False)
        episodes.envs = [ObservationLog(env) for env in episodes.envs]
        episodes.run(policy, (mean, var), 0, False)
        episodes.close()
        assert len(rows) > 10
        assert_rows_are_normalized_observations(rows, episodes.envs, mean, var)
    assert np.mean(np.abs(rows) == 10) > 0.1  # the clip did act


# ----------------------------------------------------------------------------------------------
# Cascade: the whole stack trains; normalization carried across iterations of a discretized Box task
# ----------------------------------------------------------------------------------------------
TINY = dict(env_id="InvertedPendulum-v4", num_envs=2, num_steps=64, num_minibatches=2, update_epochs=1, quiet=True)


@pytest.mark.parametrize("freeze_previous", [False, True])
def test_older_base_nets_keep_training(tmp_path, freeze_previous):
    """Section 3: both the ensemble's and the new net's parameters remain trainable (Fig. 4: --freeze-previous
    trains the newest net only)."""
    seen = []
    args = cpd.Args(n=2, k=256, eval_every=0, freeze_previous=freeze_previous, track_dir=str(tmp_path), **TINY)
    result = cpd.train(args, on_iteration_start=lambda s: seen.append(
        {key: value.clone() for key, value in s["actor"].state_dict().items()}))
    at_start, final = seen[1], result["actor"].state_dict()
    net_1_moved = any(not torch.equal(at_start[key][0], final[key][0]) for key in final if not key.startswith("fallback"))
    newest_moved = any(not torch.equal(at_start[key][-1], final[key][-1]) for key in final)
    assert newest_moved and net_1_moved != freeze_previous


def normalization_state(envs):
    """(obs mean, obs var, obs count, return count) of each training env's normalization wrappers."""
    states = []
    for env in envs.envs:
        obs_norm = find_wrapper(env, gym.wrappers.NormalizeObservation)
        reward_norm = find_wrapper(env, gym.wrappers.NormalizeReward)
        assert obs_norm is not None and reward_norm is not None, "a discretized Box task is normalized by default"
        rms = obs_norm.obs_rms
        states.append((rms.mean.copy(), rms.var.copy(), rms.count, reward_norm.return_rms.count))
    return states


def test_normalization_carries_over_iterations_on_a_discretized_box_task(tmp_path, monkeypatch):
    """Appendix B.3: each iteration gets a new PPO instance, but the observation/reward normalization stays; the
    evaluations (Appendix B.5) see the statistics as they are at that step."""
    seen, evaluated = [], []
    real_evaluate = cpd.evaluate

    def recording_evaluate(actor, episodes, stats, call=0, deterministic=False):
        evaluated.append(None if stats is None else (stats[0].copy(), stats[1].copy()))
        return real_evaluate(actor, episodes, stats, call, deterministic)

    monkeypatch.setattr(cpd, "evaluate", recording_evaluate)
    args = cpd.Args(n=3, k=256, eval_every=256, eval_episodes=1, track_dir=str(tmp_path), **TINY)
    result = cpd.train(args, on_iteration_start=lambda s: seen.append((s["envs"], normalization_state(s["envs"]))))
    per_env = args.k // args.num_envs

    counts = [[obs_count for _, _, obs_count, _ in states] for _, states in seen]
    return_counts = [[count for _, _, _, count in states] for _, states in seen]
    for i, (obs_counts, reward_counts) in enumerate(zip(counts, return_counts)):
        # every step of the earlier iterations (and each reset observation) is in the statistics
        assert all(c >= i * per_env for c in obs_counts), (i, obs_counts)
        assert all(c >= i * per_env for c in reward_counts), (i, reward_counts)
    for (_, before), (_, after) in zip(seen, seen[1:]):
        for (mean_0, _, count_0, _), (mean_1, var_1, count_1, _) in zip(before, after):
            assert count_1 == pytest.approx(count_0 + per_env, abs=per_env / 2)  # continued, not restarted
            assert not np.allclose(mean_0, mean_1) and np.all(var_1 > 0)
    assert all(envs is seen[0][0] for envs, _ in seen)  # one set of training envs for the whole run

    # the evaluations used the first training env's statistics of their moment: after i iterations, i * k steps
    assert len(evaluated) == args.n + 1 and all(stats is not None for stats in evaluated)
    for i in range(1, args.n):
        mean, var, _, _ = seen[i][1][0]
        np.testing.assert_allclose(evaluated[i][0], mean, rtol=0, atol=1e-12)
        np.testing.assert_allclose(evaluated[i][1], var, rtol=0, atol=1e-12)
    # and the final checkpoint keeps them, for --evaluate
    final = cpd.load_checkpoint(result["run_dir"])
    np.testing.assert_allclose(final["obs_stats"][0], evaluated[-1][0], rtol=0, atol=1e-12)


def test_args_of_the_tests_are_known_fields():
    """The settings used above exist in both scripts (a renamed flag should fail here, not silently)."""
    for script in SCRIPTS:
        names = {field.name for field in dataclasses.fields(script.Args)}
        assert {"norm_adv", "clip_vloss", "clip_coef", "ent_coef", "vf_coef", "update_epochs", "num_minibatches",
                "max_grad_norm", "learning_rate"} <= names
