"""Fast paths of the off-policy scripts: the same SAC and DDPG updates as the scripts' `sac_update` and
`ddpg_update`, with the gradients written out by hand, and the same acting as their `explore`, in numpy.

Why: an update of these small nets is mostly per-operation overhead (autograd's graph, torch's dispatch), and on
the AMD EPYC CPUs we run on torch's CPU build computes tanh ~7x and a 256-wide layer's few-column head ~9x slower
than numpy does (its matmuls go through Intel's MKL; docs/performance.md, "SAC and DDPG"). So the fast update writes each
gradient out and computes it in numpy, on views of the nets' own memory (a numpy operation on these arrays costs
~1 us, torch's ~3-7 us; torch's kernels for the ReLU and its backward, the sigmoid, SAC's tanh of its log-std and
of its sample, Adam and the soft target updates), and acting runs the one observation through numpy views of the
live weights. They are the script's update and acting, step for step: the critics' regression to the same targets, the same actor loss, the same temperature
update, the same Adam (`step_with_gradients`, the fused kernel that `minimize` also calls) and the same soft
target updates, drawing the same random numbers from the same torch generator in the same order, so a run
follows the same trajectory up to float rounding.

Nothing here is a definition. `OffPolicyFastPath.update(definition, *arguments)` runs the script's own update
(`definition`) and this one on float64 copies of everything it touches (nets, targets, optimizers and their state,
the temperature), from the same random state, on the first updates with each new actor optimizer (each Cascade
iteration's first, a resumed run's first) and then every CHECK_EVERY updates, and compares what they leave: the
optimizers' moments (the gradients), every parameter's change, the values the script logs. `act(explore, ...)`
compares the two actings likewise (CHECK_ROWS draws for the current observation, FIRST_CHECK_ROWS at a new net, one for each observation acted on since the previous check) at each new net and every
CHECK_EVERY steps. A disagreement, or an exception, switches that path off for the rest of the run with one warning
line, and the run continues with the script's own function, as `--autograd` runs it. A script's edit of its nets,
losses, update or acting therefore either changes both paths alike or shows at the next check, which comes
before the new iteration's third update.
"""

from __future__ import annotations

import contextlib
import copy
import inspect
import math
import random
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import torch
import torch.nn as nn

from .fast import KeptState, changed_buffers, describe, moved, same_setting, same_values, untouched_random_streams
from .offpolicy import step_with_gradients

# A check covers the first update with each new set of optimizers and the first complete one after it (one that
# also updates the actor, the temperature and the targets: every 2nd by default), then any update about every
# CHECK_EVERY (at random phases), and the next one whenever the nets' buffers changed; acting at each new net, about
# every CHECK_EVERY steps and after a buffer of the actor changed. A check costs about
# six float64 updates (DDPG: ~10 ms, SAC 256-wide: ~50 ms): under 1% of a run at this spacing.
CHECK_EVERY = 2000
# Relative differences above which the two updates disagree. The gradients (in Adam's moments), the losses and
# values agree to ~1e-11 in float64: more than 1e-16, as log(1 - y^2) and tanh's 1 - y^2 near |y| = 1 amplify the
# last bit of a sum (tests/test_fast_offpolicy.py measures it). A parameter's change is Adam's normalized step
# g / (|g| + eps), which amplifies the relative rounding of a gradient element near eps by orders of magnitude (to
# ~1e-13 / (4 eps)); an edit of the method changes some number by far more (a loss term, a bound, a target step:
# 1e-3 and up).
TOLERANCE = 1e-8
STEP_TOLERANCE = 1e-4
# an acting check draws this many actions for the current observation (repeated), so that an edit of the noise shows
CHECK_ROWS = 64
# ... and this many at a new net's first check (a hack-safety hunt: a clip of the noise at 3 sigma passed 64 draws
# most of the time, and the run acted with the unclipped noise until the next check, ~2000 steps on; 2 x 1024 draws
# of each action dimension miss it with a chance of ~4e-3 per dimension, at ~0.2-1 s once a net)
FIRST_CHECK_ROWS = 1024
# a change, state or value is compared relative to at least this fraction of the largest of its kind: a parameter
# whose gradient cancels to ~0 (a bias summed over the batch) has only rounding to compare
FLOOR = 1e-3


# ----------------------------------------------------------------------------------------------
# Kernels, in numpy on views of the nets' memory (a numpy operation on these small arrays costs ~1 us, torch's
# ~3-7 us; products through numpy's OpenBLAS)
# ----------------------------------------------------------------------------------------------
def view(t: torch.Tensor) -> np.ndarray:
    """The tensor's memory as a numpy array (no copy: an optimizer's in-place step shows in it)."""
    return t.detach().numpy()


def transposed(a: np.ndarray) -> np.ndarray:
    return np.swapaxes(a, -1, -2)


def matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b (batched, broadcast) by numpy's BLAS; an outer product (inner dimension 1: a critic's one-unit output, a
    fallback logit) as the broadcast product it is, which numpy's matmul computes ~10x slower without BLAS."""
    return a * b if a.shape[-1] == 1 else np.matmul(a, b)


def sum_rows(x: np.ndarray) -> np.ndarray:
    """x.sum(-2, keepdims=True) (over the batch: a bias's gradient) as one BLAS product with a row of ones: numpy
    reduces over a middle axis ~10x slower (a [6, 256, 16] array: 50 us against 3 us)."""
    return matmul(np.ones((1, x.shape[-2]), x.dtype), x)


def sum_last(x: np.ndarray) -> np.ndarray:
    """x.sum(-1, keepdims=True) as one BLAS product with a column of ones: numpy reduces many short rows (an
    action's 3 columns) ~10x slower."""
    return matmul(x, np.ones((x.shape[-1], 1), x.dtype))


def cumsum0(x: np.ndarray) -> np.ndarray:
    """x.cumsum(0), bit for bit, one row added at a time: numpy's cumsum along the first axis of these arrays (a few
    nets' [B, D] outputs) is ~5x slower."""
    out = x.copy()
    for i in range(1, len(out)):
        out[i] += out[i - 1]
    return out


def torch_(function: Callable[[torch.Tensor], torch.Tensor], x: np.ndarray) -> np.ndarray:
    """torch's own kernel on numpy memory, where its last bit matters (the scripts' sigmoid, and tanh before
    log(1 - y^2)), numpy's version would warn (exp's overflow in a sigmoid) or is slower (ReLU)."""
    return function(torch.from_numpy(x)).numpy()


def activation_name(module: nn.Module) -> str:
    """'tanh' or 'relu': the hidden activation a script's net applies (SAC's nets have no attribute: ReLU)."""
    activation = getattr(module, "activation", torch.relu)
    if activation is torch.tanh:
        return "tanh"
    if activation is torch.relu:
        return "relu"
    raise ValueError(f"no hand-written gradient for the activation {activation}")


def activate_(z: np.ndarray, activation: str) -> np.ndarray:
    """z <- f(z) in place: numpy's tanh, torch's ReLU (numpy's maximum takes ~5x longer on a [2, 256, 256] batch)."""
    return np.tanh(z, out=z) if activation == "tanh" else torch_(torch.relu_, z)


def activation_backward(grad: np.ndarray, out: np.ndarray, activation: str) -> np.ndarray:
    """grad * f'(z), written with the activation's output: 1 - tanh^2, or the ReLU's mask."""
    if activation == "tanh":
        return grad * (1 - out * out)
    # autograd's own kernel (out > 0 iff the ReLU's input was): 0 where out <= 0, even for a non-finite grad (a
    # product with the mask would give NaN there), the grad elsewhere; numpy's where() takes ~30x longer
    return torch.ops.aten.threshold_backward(torch.from_numpy(grad), torch.from_numpy(out), 0).numpy()


# ----------------------------------------------------------------------------------------------
# A stack of m MLPs with weights [m, in, out] (the critics; the actors' hidden layers)
# ----------------------------------------------------------------------------------------------
def stacked_forward(layers: list[tuple[np.ndarray, np.ndarray]], x: np.ndarray, activation: str,
                    activate_last: bool) -> list[np.ndarray]:
    """Each layer's output (after its activation), for input x [B, in] read by every member, or [m, B, in]."""
    outs = []
    for i, (weight, bias) in enumerate(layers):
        z = matmul(x if i == 0 else outs[-1], weight)
        z += bias
        outs.append(activate_(z, activation) if activate_last or i < len(layers) - 1 else z)
    return outs


def stacked_backward(layers: list[tuple[np.ndarray, np.ndarray]], x: np.ndarray, outs: list[np.ndarray],
                     grad: np.ndarray, activation: str, activate_last: bool, weights: bool = True,
                     input_columns: slice | None = None) -> tuple[list[np.ndarray], np.ndarray | None]:
    """Back through `stacked_forward` from the gradient of its last output: the gradients [weight, bias, ...] of
    every layer (with `weights`) and, with `input_columns`, of those columns of the input x (summed over members
    for a shared x)."""
    grads: list[np.ndarray] = []
    for i in reversed(range(len(layers))):
        if activate_last or i < len(layers) - 1:
            grad = activation_backward(grad, outs[i], activation)
        if weights:
            below = x if i == 0 else outs[i - 1]
            grads[:0] = [matmul(transposed(below), grad), sum_rows(grad)]
        if i > 0:
            grad = matmul(grad, transposed(layers[i][0]))
    if input_columns is None:
        return grads, None
    grad_x = matmul(grad, transposed(layers[0][0][:, input_columns]))  # only the rows of W_1 these columns meet
    return grads, grad_x.sum(0) if x.ndim == 2 else grad_x


def members(parameter_list: nn.ParameterList) -> list[nn.Parameter]:
    """The parameters of a ParameterList, in order (its indexing costs ~4 us per item; this, one dict read)."""
    return list(parameter_list._parameters.values())


def weight_grads_by_parameter(weights: list[nn.Parameter], biases: list[nn.Parameter], grads: list[np.ndarray],
                              into: dict[nn.Parameter, np.ndarray]) -> None:
    for weight, bias, grad_weight, grad_bias in zip(weights, biases, grads[0::2], grads[1::2]):
        into[weight], into[bias] = grad_weight, grad_bias


# ----------------------------------------------------------------------------------------------
# The Cascade combination C_n = sum_i w_i b_i and its gradient
# ----------------------------------------------------------------------------------------------
def cascade_contributions(fallback: np.ndarray) -> np.ndarray:
    """w_i = (1 - l_i) prod_{j>i} l_j (l_1 := 0) of fallbacks [n-1, B, 1]: [n, B, 1]."""
    ones = np.ones((1, *fallback.shape[1:]), fallback.dtype)  # (fallback has no rows at n = 1)
    later = np.concatenate([fallback, ones])  # [l_2, ..., l_n, 1]
    for i in range(len(later) - 2, -1, -1):  # later_i = prod_{j>i} l_j: a reversed cumprod, as a loop ~2x faster
        later[i] *= later[i + 1]
    return np.concatenate([ones, 1 - fallback]) * later


def cascade_backward(fallback: np.ndarray, weighted: np.ndarray, contribution: np.ndarray,
                     grad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of C = sum_i weighted_i (weighted_i = w_i b_i) with respect to each net's output b_i, [n, B, D],
    and each fallback logit, [n-1, B, 1]. Without a division: for C_i = l_i C_{i-1} + (1 - l_i) b_i,
    dC/dlogit_i = l_i (1 - l_i) prod_{j>i} l_j (C_{i-1} - b_i) = (1 - l_i) S_{i-1} - l_i w_i b_i, where
    S_{i-1} = sum_{j<i} w_j b_j (the products prod_{j>i} l_j cancel against the partial ensemble's weights)."""
    partial = cumsum0(weighted[:-1])  # S_1 .. S_{n-1}
    below = sum_last(partial * grad)
    own = sum_last(weighted[1:] * grad)
    grad_logit = (1 - fallback) * below - fallback * own
    return contribution * grad, grad_logit


def cascade_heads(top: np.ndarray, head: tuple[np.ndarray, np.ndarray],
                  fallback_head: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """From the nets' top hidden layers [n, B, H]: each net's output [n, B, D] (its head), the fallbacks l_i of
    nets 2..n [n-1, B, 1] (their fallback logits' sigmoid) and every net's contribution w_i [n, B, 1]."""
    out = matmul(top, head[0])
    out += head[1]
    logit = matmul(top[1:], fallback_head[0])
    logit += fallback_head[1]
    fallback = torch_(torch.sigmoid_, logit)
    return out, fallback, cascade_contributions(fallback)


class CascadePass:
    """One forward pass of a script's CascadeActor (all nets at once) on obs [B, obs_dim], kept for its backward
    pass. The actor's outputs of every net (`head`: SAC's [mean | raw log-std], DDPG's mu) are combined by the
    fallbacks."""

    def __init__(self, actor: nn.Module, obs: np.ndarray, head: tuple[nn.Parameter, nn.Parameter]):
        self.actor, self.obs = actor, obs
        self.activation = activation_name(actor)
        self.hidden_params = (members(actor.hidden_weights), members(actor.hidden_biases))
        self.hidden = [(view(w), view(b)) for w, b in zip(*self.hidden_params)]
        self.head_params = head
        self.head = (view(head[0]), view(head[1]))
        self.fallback_head = (view(actor.fallback_weight), view(actor.fallback_bias))
        self.trunk = stacked_forward(self.hidden, obs, self.activation, activate_last=True)
        self.out, self.fallback, self.contribution = cascade_heads(self.trunk[-1], self.head, self.fallback_head)
        self.weighted = self.contribution * self.out

    def combined(self) -> np.ndarray:
        return self.weighted.sum(0)

    def backward_combined(self, grad_combined: np.ndarray, into: dict[nn.Parameter, np.ndarray]) -> None:
        """The actor's parameter gradients from the gradient of the combination C = sum_i w_i b_i, [B, D]."""
        self.backward(*cascade_backward(self.fallback, self.weighted, self.contribution, grad_combined), into)

    def backward(self, grad_out: np.ndarray, grad_logit: np.ndarray, into: dict[nn.Parameter, np.ndarray]) -> None:
        """The actor's parameter gradients from those of each net's output [n, B, D] and fallback logit."""
        top = self.trunk[-1]
        actor = self.actor
        into[self.head_params[0]] = matmul(transposed(top), grad_out)
        into[self.head_params[1]] = sum_rows(grad_out)
        into[actor.fallback_weight] = matmul(transposed(top[1:]), grad_logit)
        into[actor.fallback_bias] = sum_rows(grad_logit)
        grad_top = matmul(grad_out, transposed(self.head[0]))
        grad_top[1:] += matmul(grad_logit, transposed(self.fallback_head[0]))
        grads, _ = stacked_backward(self.hidden, self.obs, self.trunk, grad_top, self.activation, activate_last=True)
        weight_grads_by_parameter(*self.hidden_params, grads, into)


class CriticPass:
    """One forward pass of a script's stacked critics (QNetworks) on (obs, actions), kept for its backward pass."""

    def __init__(self, qf: nn.Module, obs: np.ndarray, actions: np.ndarray):
        self.qf, self.obs_dim = qf, obs.shape[1]
        self.params = (members(qf.weights), members(qf.biases))
        self.layers = [(view(w), view(b)) for w, b in zip(*self.params)]
        self.activation = activation_name(qf)
        self.x = np.concatenate([obs, actions], 1)
        self.outs = stacked_forward(self.layers, self.x, self.activation, activate_last=False)
        self.q = self.outs[-1][..., 0]  # [m, B]

    def backward(self, grad_q: np.ndarray, weights: bool = True,
                 input_columns: slice | None = None) -> tuple[list[np.ndarray], np.ndarray | None]:
        return stacked_backward(self.layers, self.x, self.outs, grad_q[..., None], self.activation,
                                activate_last=False, weights=weights, input_columns=input_columns)


def critic_input_grad(qf: nn.Module, obs: np.ndarray, actions: np.ndarray,
                      grad_q: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Q values [m, B] of (obs, actions), and d(sum grad_q(Q) * Q)/d actions [B, A] (no weight gradient)."""
    critics = CriticPass(qf, obs, actions)
    _, grad_actions = critics.backward(grad_q(critics.q), weights=False, input_columns=slice(critics.obs_dim, None))
    return critics.q, grad_actions


def critic_step(qf: nn.Module, optimizer: torch.optim.Optimizer, obs: np.ndarray, actions: np.ndarray,
                target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One Adam step of every critic on the mean squared error to `target` [B]: their values [m, B] and each
    critic's loss [m]."""
    critics = CriticPass(qf, obs, actions)
    error = critics.q - target
    grads, _ = critics.backward(error * (2.0 / len(target)))
    into: dict[nn.Parameter, np.ndarray] = {}
    weight_grads_by_parameter(*critics.params, grads, into)
    apply_gradients(optimizer, into)
    return critics.q, (error * error).mean(1)


def critic_values(qf: nn.Module, obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
    return CriticPass(qf, obs, actions).q


def apply_gradients(optimizer: torch.optim.Optimizer, grads: dict[nn.Parameter, np.ndarray]) -> None:
    """The optimizer's step with these gradients (`minimize` after its autograd.grad); every parameter it holds
    must have one: a parameter the hand-written update does not know of (an edit's) raises here."""
    params = [p for group in optimizer.param_groups for p in group["params"]]
    missing = [tuple(p.shape) for p in params if p not in grads]
    if missing:
        raise KeyError(f"the optimizer holds a parameter of shape {missing[0]} the hand-written update has no "
                       "gradient for")
    # contiguous: torch's fused CPU Adam steps a strided gradient wrongly, without an error
    step_with_gradients(optimizer, params, [torch.from_numpy(np.ascontiguousarray(grads[p])) for p in params])


@torch.no_grad()
def lerp_targets(target: nn.Module, source: nn.Module, tau: float) -> None:
    torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)


def as_tensors(out: dict) -> dict:
    """The logged values as tensors, as the scripts' updates return them."""
    return {key: torch.from_numpy(np.asarray(value)) if isinstance(value, np.ndarray | np.generic) else value
            for key, value in out.items()}


# ----------------------------------------------------------------------------------------------
# Acting in the training env: one observation through all nets, in numpy on views of the live weights
# ----------------------------------------------------------------------------------------------
class NumpyActor:
    """Views (no copies: the optimizer's in-place steps show at once) of a script's CascadeActor's weights, kept
    between steps, and its forward in numpy."""

    def __init__(self, head: tuple[str, str]):
        self.head = head
        self.cached: tuple = ()  # (actor, its hidden-layer tuple, its heads tuple, the views)

    def views(self, actor: nn.Module) -> tuple:
        # the script's actor rebuilds its `_hidden`/`_heads` tuples whenever it replaces a Parameter (a new net)
        cached = self.cached
        if (not cached or cached[0] is not actor or cached[1] is not actor._hidden or cached[2] is not actor._heads
                or any(p.data_ptr() != pointer for p, pointer in cached[4])):  # (`p.data = ...` swaps the memory)
            hidden = [(view(w), view(b)) for w, b in zip(members(actor.hidden_weights), members(actor.hidden_biases))]
            head = [view(getattr(actor, name)) for name in self.head]
            fallback = (view(actor.fallback_weight), view(actor.fallback_bias))
            params = [*members(actor.hidden_weights), *members(actor.hidden_biases), actor.fallback_weight,
                      actor.fallback_bias, *(getattr(actor, name) for name in self.head)]
            self.cached = cached = (actor, actor._hidden, actor._heads, (hidden, head, fallback, activation_name(actor)),
                                    [(p, p.data_ptr()) for p in params])
        return cached[3]

    def forward(self, actor: nn.Module, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each net's output [n, B, D] and its contribution w_i [n, B, 1] for obs [B, obs_dim]."""
        hidden, head, fallback_head, activation = self.views(actor)
        out, _, contribution = cascade_heads(stacked_forward(hidden, obs, activation, activate_last=True)[-1], head,
                                             fallback_head)
        return out, contribution


# ----------------------------------------------------------------------------------------------
# SAC (cascade_sac.py's sac_update)
# ----------------------------------------------------------------------------------------------
class SACFast:
    """`sac_update` with hand-written gradients. `log_std_bounds`: the script's (LOG_STD_MIN, LOG_STD_MAX)."""

    def __init__(self, log_std_bounds: tuple[float, float]):
        self.log_std_min, self.log_std_max = log_std_bounds
        self.numpy_actor = NumpyActor(("head_weight", "head_bias"))

    def log_std(self, bounded: np.ndarray) -> np.ndarray:
        """The combined raw log-std, squashed to (-1, 1), rescaled to the script's bounds (CleanRL's)."""
        return self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (bounded + 1)

    def explore(self, actor: nn.Module, obs: np.ndarray) -> np.ndarray:
        """`explore`'s action (a sample of the squashed Gaussian) in numpy, drawing the same torch noise."""
        out, contribution = self.numpy_actor.forward(actor, obs.astype(actor.action_scale.numpy().dtype))
        combined = (contribution * out).sum(0)
        a = actor.act_dim
        log_std = self.log_std(np.tanh(combined[:, a:]))
        noise = torch.randn(combined[:, :a].shape).numpy().astype(combined.dtype)  # squashed_sample's draw
        y = np.tanh(combined[:, :a] + np.exp(log_std) * noise)
        return y * actor.action_scale.numpy() + actor.action_bias.numpy()

    def sample(self, actor: nn.Module, obs: np.ndarray) -> dict:
        """The actor's squashed Gaussian sample on obs, with what its backward pass needs."""
        cascade = CascadePass(actor, obs, (actor.head_weight, actor.head_bias))
        combined = cascade.combined()
        a = actor.act_dim
        # torch's tanh on the [B, A] outputs, as the script: log(1 - y^2) near |y| = 1 would turn the last-bit
        # difference of another tanh into ~1e-10 of the log-prob
        mean, bounded = combined[:, :a], torch_(torch.tanh, combined[:, a:])
        log_std = self.log_std(bounded)
        # squashed_sample's draw: the CPU generator, in the default dtype (float32; the checks' float64)
        noise = torch.randn(mean.shape).numpy().astype(mean.dtype, copy=False)
        std = np.exp(log_std)
        y = torch_(torch.tanh, mean + std * noise)
        scale, bias = view(actor.action_scale), view(actor.action_bias)
        squash = scale * (1 - y * y) + 1e-6
        log_prob = sum_last(-0.5 * noise * noise - log_std - 0.5 * math.log(2 * math.pi) - np.log(squash))[:, 0]
        return {"cascade": cascade, "action": y * scale + bias, "log_prob": log_prob, "y": y, "noise": noise,
                "std": std, "bounded": bounded, "squash": squash, "scale": scale}

    def actor_grads(self, s: dict, grad_action: np.ndarray, grad_log_prob: float) -> dict:
        """d/d(actor's parameters) of sum(grad_action * action) + grad_log_prob * sum(log_prob)."""
        y, scale = s["y"], s["scale"]
        grad_y = grad_action * scale + grad_log_prob * 2 * y * scale / s["squash"]
        grad_u = grad_y * (1 - y * y)
        grad_log_std = grad_u * s["std"] * s["noise"] - grad_log_prob
        half_range = 0.5 * (self.log_std_max - self.log_std_min)
        grad_raw = grad_log_std * half_range * (1 - s["bounded"] * s["bounded"])
        into: dict[nn.Parameter, np.ndarray] = {}
        s["cascade"].backward_combined(np.concatenate([grad_u, grad_raw], 1), into)
        return into

    def __call__(self, args: Any, step_in_iteration: int, batch: tuple[torch.Tensor, ...], actor: nn.Module,
                 qf: nn.Module, qf_target: nn.Module, q_optimizer: torch.optim.Optimizer,
                 actor_optimizer: torch.optim.Optimizer, alpha: float, log_alpha: torch.Tensor,
                 a_optimizer: torch.optim.Optimizer) -> dict:
        b_obs, b_actions, b_rewards, b_next_obs, b_dones = (view(t) for t in batch)
        batch_size = len(b_obs)
        following = self.sample(actor, b_next_obs)
        min_qf_next = critic_values(qf_target, b_next_obs, following["action"]).min(0) - alpha * following["log_prob"]
        next_q_value = b_rewards + (1 - b_dones) * args.gamma * min_qf_next
        qf_a_values, losses = critic_step(qf, q_optimizer, b_obs, b_actions, next_q_value)
        out = {"qf_a_values": qf_a_values, "qf1_loss": losses[0], "qf2_loss": losses[1],
               "qf_loss": losses[0] + losses[1]}

        if step_in_iteration % args.policy_frequency == 0:
            for _ in range(args.policy_frequency):
                s = self.sample(actor, b_obs)

                def grad_q(q: np.ndarray, s: dict = s) -> np.ndarray:  # d mean(-min_j Q_j) / dQ: the smaller critic
                    smaller = q.argmin(0)
                    columns = np.arange(q.shape[1])
                    s["min_q"] = q[smaller, columns]
                    grad = np.zeros_like(q)
                    grad[smaller, columns] = -1.0 / batch_size
                    return grad

                _, grad_action = critic_input_grad(qf, b_obs, s["action"], grad_q)
                out["actor_loss"] = (alpha * s["log_prob"] - s["min_q"]).mean()
                apply_gradients(actor_optimizer, self.actor_grads(s, grad_action, alpha / batch_size))
                if args.autotune:
                    log_pi = self.sample(actor, b_obs)["log_prob"]
                    alpha_loss = (-np.exp(view(log_alpha)) * (log_pi + -float(actor.act_dim))).mean()
                    out["alpha_loss"] = alpha_loss
                    apply_gradients(a_optimizer, {log_alpha: np.reshape(alpha_loss, 1)})  # d/dlog_alpha = the loss
                    alpha = log_alpha.exp().item()

        if step_in_iteration % args.target_network_frequency == 0:
            lerp_targets(qf_target, qf, args.tau)
        out["alpha"] = alpha
        return as_tensors(out)


# ----------------------------------------------------------------------------------------------
# DDPG (cascade_ddpg.py's ddpg_update)
# ----------------------------------------------------------------------------------------------
class DDPGFast:
    """`ddpg_update` with hand-written gradients."""

    def __init__(self):
        self.numpy_actor = NumpyActor(("mu_weight", "mu_bias"))

    def explore(self, actor: nn.Module, obs: np.ndarray, noise: float) -> np.ndarray:
        """`explore`'s action (the cascade's, plus clipped Gaussian noise) in numpy, drawing the same torch noise."""
        scale, bias = actor.action_scale.numpy(), actor.action_bias.numpy()
        out, contribution = self.numpy_actor.forward(actor, obs.astype(scale.dtype))
        if actor.combine_before_tanh:
            action = np.tanh((contribution * out).sum(0)) * scale + bias
        else:
            action = (contribution * np.tanh(out)).sum(0) * scale + bias
        if noise:
            action = action + torch.randn(action.shape).numpy().astype(action.dtype) * (scale * noise)
        return np.maximum(np.minimum(action, bias + scale), bias - scale)

    @staticmethod
    def actor_pass(actor: nn.Module, obs: np.ndarray) -> tuple[CascadePass, np.ndarray, np.ndarray]:
        """The actor's action on obs (and the pass and the squashed value before scaling, for the backward)."""
        cascade = CascadePass(actor, obs, (actor.mu_weight, actor.mu_bias))
        if actor.combine_before_tanh:
            squashed = np.tanh(cascade.combined())
        else:
            cascade.squashed = np.tanh(cascade.out)
            squashed = (cascade.contribution * cascade.squashed).sum(0)
        return cascade, squashed, squashed * view(actor.action_scale) + view(actor.action_bias)

    @staticmethod
    def actor_grads(actor: nn.Module, cascade: CascadePass, squashed: np.ndarray, grad_action: np.ndarray) -> dict:
        grad_squashed = grad_action * view(actor.action_scale)
        into: dict[nn.Parameter, np.ndarray] = {}
        if actor.combine_before_tanh:
            cascade.backward_combined(grad_squashed * (1 - squashed * squashed), into)
        else:  # C = sum_i w_i tanh(mu_i): the combination's gradient on the squashed outputs, then each tanh's
            grad_each, grad_logit = cascade_backward(cascade.fallback, cascade.contribution * cascade.squashed,
                                                     cascade.contribution, grad_squashed)
            cascade.backward(grad_each * (1 - cascade.squashed * cascade.squashed), grad_logit, into)
        return into

    def __call__(self, args: Any, step_in_iteration: int, batch: tuple[torch.Tensor, ...], actor: nn.Module,
                 target_actor: nn.Module, qf: nn.Module, qf_target: nn.Module, q_optimizer: torch.optim.Optimizer,
                 actor_optimizer: torch.optim.Optimizer) -> dict:
        b_obs, b_actions, b_rewards, b_next_obs, b_dones = (view(t) for t in batch)
        _, _, next_actions = self.actor_pass(target_actor, b_next_obs)
        next_q_value = b_rewards + (1 - b_dones) * args.gamma * critic_values(qf_target, b_next_obs, next_actions)[0]
        qf_a_values, losses = critic_step(qf, q_optimizer, b_obs, b_actions, next_q_value)
        out = {"qf1_a_values": qf_a_values[0], "qf1_loss": losses[0]}

        if step_in_iteration % args.policy_frequency == 0:
            cascade, squashed, action = self.actor_pass(actor, b_obs)
            q, grad_action = critic_input_grad(qf, b_obs, action, lambda q: np.full_like(q, -1.0 / len(b_obs)))
            out["actor_loss"] = -q[0].mean()
            apply_gradients(actor_optimizer, self.actor_grads(actor, cascade, squashed, grad_action))
            lerp_targets(target_actor, actor, args.tau)
            lerp_targets(qf_target, qf, args.tau)
        return as_tensors(out)


# ----------------------------------------------------------------------------------------------
# The run-time check against the script's update, and the switch
# ----------------------------------------------------------------------------------------------
def float64_twins(arguments: tuple) -> tuple:
    """The update's arguments with every module, optimizer (state included) and tensor copied to float64; a
    tensor or parameter shared by several (log_alpha and its optimizer) stays shared."""
    twin_of: dict[int, torch.Tensor] = {}

    def tensor(t: torch.Tensor) -> torch.Tensor:
        if id(t) not in twin_of:
            # a copy even of a float64 tensor (.double() would return the tensor itself, and the check step it)
            twin = t.detach().to(torch.float64, copy=True) if t.is_floating_point() else t.detach().clone()
            twin_of[id(t)] = twin.requires_grad_(t.requires_grad)
        return twin_of[id(t)]

    def module(m: nn.Module) -> nn.Module:
        twin = copy.deepcopy(m).double()
        for original, copied in zip(m.parameters(), twin.parameters()):
            twin_of[id(original)] = copied
        return twin

    def optimizer(o: torch.optim.Optimizer) -> torch.optim.Optimizer:
        groups = [{**{k: v for k, v in g.items() if k != "params"}, "params": [twin_of[id(p)] for p in g["params"]]}
                  for g in o.param_groups]
        twin = type(o)(groups, **o.defaults)
        # the state (moments, step counts) follows the params to float64; deep-copied first, as load_state_dict
        # keeps a tensor that needs no cast (the fused Adam's float32 step counts) and the twin would step the run's
        twin.load_state_dict(copy.deepcopy(o.state_dict()))
        return twin

    # modules and tensors first: optimizers refer to their parameters
    copied = [module(a) if isinstance(a, nn.Module) else
              tuple(tensor(t) for t in a) if isinstance(a, tuple) else
              tensor(a) if isinstance(a, torch.Tensor) else a for a in arguments]
    return tuple(optimizer(a) if isinstance(a, torch.optim.Optimizer) else c for a, c in zip(arguments, copied))


def argument_names(function: Callable) -> list[str]:
    """The names of `function`'s positional parameters (`args`, `qf`, `log_alpha`), for the checks' messages; [] if
    it has no signature (the messages then say "argument 3")."""
    try:
        parameters = inspect.signature(function).parameters.values()
    except (TypeError, ValueError):
        return []
    return [p.name for p in parameters if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]


def argument_label(names: list[str] | tuple, i: int) -> str:
    """The update's own name for its argument i (`qf`, `log_alpha`), else its position."""
    return names[i] if i < len(names) else f"argument {i + 1}"


def disagreement(arguments: tuple, reference: tuple, fast: tuple, reference_out: dict, fast_out: dict,
                 labels: tuple | list = ()) -> tuple[str | None, float]:
    """What the fast update left differently from the script's (None: nothing beyond float64 rounding), and the
    largest relative difference of all."""
    if set(reference_out) != set(fast_out):
        return f"the update returns {sorted(reference_out)}, the fast path {sorted(fast_out)}", math.inf
    pairs: list[tuple[str, list, list, float, float]] = []  # (what, reference, fast, floor scale, tolerance)
    for i, (original, ref, new) in enumerate(zip(arguments, reference, fast)):
        if isinstance(original, nn.Module):
            before = [p.detach().double() for p in original.parameters()]
            names = [name for name, _ in original.named_parameters()]
            ref_moves = [p.detach() - b for p, b in zip(ref.parameters(), before)]
            fast_moves = [p.detach() - b for p, b in zip(new.parameters(), before)]
            pairs += [(f"the change of {argument_label(labels, i)}'s {name}", [r], [f], max_abs(ref_moves),
                       STEP_TOLERANCE)
                      for name, r, f in zip(names, ref_moves, fast_moves)]
            # its buffers too: running statistics an edit keeps there and updates in the update (a fault hunt: the
            # fast update left them at their initial values, which the forward agrees with, silently)
            ref_buffers, fast_buffers = dict(ref.named_buffers()), dict(new.named_buffers())
            if set(ref_buffers) != set(fast_buffers):
                return f"{argument_label(labels, i)} holds other buffers after the fast update", math.inf
            pairs += [(f"{argument_label(labels, i)}'s buffer {name}", [ref_buffers[name].detach().double()],
                       [fast_buffers[name].detach().double()], 0.0, TOLERANCE) for name in ref_buffers
                      if not same_values(ref_buffers[name], fast_buffers[name])]  # (inf, NaN: the same)
        elif isinstance(original, torch.optim.Optimizer):
            ref_states = [v for p in (p for g in ref.param_groups for p in g["params"]) for v in ref.state[p].values()
                          if isinstance(v, torch.Tensor) and v.dim()]
            new_states = [v for p in (p for g in new.param_groups for p in g["params"]) for v in new.state[p].values()
                          if isinstance(v, torch.Tensor) and v.dim()]
            if len(ref_states) != len(new_states):
                return f"{argument_label(labels, i)} (an optimizer) holds another state", math.inf
            pairs += [(f"{argument_label(labels, i)}'s optimizer state", [r], [f], max_abs(ref_states), TOLERANCE)
                      for r, f in zip(ref_states, new_states)]
            # and its settings (a fault hunt: a learning rate decayed inside the update was not decayed by the fast
            # one, silently: the moments do not depend on it, and a small decay moves a step by less than its tolerance)
            for ref_group, new_group in zip(ref.param_groups, new.param_groups):
                for key in sorted({*ref_group, *new_group} - {"params"}):
                    if not same_setting(ref_group.get(key), new_group.get(key)):
                        return (f"{argument_label(labels, i)}'s {key} is {new_group.get(key)} after the fast update, "
                                f"{ref_group.get(key)} after the script's"), math.inf
        elif isinstance(original, torch.Tensor):
            pairs.append((argument_label(labels, i), [ref.detach()], [new.detach()], 0.0, TOLERANCE))
    for key in reference_out:
        r, f = torch.as_tensor(reference_out[key]).double(), torch.as_tensor(fast_out[key]).double()
        pairs.append((f"'{key}'", [r.detach()], [f.detach()], 0.0, TOLERANCE))
    worst = 0.0
    for what, ref_tensors, fast_tensors, largest, tolerance in pairs:
        r, f = ref_tensors[0], fast_tensors[0]
        if r.shape != f.shape:
            return f"{what} has shape {tuple(f.shape)}, not {tuple(r.shape)}", math.inf
        if not r.numel():
            continue
        scale = max(r.abs().max().item(), f.abs().max().item(), FLOOR * largest, 1e-30)
        error = (f - r).abs().max().item() / scale
        if not error <= tolerance:
            return f"{what} differs (max relative error {error:.1e})", error
        worst = max(worst, error * TOLERANCE / tolerance)  # in units of TOLERANCE
    return None, worst


@contextlib.contextmanager
def float64_by_default() -> Iterator[None]:
    """Inside, torch.randn & co. draw float64, as the checks' copies compute: else the script's float32 noise (its
    `noise.pow(2)`) would put float32 rounding into the float64 comparison."""
    dtype = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        yield
    finally:
        torch.set_default_dtype(dtype)


def max_abs(tensors: list[torch.Tensor]) -> float:
    return max((t.abs().max().item() for t in tensors if t.numel()), default=0.0)


class OffPolicyFastPath:
    """Runs an update (`update`) and acting (`act`) through the fast paths or, when off, the script's own function,
    checking each fast path against it (module docstring). `announce(message, step)` gets the one-line warning when
    one switches off."""

    def __init__(self, enabled: bool, fast: SACFast | DDPGFast, announce: Callable[[str, int], None] | None = None,
                 complete: Callable[[int], bool] = lambda step_in_iteration: True):
        """`complete(step_in_iteration)`: does the update of that step run every part (critics, actor, temperature,
        targets)? Each check after an iteration's first update waits for such an update."""
        self.on = self.acting = enabled  # the update's fast path; acting's
        self.fast_update, self.fast_explore = fast, fast.explore
        self.announce, self.complete = announce, complete
        self.optimizers: tuple = ()  # the optimizers of the latest update: new ones start a new iteration
        self.updates = 0  # updates since then
        self.next_check = 0  # the update count from which the next check is due
        self.complete_checked = False  # has a complete update been checked since the latest new optimizers?
        # the nets' buffers at the latest update and acting checks: a change by the loop (statistics a forward reads)
        # brings the next check forward (a review: it waited for the periodic one, ~2000 steps on)
        self.update_buffers: list[torch.Tensor] = []
        self.acting_buffers: list[torch.Tensor] = []
        self.acting_key: tuple = ()  # (actor, its size) at the latest acting check
        self.acts = 0  # acting steps since then
        self.acted: list[np.ndarray] = []  # the observations the numpy path acted on since then (the next check's too)
        self.next_acting_check = 0
        # the checks' spacing is drawn from their own generator (the run's streams are untouched): a fixed spacing would
        # check only one phase of an edit that acts every so many steps
        self.spacing = random.Random(0)
        self.checks = 0  # checks passed (updates and acting)
        self.worst = 0.0  # the largest difference a passed check saw (relative; a step's scaled by TOLERANCE/STEP_TOLERANCE)
        self.check_seconds = 0.0
        self.messages: list[str] = []

    def gap(self) -> int:
        """Steps to the next periodic check: CHECK_EVERY on average, at a random phase."""
        return self.spacing.randint(CHECK_EVERY // 2, 3 * CHECK_EVERY // 2)

    def act(self, definition: Callable[..., torch.Tensor], actor: nn.Module, obs: np.ndarray, *extra: Any,
            step: int = 0) -> np.ndarray:
        """`definition(actor, obs, *extra)` as numpy actions, by the numpy path when it is on (checked first at a new
        net, a new actor, and every CHECK_EVERY steps)."""
        if self.acting:
            key = self.acting_key
            new = not key or key[0] is not actor or key[1] != actor.size
            if new or self.acts >= self.next_acting_check or moved(list(actor.buffers()), self.acting_buffers):
                self.acting_key, self.acts, self.next_acting_check = (actor, actor.size), 0, self.gap()
                self.acting_buffers = [b.detach().clone() for b in actor.buffers()]
                acted, self.acted = self.acted, []
                try:
                    what = self.check_acting(definition, actor, obs, extra, acted,
                                             FIRST_CHECK_ROWS if new else CHECK_ROWS)
                except Exception as exc:
                    what = f"the numpy acting path fails on this actor ({describe(exc)})"
                if what is not None:
                    self.switch_off(what, step, acting=True)
            if self.acting:
                self.acts += 1
                self.acted.append(np.array(obs))  # (a copy: the loop may reuse its array)
                return self.fast_explore(actor, obs, *extra)
        with torch.inference_mode():  # acting: no autograd bookkeeping at all
            observations = torch.as_tensor(obs, dtype=torch.float32, device=actor.action_scale.device)
            return definition(actor, observations, *extra).cpu().numpy()

    def check_acting(self, definition: Callable[..., torch.Tensor], actor: nn.Module, obs: np.ndarray,
                     extra: tuple, acted: list[np.ndarray] = (), draws: int = CHECK_ROWS) -> str | None:
        """`definition` and the numpy path on a float64 copy of the actor, `draws` draws for obs and one for each
        observation `acted` on since the previous check (so that an edit acting on some observations only, a clip,
        is met at the next check once the run has acted on one), from the same random state; what differs."""
        start = time.perf_counter()
        try:
            twin = copy.deepcopy(actor).double()
            rows = np.repeat(obs, draws, axis=0).astype(np.float64)
            acted = [a for a in acted if a.shape[1:] == obs.shape[1:]]
            if acted:
                rows = np.concatenate([rows, *acted]).astype(np.float64)
            with float64_by_default():
                # twice: an explore that keeps state between calls (Ornstein-Uhlenbeck noise, sticky actions) shows
                # in its second call, if not already in the names it binds (which the check then undoes)
                with KeptState(definition, {"actor": twin}) as watch:
                    with untouched_random_streams(), torch.inference_mode():  # the script's draws
                        reference = [definition(twin, torch.as_tensor(rows), *extra).detach().numpy()
                                     for _ in range(2)]
                    kept = watch.changes()
                if kept:
                    return f"explore keeps state between calls ({kept}), while the numpy acting path draws afresh"
                changed = changed_buffers([("actor", twin, actor)])
                if changed:  # (a review: statistics updated while exploring, read by no forward, went unseen)
                    return f"explore changes the buffer {changed[0]}, which the numpy acting path does not"
                with untouched_random_streams():  # the same draws again
                    fast = [self.fast_explore(twin, rows, *extra) for _ in range(2)]
            if fast[0].shape != reference[0].shape:
                return f"the numpy acting path gives actions of shape {fast[0].shape}, explore {reference[0].shape}"
            errors = [float(np.abs(f - r).max() / max(np.abs(r).max(), 1e-30)) for f, r in zip(fast, reference)]
            error = max(errors)
            if not errors[0] <= TOLERANCE:
                return f"the numpy acting path's actions differ from explore's (max relative error {errors[0]:.1e})"
            if not error <= TOLERANCE:
                return ("explore keeps state between calls (its second call on the same observations draws otherwise "
                        f"than the numpy acting path, max relative error {error:.1e}), while the numpy acting path "
                        "draws afresh")
            self.checks += 1
            self.worst = max(self.worst, error)
            return None
        finally:
            self.check_seconds += time.perf_counter() - start

    def update(self, definition: Callable[..., dict], *arguments: Any, step: int = 0) -> dict:
        """`definition(*arguments)`, by the fast path when it is on (checked first when a check is due)."""
        if not self.on:
            return definition(*arguments)
        optimizers = tuple(a for a in arguments if isinstance(a, torch.optim.Optimizer))
        if len(optimizers) != len(self.optimizers) or any(a is not b for a, b in zip(optimizers, self.optimizers)):
            # new optimizers: a new iteration, a resumed run, a reset critic. Check this update, then the first
            # complete one (the actor's, the temperature's and the targets' updates come every few steps)
            self.optimizers, self.updates, self.next_check = optimizers, 0, 0
        first = self.updates == 0
        if first:
            self.complete_checked = False
        # the first check after the first update waits for a complete update; the later ones fall on any update (an
        # edit may act on incomplete ones only: a condition on odd steps)
        due = self.updates >= self.next_check and (self.complete_checked or self.complete(arguments[1]))
        buffers = [b for a in arguments if isinstance(a, nn.Module) for b in a.buffers()]
        forced = not first and moved(buffers, self.update_buffers)  # (the periodic checks keep their schedule)
        if first or due or forced:
            self.update_buffers = [b.detach().clone() for b in buffers]
            if due:
                self.next_check = self.updates + self.gap()
                self.complete_checked = True
            try:
                what = self.check(definition, arguments)
            except Exception as exc:  # an edit the fast path cannot follow (a new layer, another activation...)
                what = f"the fast update fails on these nets ({describe(exc)})"
            if what is not None:
                self.switch_off(what, step)
                return definition(*arguments)
        self.updates += 1
        # numpy would warn of an overflow where torch returns inf silently (a diverging run: its guard stops it)
        with torch.no_grad(), np.errstate(over="ignore", invalid="ignore"):
            return self.fast_update(*arguments)

    def check(self, definition: Callable[..., dict], arguments: tuple) -> str | None:
        """Run the script's update and the fast one on float64 copies, from the same random state; what differs."""
        start = time.perf_counter()
        names = argument_names(definition)
        hooked = [f"{argument_label(names, i)}.{name}" for i, a in enumerate(arguments)
                  if isinstance(a, nn.Module) for name, p in a.named_parameters()
                  if p._backward_hooks or getattr(p, "_post_accumulate_grad_hooks", None)]
        if hooked:
            return f"{hooked[0]} has a gradient hook, which the hand-written update does not apply"
        try:
            with float64_by_default(), np.errstate(over="ignore", invalid="ignore"):
                with untouched_random_streams():  # the script's draws (the run's streams stay where they are)
                    reference = float64_twins(arguments)
                    with KeptState(definition, {"args": arguments[0]}) as watch:  # (its call leaves nothing behind)
                        reference_out = definition(*reference)
                        kept = watch.changes()
                    if kept:  # (a schedule of args, a counter: the script's update runs only in the checks)
                        name = getattr(definition, "__name__", "the update")
                        return f"{name} keeps state between calls ({kept}), which the fast update does not"
                with untouched_random_streams(), torch.no_grad():  # the same draws again
                    fast = float64_twins(arguments)
                    fast_out = self.fast_update(*fast)
            what, worst = disagreement(arguments, reference, fast, reference_out, fast_out, names)
            if what is None:
                self.checks += 1
                self.worst = max(self.worst, worst)
            return what
        finally:
            self.check_seconds += time.perf_counter() - start

    def switch_off(self, what: str, step: int, acting: bool = False) -> None:
        if acting:
            self.acting = False
        else:
            self.on = False
        path, definition = ("fast acting", "explore") if acting else ("fast update", "the script's own update")
        message = (f"{path} check at global_step={step}: {what}; continuing with {definition} (as --autograd). If "
                   "the script was edited on purpose, this is expected; edit cascade_plumbing/fast_offpolicy.py to "
                   "match it to get the speed back")
        self.messages.append(message)
        if self.announce is not None:
            self.announce(message, step)
