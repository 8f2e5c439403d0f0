"""The hand-written PPO gradients against autograd on CleanRL's loss, written independently here."""

import pytest
import torch
from torch.distributions import Normal

import cascade_plumbing.fast as fast
import cascade_ppo_continuous as cpc
import ppo_baseline as pb
from test_cascade_net import make_actor, reference_forward


@pytest.fixture(autouse=True)
def float64():
    """In double precision the hand-written and autograd gradients agree to ~1e-12, so a tight
    tolerance catches even a small mistake in a rarely taken branch."""
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(torch.float32)


def cleanrl_loss(mean, log_std, value, actions, old_logprob, advantages, returns, old_value, args):
    """ppo_continuous_action.py's loss, with torch.distributions and autograd."""
    dist = Normal(mean, log_std.exp())
    logratio = dist.log_prob(actions).sum(1) - old_logprob
    ratio = logratio.exp()
    if args.norm_adv:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    pg_loss = torch.max(-advantages * ratio, -advantages * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)).mean()
    if args.clip_vloss:
        v_clipped = old_value + torch.clamp(value - old_value, -args.clip_coef, args.clip_coef)
        v_loss = 0.5 * torch.max((value - returns) ** 2, (v_clipped - returns) ** 2).mean()
    else:
        v_loss = 0.5 * ((value - returns) ** 2).mean()
    return pg_loss - args.ent_coef * dist.entropy().sum(1).mean() + v_loss * args.vf_coef, ratio


def minibatch(actor_fn, critic, obs_dim, act_dim, batch=64, seed=0):
    """Random minibatch whose old log-probs and values are near the current ones, so that some
    ratios and some values fall outside the clip range and some inside."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(batch, obs_dim, generator=g)
    actions = torch.randn(batch, act_dim, generator=g)
    with torch.no_grad():
        mean, log_std = actor_fn(obs)[:2]
        old_logprob = Normal(mean, log_std.exp()).log_prob(actions).sum(1) + 0.3 * torch.randn(batch, generator=g)
        old_value = critic(obs).squeeze(1) + 0.3 * torch.randn(batch, generator=g)
    return obs, actions, old_logprob, torch.randn(batch, generator=g), torch.randn(batch, generator=g), old_value


ARG_VARIANTS = [
    dict(norm_adv=True, clip_vloss=True, ent_coef=0.0),  # the defaults
    dict(norm_adv=False, clip_vloss=False, ent_coef=0.01),
    dict(norm_adv=True, clip_vloss=False, ent_coef=0.0),
    dict(norm_adv=False, clip_vloss=True, ent_coef=0.05),
]


def randomize(module: torch.nn.Module, seed: int) -> None:
    """Larger weights than the init (whose mean head is ~0.01): gradients of every size get tested."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(0.5 * torch.randn(p.shape, generator=g))


def assert_same_parts(fast_parts: dict, parts: dict) -> None:
    """The training loop reads `parts` from whichever path stepped (the ratios, the entropy, the losses): the
    hand-written update returns the keys `ppo_loss` returns, with the same values."""
    assert fast_parts.keys() == parts.keys()
    for key, value in parts.items():
        torch.testing.assert_close(torch.as_tensor(fast_parts[key]), torch.as_tensor(value).detach(), rtol=1e-9,
                                   atol=1e-12, msg=key)


@pytest.mark.parametrize("variant", ARG_VARIANTS)
def test_baseline_gradients_match_autograd(variant):
    args = pb.Args(**variant)
    actor, critic = pb.Actor(7, 3, 16), pb.make_critic(7)
    randomize(actor, 1)
    randomize(critic, 2)
    obs, actions, old_logprob, adv, returns, old_value = minibatch(actor, critic, 7, 3)
    params = [*actor.parameters(), *critic.parameters()]

    mean, log_std = actor(obs)
    ref_loss, parts = pb.ppo_loss(mean, log_std, critic(obs).squeeze(1), actions, old_logprob, adv, returns,
                                  old_value, args)
    ratio = parts["ratio"]
    ref_grads = torch.autograd.grad(ref_loss, params)
    clipped = ((ratio - 1).abs() > args.clip_coef).float().mean()
    assert 0.1 < clipped < 0.9, "the minibatch should exercise both sides of the clip"

    flat = fast.share_one_buffer(params)
    flat.grad.fill_(float("nan"))  # every gradient entry must be written
    with torch.no_grad():
        loss, fast_parts = fast.mlp_ppo_gradients(actor, critic, (obs, actions, old_logprob, adv, returns, old_value), args)
    torch.testing.assert_close(loss, ref_loss.detach(), rtol=1e-9, atol=1e-12)
    assert_same_parts(fast_parts, parts)
    for p, ref in zip(params, ref_grads):
        torch.testing.assert_close(p.grad, ref, rtol=1e-9, atol=1e-12)


def test_shared_buffer_keeps_values_and_clipping_matches_torch():
    actor, critic = pb.Actor(5, 2, 8), pb.make_critic(5)
    params = [*actor.parameters(), *critic.parameters()]
    before = [p.detach().clone() for p in params]
    flat = fast.share_one_buffer(params)
    for p, b in zip(params, before):
        assert torch.equal(p, b)
    g = torch.Generator().manual_seed(0)
    flat.grad.copy_(torch.randn(flat.shape, generator=g))
    reference_params = [torch.nn.Parameter(p.detach().clone()) for p in params]
    for rp, p in zip(reference_params, params):
        rp.grad = p.grad.clone()
    torch.nn.utils.clip_grad_norm_(reference_params, 0.5)
    fast.clip_grad_norm(flat, 0.5)
    for p, rp in zip(params, reference_params):
        torch.testing.assert_close(p.grad, rp.grad)
    # an optimizer step on the buffer moves the named parameters
    optimizer = pb.make_optimizer(None, None, flat, 1e-2)
    optimizer.step()
    assert not torch.equal(params[0], before[0])


@pytest.mark.parametrize("variant", ARG_VARIANTS)
def test_script_loss_is_cleanrls(variant):
    """The script's ppo_loss (section 1, what users edit) is CleanRL's loss: value and gradient."""
    args = cpc.Args(**variant)
    actor, critic = make_actor(3, seed=4), cpc.make_critic(5)
    randomize(critic, 5)
    obs, actions, old_logprob, adv, returns, old_value = minibatch(actor, critic, 5, 3, seed=7)
    params = [*actor.parameters(), *critic.parameters()]
    mean, log_std, *_ = actor(obs)
    value = critic(obs).squeeze(1)
    ours, parts = cpc.ppo_loss(mean, log_std, value, actions, old_logprob, adv, returns, old_value, args)
    reference, ratio = cleanrl_loss(mean, log_std, value, actions, old_logprob, adv, returns, old_value, args)
    torch.testing.assert_close(ours, reference, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(parts["ratio"], ratio)
    for got, want in zip(torch.autograd.grad(ours, params, allow_unused=True, retain_graph=True),
                         torch.autograd.grad(reference, params, allow_unused=True)):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("n,layers,frozen,variant", [
    (1, 2, 0, 0), (2, 2, 0, 0), (4, 1, 0, 1), (6, 2, 0, 0), (6, 2, 0, 3), (5, 3, 4, 0), (3, 2, 2, 2),
])
def test_cascade_gradients_match_autograd_through_the_plain_loop(n, layers, frozen, variant):
    """The fast path's hand-written gradients (ppo_loss_gradients, cascade_backward, mlp_backward) against
    autograd through the script's ppo_loss on the net-by-net recursion of the tests."""
    args = cpc.Args(**ARG_VARIANTS[variant])
    actor = make_actor(n, layers=layers, seed=n)  # weights randomized away from the init
    actor.freeze_below(frozen)
    critic = cpc.make_critic(5)
    randomize(critic, 3)
    obs, actions, old_logprob, adv, returns, old_value = minibatch(
        lambda x: reference_forward(actor, x), critic, 5, 3, seed=n)
    params = [*actor.parameters(), *critic.parameters()]

    mean, log_std, *_ = reference_forward(actor, obs)
    ref_loss, parts = cpc.ppo_loss(mean, log_std, critic(obs).squeeze(1), actions, old_logprob, adv, returns,
                                   old_value, args)
    ratio = parts["ratio"]
    clipped = ((ratio - 1).abs() > args.clip_coef).float().mean()
    assert 0.05 < clipped < 0.95, "the minibatch should exercise both sides of the clip"
    grads = torch.autograd.grad(ref_loss, params, allow_unused=True)  # n = 1: the fallback head is empty
    ref_grads = {p: torch.zeros_like(p) if g is None else g for p, g in zip(params, grads)}
    for _, p, first_net in actor.base_net_parameters():  # frozen nets get no gradient
        ref_grads[p][: max(frozen - first_net, 0)] = 0.0

    flat = fast.share_one_buffer(params)
    flat.grad.fill_(float("nan"))  # every gradient entry must be written
    with torch.no_grad():
        loss, fast_parts = fast.cascade_ppo_gradients(actor, critic, (obs, actions, old_logprob, adv, returns, old_value), args)
    torch.testing.assert_close(loss, ref_loss.detach(), rtol=1e-9, atol=1e-12)
    assert_same_parts(fast_parts, parts)
    for p in params:
        torch.testing.assert_close(p.grad, ref_grads[p], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("n,frozen", [(1, 0), (3, 0), (4, 2)])
def test_autograd_path_writes_the_same_gradients(n, frozen):
    """autograd_gradients (section 1, the --autograd path) and fast_gradients (section 2) agree."""
    args = cpc.Args()
    actor = make_actor(n, seed=n + 10)
    actor.freeze_below(frozen)
    critic = cpc.make_critic(5)
    randomize(critic, 6)
    batch = minibatch(actor, critic, 5, 3, seed=n)
    params = [*actor.parameters(), *critic.parameters()]
    flat = fast.share_one_buffer(params)
    with torch.no_grad():
        loss, _ = fast.cascade_ppo_gradients(actor, critic, batch, args)
    fast_grad = flat.grad.clone()
    flat.grad.fill_(float("nan"))
    with torch.no_grad():
        auto_loss, _ = cpc.autograd_gradients(actor, critic, params, batch, args)
    torch.testing.assert_close(auto_loss, loss, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(flat.grad, fast_grad, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("module", [pb, cpc])
def test_adam_step_equals_torch_optimizer_step_bit_for_bit(module):
    """adam_step calls the fused kernel directly; it must do exactly what Adam.step() does, through
    learning-rate changes (annealing) and a checkpoint round trip of the optimizer state."""
    g = torch.Generator().manual_seed(0)
    start = torch.randn(300, generator=g, dtype=torch.float32)
    grads = [torch.randn(300, generator=g, dtype=torch.float32) * 10.0 ** -k for k in range(8)]

    def run(step, restore_after=None):
        flat = torch.nn.Parameter(start.clone())
        flat.grad = torch.zeros_like(flat)
        optimizer = module.make_optimizer(None, None, flat, 3e-4)
        with torch.inference_mode():  # as in training
            for i, grad in enumerate(grads):
                if i == restore_after:  # a fresh optimizer from the saved state, as a resumed run makes
                    saved = optimizer.state_dict()
                    optimizer = module.make_optimizer(None, None, flat, 3e-4)
                    optimizer.load_state_dict(saved)
                optimizer.param_groups[0]["lr"] = 3e-4 * (1 - i / len(grads))
                flat.grad.copy_(grad)
                step(optimizer)
        return flat.detach(), optimizer.state[flat]

    reference, reference_state = run(lambda optimizer: optimizer.step())
    for restore_after in (None, 3):
        result, state = run(fast.adam_step, restore_after)
        assert torch.equal(result, reference)
        for key in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(state[key], reference_state[key])
    assert not torch.equal(reference, start)


def test_a_loss_that_cancels_to_near_zero_is_no_disagreement():
    """Late in a run the policy loss can cancel half the value loss down to ~1e-7, where the two paths' float64
    rounding (~1e-16) read as a relative error of ~1e-9 and switched an Ant-v4 run's fast path off at 5.8M steps.
    The loss is compared on the scale of its O(1) terms, as its parts are; a real difference is still one."""
    paths = fast.FastPaths(True, None, None)
    loss = torch.tensor(1e-7, dtype=torch.float64)
    parts = {"policy_loss": torch.tensor(-5e-8, dtype=torch.float64)}
    gradient = [torch.ones(3, dtype=torch.float64)]
    assert paths.disagreement(["w"], loss, parts, gradient, loss + 2e-16, parts, gradient) is None
    message = paths.disagreement(["w"], loss, parts, gradient, loss + 1e-9, parts, gradient)
    assert message is not None and "another loss" in message


def test_the_optimizer_checks_copy_leaves_the_runs_settings_alone():
    """A review: the check's float64 copy of the optimizer shared a tensor learning rate with the run's, so an
    `optimizer_step` that decays it in place changed the run's own rate inside the check."""
    flat = torch.nn.Parameter(torch.zeros(3))
    optimizer = torch.optim.Adam([flat], lr=torch.tensor(3e-4), eps=1e-5)
    _, twin = fast.float64_optimizer(optimizer)
    twin.param_groups[0]["lr"].mul_(0.5)
    assert optimizer.param_groups[0]["lr"].item() == pytest.approx(3e-4)
