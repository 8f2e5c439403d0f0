"""The off-policy fast path (cascade_plumbing/fast_offpolicy.py) against the scripts' own updates.

- The hand-written SAC and DDPG updates leave what `sac_update` and `ddpg_update` leave (every parameter's change,
  every optimizer state, every logged value) to float64 rounding, Cascade and baseline, --autotune on and off,
  both DDPG squashes and activations, over consecutive updates (critic-only ones and ones with the actor's);
  in float32 they agree to float32 rounding.
- The run-time check catches an edit: of the script's update, of its nets, of the fast path itself; the run then
  continues with the script's update, with one warning line; a check leaves the run's random stream as it was.
- A real run keeps the fast path on, checks it, and `--autograd` turns it off.
"""

import copy
import functools
import math
import random
import types

import numpy as np
import pytest
import torch

import cascade_ddpg as cd
import cascade_sac as cs
from cascade_plumbing import fast_offpolicy as fo
from cascade_plumbing.offpolicy import step_with_gradients
from cascade_plumbing.replay import ReplayBuffer
from helpers import perturb, replay_batch

OBS_DIM, ACT_DIM, BATCH = 7, 3, 64
LOW, HIGH = np.array([-1.0, -2.0, 0.0]), np.array([1.0, 2.0, 3.0])  # asymmetric bounds: scale and bias matter


def batch(seed):
    return replay_batch(seed, BATCH, OBS_DIM, [-1.0] * ACT_DIM, [1.0] * ACT_DIM, done_every=5)


def sac_setup(n, autotune, hidden=32, seed=0):
    torch.manual_seed(seed)
    args = cs.Args(n=n, autotune=autotune)
    actor = cs.CascadeActor(OBS_DIM, ACT_DIM, hidden, 2, 0.5, LOW, HIGH)
    for _ in range(n):
        actor.add_base_net()
    perturb(actor, 0.3, seed)
    qf = cs.QNetworks(OBS_DIM, ACT_DIM, hidden_size=hidden)
    qf_target = perturb(copy.deepcopy(qf), 0.05, seed + 1)
    log_alpha = torch.zeros(1, requires_grad=True)
    state = {"args": args, "actor": actor, "qf": qf, "qf_target": qf_target,
             "q_optimizer": cs.make_adam(list(qf.parameters()), 1e-3),
             "actor_optimizer": cs.make_adam(list(actor.parameters()), 3e-4),
             "log_alpha": log_alpha, "a_optimizer": cs.make_adam([log_alpha], 1e-3), "alpha": 0.2}
    return state


def sac_arguments(state, step, seed):
    s = state
    return (s["args"], step, batch(seed), s["actor"], s["qf"], s["qf_target"], s["q_optimizer"],
            s["actor_optimizer"], s["alpha"], s["log_alpha"], s["a_optimizer"])


def ddpg_setup(n, combine_before_tanh, activation, seed=0):
    torch.manual_seed(seed)
    args = cd.Args(n=n, combine_before_tanh=combine_before_tanh, activation=activation)
    actor = cd.CascadeActor(OBS_DIM, ACT_DIM, 16, 2, 0.5, LOW, HIGH, activation, combine_before_tanh)
    for _ in range(n):
        actor.add_base_net()
    perturb(actor, 0.3, seed)
    qf = cd.QNetworks(OBS_DIM, ACT_DIM, hidden_size=32, activation=activation)
    return {"args": args, "actor": actor, "target_actor": perturb(copy.deepcopy(actor), 0.05, seed + 2), "qf": qf,
            "qf_target": perturb(copy.deepcopy(qf), 0.05, seed + 1),
            "q_optimizer": cd.make_adam(list(qf.parameters()), 3e-4, 1e-5),
            "actor_optimizer": cd.make_adam(list(actor.parameters()), 3e-4, 1e-5)}


def ddpg_arguments(state, step, seed):
    s = state
    return (s["args"], step, batch(seed), s["actor"], s["target_actor"], s["qf"], s["qf_target"],
            s["q_optimizer"], s["actor_optimizer"])


SAC_CASES = [(1, False), (1, True), (3, False), (3, True)]
DDPG_CASES = [(n, before, act) for n in (1, 4) for before in (True, False) for act in ("tanh", "relu")]


def checked_updates(fast_update, definition, state, arguments, steps=4):
    """`steps` consecutive updates (the first with Adam's state creation, critic-only and actor steps), each
    compared in float64 by the fast path's own check; returns the largest relative disagreement seen."""
    path = fo.OffPolicyFastPath(True, fast_update)
    for step in range(steps):
        arguments_now = arguments(state, step, seed=step)
        what = path.check(definition, arguments_now)
        assert what is None, what
        out = definition(*arguments_now)  # the run moves on by the script's own update
        if "alpha" in out:
            state["alpha"] = out["alpha"]
    assert path.checks == steps
    return path.worst


@pytest.mark.parametrize("n,autotune", SAC_CASES)
def test_sac_fast_update_equals_sac_update(n, autotune):
    state = sac_setup(n, autotune)
    worst = checked_updates(fo.SACFast((cs.LOG_STD_MIN, cs.LOG_STD_MAX)), cs.sac_update, state, sac_arguments)
    assert worst < 1e-9, worst  # float64 rounding, amplified near |tanh| = 1: ~1e-11; the run tolerates 1e-8


@pytest.mark.parametrize("n,before,activation", DDPG_CASES)
def test_ddpg_fast_update_equals_ddpg_update(n, before, activation):
    state = ddpg_setup(n, before, activation)
    worst = checked_updates(fo.DDPGFast(), cd.ddpg_update, state, ddpg_arguments)
    assert worst < 1e-9, worst


def test_float32_fast_update_tracks_the_definition():
    """In the run's float32 the two agree to float32 rounding over a few updates (the same draws)."""
    for setup, arguments, fast, definition in (
            (lambda: sac_setup(3, True), sac_arguments, fo.SACFast((cs.LOG_STD_MIN, cs.LOG_STD_MAX)), cs.sac_update),
            (lambda: ddpg_setup(4, True, "tanh"), ddpg_arguments, fo.DDPGFast(), cd.ddpg_update)):
        reference, ours = setup(), setup()
        for step in range(4):
            torch.manual_seed(100 + step)
            out = definition(*arguments(reference, step, step))
            torch.manual_seed(100 + step)
            with torch.no_grad():
                fast_out = fast(*arguments(ours, step, step))
            reference["alpha"] = ours["alpha"] = out.get("alpha", 0.0)
            assert set(out) == set(fast_out)
            for key in out:
                assert torch.allclose(torch.as_tensor(fast_out[key]).float(), torch.as_tensor(out[key]).float(),
                                      rtol=1e-4, atol=1e-6), key
        for key in ("actor", "qf", "qf_target"):
            for p, q in zip(reference[key].parameters(), ours[key].parameters()):
                assert torch.allclose(p, q, rtol=1e-4, atol=1e-6), key


@pytest.mark.parametrize("script", [cs, cd])
def test_the_replay_buffers_strided_batch_gives_contiguous_float32_gradients(script, monkeypatch):
    """On the column views the replay buffer hands over (strided, as in a run), the fast update steps Adam with
    contiguous float32 gradients of the parameters' shapes (torch's fused CPU Adam steps a strided gradient wrongly,
    without an error), and leaves what it leaves on contiguous copies of the same batch."""
    buffer = ReplayBuffer(500, OBS_DIM, ACT_DIM)
    rng = np.random.default_rng(0)
    for _ in range(300):
        buffer.add(rng.standard_normal((1, OBS_DIM)), rng.standard_normal((1, OBS_DIM)),
                   rng.uniform(-1, 1, (1, ACT_DIM)), rng.standard_normal(1), rng.random(1) < 0.1)
    np.random.seed(3)
    strided = buffer.sample(64, torch.device("cpu"))
    assert not all(t.is_contiguous() for t in strided)
    seen = []

    def recording(optimizer, params, grads):
        seen.extend((tuple(p.shape), tuple(g.shape), g.dtype, g.is_contiguous()) for p, g in zip(params, grads))
        return step_with_gradients(optimizer, params, grads)

    monkeypatch.setattr(fo, "step_with_gradients", recording)
    if script is cs:
        setup, arguments, fast = (lambda: sac_setup(3, True)), sac_arguments, fo.SACFast((cs.LOG_STD_MIN, cs.LOG_STD_MAX))
    else:
        setup, arguments, fast = (lambda: ddpg_setup(4, False, "relu")), ddpg_arguments, fo.DDPGFast()
    states = []
    for batch_ in (strided, tuple(t.contiguous() for t in strided)):
        state = setup()
        for step in range(2):  # a critic-only and an actor step (policy frequency 2)
            torch.manual_seed(step)
            with torch.no_grad():
                out = fast(*(arguments(state, step, 0)[:2] + (batch_,) + arguments(state, step, 0)[3:]))
            state["alpha"] = out.get("alpha", 0.0)
        states.append(state)
    assert seen and all(p == g and dtype == torch.float32 and contiguous for p, g, dtype, contiguous in seen), seen
    for key in ("actor", "qf"):
        for p, q in zip(states[0][key].parameters(), states[1][key].parameters()):
            assert torch.allclose(p, q, rtol=1e-6, atol=1e-7), key


def test_matmul_is_numpys_product_also_for_an_outer_product():
    """The kernel's shortcut for an inner dimension of 1 (a broadcast product) gives numpy's matmul bit for bit,
    batched and broadcast; other shapes are numpy's matmul itself."""
    rng = np.random.default_rng(0)
    for a_shape, b_shape in (((3, 256, 1), (3, 1, 16)), ((256, 1), (2, 1, 64)), ((0, 256, 1), (0, 1, 16)),
                             ((2, 256, 64), (2, 64, 1)), ((256, 14), (2, 14, 64))):
        for dtype in (np.float32, np.float64):
            a, b = rng.standard_normal(a_shape).astype(dtype), rng.standard_normal(b_shape).astype(dtype)
            product = fo.matmul(a, b)
            assert product.dtype == dtype and np.array_equal(product, np.matmul(a, b)), (a_shape, b_shape)


def wrong(function, **changes):
    """`function` with some of its globals replaced (an edit of the script a researcher might make)."""
    return types.FunctionType(function.__code__, {**function.__globals__, **changes}, function.__name__,
                              function.__defaults__, function.__closure__)


class L1Loss:
    """An edit of the critics' loss: F.mse_loss replaced by the mean absolute error."""

    @staticmethod
    def mse_loss(a, b):
        return (a - b).abs().mean()


class ShiftedActor(cs.CascadeActor):
    """An edit of the net: the mean gets a constant offset."""

    def forward(self, obs):
        mean, log_std, fallback, contribution = super().forward(obs)
        return mean + 0.01, log_std, fallback, contribution


class OffsetActor(cs.CascadeActor):
    """An edit that adds a parameter: a learned offset of the mean."""

    def __init__(self, *args):
        super().__init__(*args)
        self.offset = torch.nn.Parameter(torch.full((ACT_DIM,), 0.1))

    def forward(self, obs):
        mean, log_std, fallback, contribution = super().forward(obs)
        return mean + self.offset, log_std, fallback, contribution


def edited(script, edit, state, monkeypatch):
    """The script's update with `edit` made; the state is changed where the edit is of the net."""
    if edit == "critic loss":
        return wrong(script.sac_update if script is cs else script.ddpg_update, F=L1Loss)
    if edit == "contributions":  # the nets' combination: reversed
        monkeypatch.setattr(script, "contributions", lambda fallback, original=script.contributions:
                            original(fallback).flip(0))
    elif edit == "soft update":  # half the target step
        monkeypatch.setattr(script, "soft_update", lambda target, source, tau, original=script.soft_update:
                            original(target, source, tau / 2))
    elif edit == "log-std bound":  # [-6, 2] instead of [-5, 2]
        monkeypatch.setattr(cs, "bounded_log_std", lambda raw: -6.0 + 4.0 * (torch.tanh(raw) + 1))
    elif edit in ("net", "new parameter"):
        actor = (ShiftedActor if edit == "net" else OffsetActor)(OBS_DIM, ACT_DIM, 32, 2, 0.5, LOW, HIGH)
        for _ in range(state["actor"].size):
            actor.add_base_net()
        actor.load_state_dict(state["actor"].state_dict(), strict=False)
        state["actor"], state["actor_optimizer"] = actor, cs.make_adam(list(actor.parameters()), 3e-4)
    return cs.sac_update if script is cs else cd.ddpg_update


@pytest.mark.parametrize("script,edit", [(cs, e) for e in ("critic loss", "contributions", "soft update",
                                                             "log-std bound", "net", "new parameter")]
                         + [(cd, e) for e in ("critic loss", "contributions", "soft update")])
def test_check_catches_an_edit_of_the_script(script, edit, monkeypatch):
    """An edit of the script's update or nets switches the fast path off at its first checks, with one message, and
    the run goes on with the edited update."""
    state = sac_setup(3, True) if script is cs else ddpg_setup(3, True, "tanh")
    definition = edited(script, edit, state, monkeypatch)
    messages = []
    fast = fo.SACFast((cs.LOG_STD_MIN, cs.LOG_STD_MAX)) if script is cs else fo.DDPGFast()
    path = fo.OffPolicyFastPath(True, fast, announce=lambda message, step: messages.append(message))
    arguments = sac_arguments if script is cs else ddpg_arguments
    for step in range(3):
        out = path.update(definition, *arguments(state, step, step), step=step)
        state["alpha"] = out.get("alpha", 0.0)
    expected = "fails on these nets" if edit == "new parameter" else "differs"
    assert not path.on and len(messages) == 1 and expected in messages[0], messages
    assert "argument " not in messages[0]  # what differs is named as the update names it (`qf`, `q_optimizer`)


def decaying_lr(update, factor, first):
    """An edit (a fault hunt): every optimizer's learning rate decayed inside the update, before or after its steps."""
    @functools.wraps(update)
    def edited_update(*arguments):
        if first:
            decay(arguments, factor)
        out = update(*arguments)
        if not first:
            decay(arguments, factor)
        return out
    return edited_update


def decay(arguments, factor):
    for optimizer in (a for a in arguments if isinstance(a, torch.optim.Optimizer)):
        for group in optimizer.param_groups:
            group["lr"] *= factor


def updating_a_buffer(update):
    """An edit (a fault hunt): running statistics kept in a module buffer (here the critic's) and updated in the
    update, after the forward used them (at their initial values, which change nothing)."""
    @functools.wraps(update)
    def edited_update(*arguments):
        out = update(*arguments)
        for module in (a for a in arguments if isinstance(a, torch.nn.Module) and hasattr(a, "reward_mean")):
            module.reward_mean.lerp_(torch.ones_like(module.reward_mean), 0.01)
        return out
    return edited_update


@pytest.mark.parametrize("script", [cs, cd])
@pytest.mark.parametrize("edit", ["lr decay after the steps", "slight lr decay before them", "buffer statistics"])
def test_check_catches_an_edit_of_what_the_update_leaves_besides_the_parameters(script, edit):
    """A fault hunt: a learning rate decayed inside the update (CleanRL-style), or statistics kept in a module buffer,
    were silently ignored by the fast update: the moments do not depend on the rate, a decay of 5e-5 moves a step less
    than its tolerance, and buffers at their initial values change no forward. Now the optimizers' settings and the
    modules' buffers are compared too: switched off at the first check, the run goes on with the edited update."""
    state = sac_setup(2, False) if script is cs else ddpg_setup(2, True, "tanh")
    update = cs.sac_update if script is cs else cd.ddpg_update
    if edit == "buffer statistics":
        state["qf"].register_buffer("reward_mean", torch.zeros(()))
        definition = updating_a_buffer(update)
    else:
        definition = decaying_lr(update, 0.995 if "after" in edit else 0.99995, first="before" in edit)
    messages = []
    fast = fo.SACFast((cs.LOG_STD_MIN, cs.LOG_STD_MAX)) if script is cs else fo.DDPGFast()
    path = fo.OffPolicyFastPath(True, fast, announce=lambda message, step: messages.append(message))
    arguments = sac_arguments if script is cs else ddpg_arguments
    lr = state["q_optimizer"].param_groups[0]["lr"]
    out = path.update(definition, *arguments(state, 0, 0), step=0)
    state["alpha"] = out.get("alpha", 0.0)
    assert not path.on and len(messages) == 1, messages
    expected = "qf's buffer reward_mean differs" if edit == "buffer statistics" else "q_optimizer's lr is"
    assert expected in messages[0], messages
    # the update of the check's step is the edited one, on the run's own state (nothing missed)
    if edit == "buffer statistics":
        assert state["qf"].reward_mean.item() == pytest.approx(0.01)
    else:
        assert state["q_optimizer"].param_groups[0]["lr"] == pytest.approx(lr * (0.995 if "after" in edit else 0.99995))


def test_check_catches_a_wrong_fast_path(monkeypatch):
    """A fast path that computes a wrong gradient (here: the fallback logits' sign) is switched off, and the
    update of that step is the definition's."""
    def wrong_backward(fallback, weighted, contribution, grad):
        grad_out, grad_logit = cascade_backward(fallback, weighted, contribution, grad)
        return grad_out, -grad_logit

    cascade_backward = fo.cascade_backward
    monkeypatch.setattr(fo, "cascade_backward", wrong_backward)
    state = ddpg_setup(3, True, "tanh")
    reference = copy.deepcopy(state)
    path = fo.OffPolicyFastPath(True, fo.DDPGFast())
    path.update(cd.ddpg_update, *ddpg_arguments(state, 0, 0), step=0)
    assert not path.on and "fallback" in path.messages[0]
    cd.ddpg_update(*ddpg_arguments(reference, 0, 0))
    for p, q in zip(state["actor"].parameters(), reference["actor"].parameters()):
        assert torch.equal(p, q)


def test_a_check_leaves_the_random_streams_and_the_run_as_without_it():
    """A checked update and an unchecked one leave the same nets and the same torch, numpy and Python random
    states, bit for bit."""
    results = []
    for checked in (True, False):
        state = sac_setup(2, True)
        torch.manual_seed(5)
        np.random.seed(5)
        random.seed(5)
        path = fo.OffPolicyFastPath(True, fo.SACFast((cs.LOG_STD_MIN, cs.LOG_STD_MAX)))
        if not checked:  # as if these optimizers had been checked already and no check were due
            path.optimizers = (state["q_optimizer"], state["actor_optimizer"], state["a_optimizer"])
            path.updates, path.next_check = 1, 10**9
            path.update_buffers = [b.clone() for a in sac_arguments(state, 0, 0) if isinstance(a, torch.nn.Module)
                                   for b in a.buffers()]
        for step in range(3):
            out = path.update(cs.sac_update, *sac_arguments(state, step, step), step=step)
            state["alpha"] = out["alpha"]
        results.append((torch.get_rng_state(), np.random.random(), random.random(),
                        [p.clone() for p in state["actor"].parameters()], [p.clone() for p in state["qf"].parameters()],
                        path.checks))
    (rng_a, np_a, py_a, actor_a, qf_a, checks_a), (rng_b, np_b, py_b, actor_b, qf_b, checks_b) = results
    assert checks_a == 1 and checks_b == 0  # the first update (also a complete one); the next is ~2000 updates on
    assert torch.equal(rng_a, rng_b) and np_a == np_b and py_a == py_b
    assert all(torch.equal(p, q) for p, q in zip(actor_a + qf_a, actor_b + qf_b))


def test_an_edit_drawing_from_numpy_leaves_the_run_as_autograd_runs_it():
    """An edited update that draws from numpy's stream is switched off, and the run's numpy stream is where an
    --autograd run's would be: the check's own draws are undone."""
    def noisy_update(*arguments):
        out = cd.ddpg_update(*arguments)
        out["qf1_loss"] = out["qf1_loss"] + float(np.random.normal(scale=1e-3))
        return out

    draws = []
    for fast_on in (True, False):
        state = ddpg_setup(1, True, "tanh")
        np.random.seed(11)
        path = fo.OffPolicyFastPath(fast_on, fo.DDPGFast())
        path.update(noisy_update, *ddpg_arguments(state, 0, 0), step=0)
        draws.append(np.random.random())
        assert not path.on
    assert draws[0] == draws[1]


def test_checks_come_at_each_iteration_start_and_then_at_random_phases(monkeypatch):
    """The first update with new optimizers and the first complete one after it, then any update about every
    CHECK_EVERY, at varying phases (so that an edit acting every so many steps is met, also on incomplete updates
    only: a researcher's probe, 2026-12-05, found a condition on odd steps never checked once the first update
    fell on an even one)."""
    monkeypatch.setattr(fo, "CHECK_EVERY", 10)
    state = ddpg_setup(1, True, "tanh")
    path = fo.OffPolicyFastPath(True, fo.DDPGFast(), complete=lambda step: step % 2 == 0)
    checked = []
    check = path.check
    monkeypatch.setattr(path, "check", lambda definition, arguments: checked.append(arguments[1])
                        or check(definition, arguments))
    for step in range(1, 201):  # (an iteration's updates start at an odd step by default: learning_starts + 1)
        path.update(cd.ddpg_update, *ddpg_arguments(state, step, step), step=step)
    assert checked[:2] == [1, 2]  # the first update, then the first complete one
    assert {step % 2 for step in checked[2:]} == {0, 1}  # complete and incomplete updates alike
    gaps = np.diff(checked[1:])
    assert 10 <= len(checked) <= 40 and gaps.min() >= 5 and len(set(step % 20 for step in checked[1:])) >= 5
    state["actor_optimizer"] = cd.make_adam(list(state["actor"].parameters()), 3e-4, 1e-5)  # a new iteration
    path.update(cd.ddpg_update, *ddpg_arguments(state, 1, 1), step=201)
    assert checked[-1] == 1 and path.on


def test_an_edit_acting_every_few_steps_is_caught(monkeypatch):
    """A periodic edit (a hard copy of the targets every 10th step) switches the fast path off within a few checks,
    however the checks' spacing falls."""
    monkeypatch.setattr(fo, "CHECK_EVERY", 20)

    def hard_copy_every_10th(args, step_in_iteration, batch, actor, target_actor, qf, qf_target, *optimizers):
        out = cd.ddpg_update(args, step_in_iteration, batch, actor, target_actor, qf, qf_target, *optimizers)
        if step_in_iteration % 10 == 0:
            cd.soft_update(qf_target, qf, 1.0)
        return out

    state = ddpg_setup(1, True, "tanh")
    path = fo.OffPolicyFastPath(True, fo.DDPGFast(), complete=lambda step: step % 2 == 0)
    for step in range(1, 1001):
        path.update(hard_copy_every_10th, *ddpg_arguments(state, step, step % 7), step=step)
        if not path.on:
            break
    assert not path.on and "differs" in path.messages[0]


def test_numpy_acting_follows_weights_whose_memory_is_replaced():
    """`p.data = ...` (a new tensor for a parameter) is seen at the next step, not only at the next check."""
    actor, explore, fast, extra = acting_setup(("ddpg", 2, True, "tanh", 0.0))
    path = fo.OffPolicyFastPath(True, fast)
    obs = np.ones((1, OBS_DIM), np.float32)
    path.act(explore, actor, obs, *extra)
    actor.mu_weight.data = actor.mu_weight.data + 0.5
    with torch.inference_mode():
        expected = explore(actor, torch.as_tensor(obs), *extra).numpy()
    np.testing.assert_allclose(path.act(explore, actor, obs, *extra), expected, rtol=1e-5, atol=1e-6)


def test_float64_copies_never_share_memory_with_the_run():
    log_alpha = torch.zeros(1, dtype=torch.float64, requires_grad=True)
    module = torch.nn.Linear(2, 2).double()
    (twin_alpha, twin_module) = fo.float64_twins((log_alpha, module))
    assert twin_alpha.data_ptr() != log_alpha.data_ptr()
    assert all(p.data_ptr() != q.data_ptr() for p, q in zip(module.parameters(), twin_module.parameters()))


@pytest.mark.parametrize("script", [cs, cd])
def test_a_run_keeps_the_fast_path_on_and_autograd_turns_it_off(script, tmp_path):
    common = dict(env_id="Pendulum-v1", n=2, k=400, learning_starts=100, batch_size=32, eval_every=0, quiet=True,
                  track_dir=str(tmp_path))
    result = script.train(script.Args(**common))
    fast = result["fast_path"]
    assert fast.on and fast.acting and not fast.messages
    assert fast.checks == 2 * (2 + 1)  # two iterations: the span of two updates and the acting at each start
    result = script.train(script.Args(**common, autograd=True))
    fast = result["fast_path"]
    assert not fast.on and not fast.acting and fast.checks == 0


# ----------------------------------------------------------------------------------------------
# Acting: the numpy path against the script's `explore`
# ----------------------------------------------------------------------------------------------
ACTING_CASES = [("sac", n, None, None, None) for n in (1, 3)] + [
    ("ddpg", n, before, act, noise) for n in (1, 4) for before in (True, False) for act in ("tanh", "relu")
    for noise in (0.0, 0.1)]


def acting_setup(case):
    kind, n, before, activation, noise = case
    if kind == "sac":
        state = sac_setup(n, False)
        return state["actor"], cs.explore, fo.SACFast((cs.LOG_STD_MIN, cs.LOG_STD_MAX)), ()
    state = ddpg_setup(n, before, activation)
    return state["actor"], cd.explore, fo.DDPGFast(), (noise,)


@pytest.mark.parametrize("case", ACTING_CASES, ids=str)
def test_numpy_acting_equals_explore(case):
    """float64: the same actions to rounding (CHECK_ROWS draws); float32: the same actions to float32 rounding."""
    actor, explore, fast, extra = acting_setup(case)
    path = fo.OffPolicyFastPath(True, fast)
    obs = np.random.default_rng(0).normal(size=(1, OBS_DIM)).astype(np.float32) * 2
    assert path.check_acting(explore, actor, obs, extra) is None
    assert path.worst < 1e-12, path.worst
    torch.manual_seed(3)
    with torch.inference_mode():
        reference = explore(actor, torch.as_tensor(obs), *extra).numpy()
    torch.manual_seed(3)
    np.testing.assert_allclose(fast.explore(actor, obs, *extra), reference, rtol=1e-5, atol=1e-6)


def explore_doubled_noise(actor, obs, noise):
    return cd.explore(actor, obs, 2 * noise)


def explore_mean_action(actor, obs):
    return actor.get_action(obs)[2]


@pytest.mark.parametrize("script", ["sac", "ddpg"])
def test_check_catches_an_edit_of_explore(script):
    """An edited `explore` switches the numpy acting off at the first step, with one message; the run acts with
    the edit (the update's fast path stays on)."""
    if script == "sac":
        actor, _, fast, extra = acting_setup(("sac", 2, None, None, None))
        edited_explore = explore_mean_action
    else:
        actor, _, fast, extra = acting_setup(("ddpg", 2, True, "tanh", 0.1))
        edited_explore = explore_doubled_noise
    messages = []
    path = fo.OffPolicyFastPath(True, fast, announce=lambda message, step: messages.append(message))
    obs = np.ones((1, OBS_DIM), np.float32)
    torch.manual_seed(4)
    action = path.act(edited_explore, actor, obs, *extra, step=7)
    torch.manual_seed(4)
    with torch.inference_mode():
        expected = edited_explore(actor, torch.as_tensor(obs), *extra).numpy()
    assert not path.acting and path.on and len(messages) == 1
    assert messages[0].startswith("fast acting check at global_step=7") and "differ" in messages[0]
    np.testing.assert_array_equal(action, expected)


def explore_noise_clipped_at_3_sigma(actor, obs, noise):
    action, _, _ = actor(obs)
    action = action + torch.randn(action.shape).clamp(-3.0, 3.0) * (actor.action_scale * noise)
    return torch.maximum(torch.minimum(action, actor.action_bias + actor.action_scale),
                         actor.action_bias - actor.action_scale)


class ShiftedCritic(cd.QNetworks):
    """An edit: the critic's values shifted by a buffer the loop sets (statistics a forward reads)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.register_buffer("shift", torch.zeros(()))
        self.register_buffer("obs_high", torch.full((OBS_DIM,), math.inf))  # constant, read by nothing

    def forward(self, obs, actions):
        return super().forward(obs, actions) - self.shift


def test_a_buffer_the_loop_changes_brings_the_next_checks_forward():
    """A review: a buffer changed by the loop between checks (here the critic's shift, read by its forward) went
    unseen until the periodic check, ~2000 updates on, while the fast update trained on the unshifted values. Now the
    next update is checked; a constant buffer of inf is no change (it read as one: (inf - inf) is NaN)."""
    state = ddpg_setup(1, True, "tanh")
    critic = ShiftedCritic(OBS_DIM, ACT_DIM, hidden_size=32, activation="tanh")
    critic.load_state_dict({**state["qf"].state_dict(), "shift": torch.zeros(()),
                            "obs_high": torch.full((OBS_DIM,), math.inf)})
    state["qf"], state["q_optimizer"] = critic, cd.make_adam(list(critic.parameters()), 3e-4, 1e-5)
    messages = []
    path = fo.OffPolicyFastPath(True, fo.DDPGFast(), announce=lambda message, step: messages.append(message))
    for step in range(1, 6):  # the first (checked), then unchecked ones: nothing changed
        path.update(cd.ddpg_update, *ddpg_arguments(state, step, step), step=step)
    assert path.on and path.checks == 1, messages  # (the first update, a complete one)
    critic.shift.fill_(1.0)  # the loop's edit
    path.update(cd.ddpg_update, *ddpg_arguments(state, 6, 6), step=6)
    assert not path.on and len(messages) == 1 and "differs" in messages[0], messages


def explore_counting(actor, obs, noise):
    """An edit: explore counts its calls in a buffer of the actor (read by no forward)."""
    actor.calls.add_(1)
    return cd.explore(actor, obs, noise)


def test_an_explore_that_changes_a_buffer_switches_acting_off():
    """A review: a buffer changed inside explore (and read by no forward) was never changed on the numpy path, and
    no check saw it: the check's own calls changed only its copy."""
    actor, _, fast, extra = acting_setup(("ddpg", 2, True, "tanh", 0.1))
    actor.register_buffer("calls", torch.zeros(()))
    messages = []
    path = fo.OffPolicyFastPath(True, fast, announce=lambda message, step: messages.append(message))
    path.act(explore_counting, actor, np.zeros((1, OBS_DIM), np.float32), *extra, step=1)
    assert not path.acting and "explore changes the buffer actor.calls" in messages[0], messages
    assert actor.calls.item() == 1  # the step itself acted through the edited explore


def test_an_edit_of_rare_draws_is_caught_at_a_new_nets_first_acting_check():
    """A hack-safety hunt: DDPG's noise clipped at 3 sigma changes ~0.3% of the draws, and passed the acting check's
    64 draws most of the time; the run then explored with the unclipped noise until the next check (~2000 steps on).
    A new net's first check draws 1024 per dimension: caught at the first step, whatever the seed."""
    for seed in range(20):
        actor, _, fast, extra = acting_setup(("ddpg", 2, True, "tanh", 0.1))
        path = fo.OffPolicyFastPath(True, fast)
        torch.manual_seed(seed)
        path.act(explore_noise_clipped_at_3_sigma, actor, np.zeros((1, OBS_DIM), np.float32), *extra, step=1)
        assert not path.acting, seed


ou_noise = None  # the Ornstein-Uhlenbeck state of `explore_ou`, a global of this module as it would be of a script


def explore_ou(actor, obs, noise):
    """DDPG's classic exploration: the action plus Ornstein-Uhlenbeck noise, kept in a global between steps."""
    global ou_noise
    action, _, _ = actor(obs)
    step = torch.randn(action.shape, device=action.device)
    ou_noise = step * noise if ou_noise is None else ou_noise - 0.15 * ou_noise + noise * step
    return cd.add_noise(action + ou_noise * actor.action_scale, actor, 0.0)


def explore_sticky(actor, obs, noise):
    """The previous step's action again, every other call, kept on the actor."""
    previous = getattr(actor, "previous_action", None)
    actor.previous_action = None if previous is not None else cd.explore(actor, obs, noise)
    return previous if previous is not None else actor.previous_action


class StickyMemory:
    """The same sticky actions, kept inside an object (no name is bound anew: only the second call tells)."""
    previous = {}

    @classmethod
    def explore(cls, actor, obs, noise):
        if "action" in cls.previous:
            return cls.previous.pop("action")
        cls.previous["action"] = cd.explore(actor, obs, noise)
        return cls.previous["action"]


@pytest.mark.parametrize("edit,expected", [(explore_ou, "explore keeps state between calls (it sets global ou_noise)"),
                                           (explore_sticky, "(it sets actor.previous_action)"),
                                           (StickyMemory.explore, "(its second call on the same observations")])
def test_an_explore_that_keeps_state_between_calls_switches_acting_off(edit, expected):
    """A researcher's probe (2026-12-05, of the PPO scripts' act): the check called explore once, on a fresh copy of
    the actor, so state kept between calls (OU noise, sticky actions) went unseen and the numpy path's white noise
    was used. Now explore is called twice; what it binds anew is named and undone, and the run acts through it."""
    global ou_noise
    ou_noise = None
    StickyMemory.previous.clear()
    actor, _, fast, extra = acting_setup(("ddpg", 2, True, "tanh", 0.1))
    messages = []
    path = fo.OffPolicyFastPath(True, fast, announce=lambda message, step: messages.append(message))
    obs = np.ones((1, OBS_DIM), np.float32)
    torch.manual_seed(4)
    path.act(edit, actor, obs, *extra, step=7)
    assert not path.acting and len(messages) == 1 and expected in messages[0], messages
    assert "explore keeps state between calls" in messages[0]
    if edit is explore_ou:
        assert ou_noise is not None and ou_noise.shape == (1, 3)  # the run's own first call, not the check's rows


def test_acting_checks_at_each_new_net_and_about_every_check_every_steps(monkeypatch):
    monkeypatch.setattr(fo, "CHECK_EVERY", 4)
    actor, explore, fast, extra = acting_setup(("ddpg", 1, True, "tanh", 0.1))
    path = fo.OffPolicyFastPath(True, fast)
    obs = np.ones((1, OBS_DIM), np.float32)
    for _ in range(40):
        path.act(explore, actor, obs, *extra)
    assert 7 <= path.checks <= 21  # the first step, then every 2 to 6 steps
    checks = path.checks
    actor.add_base_net()
    path.act(explore, actor, obs, *extra)
    assert path.checks == checks + 1 and path.acting


def test_an_acting_check_leaves_the_random_stream_and_the_actions_as_without_it():
    actions, states = [], []
    for checked in (True, False):
        actor, explore, fast, extra = acting_setup(("sac", 3, None, None, None))
        path = fo.OffPolicyFastPath(True, fast)
        if not checked:  # as if this actor had been checked and no check were due
            path.acting_key, path.acts, path.next_acting_check = (actor, actor.size), 1, 10**9
            path.acting_buffers = [b.clone() for b in actor.buffers()]
        torch.manual_seed(9)
        actions.append(path.act(explore, actor, np.ones((1, OBS_DIM), np.float32)))
        states.append(torch.get_rng_state())
        assert path.checks == int(checked)
    np.testing.assert_array_equal(*actions)
    assert torch.equal(*states)


update_count = 0  # a global counter kept by `ddpg_update_counting`, as an edit of a script might
running = {"critic_loss": 0.0}  # running statistics kept inside a global dict


def ddpg_update_decaying_tau(args, *rest):
    out = cd.ddpg_update(args, *rest)
    args.tau = args.tau * 0.5  # a schedule of the target step, kept in args
    return out


def ddpg_update_counting(*arguments):
    global update_count
    update_count += 1
    return cd.ddpg_update(*arguments)


def ddpg_update_averaging(*arguments):
    out = cd.ddpg_update(*arguments)
    running["critic_loss"] = 0.9 * running["critic_loss"] + 0.1 * float(out["qf1_loss"].detach())
    return out


@pytest.mark.parametrize("edit,named", [(ddpg_update_decaying_tau, "it sets args.tau"),
                                        (ddpg_update_counting, "it sets global update_count"),
                                        (ddpg_update_averaging, "it sets the contents of global running")])
def test_an_update_that_keeps_state_between_calls_switches_the_fast_update_off(edit, named):
    """A researcher's probe (2026-12-05): an update that changed `args` (a decaying tau) passed the check, whose
    float64 run changed the run's own args first, and was then ignored: the fast update never changes it. Counters and
    running statistics kept in globals counted the checks, not the updates. Now such state is named, the check's
    call leaves nothing behind, and the run continues with the script's update from that step on, as --autograd."""
    global update_count
    update_count = 0
    running["critic_loss"] = 0.0
    state = ddpg_setup(1, True, "tanh")
    messages = []
    path = fo.OffPolicyFastPath(True, fo.DDPGFast(), announce=lambda message, step: messages.append(message))
    path.update(edit, *ddpg_arguments(state, 1, 1), step=1)
    assert not path.on and len(messages) == 1 and f"{edit.__name__} keeps state between calls ({named})" in messages[0]
    # the step ran once, by the script's update: as often as an --autograd run would have run it
    assert state["args"].tau == cd.Args().tau * (0.5 if edit is ddpg_update_decaying_tau else 1.0)
    assert update_count == (1 if edit is ddpg_update_counting else 0)
    assert (running["critic_loss"] != 0.0) == (edit is ddpg_update_averaging)


class NoiseProcess:
    """Ornstein-Uhlenbeck noise as a class (the classic DDPG code), its state as wide as the batch it last saw."""

    def __init__(self):
        self.state = None

    def sample(self, shape):
        step = torch.randn(shape)
        self.state = step * 0.1 if self.state is None or self.state.shape != shape else 0.85 * self.state + 0.1 * step
        return self.state


ou_process = NoiseProcess()


def explore_ou_object(actor, obs, noise):
    action, _, _ = actor(obs)
    return cd.add_noise(action + ou_process.sample(action.shape) * actor.action_scale, actor, 0.0)


def test_an_explore_keeping_state_inside_an_object_is_named_and_left_as_it_was():
    """The noise process kept in an object: the check's calls changed it to the check's 64 rows, and the run's next
    step then returned 64 actions for one observation (a crash in the env). Now its contents are compared, named,
    and put back as they were before the check."""
    ou_process.state = None
    actor, _, fast, extra = acting_setup(("ddpg", 2, True, "tanh", 0.1))
    messages = []
    path = fo.OffPolicyFastPath(True, fast, announce=lambda message, step: messages.append(message))
    action = path.act(explore_ou_object, actor, np.ones((1, OBS_DIM), np.float32), *extra, step=3)
    assert not path.acting and "(it sets the contents of global ou_process)" in messages[0], messages
    assert action.shape == (1, ACT_DIM) and ou_process.state.shape == (1, ACT_DIM)  # the run's own first call


def explore_clipped(explore):
    """`explore` on observations clipped to ±3: an edit that acts on large observations only."""
    return lambda actor, obs, *extra: explore(actor, obs.clamp(-3.0, 3.0), *extra)


@pytest.mark.parametrize("script", ["sac", "ddpg"])
def test_the_acting_check_covers_every_observation_acted_on_since_the_last(script):
    """An issue: an edit that acts on some observations only (a clip) was met only if the check's one observation
    was one of them. A check now also draws for every observation the numpy path acted on since the previous check
    (one on a large observation among small ones here), and switches acting off there."""
    actor, explore, fast, extra = acting_setup(("sac", 2, None, None, None) if script == "sac"
                                               else ("ddpg", 2, True, "tanh", 0.1))
    messages = []
    path = fo.OffPolicyFastPath(True, fast, announce=lambda message, step: messages.append(message))
    small = np.full((1, OBS_DIM), 0.5, np.float32)
    large = np.full((1, OBS_DIM), 0.5, np.float32)
    large[0, 0] = 6.0
    edited_explore = explore_clipped(explore)
    path.act(edited_explore, actor, small, *extra, step=0)  # checked on the small observation only: no difference
    assert path.acting and messages == []
    path.next_acting_check = 4  # (the first call counted one step)
    for step, obs in enumerate([small, large, small], start=1):
        path.act(edited_explore, actor, obs, *extra, step=step)
    assert path.acting  # no check between two checks
    path.act(edited_explore, actor, small, *extra, step=4)  # the check: the large observation acted on is among its
    assert not path.acting and len(messages) == 1, messages
    assert messages[0].startswith("fast acting check at global_step=4") and "differ" in messages[0], messages[0]
    assert path.acted == []
