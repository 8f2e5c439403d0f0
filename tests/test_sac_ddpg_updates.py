"""One update of each off-policy script against a plain reference written here (CleanRL's SAC and DDPG, paper
Appendix H): on a fixed replay batch with terminations, `cascade_sac.sac_update` and `cascade_ddpg.ddpg_update`
must move every parameter, and report every loss, as the reference does, up to float64 rounding.

The reference spells out what the scripts' updates fold into batched code: the Bellman target (no bootstrap
after a termination), the twin-Q minimum and the entropy term (SAC), alpha's loss (--autotune), the delayed
actor updates (`policy_frequency`), and the soft target updates. It uses the scripts' nets only for the actor's
forward (checked against a plain loop over the base nets in tests/test_sac_ddpg.py); the critics are evaluated
here one by one from their weights. The optimizers are plain SGD: a parameter then moves by exactly lr times
its gradient, so a wrong term of a loss shows (Adam's first step is about lr * sign(gradient) and would hide
most of them)."""

import copy
import math

import numpy as np
import pytest
import torch

import cascade_ddpg as cd
import cascade_sac as cs
from helpers import perturb, replay_batch

OBS_DIM, ACT_DIM, BATCH = 5, 3, 16
LOW, HIGH = np.array([-1.0, -2.0, 0.0]), np.array([1.0, 2.0, 3.0])  # asymmetric bounds: scale and bias matter
LR = 0.05
STEPS = range(4)  # steps_in_iteration of four consecutive updates: the delays skip some of them


@pytest.fixture(autouse=True)
def float64():
    """Everything in float64, the noise the actors draw included, so rounding (~1e-15) is far from any error."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


def fixed_batch():
    """(obs, actions, rewards, next_obs, dones) as ReplayBuffer.sample gives them; every third row terminated."""
    return replay_batch(7, BATCH, OBS_DIM, LOW, HIGH, obs_scale=2, reward_scale=3, done_every=3)


def perturbed(module, scale, seed):
    """The module with every parameter moved off its init (fallbacks then differ between nets and states)."""
    return perturb(module, scale, seed).double()


def plain_q(qf, obs, actions, activation):
    """Each critic of a stacked QNetworks on its own: [obs, action] -> H -> H -> 1. Returns [num_q, B]."""
    values = []
    for i in range(qf.weights[0].shape[0]):
        x = torch.cat([obs, actions], 1)
        for layer, (weight, bias) in enumerate(zip(qf.weights, qf.biases)):
            x = x @ weight[i] + bias[i, 0]
            if layer < len(qf.weights) - 1:
                x = activation(x)
        values.append(x[:, 0])
    return torch.stack(values)


def sgd(params, loss):
    grads = torch.autograd.grad(loss, params, allow_unused=True)  # unused: the fallback head of a single net
    with torch.no_grad():
        for p, g in zip(params, grads):
            if g is not None:
                p.sub_(LR * g)


def soft(target, source, tau):
    with torch.no_grad():
        for t, s in zip(target.parameters(), source.parameters()):
            t.copy_((1 - tau) * t + tau * s)


def assert_same(module, reference):
    for (name, p), q in zip(module.named_parameters(), reference.parameters()):
        torch.testing.assert_close(p, q, rtol=1e-10, atol=1e-12, msg=name)


# ----------------------------------------------------------------------------------------------
# SAC
# ----------------------------------------------------------------------------------------------
def plain_sac_sample(actor, obs):
    """CleanRL's get_action, drawing its noise from the global RNG as the script does: a sample of
    N(mean, std) squashed by tanh into the bounds, and its log-probability with the tanh correction [B]."""
    mean, log_std, _, _ = actor(obs)
    std = log_std.exp()
    x = mean + std * torch.randn(mean.shape)
    y = torch.tanh(x)
    scale, bias = torch.as_tensor((HIGH - LOW) / 2), torch.as_tensor((HIGH + LOW) / 2)
    log_prob = torch.distributions.Normal(mean, std).log_prob(x) - torch.log(scale * (1 - y.pow(2)) + 1e-6)
    return y * scale + bias, log_prob.sum(1)


def reference_sac_update(args, step, batch, actor, qf, qf_target, log_alpha, alpha):
    """Returns the losses and alpha; updates the nets and log_alpha in place."""
    obs, actions, rewards, next_obs, dones = batch
    with torch.no_grad():
        next_actions, next_log_prob = plain_sac_sample(actor, next_obs)
        soft_value = plain_q(qf_target, next_obs, next_actions, torch.relu).min(0).values - alpha * next_log_prob
        target = rewards + args.gamma * (1 - dones) * soft_value
    q = plain_q(qf, obs, actions, torch.relu)
    losses = {"qf_a_values": q, "qf1_loss": ((q[0] - target) ** 2).mean(), "qf2_loss": ((q[1] - target) ** 2).mean()}
    losses["qf_loss"] = losses["qf1_loss"] + losses["qf2_loss"]
    sgd(list(qf.parameters()), losses["qf_loss"])
    if step % args.policy_frequency == 0:  # delayed, and as many actor updates as steps skipped
        for _ in range(args.policy_frequency):
            pi, log_prob = plain_sac_sample(actor, obs)
            losses["actor_loss"] = (alpha * log_prob - plain_q(qf, obs, pi, torch.relu).min(0).values).mean()
            sgd(list(actor.parameters()), losses["actor_loss"])
            if args.autotune:  # towards the target entropy -act_dim, on a fresh sample of the updated actor
                with torch.no_grad():
                    _, log_prob = plain_sac_sample(actor, obs)
                losses["alpha_loss"] = (-log_alpha.exp() * (log_prob - ACT_DIM)).mean()
                sgd([log_alpha], losses["alpha_loss"])
                alpha = math.exp(log_alpha.item())
    if step % args.target_network_frequency == 0:
        soft(qf_target, qf, args.tau)
    return {**losses, "alpha": alpha}


@pytest.mark.parametrize("n", [1, 3], ids=["baseline", "cascade"])
@pytest.mark.parametrize("autotune", [False, True], ids=["fixed_alpha", "autotune"])
@pytest.mark.parametrize("policy_frequency,target_network_frequency", [(2, 1), (3, 2)])
def test_sac_update_matches_reference(n, autotune, policy_frequency, target_network_frequency):
    args = cs.Args(gamma=0.9, tau=0.2, alpha=0.3, autotune=autotune, policy_frequency=policy_frequency,
                   target_network_frequency=target_network_frequency)
    torch.manual_seed(0)
    actor = cs.CascadeActor(OBS_DIM, ACT_DIM, 8, 2, 0.5, LOW, HIGH)
    for _ in range(n):
        actor.add_base_net()
    actor = perturbed(actor, 0.3, seed=1)
    qf = perturbed(cs.QNetworks(OBS_DIM, ACT_DIM, hidden_size=8), 0.1, seed=2)
    qf_target = perturbed(copy.deepcopy(qf), 0.1, seed=3)  # targets lag behind the critics
    log_alpha = torch.tensor([-1.0], requires_grad=True)
    alpha = math.exp(-1.0) if autotune else args.alpha
    ref = {"actor": copy.deepcopy(actor), "qf": copy.deepcopy(qf), "qf_target": copy.deepcopy(qf_target),
           "log_alpha": log_alpha.detach().clone().requires_grad_(True)}
    ref_alpha = alpha
    q_optimizer = torch.optim.SGD(qf.parameters(), lr=LR)
    actor_optimizer = torch.optim.SGD(actor.parameters(), lr=LR)
    a_optimizer = torch.optim.SGD([log_alpha], lr=LR)
    batch = fixed_batch()
    for step in STEPS:
        torch.manual_seed(100 + step)
        out = cs.sac_update(args, step, batch, actor, qf, qf_target, q_optimizer, actor_optimizer, alpha, log_alpha,
                            a_optimizer)
        alpha = out["alpha"]
        torch.manual_seed(100 + step)  # the same noise, drawn in the same order
        expected = reference_sac_update(args, step, batch, ref["actor"], ref["qf"], ref["qf_target"],
                                        ref["log_alpha"], ref_alpha)
        ref_alpha = expected["alpha"]
        assert ("actor_loss" in out) == (step % policy_frequency == 0)
        assert ("alpha_loss" in out) == (autotune and step % policy_frequency == 0)
        for key, value in expected.items():
            torch.testing.assert_close(torch.as_tensor(out[key]).double(), torch.as_tensor(value).double(),
                                       rtol=1e-10, atol=1e-12, msg=f"step {step}: {key}")
        for name, module in [("actor", actor), ("qf", qf), ("qf_target", qf_target)]:
            assert_same(module, ref[name])
        torch.testing.assert_close(log_alpha, ref["log_alpha"], rtol=1e-10, atol=1e-12)
    assert (alpha != args.alpha) if autotune else (alpha == args.alpha)  # fixed unless tuned


# ----------------------------------------------------------------------------------------------
# DDPG
# ----------------------------------------------------------------------------------------------
def reference_ddpg_update(args, step, batch, actor, target_actor, qf, qf_target):
    obs, actions, rewards, next_obs, dones = batch
    with torch.no_grad():
        next_actions = target_actor(next_obs)[0]
        target = rewards + args.gamma * (1 - dones) * plain_q(qf_target, next_obs, next_actions, torch.tanh)[0]
    q = plain_q(qf, obs, actions, torch.tanh)[0]
    losses = {"qf1_a_values": q, "qf1_loss": ((q - target) ** 2).mean()}
    sgd(list(qf.parameters()), losses["qf1_loss"])
    if step % args.policy_frequency == 0:  # delayed: the actor, then both targets
        losses["actor_loss"] = -plain_q(qf, obs, actor(obs)[0], torch.tanh)[0].mean()
        sgd(list(actor.parameters()), losses["actor_loss"])
        soft(target_actor, actor, args.tau)
        soft(qf_target, qf, args.tau)
    return losses


@pytest.mark.parametrize("n", [1, 3], ids=["baseline", "cascade"])
@pytest.mark.parametrize("policy_frequency", [1, 2])
def test_ddpg_update_matches_reference(n, policy_frequency):
    args = cd.Args(gamma=0.9, tau=0.2, policy_frequency=policy_frequency)
    torch.manual_seed(0)
    actor = cd.CascadeActor(OBS_DIM, ACT_DIM, 8, 2, 0.5, LOW, HIGH)  # tanh, combined before the squash
    for _ in range(n):
        actor.add_base_net()
    actor = perturbed(actor, 0.3, seed=1)
    target_actor = perturbed(copy.deepcopy(actor), 0.1, seed=4)
    qf = perturbed(cd.QNetworks(OBS_DIM, ACT_DIM, hidden_size=8), 0.1, seed=2)
    qf_target = perturbed(copy.deepcopy(qf), 0.1, seed=3)
    ref = {name: copy.deepcopy(module) for name, module in
           [("actor", actor), ("target_actor", target_actor), ("qf", qf), ("qf_target", qf_target)]}
    q_optimizer = torch.optim.SGD(qf.parameters(), lr=LR)
    actor_optimizer = torch.optim.SGD(actor.parameters(), lr=LR)
    batch = fixed_batch()
    for step in STEPS:
        out = cd.ddpg_update(args, step, batch, actor, target_actor, qf, qf_target, q_optimizer, actor_optimizer)
        expected = reference_ddpg_update(args, step, batch, ref["actor"], ref["target_actor"], ref["qf"],
                                         ref["qf_target"])
        assert ("actor_loss" in out) == (step % policy_frequency == 0)
        for key, value in expected.items():
            torch.testing.assert_close(out[key], value, rtol=1e-10, atol=1e-12, msg=f"step {step}: {key}")
        for name, module in [("actor", actor), ("target_actor", target_actor), ("qf", qf), ("qf_target", qf_target)]:
            assert_same(module, ref[name])


# ----------------------------------------------------------------------------------------------
# The scripts' `minimize`: the fused Adam kernel called directly, as optimizer.step() would
# ----------------------------------------------------------------------------------------------
def minimize_and_step_alike(script, qf, optimizer, reference, ref_optimizer, step):
    """One script.minimize on qf and one zero_grad/backward/step on its copy, on the fixed batch: the same weights."""
    obs, actions, rewards, _, _ = fixed_batch()
    script.minimize(optimizer, ((qf(obs, actions) - rewards) ** 2).mean())
    ref_optimizer.zero_grad()
    ((reference(obs, actions) - rewards) ** 2).mean().backward()
    ref_optimizer.step()
    for p, q in zip(qf.parameters(), reference.parameters()):
        assert torch.equal(p, q), f"step {step}"


@pytest.mark.parametrize("script", [cs, cd], ids=["sac", "ddpg"])
def test_minimize_is_adam_step_bit_for_bit(script):
    """minimize(optimizer, loss) moves the parameters and leaves the optimizer's state (what a checkpoint saves)
    exactly as zero_grad(), backward() and step() do, over steps with a changing learning rate."""
    torch.manual_seed(0)
    qf = script.QNetworks(OBS_DIM, ACT_DIM, hidden_size=8)
    reference = copy.deepcopy(qf)
    make = (lambda p: script.make_adam(p, 1e-2)) if script is cs else (lambda p: script.make_adam(p, 1e-2, 1e-5))
    optimizer, ref_optimizer = make(list(qf.parameters())), make(list(reference.parameters()))
    plain_steps = []
    optimizer.step = lambda *a, step=optimizer.step: plain_steps.append(1) or step(*a)
    for step in range(4):
        for opt in (optimizer, ref_optimizer):
            opt.param_groups[0]["lr"] = 1e-2 / (step + 1)
        minimize_and_step_alike(script, qf, optimizer, reference, ref_optimizer, step)
    for state, ref_state in zip(optimizer.state_dict()["state"].values(), ref_optimizer.state_dict()["state"].values()):
        for key in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(state[key], ref_state[key]), key
    assert len(plain_steps) == 1  # only the first step (it creates the state) goes through step()


OTHER_OPTIMIZERS = {  # what a hacker may put in make_adam: each must step exactly as zero_grad/backward/step
    "adamw": lambda params: torch.optim.AdamW(params, lr=1e-2, weight_decay=0.1, fused=True),
    "amsgrad": lambda params: torch.optim.Adam(params, lr=1e-2, amsgrad=True, fused=True),
    "two groups": lambda params: torch.optim.Adam([{"params": params[:2]}, {"params": params[2:], "lr": 1e-3}],
                                                  lr=1e-2, fused=True),
}


@pytest.mark.parametrize("make", OTHER_OPTIMIZERS.values(), ids=OTHER_OPTIMIZERS.keys())
def test_minimize_steps_any_other_optimizer_as_its_step_would(make):
    """The direct kernel call is only for torch's plain fused Adam over one group: AdamW's decoupled decay,
    amsgrad and a second parameter group (with its own learning rate) must not be dropped."""
    torch.manual_seed(0)
    qf = cs.QNetworks(OBS_DIM, ACT_DIM, hidden_size=8)
    reference = copy.deepcopy(qf)
    optimizer, ref_optimizer = make(list(qf.parameters())), make(list(reference.parameters()))
    for step in range(4):
        minimize_and_step_alike(cs, qf, optimizer, reference, ref_optimizer, step)
