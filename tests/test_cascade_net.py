"""The Cascade net's math against a plain loop over the nets, gradients (parameter counts: test_method.py)."""

import math

import numpy as np
import pytest
import torch

import cascade_plumbing.fast as fast
import cascade_ppo_continuous as cpc
import ppo_baseline


def make_actor(n, obs_dim=5, act_dim=3, hidden=7, layers=2, fallback_init=0.5, randomize=True, seed=0):
    torch.manual_seed(seed)
    actor = cpc.CascadeActor(obs_dim, act_dim, hidden, layers, fallback_init)
    for _ in range(n):
        actor.add_base_net()
    if randomize:  # move away from the init so fallbacks differ between nets and states
        with torch.no_grad():
            for p in actor.parameters():
                p.normal_(0.0, 0.7)
    return actor


def reference_forward(actor, obs):
    """Independent reference: evaluate each base net on its own, then apply the recursion
    C_1 = b_1, C_i = l_i C_{i-1} + (1 - l_i) b_i one net at a time."""
    means, log_stds, fallbacks = [], [], []
    for i in range(actor.size):
        h = obs
        for w, b in zip(actor.hidden_weights, actor.hidden_biases):
            h = torch.tanh(h @ w[i] + b[i, 0])
        means.append(h @ actor.mean_weight[i] + actor.mean_bias[i, 0])
        log_stds.append(actor.log_std[i].expand(obs.shape[0], -1))
        if i > 0:
            fallbacks.append(torch.sigmoid(h @ actor.fallback_weight[i - 1] + actor.fallback_bias[i - 1, 0]))
    mean, log_std = means[0], log_stds[0]
    share = torch.zeros(actor.size, obs.shape[0], 1)  # each net's weight in C, tracked through the recursion
    share[0] = 1.0
    for i in range(1, actor.size):
        lam = fallbacks[i - 1]
        mean = lam * mean + (1 - lam) * means[i]
        log_std = lam * log_std + (1 - lam) * log_stds[i]
        one_hot = torch.zeros_like(share)
        one_hot[i] = 1.0
        share = lam.unsqueeze(0) * share + (1 - lam).unsqueeze(0) * one_hot
    fallback = torch.stack([f.squeeze(-1) for f in fallbacks]) if fallbacks else torch.zeros(0, obs.shape[0])
    return mean, log_std, fallback, share.squeeze(-1), means


@pytest.mark.parametrize("n,layers", [(1, 2), (2, 2), (3, 1), (6, 2), (8, 3)])
def test_combination_matches_plain_loop(n, layers):
    actor = make_actor(n, layers=layers, seed=n)
    obs = torch.randn(64, 5) * 2
    with torch.no_grad():
        mean, log_std, fallback, weight = actor(obs)
        ref_mean, ref_log_std, ref_fallback, ref_weight, _ = reference_forward(actor, obs)
    torch.testing.assert_close(mean, ref_mean, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(log_std, ref_log_std, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(fallback, ref_fallback, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(weight, ref_weight, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(weight.sum(0), torch.ones(64))
    if n > 1:
        # w_1 is the fallback product; the randomized nets really mix (no net dominates everywhere)
        torch.testing.assert_close(weight[0], fallback.prod(0), rtol=1e-5, atol=1e-6)
        assert fallback.std() > 0.05


def test_member_is_the_net_alone():
    actor = make_actor(4)
    obs = torch.randn(10, 5)
    with torch.no_grad():
        *_, ref_means = reference_forward(actor, obs)
        for i in range(4):
            mean, log_std = actor.member(obs, i)
            torch.testing.assert_close(mean, ref_means[i], rtol=1e-5, atol=1e-5)
            torch.testing.assert_close(log_std, actor.log_std[i].expand(10, -1))


@pytest.mark.parametrize("fallback_init", [0.05, 0.5, 0.9])
def test_new_net_starts_at_fallback_init(fallback_init):
    actor = make_actor(4, fallback_init=fallback_init, randomize=False, hidden=16)
    with torch.no_grad():
        _, _, fallback, weight = actor(torch.randn(256, 5))
    assert fallback.shape == (3, 256)
    assert (fallback - fallback_init).abs().max() < 0.02
    # the bottom net's share starts at fallback_init^(n-1)
    assert abs(weight[0].mean().item() - fallback_init**3) < 0.02


def test_growing_keeps_existing_nets():
    actor = make_actor(2)
    obs = torch.randn(16, 5)
    before = {name: p.detach().clone() for name, p, _ in actor.base_net_parameters()}
    actor.add_base_net()
    assert actor.size == 3
    for name, p, _ in actor.base_net_parameters():
        old = before[name]
        torch.testing.assert_close(p.detach()[: old.shape[0]], old)
    with torch.no_grad():  # with the new net's fallback forced to 1, the output is the old ensemble
        actor.fallback_bias[-1] = 50.0
        actor.fallback_weight[-1] = 0.0
        mean3, *_ = actor(obs)
    small = make_actor(2)
    with torch.no_grad():
        mean2, *_ = small(obs)
    torch.testing.assert_close(mean3, mean2, rtol=1e-5, atol=1e-5)


def net_grad_norms(actor):
    """Gradient norm of every base net (summed over all its parameters)."""
    norms = torch.zeros(actor.size)
    for _, p, first in actor.base_net_parameters():
        if p.grad is None:
            continue
        for row in range(p.shape[0]):
            norms[first + row] += p.grad[row].pow(2).sum()
    return norms.sqrt()


def backward(actor, obs, path):
    """Gradients of mean^2 + log_std, through autograd or the hand-written backward training uses."""
    if path == "autograd":
        for p in actor.parameters():
            p.grad = None
        mean, log_std, _, _ = actor(obs)
        (mean.pow(2).sum() + log_std.sum()).backward()
    else:
        if not hasattr(actor, "flat"):
            actor.flat = fast.share_one_buffer(list(actor.parameters()))
        with torch.no_grad():
            cache = {}
            mean, log_std, _, _ = actor(obs, cache)
            fast.cascade_backward(actor, cache, 2 * mean, torch.ones_like(log_std))


@pytest.mark.parametrize("path", ["autograd", "hand-written"])
def test_gradients_reach_every_net(path):
    actor = make_actor(4)
    backward(actor, torch.randn(32, 5), path)
    assert (net_grad_norms(actor) > 1e-6).all()


@pytest.mark.parametrize("path", ["autograd", "hand-written"])
def test_freeze_previous_trains_only_the_newest(path):
    actor = make_actor(4)
    actor.freeze_below(3)
    frozen = {name: p.detach().clone() for name, p, _ in actor.base_net_parameters()}
    for _ in range(3):
        backward(actor, torch.randn(32, 5), path)
        norms = net_grad_norms(actor)
        assert (norms[:3] == 0).all() and norms[3] > 1e-6
        with torch.no_grad():  # a plain gradient step (Adam would move frozen rows through its momentum: none here)
            for p in actor.parameters():
                p -= 0.01 * p.grad
    for name, p, first in actor.base_net_parameters():
        rows = 3 - first  # rows of this parameter that belong to nets 1..3
        torch.testing.assert_close(p.detach()[:rows], frozen[name][:rows], rtol=0, atol=0)
        assert not torch.equal(p.detach()[rows:], frozen[name][rows:])


def test_gaussian_entropy_matches_torch_normal():
    mean, log_std = torch.randn(8, 3), torch.randn(8, 3) * 0.3
    dist = torch.distributions.Normal(mean, log_std.exp())
    torch.testing.assert_close(fast.gaussian_entropy(log_std), dist.entropy().sum(-1))


def test_contributions_closed_form_small_case():
    lam2, lam3 = 0.3, 0.8
    w = cpc.contributions(torch.tensor([[lam2], [lam3]])).flatten()
    expected = torch.tensor([lam2 * lam3, (1 - lam2) * lam3, 1 - lam3])
    torch.testing.assert_close(w, expected)
    assert math.isclose(w.sum().item(), 1.0, rel_tol=1e-6)
    # a single net carries the whole output; saturated fallbacks give exact zeros, never NaN
    assert torch.equal(cpc.contributions(torch.zeros(0, 4)), torch.ones(1, 4))
    w = cpc.contributions(torch.sigmoid(torch.tensor([[-200.0, 200.0]])))
    assert torch.equal(w, torch.tensor([[0.0, 1.0], [1.0, 0.0]]))


def test_gae_matches_cleanrl_tensor_loop():
    rng = np.random.default_rng(0)
    T, E = 64, 3
    rewards = rng.normal(size=(T, E)).astype(np.float32)
    dones = (rng.random((T, E)) < 0.1).astype(np.float32)
    values = rng.normal(size=(T, E)).astype(np.float32)
    next_value, next_done = rng.normal(size=E).astype(np.float32), np.array([0, 1, 0], dtype=np.float32)
    got = cpc.compute_gae(rewards, dones, values, next_value, next_done, 0.99, 0.95)
    # CleanRL ppo_continuous_action.py, written out with tensors
    r, d, v = map(torch.as_tensor, (rewards, dones, values))
    advantages, last = torch.zeros_like(r), 0
    for t in reversed(range(T)):
        nonterminal = 1.0 - (torch.as_tensor(next_done) if t == T - 1 else d[t + 1])
        nextvalues = torch.as_tensor(next_value) if t == T - 1 else v[t + 1]
        delta = r[t] + 0.99 * nextvalues * nonterminal - v[t]
        last = delta + 0.99 * 0.95 * nonterminal * last
        advantages[t] = last
    np.testing.assert_allclose(got, advantages.numpy(), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("n,layers", [(1, 2), (2, 2), (6, 2), (3, 1), (4, 3)])
def test_numpy_policy_used_for_acting_matches_the_torch_forward(n, layers):
    actor = make_actor(n, layers=layers, seed=n)
    obs = torch.randn(4, 5)
    with torch.no_grad():
        mean, log_std, _, _ = actor(obs)
    policy = fast.numpy_cascade_policy(actor)
    np_mean, np_log_std = policy(obs.numpy())
    assert np_mean.dtype == np.float32 and np_log_std.dtype == np.float32
    np.testing.assert_allclose(np_mean, mean.numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np_log_std, log_std.numpy(), rtol=1e-5, atol=1e-6)
    for row in range(len(obs)):  # batch size 1, as in a rollout
        np.testing.assert_allclose(policy(obs[row : row + 1].numpy())[0], np_mean[row : row + 1], rtol=1e-5, atol=1e-6)
    # the policy holds copies: an update of the weights (in place, as Adam does) does not reach it
    with torch.no_grad():
        for p in actor.parameters():
            p.add_(1.0)
    np.testing.assert_array_equal(policy(obs.numpy())[0], np_mean)
    # a saturated fallback (sigmoid of a very negative logit) stays finite and silent in numpy
    with torch.no_grad():
        if n > 1:
            actor.fallback_bias[-1] = -1e4
    with np.errstate(over="raise", invalid="raise", divide="raise"):  # underflow to 0 is expected
        np_mean, _ = fast.numpy_cascade_policy(actor)(obs.numpy())
    with torch.no_grad():
        torch.testing.assert_close(torch.from_numpy(np_mean), actor(obs)[0], rtol=1e-5, atol=1e-6)


def test_baseline_numpy_policy_matches_the_torch_forward():
    torch.manual_seed(0)
    actor = ppo_baseline.Actor(5, 3, 16)
    with torch.no_grad():
        for p in actor.parameters():
            p.normal_(0.0, 0.5)
        obs = torch.randn(4, 5)
        mean, log_std = actor(obs)
    np_mean, np_log_std = fast.numpy_mlp_policy(actor)(obs.numpy())
    np.testing.assert_allclose(np_mean, mean.numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.broadcast_to(np_log_std, np_mean.shape), log_std.detach().numpy())


def test_empty_stack_acts_with_zero_mean_and_unit_std():
    """Step 0 is evaluated before net 1 exists: the empty ensemble is N(0, 1), in torch and numpy."""
    actor = cpc.CascadeActor(5, 3, 7, 2, 0.5)
    obs = torch.randn(4, 5)
    with torch.no_grad():
        mean, log_std, fallback, weight = actor(obs)
    assert torch.equal(mean, torch.zeros(4, 3)) and torch.equal(log_std, torch.zeros(4, 3))
    np_mean, np_log_std = fast.numpy_cascade_policy(actor)(obs.numpy())
    assert (np_mean == 0).all() and (np_log_std == 0).all() and np_mean.shape == (4, 3)


@pytest.mark.parametrize("num_envs,act_dim", [(1, 6), (2, 3), (1, 17), (4, 6)])
def test_rollout_sampler_draws_what_act_draws_step_by_step(num_envs, act_dim):
    """The fast rollout sampler (which may draw a whole rollout's noise at its first call) gives, step after step,
    the actions `act` samples one step at a time from the same seed, and leaves torch's RNG where `act` does;
    below 16 numbers per step (HalfCheetah: 6) in one draw, from 16 on (Humanoid: 17) one draw per step."""
    steps, obs_dim = 7, 5
    actor = cpc.CascadeActor(obs_dim, act_dim, 8, 2, 0.5)
    for _ in range(2):
        actor.add_base_net()
    observations = torch.randn(steps, num_envs, obs_dim).numpy()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(7)
        expected = [cpc.act(actor, obs) for obs in observations]
        state = torch.get_rng_state()
        torch.manual_seed(7)
        sampler = fast.numpy_gaussian_sampler(fast.numpy_cascade_policy(actor), calls=steps)
        got = [sampler(obs) for obs in observations]
        assert torch.equal(torch.get_rng_state(), state)
    np.testing.assert_allclose(np.stack(got), np.stack(expected), rtol=1e-5, atol=1e-6)
    assert fast.bulk_draws_match((num_envs, act_dim), np.float32) == (num_envs * act_dim < 16)
