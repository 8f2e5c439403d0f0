"""Fast paths of the PPO scripts: the same acting and the same update as the script's section 1, faster.

A rollout acts 2048 times on one observation, and a PPO minibatch is 64 samples through nets of a few
thousand weights: per-call overhead, not arithmetic, sets the speed. So acting runs in numpy on copies of
the weights, and the update's gradients are written out by hand (no autograd graph), into one flat
parameter buffer stepped by the fused Adam kernel.

Nothing here is a definition. `FastPaths` checks each path against the script's own section 1 while the
run trains, in float64 so that rounding (~1e-15) and a real difference (an edit: >= 1e-7) are far apart:
- acting, at every rollout start: the script's `act(actor, obs)` (its forward and its `sample_action`)
  against the numpy forward plus the numpy Gaussian sampler, both drawing from the same torch RNG state
  (a new seed every rollout, 256 rows at least, so that an edit of the noise's tails shows); and after each
  rollout, every one of its actions: the means and log-stds the numpy path drew them around against section 1's
  forward over all of the rollout's observations (which the loop computes for the update anyway), the observations
  beyond float32 rounding checked again in float64 (`rollout_done`);
- the update, on every minibatch of the first update with each new optimizer (each Cascade iteration's first),
  then on the last minibatch of every update (after all the others: the ratios and values have moved, so that
  the clipping matters): the script's
  `autograd_gradients` (the loss, its parts and its gradient by autograd, whatever the script computes there)
  against the hand-written loss, parts and gradients, and the script's `optimizer_step` (the clip and the
  optimizer it made) against the fast step, on copies of the optimizer and its state, with those gradients
  and with them scaled up 1000 times (so that the norm clip acts).
A path that disagrees, or raises, is switched off for the rest of the run with one warning line, and the
run continues through section 1, exactly as `--autograd` runs. A non-finite loss or gradient of section 1 on
a checked minibatch switches the gradients off too, so that the run's non-finite guard sees section 1's.
"""

from __future__ import annotations

import collections
import contextlib
import copy
import functools
import math
import random
import time
import types
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import torch
import torch.nn as nn
import torch.optim.optimizer as optimizer_module


def share_one_buffer(params: list[nn.Parameter]) -> nn.Parameter:
    """Make every parameter, and its .grad, a view into one flat buffer; return that buffer as a Parameter.

    The optimizer then updates a single tensor and the gradient norm is one reduction, instead of
    one small op per parameter. Values are unchanged; both gradient paths overwrite the .grad views
    every minibatch (so there is no zero_grad)."""
    flat = nn.Parameter(torch.cat([p.detach().reshape(-1) for p in params]))
    flat.grad = torch.zeros_like(flat)
    offset = 0
    for p in params:
        p.data = flat.data[offset : offset + p.numel()].view_as(p)
        p.grad = flat.grad[offset : offset + p.numel()].view_as(p)
        offset += p.numel()
    return flat


def clip_grad_norm(flat: nn.Parameter, max_norm: float) -> None:
    """torch.nn.utils.clip_grad_norm_ on the one gradient buffer: scale by min(1, max_norm / (norm + 1e-6))."""
    flat.grad.mul_(torch.clamp(max_norm / (flat.grad.norm() + 1e-6), max=1.0))


def adam_step(optimizer: torch.optim.Adam) -> None:
    """`optimizer.step()` for our one flat parameter: a direct call of the fused kernel that step() ends in.

    step() spends ~30 us per call grouping tensors and checking options (~4x the kernel itself) in a
    tight loop, and measured ~100 us per minibatch inside the training loop: ~30 ms of an update's 320
    minibatches. The state stays in the optimizer as usual (checkpoints unchanged);
    tests/test_gradients.py checks this against step() bit for bit, so a torch that changes the kernel's
    signature fails there.
    """
    group = optimizer.param_groups[0]
    (param,) = group["params"]
    state = optimizer.state.get(param)
    if not state or not plain_fused_adam(optimizer):  # the first step creates the state; AdamW, amsgrad & co.
        # outside inference mode (FastPaths.update runs in it): a state created there could not be stepped by
        # section 1's optimizer_step, should the fast path switch itself off later
        with torch.inference_mode(False):
            optimizer.step()
        return
    state["step"] += 1  # as step() does before the kernel
    beta1, beta2 = group["betas"]
    torch._fused_adam_([param], [param.grad], [state["exp_avg"]], [state["exp_avg_sq"]], [], [state["step"]],
                       amsgrad=False, lr=group["lr"], beta1=beta1, beta2=beta2, weight_decay=group["weight_decay"],
                       eps=group["eps"], maximize=False)


def plain_fused_adam(optimizer: torch.optim.Optimizer) -> bool:
    """Is `optimizer` exactly what the direct kernel call in `adam_step` computes: torch's Adam itself (not a
    subclass such as AdamW), fused, without amsgrad, maximize, decoupled weight decay or step hooks?"""
    group = optimizer.param_groups[0]
    hooks = (optimizer._optimizer_step_pre_hooks, optimizer._optimizer_step_post_hooks,
             optimizer_module._global_optimizer_pre_hooks, optimizer_module._global_optimizer_post_hooks)
    return (type(optimizer) is torch.optim.Adam and len(optimizer.param_groups) == 1 and group["fused"]
            and not any(hooks)  # step() runs them, the kernel call would not
            and not (group["amsgrad"] or group["maximize"] or group["capturable"] or group["differentiable"]
                     or group.get("decoupled_weight_decay", False)))


def fast_optimizer_step(flat: nn.Parameter, optimizer: torch.optim.Adam, max_norm: float) -> None:
    """nn.utils.clip_grad_norm_ and optimizer.step() on the one parameter buffer, without their overhead."""
    clip_grad_norm(flat, max_norm)
    adam_step(optimizer)


# Relative disagreement (max |fast - reference| / max |reference|, in float64) above which a fast path
# counts as not matching section 1. Measured on the unmodified script: at most ~1e-13 (docs/hacking.md,
# the checks); the smallest edit tried (0.01 * mean.pow(2).mean() added to the loss) differs by ~2e-7 at the
# first update, when the means are still ~0.01, and by more as they grow.
FAST_PATH_TOLERANCE = 1e-9
# The loss and its parts (policy and value loss, entropy, ratios) are compared relative to at least this: they
# are built from O(1) numbers (normalized advantages, ratios near 1), and some are near zero by cancellation.
PARTS_SCALE = 1e-2
GRADIENT_FLOOR = 1e-3
# Two values of an optimizer setting (lr, betas, eps) that a section-1 step and a fast step leave are the same
# within this relative difference: float64 rounding of a setting an edit recomputes, not a changed schedule.
SETTING_TOLERANCE = 1e-8


def same_values(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Equal, NaN where NaN (a buffer of inf or NaN sentinels is unchanged, not changed)."""
    return a.shape == b.shape and bool(((a == b) | (a.isnan() & b.isnan())).all())


def same_setting(a: Any, b: Any) -> bool:
    """Whether two values of an optimizer's setting (lr, betas, eps, ...) are the same, numbers to float64 rounding (a
    tensor lr as a float; a list as the tuple it equals): the PPO and off-policy checks compare settings alike."""
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(same_setting(x, y) for x, y in zip(a, b))
    numbers = (int, float, torch.Tensor)
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool) and not isinstance(b, bool):
        x, y = float(a), float(b)
        return x == y or abs(x - y) <= SETTING_TOLERANCE * max(abs(x), abs(y))
    return a == b


def moved(buffers: list[torch.Tensor], checked: list[torch.Tensor]) -> bool:
    """Whether the nets' `buffers` differ from their copies at the latest check (nothing to compare: no buffers)."""
    return len(buffers) != len(checked) or not all(same_values(a, b) for a, b in zip(buffers, checked))


def changed_buffers(twins: list[tuple[str, nn.Module, nn.Module]]) -> list[str]:
    """The buffers ("role.name") that differ between each (role, copy, module): what a checked call changed."""
    return [f"{role}.{name}" for role, twin, module in twins
            for (name, new), old in zip(twin.named_buffers(), module.buffers())
            if not same_values(new, old.detach().to(new.dtype))]


def relative_error(fast: list[torch.Tensor], reference: list[torch.Tensor], floor: float = 1e-30) -> float:
    """max |fast - reference| / the larger of max |reference| and max |fast| (so a zero reference against a
    non-zero value reads 1, all wrong, not 1e27), and of `floor`: for values that are sums of cancelling O(1)
    terms (the policy loss of normalized advantages at ratio 1 is ~1e-17), their rounding is ~1e-16 absolute."""
    fast_flat = torch.cat([t.reshape(-1) for t in fast])
    reference_flat = torch.cat([t.reshape(-1) for t in reference])
    if not len(reference_flat):
        return 0.0
    scale = max(reference_flat.abs().max().item(), fast_flat.abs().max().item(), floor)
    return (fast_flat - reference_flat).abs().max().item() / scale


def float64_copy(module: nn.Module) -> nn.Module:
    """A float64 copy with zeroed .grad buffers; copying draws no random numbers (the run's RNG is untouched)."""
    twin = copy.deepcopy(module).double()
    for param in twin.parameters():
        param.grad = torch.zeros_like(param)
    return twin


def same_tensors(twin: nn.Module, module: nn.Module) -> bool:
    """Do `twin` and `module` have parameters and buffers of the same names and shapes (in the same order)?"""
    def layout(m: nn.Module) -> list:
        return [(name, t.shape) for name, t in (*m.named_parameters(), *m.named_buffers())]
    return layout(twin) == layout(module)


def block_diagonal(blocks: torch.Tensor) -> np.ndarray:
    """[n, r, c] -> the [n*r, n*c] numpy matrix with the blocks on its diagonal (zeros elsewhere)."""
    return torch.block_diag(*blocks.detach().cpu()).numpy()


# At batch size 1 every numpy call costs about a microsecond and the nets' arithmetic is negligible,
# so this forward is arranged for few, simple calls: the nets sit side by side in one row ([B, n*H];
# later layers are block-diagonal matrices, plain 2D matmuls), and one head matrix gives every net's
# mean, its log-std (a bias-only column block) and its fallback logit as the two columns -z, z. The
# combination is two more matmuls: one maps (softplus(-z) | softplus(z)) to log w_i, repeated over net
# i's columns, the other sums the weighted columns over the nets. With 6 nets of 16 (the paper's) this
# takes 9 us per call against 11 for a batched matmul per layer. The block-diagonal matrices grow as
# (n*H)^2, so past n*H ~ 250 it is slower (6 nets of 64: 18 us against 13).
def numpy_acting_forward(layers: tuple, head_weight: np.ndarray, head_bias: np.ndarray, spread: np.ndarray,
                         gather: np.ndarray, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """obs [B, obs_dim] -> mean, log-std [B, A] of the ensemble, as `CascadeActor.forward`. The head's columns
    are, per net, (mean | log-std), then -z_2..-z_n, z_2..z_n; `spread` maps (softplus(-z) | softplus(z)) =
    (-log l | -log(1 - l)) to log w_i on each of net i's columns, `gather` [n*2A, 2A] sums over the nets."""
    hidden = obs
    for weight, bias in layers:
        hidden = np.tanh(hidden @ weight + bias)  # [B, n*H]: all nets side by side
    heads = hidden @ head_weight + head_bias
    per_net = gather.shape[0]  # n*2A columns: (b_i | log-std_i) of every net
    weight = np.exp(np.logaddexp(0.0, heads[:, per_net:]) @ spread)  # w_i, repeated over net i's columns
    combined = (weight * heads[:, :per_net]) @ gather  # sum_i w_i (b_i | log-std_i)
    act_dim = gather.shape[1] // 2
    return combined[:, :act_dim], combined[:, act_dim:]


def numpy_cascade_policy(actor: nn.Module) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """obs [B, obs_dim] (numpy) -> ensemble mean, log-std, as `actor.forward`, computed on numpy copies of
    the current weights (in their dtype): for acting during a rollout (the copies do not follow updates)."""
    n, act_dim = actor.size, actor.act_dim
    if n == 0:  # the empty stack (step-0 evaluation): N(0, 1)
        return lambda obs: (np.zeros((len(obs), act_dim), np.float32),) * 2
    mean_weight, mean_bias, fallback_weight, fallback_bias, log_stds = (
        t.detach().cpu() for t in (actor.mean_weight, actor.mean_bias, actor.fallback_weight, actor.fallback_bias,
                                   actor.log_std))
    layers = []
    for i, (weight, bias) in enumerate(zip(actor.hidden_weights, actor.hidden_biases)):
        # the first layer reads the shared observation: the nets' weights side by side
        matrix = torch.cat(list(weight.detach().cpu()), 1).numpy() if i == 0 else block_diagonal(weight)
        layers.append((matrix, bias.detach().cpu().reshape(1, -1).numpy().copy()))
    per_net = block_diagonal(torch.cat([mean_weight, torch.zeros_like(mean_weight)], 2))  # (mean | log-std)
    fallback = block_diagonal(torch.cat([fallback_weight.new_zeros(1, actor.hidden_size, 1), fallback_weight]))[:, 1:]
    head_weight = np.concatenate([per_net, -fallback, fallback], 1)
    head_bias = torch.cat([torch.cat([mean_bias[:, 0], log_stds], 1).reshape(-1),
                           -fallback_bias.reshape(-1), fallback_bias.reshape(-1)]).numpy()[None]
    # log w = above @ log l + own @ log(1 - l), with above = at-or-above minus own (the diagonal j = i)
    own = np.eye(n, n - 1, k=-1, dtype=np.float32)
    above = np.triu(np.ones((n, n - 1), np.float32), -1) - own  # net i reads l_j for j >= i
    neg_log_contribution = -np.concatenate([above, own], 1).T  # [2(n-1), n]
    repeat = np.kron(np.eye(n, dtype=np.float32), np.ones((1, 2 * act_dim), np.float32))  # [n, n*2A]
    gather = np.tile(np.eye(2 * act_dim, dtype=np.float32), (n, 1))  # [n*2A, 2A]
    return functools.partial(numpy_acting_forward, tuple(layers), head_weight, head_bias,
                             neg_log_contribution @ repeat, gather)


LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)
# g * (1 - h^2) for h = tanh(z): autograd's own kernel for tanh's derivative, one op instead of two
tanh_backward = torch.ops.aten.tanh_backward


def gaussian_entropy(log_std: torch.Tensor) -> torch.Tensor:
    return (0.5 + LOG_SQRT_2PI + log_std).sum(-1)


def ppo_loss_gradients(
    mean: torch.Tensor, log_std: torch.Tensor, value: torch.Tensor, actions: torch.Tensor, old_logprob: torch.Tensor,
    advantages: torch.Tensor, returns: torch.Tensor, old_value: torch.Tensor, args: Any,
) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor, torch.Tensor]:
    """`ppo_loss` and its gradient w.r.t. the nets' outputs, written out by hand.

    mean, log_std [B, A] (log_std per sample), value [B]. Returns (losses, dL/dmean [B, A],
    dL/dlog_std [B, A], dL/dvalue [B, 1]); `losses` holds the loss, its terms, the entropy, the log-ratio and ratio.
    """
    batch = len(value)
    # log pi(a|s) = sum_j -u_j^2/2 - log_std_j - log sqrt(2 pi), with u = (a - mean) / std
    inv_std = torch.exp(-log_std)
    u = (actions - mean) * inv_std
    u2 = u * u
    newlogprob = (u2.mul(-0.5) - log_std).sum(1) - LOG_SQRT_2PI * u.shape[1]
    logratio = newlogprob - old_logprob
    ratio = logratio.exp()
    if args.norm_adv:
        adv_std, adv_mean = torch.std_mean(advantages)
        advantages = (advantages - adv_mean) / (adv_std + 1e-8)

    # Policy loss mean(max(-A r, -A clip(r, 1-eps, 1+eps))). Its gradient w.r.t. r is -A/B wherever
    # the unclipped term is the max (inside the clip range both terms are equal: autograd's halves
    # add up to the same) and 0 elsewhere; dr/dlogprob = r, so dL/dlogprob = (-A r)/B there.
    pg_loss1 = -advantages * ratio
    pg_loss2 = -advantages * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)
    pg_loss = torch.max(pg_loss1, pg_loss2).mean()
    grad_logprob = (pg_loss1 * (pg_loss1 >= pg_loss2)).div_(batch).unsqueeze(1)
    # dlogprob/dmean = u / std, dlogprob/dlog_std = u^2 - 1
    grad_mean = grad_logprob * u * inv_std
    grad_log_std = grad_logprob * u2 - grad_logprob

    # Value loss 0.5 mean(max((v - R)^2, (v_clip - R)^2)) with v_clip = v_old + clip(v - v_old, -eps, eps);
    # the clipped branch passes a gradient only where v - v_old is inside the clip range.
    if args.clip_vloss:
        v_clipped = old_value + torch.clamp(value - old_value, -args.clip_coef, args.clip_coef)
        v_loss_unclipped, v_loss_clipped = (value - returns) ** 2, (v_clipped - returns) ** 2
        v_loss = 0.5 * torch.max(v_loss_unclipped, v_loss_clipped).mean()
        inside = (value - old_value).abs() <= args.clip_coef
        grad_v = torch.where(v_loss_unclipped >= v_loss_clipped, value - returns,
                             torch.where(inside, v_clipped - returns, 0.0))
    else:
        v_loss = 0.5 * ((value - returns) ** 2).mean()
        grad_v = value - returns
    grad_value = grad_v.mul_(args.vf_coef / batch)[:, None]

    entropy = gaussian_entropy(log_std).mean()
    loss = pg_loss + args.vf_coef * v_loss
    if args.ent_coef:  # loss - c * mean_b entropy_b; d/dlog_std_bj = -c/B (with the default c = 0: skipped)
        loss = loss - args.ent_coef * entropy
        grad_log_std -= args.ent_coef / batch
    # the same parts as `ppo_loss` returns, so that the training loop reads the same keys on either path
    losses = {"loss": loss, "policy_loss": pg_loss, "value_loss": v_loss, "entropy": entropy,
              "logratio": logratio, "ratio": ratio}
    return losses, grad_mean, grad_log_std, grad_value


def cascade_backward(actor: nn.Module, cache: dict, grad_mean: torch.Tensor, grad_log_std: torch.Tensor) -> None:
    """Write every actor parameter's .grad from dL/dmean, dL/dlog_std [B, A] of `actor(obs, cache)`."""
    activations, means, fallback_logit, contribution = (
        cache[key] for key in ("activations", "means", "fallback_logit", "contribution"))
    hidden_layers = actor.hidden_layers
    mean_weight, mean_bias, fallback_weight, fallback_bias, log_std = (  # one lookup each: nn.Module's are slow
        actor.mean_weight, actor.mean_bias, actor.fallback_weight, actor.fallback_bias, actor.log_std)
    # C_n = sum_i w_i b_i: net i's outputs get w_i times the ensemble's gradient
    grad_means = contribution[..., None] * grad_mean  # [n, B, A]
    torch.mm(contribution, grad_log_std, out=log_std.grad)  # sum over the batch of w_i dL/dlog_std
    hidden = activations[-1]
    torch.bmm(hidden.transpose(1, 2), grad_means, out=mean_weight.grad)
    torch.sum(grad_means, 1, keepdim=True, out=mean_bias.grad)
    grad_hidden = torch.bmm(grad_means, mean_weight.transpose(1, 2))  # [n, B, H]
    if fallback_logit.shape[0]:
        # Fallback k (net k >= 2) acts through C_k = l_k C_{k-1} + (1 - l_k) b_k, and C_n changes by
        # later_k = prod_{j>k} l_j per unit of C_k, so with g = (dL/dmean, dL/dlog_std) and z_k = logit(l_k):
        #   dL/dz_k = l_k (1 - l_k) later_k <g, C_{k-1} - b_k> = (1 - l_k) S_{k-1} - l_k w_k q_k,
        # where q_k = <g, b_k> and S_k = sum_{i<=k} w_i q_i = later_k <g, C_k> (a cumulative sum, no division).
        # Written as S_{k-1} - l_k S_k it would cancel ~-log10(1 - l_k) digits once a fallback saturates;
        # 1 - l_k = sigmoid(-z_k) keeps its digits.
        weighted_q = torch.addcmul((grad_means * means).sum(-1), contribution, log_std @ grad_log_std.T)  # [n, B]
        partial_sums = weighted_q.cumsum(0)  # S_1..S_n
        grad_logit = (torch.sigmoid(-fallback_logit) * partial_sums[:-1]
                      - torch.sigmoid(fallback_logit) * weighted_q[1:]).unsqueeze(-1)
        torch.bmm(hidden[1:].transpose(1, 2), grad_logit, out=fallback_weight.grad)
        torch.sum(grad_logit, 1, keepdim=True, out=fallback_bias.grad)
        grad_hidden[1:].baddbmm_(grad_logit, fallback_weight.transpose(1, 2))
    for i in reversed(range(len(hidden_layers))):
        weight_i, bias_i = hidden_layers[i]
        below = activations[i] if i else activations[0].expand(grad_hidden.shape[0], -1, -1)  # obs, shared
        grad_z = tanh_backward(grad_hidden, hidden)  # g tanh' = g (1 - h^2)
        torch.bmm(below.transpose(1, 2), grad_z, out=weight_i.grad)
        torch.sum(grad_z, 1, keepdim=True, out=bias_i.grad)
        if i:
            grad_hidden = torch.bmm(grad_z, weight_i.transpose(1, 2))
        hidden = below
    if actor.num_frozen:  # frozen nets get no gradient (section 1 detaches them)
        for _, param, first_net in actor.base_net_parameters():
            param.grad[: actor.frozen_rows(first_net)] = 0.0


def mlp_backward(mlp: nn.Module, x: torch.Tensor, hidden: list[torch.Tensor], grad_output: torch.Tensor) -> None:
    """Write dL/dW and dL/db into the parameters' .grad, given dL/d(output) of `mlp(x, hidden)`."""
    inputs = [x, *hidden]
    for i in reversed(range(len(mlp.layers))):
        weight, bias = mlp.layers[i]
        torch.mm(inputs[i].T, grad_output, out=weight.grad)  # dL/dW = input^T dL/dz
        torch.sum(grad_output, 0, out=bias.grad)
        if i:  # dL/dz of the layer below: g * tanh'(z) = g * (1 - h^2), with g = dL/dz W^T
            grad_output = tanh_backward(torch.mm(grad_output, weight.T), inputs[i])


def cascade_ppo_gradients(actor: nn.Module, critic: nn.Module, minibatch: tuple, args: Any,
                   output_grads: list | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """`autograd_gradients` by hand: the loss of one minibatch, its gradient written into every .grad.
    `output_grads` receives dL/dmean, dL/dlog_std, dL/dvalue (for the check)."""
    obs, actions, old_logprob, advantages, returns, old_value = minibatch
    cache, critic_hidden = {}, []
    mean, log_std, _, _ = actor(obs, cache)
    value = critic(obs, critic_hidden).squeeze(1)
    losses, grad_mean, grad_log_std, grad_value = ppo_loss_gradients(
        mean, log_std, value, actions, old_logprob, advantages, returns, old_value, args)
    if output_grads is not None:
        output_grads += [grad_mean, grad_log_std, grad_value.squeeze(1)]
    cascade_backward(actor, cache, grad_mean, grad_log_std)
    mlp_backward(critic, obs, critic_hidden, grad_value)
    return losses.pop("loss"), losses


def numpy_mlp_forward(layers: tuple, x: np.ndarray) -> np.ndarray:
    """`TanhMLP.forward` in numpy, on ((W, b), ...): at batch size 1 numpy's per-call overhead is a third of
    torch's, and its smaller code path leaves the simulator's own code in the CPU caches."""
    *inner, (last_weight, last_bias) = layers
    for weight, bias in inner:
        x = np.tanh(x @ weight + bias)
    return x @ last_weight + last_bias




def numpy_mlp_policy(actor: nn.Module) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """obs [B, obs_dim] (numpy) -> mean [B, A], log-std [1, A], as `actor.forward`, computed on numpy copies
    of the current weights (in their dtype): for acting during a rollout (the copies do not follow updates)."""
    layers = tuple((w.detach().cpu().numpy().copy(), b.detach().cpu().numpy().copy()) for w, b in actor.mean_net.layers)
    log_std = actor.log_std.detach().cpu().numpy().copy()
    return lambda obs: (numpy_mlp_forward(layers, obs), log_std)




def actor_backward(actor: nn.Module, obs: torch.Tensor, hidden: list[torch.Tensor], grad_mean: torch.Tensor,
                   grad_log_std: torch.Tensor) -> None:
    """Write the actor's .grad from dL/dmean and dL/dlog_std [B, A] of `actor(obs, hidden)`."""
    mlp_backward(actor.mean_net, obs, hidden, grad_mean)
    torch.sum(grad_log_std, 0, keepdim=True, out=actor.log_std.grad)  # one vector shared by the batch




def mlp_ppo_gradients(actor: nn.Module, critic: nn.Module, minibatch: tuple, args: Any,
                   output_grads: list | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """`autograd_gradients` by hand: the loss of one minibatch, its gradient written into every .grad.
    `output_grads` receives dL/dmean, dL/dlog_std, dL/dvalue (for the check)."""
    obs, actions, old_logprob, advantages, returns, old_value = minibatch
    actor_hidden, critic_hidden = [], []
    mean, log_std = actor(obs, actor_hidden)
    value = critic(obs, critic_hidden).squeeze(1)
    losses, grad_mean, grad_log_std, grad_value = ppo_loss_gradients(
        mean, log_std, value, actions, old_logprob, advantages, returns, old_value, args)
    if output_grads is not None:
        output_grads += [grad_mean, grad_log_std, grad_value.squeeze(1)]
    actor_backward(actor, obs, actor_hidden, grad_mean, grad_log_std)
    mlp_backward(critic, obs, critic_hidden, grad_value)
    return losses.pop("loss"), losses


def numpy_gaussian_sampler(policy: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], calls: int = 0,
                           record: list | None = None) -> Callable[[np.ndarray], np.ndarray]:
    """obs -> a sample of Normal(mean, exp(log_std)) as torch's `Normal.sample()` draws it: one standard normal
    per action entry from torch's RNG (the same draws, in the same order: `normal_` on a tensor of the actions'
    shape), then mean + std * noise.

    `calls`, when given, is the number of calls to come (a rollout's steps). If each call draws fewer than
    SERIAL_NORMAL numbers, the noise of all of them is drawn at the first call with one `normal_` (a torch call
    per env step costs ~10-20 us in a rollout loop, a cold path between two MuJoCo steps): torch fills such
    tensors one number after the other, so the draws and the RNG state afterwards are those of one call per
    step; `bulk_draws_match` confirms it on the running torch, else every call draws its own.

    `record`, when given, receives the (mean, log-std) of every call: what the rollout's actions were drawn around,
    compared after the rollout with section 1's forward over the same observations (`FastPaths.rollout_done`)."""
    noise_np, index, state_after_draw = np.empty((0, 0)), 0, b""

    def sample(obs: np.ndarray) -> np.ndarray:
        nonlocal noise_np, index, state_after_draw
        mean, log_std = policy(obs)
        if record is not None:
            record.append((mean, log_std))
        if index == len(noise_np) or noise_np.shape[1:] != mean.shape or noise_np.dtype != mean.dtype:
            rows = calls if index == 0 and calls > 1 and bulk_draws_match(mean.shape, mean.dtype) else 1
            noise_np, index = standard_normals(rows, mean.shape, mean.dtype), 0
            state_after_draw = torch.get_rng_state().numpy().tobytes() if rows > 1 else b""
        elif index == len(noise_np) - 1 and state_after_draw:
            # the bulk draw is only act()'s step-by-step draws if nothing else drew from torch's RNG in between
            # (an edit of the rollout loop): checked once, at the last step, where any such draw shows
            if torch.get_rng_state().numpy().tobytes() != state_after_draw:
                raise RuntimeError("the rollout drew from torch's random numbers beside the policy's sampling (an "
                                   "edit of the loop?): the numpy path draws a rollout's action noise at its first "
                                   "step, so this rollout's noise came in another order than act() draws it")
        noise = noise_np[index]
        index += 1
        return mean + np.exp(log_std) * noise

    return sample


SERIAL_NORMAL = 16  # torch's CPU normal_ fills a tensor of fewer numbers (or a strided one) one number at a time


def standard_normals(rows: int, shape: tuple, dtype: np.dtype) -> np.ndarray:
    """[rows, *shape] standard normals from torch's RNG. For rows > 1, one `normal_` on a strided view (the last
    axis padded by one), which torch fills one number at a time in row order (its serial kernel)."""
    if rows == 1:
        storage = np.empty((1, *shape), dtype)
        torch.from_numpy(storage).normal_()
        return storage
    storage = np.empty((rows, *shape[:-1], shape[-1] + 1), dtype)
    noise = torch.from_numpy(storage)[..., : shape[-1]]
    noise.normal_()
    return storage[..., : shape[-1]]


_bulk_checked: dict[tuple, bool] = {}


def bulk_draws_match(shape: tuple, dtype: np.dtype) -> bool:
    """Whether `standard_normals(r, shape)` draws exactly what r calls of `normal_` on a `shape` tensor draw, and
    leaves torch's RNG in the same state (checked once per shape and dtype, on a forked RNG)."""
    key = (tuple(shape), np.dtype(dtype).str)
    if key not in _bulk_checked:
        if int(np.prod(shape)) >= SERIAL_NORMAL or len(shape) == 0:
            _bulk_checked[key] = False
        else:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(CHECK_SEED)
                one_by_one = np.stack([standard_normals(1, shape, dtype)[0] for _ in range(5)])
                state = torch.get_rng_state()
                torch.manual_seed(CHECK_SEED)
                bulk = standard_normals(5, shape, dtype)
                _bulk_checked[key] = bool(np.array_equal(one_by_one, bulk)
                                          and torch.equal(state, torch.get_rng_state()))
    return _bulk_checked[key]


CHECK_SEED = 12345  # + the step: the acting check's noise, from a forked RNG (training's stream is untouched)
CHECK_ROWS = 256  # the acting check's observations are repeated to at least this many rows: ~770 noise draws
CHECK_GRADIENT_SCALES = (1.0, 1e3)  # the optimizer check steps with section 1's gradients, then 1000 times them
# After each rollout, every observation it acted on: the numpy path's means and log-stds against section 1's forward,
# both float32, as |difference of the means| / std + |difference of the log-stds| per observation. The unmodified
# scripts differ by float32 rounding: ~1e-8 (Cascade) and ~3e-7 (PPO) on Hopper-v4 and Ant-v4, more once the std is
# small; observations above this are checked again in float64 (act() against the numpy path, at FAST_PATH_TOLERANCE),
# the worst ROLLOUT_SUSPECTS at most, so a rounding above it costs only that check.
ROLLOUT_TOLERANCE = 1e-5
ROLLOUT_SUSPECTS = 64
# the observations of a rollout that differed most (however little) join the next rollout's acting check, in float64
NEXT_CHECK_ROWS = 8


def float64_optimizer(optimizer: torch.optim.Optimizer) -> tuple[nn.Parameter, torch.optim.Optimizer]:
    """A float64 copy of an optimizer over one parameter (the flat buffer), with its settings and a copy of its
    state (the step counts too: the original's stay as they are); the copy's parameter (its .grad zeroed) is
    returned with it. Another structure raises: the fast step needs one flat buffer."""
    params = [p for group in optimizer.param_groups for p in group["params"]]
    if len(params) != 1:
        raise ValueError(f"an optimizer over {len(params)} parameters; the fast step updates one flat buffer")
    param = nn.Parameter(params[0].detach().double())
    param.grad = torch.zeros_like(param)
    twin = copy.copy(optimizer)  # its class and settings; the groups and the state are the copy's own below
    # copy.copy keeps only what __getstate__ returns: the step hooks (register_step_post_hook) are carried over
    twin._optimizer_step_pre_hooks = collections.OrderedDict(optimizer._optimizer_step_pre_hooks)
    twin._optimizer_step_post_hooks = collections.OrderedDict(optimizer._optimizer_step_post_hooks)
    # (a tensor setting cloned: an optimizer_step that changes a tensor lr in place would change the run's)
    twin.param_groups = [{**{key: value.clone() if torch.is_tensor(value) else value
                             for key, value in optimizer.param_groups[0].items()}, "params": [param]}]
    twin.state = collections.defaultdict(dict)
    for key, value in optimizer.state.get(params[0], {}).items():
        if not torch.is_tensor(value):
            value = copy.deepcopy(value)
        elif key != "step" and value.is_floating_point():
            value = value.double()
        else:
            value = value.clone()
        twin.state[param][key] = value
    return param, twin


def numpy_and_python_streams() -> tuple:
    """Where numpy's and Python's global random streams stand, comparable with ==: numpy's whole state (its key
    array changes only every 624 draws, its position with each)."""
    _, key, position, has_gauss, cached_gaussian = np.random.get_state()
    return key.tobytes(), position, has_gauss, cached_gaussian, random.getstate()


@contextlib.contextmanager
def untouched_random_streams() -> Iterator[None]:
    """Whatever runs inside draws from torch's, numpy's and Python's global random streams without moving them: a
    check calls section 1 once more than an --autograd run does, and must not shift the run's random numbers."""
    numpy_state, python_state = np.random.get_state(), random.getstate()
    with torch.random.fork_rng(devices=[]):
        try:
            yield
        finally:
            np.random.set_state(numpy_state)
            random.setstate(python_state)


class KeptState:
    """What a checked function (`act`, an update) changes that outlives its call, so that a check can name it and undo
    what its own calls set: the global names of the function's module and the plain attributes of `objects` (the
    actor, `args`), compared as bindings, and the contents of the mutable globals that the function's own code names
    (a noise process's object, a dict of running statistics), copied before the call, compared after it and, where
    changed, put back: the same objects in the same places, their tensors' and arrays' values copied back in place.
    Not seen: state in a helper's globals, in function or class attributes, or deeper inside an object (the acting
    checks' second call still shows its effect). A context manager: what the calls inside it set is put back on
    leaving it."""

    def __init__(self, function: Callable, objects: dict[str, Any]):
        self.namespace = getattr(function, "__globals__", {})
        self.changed: list[str] | None = None  # the watched contents that changed (set by `changes`)
        self.globals = dict(self.namespace)
        self.objects = {label: (obj, dict(vars(obj))) for label, obj in objects.items() if hasattr(obj, "__dict__")}
        code = getattr(function, "__code__", None)
        self.contents: dict[str, tuple[Any, Any, Any]] = {}  # name: (the object, its references, a deep copy)
        for name in code.co_names if code is not None else ():
            value = self.namespace.get(name)
            if isinstance(value, (dict, list, set, torch.Tensor, np.ndarray)) or (
                    hasattr(value, "__dict__") and not callable(value) and not isinstance(value, types.ModuleType)):
                try:
                    saved = copy.deepcopy(value)
                except Exception:  # (an object that cannot be copied: not watched)
                    continue
                if saved is not value:  # (deepcopy returns some objects themselves: a logger, an Enum member)
                    self.contents[name] = (value, shallow_references(value), saved)

    def changes(self) -> str:
        """What the function set, as 'it sets global x, args.tau', or '' if nothing."""
        def rebound(before: dict, now: dict, prefix: str) -> list[str]:
            return [prefix + name for name in sorted(before.keys() | now.keys())  # (not Python's own __names__)
                    if not same_binding(before.get(name, KeptState), now.get(name, KeptState))
                    and not name.startswith("__")]
        names = rebound(self.globals, self.namespace, "global ")
        for label, (obj, attributes) in self.objects.items():
            names += rebound(attributes, vars(obj), f"{label}.")
        self.changed = self.changed_contents()
        names += [f"the contents of global {name}" for name in self.changed if f"global {name}" not in names]
        return ("it sets " + ", ".join(names)) if names else ""

    def restore(self) -> None:
        """Put back every global name, attribute and changed content as it was before the call."""
        for name in [name for name in self.namespace if name not in self.globals]:
            del self.namespace[name]
        self.namespace.update(self.globals)
        for obj, attributes in self.objects.values():
            vars(obj).clear()
            vars(obj).update(attributes)
        changed = self.changed if self.changed is not None else self.changed_contents()
        for name in changed:
            with contextlib.suppress(Exception), torch.no_grad():
                put_back(*self.contents[name])

    def changed_contents(self) -> list[str]:
        return [name for name, (value, _, saved) in self.contents.items() if not same_contents(value, saved)]

    def __enter__(self) -> KeptState:
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.restore()


IMMUTABLE = (int, float, complex, str, bytes, bool, type(None), tuple, frozenset)


def same_binding(a: Any, b: Any) -> bool:
    """The same object, or an equal immutable value (`args.clip_coef = 0.2` where it was 0.2 is no change)."""
    if a is b:
        return True
    try:
        return type(a) is type(b) and isinstance(a, IMMUTABLE) and bool(a == b)
    except Exception:
        return False


def shallow_references(value: Any) -> Any:
    """What `value` refers to, one level down (the objects themselves, not copies), to put back as they were."""
    if isinstance(value, dict):
        return dict(value)
    if isinstance(value, (list, set)):
        return type(value)(value)
    if isinstance(value, (torch.Tensor, np.ndarray)):
        return None
    return dict(vars(value))


def put_back(value: Any, references: Any, saved: Any) -> None:
    """`value` as it was: its own references back in their places, and the values of the tensors and arrays among
    them (and of `value` itself, if one) copied back in place from `saved`, the deep copy taken before."""
    if isinstance(value, torch.Tensor):
        value.copy_(saved)
        return
    if isinstance(value, np.ndarray):
        value[...] = saved
        return
    if isinstance(value, dict):
        value.clear()
        value.update(references)
        pairs = [(references[key], saved.get(key)) for key in references]
    elif isinstance(value, list):
        value[:] = references
        pairs = list(zip(references, saved))
    elif isinstance(value, set):
        value.clear()
        value.update(references)
        pairs = []
    else:
        vars(value).clear()
        vars(value).update(references)
        pairs = [(references[key], vars(saved).get(key)) for key in references]
    for item, item_saved in pairs:  # tensors and arrays one level down, changed in place
        if isinstance(item, torch.Tensor) and isinstance(item_saved, torch.Tensor) and item.shape == item_saved.shape:
            item.copy_(item_saved)
        elif isinstance(item, np.ndarray) and isinstance(item_saved, np.ndarray) and item.shape == item_saved.shape:
            item[...] = item_saved


def same_contents(a: Any, b: Any, seen: set | None = None) -> bool:
    """a and b hold the same values (tensors, arrays, containers and objects compared element by element, NaN equal
    to NaN); True where that cannot be told."""
    if a is b:
        return True
    seen = set() if seen is None else seen
    if (id(a), id(b)) in seen:  # (a cycle: already being compared)
        return True
    seen.add((id(a), id(b)))
    try:
        if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
            if not (isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor) and a.shape == b.shape
                    and a.dtype == b.dtype):
                return False
            if a.is_floating_point() or a.is_complex():
                return bool(((a == b) | (a.isnan() & b.isnan())).all())
            return bool(torch.equal(a, b))
        if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            try:
                return bool(np.array_equal(a, b, equal_nan=True))
            except TypeError:  # (arrays of objects or strings: no NaN to treat)
                return bool(np.array_equal(a, b))
        if isinstance(a, dict) and isinstance(b, dict):
            return a.keys() == b.keys() and all(same_contents(a[key], b[key], seen) for key in a)
        if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
            return len(a) == len(b) and all(same_contents(x, y, seen) for x, y in zip(a, b))
        if hasattr(a, "__dict__") and type(a) is type(b) and not callable(a):
            return same_contents(vars(a), vars(b), seen)
        if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
            return True
        return bool(a == b)
    except Exception:
        return True


class FastPaths:
    """Which fast paths are on, and their run-time checks against the script's section 1 (float64 copies).

    `numpy_policy(actor)` gives obs -> (mean, log-std) in numpy; `fast_gradients(actor, critic, minibatch, args)`
    writes the hand-written gradients into every .grad and returns (loss, parts); `definition` is section 1's
    `(autograd_gradients, optimizer_step)`, what `update` is checked against. A check that fails, or any
    exception inside a fast path, turns that path off for the rest of the run: one line through `announce`."""

    def __init__(self, enabled: bool, numpy_policy: Callable, fast_gradients: Callable,
                 announce: Callable[[str, int], None] | None = None,
                 definition: tuple[Callable, Callable] | None = None):
        self.acting = self.gradients = enabled
        self.numpy_policy, self.fast_gradients, self.announce = numpy_policy, fast_gradients, announce
        self.definition = definition
        # the largest disagreement seen by the checks that passed
        self.worst = {"acting": 0.0, "rollout": 0.0, "gradients": 0.0, "parts": 0.0, "optimizer": 0.0}
        self.check_seconds = 0.0
        self.messages: list[str] = []
        self._twins: dict[str, tuple] = {}  # "actor"/"critic" -> (the module, the step it was copied at, copy)
        self._minibatch = (None, 0, False)  # (the update's global_step, its minibatch, check all?): when to check
        self._fully_checked: torch.optim.Optimizer | None = None  # the optimizer whose first update was checked
        self._checked_buffers: list[torch.Tensor] = []  # the nets' buffers at the latest gradient check
        # the rollout the numpy path acts in: (the actor, its step, the (mean, log-std) of each of its calls)
        self._rollout: tuple[nn.Module, int, list] | None = None
        self._suspects: np.ndarray | None = None  # the last rollout's observations that differed most

    def float64_twin(self, role: str, module: nn.Module, step: int) -> nn.Module:
        """A float64 copy of `module` (actor or critic), its .grad zeroed. Deep-copied anew (every attribute: an edit
        may keep state outside the parameters) at the first check of each `step` (a rollout, an update); the other
        checks of that step (one per minibatch in a fully checked update) refresh the same copy's parameters and
        buffers in place, some 20x cheaper than a deep copy."""
        cached = self._twins.get(role)
        if cached is not None and cached[0] is module and cached[1] == step and same_tensors(cached[2], module):
            twin = cached[2]
            with torch.no_grad():
                torch._foreach_copy_([*twin.parameters(), *twin.buffers()], [*module.parameters(), *module.buffers()])
                for copied, original in zip(twin.modules(), module.modules()):  # (train/eval: a loop may switch it)
                    copied.training = original.training
                for param in twin.parameters():
                    if param.grad is None:  # (an edit of section 1 may have dropped it)
                        param.grad = torch.zeros_like(param)
                torch._foreach_zero_([param.grad for param in twin.parameters()])
            return twin
        twin = float64_copy(module)
        self._twins[role] = (module, step, twin)
        return twin

    def acting_function(self, act: Callable[[nn.Module, np.ndarray], np.ndarray], actor: nn.Module,
                        check_obs: np.ndarray, step: int, calls: int = 0, context: str = ""
                        ) -> Callable[[np.ndarray], np.ndarray]:
        """The rollout's obs -> actions: the numpy path if it draws what the script's `act(actor, obs)` draws
        from the same RNG state on `check_obs` and on the previous rollout's observations that differed most
        (repeated to CHECK_ROWS rows), else `act` itself. `calls`: the rollout's steps, if known. The actions of the
        rollout are checked once more after it, every one of them (`rollout_done`). `context` begins the warning."""
        definition = functools.partial(act, actor)
        self._rollout = None
        if not self.acting:
            return definition

        def switch_off(what: str) -> None:
            self.switch_off("acting", context + what, step)

        start = time.perf_counter()
        try:
            suspects, self._suspects = self._suspects, None
            if suspects is not None and suspects.shape[1:] == np.shape(check_obs)[1:]:
                check_obs = np.concatenate([check_obs, suspects])
            twin = self.float64_twin("actor", actor, step)
            obs = np.asarray(check_obs, dtype=np.float64)
            obs = np.tile(obs, (-(-CHECK_ROWS // max(len(obs), 1)), 1))
            with untouched_random_streams():
                torch.manual_seed(CHECK_SEED + step)
                streams = numpy_and_python_streams()
                try:
                    # twice: an act() that keeps state between calls (sticky actions, correlated noise) shows in
                    # its second call, if not already in what it sets (put back on leaving: the check's calls
                    # leave nothing behind for the run's own act())
                    with KeptState(act, {"actor": twin}) as watch:
                        reference = [torch.as_tensor(np.asarray(act(twin, obs)), dtype=torch.float64)
                                     for _ in range(2)]
                        kept = watch.changes()
                    if kept:
                        switch_off(f"act() keeps state between calls ({kept}), while the numpy acting "
                                   "path draws every action afresh")
                        return definition
                    changed = changed_buffers([("actor", twin, actor)])
                    if changed:  # (a review: statistics updated while acting, read by no forward, went unseen)
                        switch_off(f"act() changes the buffer {changed[0]}, which the numpy acting path does not")
                        return definition
                    if numpy_and_python_streams() != streams:
                        switch_off("act() draws from numpy's or Python's global random numbers, which "
                                   "the numpy acting path (torch's Gaussian noise only) does not")
                        return definition
                except Exception as exc:
                    switch_off(f"act() raised {describe(exc)} on the check's float64 copy of the "
                               f"actor{dtype_hint(exc)}")
                    return definition
                torch.manual_seed(CHECK_SEED + step)
                sampler = numpy_gaussian_sampler(self.numpy_policy(twin))
                fast = [torch.as_tensor(sampler(obs), dtype=torch.float64) for _ in range(2)]
            if fast[0].shape != reference[0].shape:
                raise ValueError(f"actions of shape {tuple(fast[0].shape)} instead of {tuple(reference[0].shape)}")
            error = relative_error(fast, reference)
            if not error <= FAST_PATH_TOLERANCE and relative_error(fast[:1], reference[:1]) <= FAST_PATH_TOLERANCE:
                switch_off("act() keeps state between calls (its second call on the same observations "
                           f"draws otherwise than the numpy acting path, max relative error {error:.1e}), while "
                           "the numpy acting path draws every action afresh")
                return definition
        except Exception as exc:  # an edit the fast path cannot follow (another shape, another net): a failed check
            switch_off(f"the numpy acting path fails on this actor ({describe(exc)})")
            return definition
        finally:
            self.check_seconds += time.perf_counter() - start
        if not error <= FAST_PATH_TOLERANCE:
            switch_off(f"the numpy acting path (forward and Gaussian sampling) draws other actions "
                       f"than act() (max relative error {error:.1e})")
            return definition
        self.worst["acting"] = max(self.worst["acting"], error)
        record: list = []
        fast_act = numpy_gaussian_sampler(self.numpy_policy(actor), calls, record)
        self._rollout = (actor, step, record)

        def guarded(obs: np.ndarray) -> np.ndarray:
            nonlocal fast_act
            if fast_act is not None:
                try:
                    return fast_act(obs)
                except Exception as exc:
                    switch_off(f"the numpy acting path raised {describe(exc)}")
                    fast_act = None
            return definition(obs)

        return guarded

    def rollout_done(self, act: Callable[[nn.Module, np.ndarray], np.ndarray], actor: nn.Module, obs: torch.Tensor,
                     mean: torch.Tensor, log_std: torch.Tensor, step: int) -> None:
        """After a rollout the numpy path acted in: every one of its actions against section 1. `mean`, `log_std`
        are section 1's forward over the rollout's observations `obs` [steps * envs, obs_dim] (the loop computes them
        anyway, for the log-probs of the update); the numpy path's means and log-stds are compared with them row by
        row (float32, a vectorized difference), and the observations where they differ by more than float32 rounding
        are checked again in float64, act() against the numpy path, as at a rollout's start. A difference there (an
        edit that acts on some observations only: a clip, a branch on the observation's size) switches acting off
        at this rollout. The observations that differed most join the next rollout's acting check."""
        rollout, self._rollout = self._rollout, None
        if rollout is None or not self.acting or rollout[0] is not actor or not rollout[2]:
            return
        _, rollout_step, record = rollout
        start = time.perf_counter()
        try:
            means, log_stds = zip(*record)
            fast_mean = np.concatenate(means)  # [calls * envs, A]
            fast_log_std = np.concatenate(log_stds)  # the same, or [calls, A] for one log-std vector per call
            if fast_log_std.shape != fast_mean.shape:
                fast_log_std = np.repeat(fast_log_std, len(fast_mean) // len(fast_log_std), axis=0)
            rows = len(fast_mean)  # (fewer than the rollout's if the numpy path raised mid-way: act() drew the rest)
            reference_mean = mean.detach()[:rows].cpu().numpy()
            reference_log_std = np.broadcast_to(log_std.detach()[:rows].cpu().numpy(), reference_mean.shape)
            with np.errstate(all="ignore"):
                difference = (np.abs(fast_mean - reference_mean) * np.exp(-reference_log_std)
                              + np.abs(fast_log_std - reference_log_std)).max(1)
            difference = np.where(np.isnan(difference), np.inf, difference)  # (a NaN is a difference too)
            keep = min(max(ROLLOUT_SUSPECTS, NEXT_CHECK_ROWS), rows)
            worst = np.argpartition(difference, rows - keep)[rows - keep:]
            worst = worst[np.argsort(difference[worst])[::-1]]  # the largest first
            observations = obs.detach()[:rows].cpu().numpy()
            self._suspects = observations[worst[:NEXT_CHECK_ROWS]].astype(np.float32)
            largest = float(difference[worst[0]])
            flagged = worst[difference[worst] > ROLLOUT_TOLERANCE]
        except Exception as exc:
            self.switch_off("acting", f"section 1's forward over the rollout's observations cannot be compared with "
                            f"the numpy acting path's ({describe(exc)})", step)
            return
        finally:
            self.check_seconds += time.perf_counter() - start
        if len(flagged):
            count = int((difference > ROLLOUT_TOLERANCE).sum())
            context = (f"the rollout from global_step={rollout_step} acted through the numpy path, whose means or "
                       f"log-stds differ from section 1's forward on {count} of its {rows} observations (up to "
                       f"{largest:.1e} in units of the policy's std; so those actions are not act()'s); on the worst "
                       f"{len(flagged)} of them ")
            suspects = self._suspects
            self.acting_function(act, actor, observations[flagged], step, context=context)
            self._rollout, self._suspects = None, suspects  # (the suspects are the next rollout's still)
            if not self.acting:
                return
        self.worst["rollout"] = max(self.worst["rollout"], largest)

    def check_update(self, actor: nn.Module, critic: nn.Module, optimizer: torch.optim.Optimizer, minibatch: tuple,
                     args: Any, step: int) -> None:
        """Compare the hand-written loss, parts and gradients with section 1's `autograd_gradients` (what
        --autograd runs) on one minibatch, on the same float64 copies; then the fast optimizer
        step with section 1's `optimizer_step`, on float64 copies of `optimizer`, with those gradients."""
        autograd_gradients, optimizer_step = self.definition
        hooked = [name for module, role in ((actor, "actor"), (critic, "critic"))
                  for name, param in module.named_parameters(prefix=role)
                  if param._backward_hooks or getattr(param, "_post_accumulate_grad_hooks", None)]
        if hooked:  # the hand-written gradients apply none, and the check's deep copies would not carry them
            self.switch_off("gradients", f"{hooked[0]} has a gradient hook (register_hook), which the hand-written "
                            "update does not apply", step)
            return
        start = time.perf_counter()
        in_section_1 = False  # is the exception, if any, section 1's own (the edit's error, met by --autograd too)?
        try:
            actor64, critic64 = self.float64_twin("actor", actor, step), self.float64_twin("critic", critic, step)
            names = [f"actor.{n}" for n, _ in actor64.named_parameters()]
            names += [f"critic.{n}" for n, _ in critic64.named_parameters()]
            params = [*actor64.parameters(), *critic64.parameters()]
            minibatch = tuple(t.detach().double() for t in minibatch)
            with untouched_random_streams():  # an edit may draw random numbers: not from training's streams
                with KeptState(autograd_gradients, {"args": args}) as watch:  # (its call leaves nothing behind)
                    in_section_1 = True
                    reference_loss, reference_parts = autograd_gradients(actor64, critic64, params, minibatch, args)
                    in_section_1 = False
                    kept = watch.changes()
                if kept:  # (a schedule of args, a counter: on the fast path the function runs only in the checks)
                    self.switch_off("gradients", f"autograd_gradients keeps state between calls ({kept}), which the "
                                    "hand-written update does not", step)
                    return
                reference = [p.grad.clone() for p in params]
                # buffers it updated (running statistics kept in the nets): the hand-written update updates none (a
                # fault hunt of the off-policy scripts: such an edit was ignored, silently)
                changed = changed_buffers([("actor", actor64, actor), ("critic", critic64, critic)])
                if changed:
                    self.switch_off("gradients", f"autograd_gradients changes the buffer {changed[0]}, which the "
                                    "hand-written update does not", step)
                    return
                # NaN where the hand-written update writes nothing: a parameter it does not know of (one an edit
                # added) then reads as a disagreement here, not as autograd's gradient left in the buffer
                for param in params:
                    param.grad.fill_(math.nan)
                with torch.no_grad():
                    fast_loss, fast_parts = self.fast_gradients(actor64, critic64, minibatch, args)
                fast = [p.grad for p in params]
                if not math.isfinite(reference_loss.item()) or not all(torch.isfinite(g).all() for g in reference):
                    self.switch_off("gradients", "autograd_gradients gives a non-finite loss or gradient (the run's "
                                    "non-finite guard judges section 1's values from here on)", step)
                    return
                what = self.disagreement(names, reference_loss, reference_parts, reference, fast_loss,
                                         fast_parts, fast)
                if what is None:
                    what = self.optimizer_disagreement(optimizer_step, optimizer, reference, args)
        except Exception as exc:
            what = (f"autograd_gradients (section 1) itself raised {describe(exc)}: an error of the edit, which "
                    "--autograd meets too" if in_section_1 else
                    f"the hand-written update cannot follow this edit ({describe(exc)})")
            self.switch_off("gradients", what, step)
            return
        finally:
            self.check_seconds += time.perf_counter() - start
        if what is not None:
            self.switch_off("gradients", what, step)

    def disagreement(self, names: list[str], reference_loss: torch.Tensor, reference_parts: dict,
                     reference: list[torch.Tensor], fast_loss: torch.Tensor, fast_parts: dict,
                     fast: list[torch.Tensor]) -> str | None:
        """What the hand-written update computes differently from autograd_gradients (None: nothing)."""
        # the loss, like its parts, is a sum of O(1) terms that can cancel to ~1e-7 late in a run (the policy loss
        # against half the value loss): relative to itself alone, float64 rounding then reads ~1e-9 (it switched
        # an Ant-v4 --start-full run off at 5.8M steps)
        error = relative_error([fast_loss.reshape(1)], [reference_loss.reshape(1)], floor=PARTS_SCALE)
        if not error <= FAST_PATH_TOLERANCE:
            return f"the hand-written update computes another loss than autograd_gradients (relative error {error:.1e})"
        worst, worst_part = error, 0.0
        for key, value in reference_parts.items():  # what the run logs and stops early on
            if key not in fast_parts:
                return f"autograd_gradients returns a part '{key}' that the hand-written update does not compute"
            error = relative_error([torch.as_tensor(fast_parts[key]).double()], [torch.as_tensor(value).double()],
                                   floor=PARTS_SCALE)
            if not error <= FAST_PATH_TOLERANCE:
                return f"the hand-written update computes another '{key}' than autograd_gradients " \
                       f"(max relative error {error:.1e})"
            worst_part = max(worst_part, error)
        # a parameter's gradient can be near zero by cancellation (a fallback bias: a sum over the batch): each is
        # compared relative to at least GRADIENT_FLOOR times the largest gradient of all, the scale of its rounding
        kept = [(name, f, r) for name, f, r in zip(names, fast, reference) if r.numel()]
        if kept:
            names, fast, reference = zip(*kept)
            largest = torch.stack(torch._foreach_norm(reference, float("inf")))
            scale = torch.maximum(torch.maximum(largest, torch.stack(torch._foreach_norm(fast, float("inf")))),
                                  GRADIENT_FLOOR * largest.max()).clamp(min=1e-30)
            errors = (torch.stack(torch._foreach_norm(torch._foreach_sub(fast, reference), float("inf"))) / scale)
            for name, error in zip(names, errors.tolist()):
                if not error <= FAST_PATH_TOLERANCE:
                    return f"the hand-written gradient of {name} differs from autograd_gradients " \
                           f"(max relative error {error:.1e})"
                worst = max(worst, error)
        self.worst["gradients"] = max(self.worst["gradients"], worst)
        self.worst["parts"] = max(self.worst["parts"], worst_part)
        return None

    def optimizer_disagreement(self, optimizer_step: Callable, optimizer: torch.optim.Optimizer,
                               gradients: list[torch.Tensor], args: Any) -> str | None:
        """Does the fast step (clip, Adam kernel) move the parameters as section 1's `optimizer_step` does?"""
        flat_gradient = torch.cat([g.reshape(-1) for g in gradients])
        optimized = sum(p.numel() for group in optimizer.param_groups for p in group["params"])
        if optimized != flat_gradient.numel():
            raise ValueError(f"an optimizer over {optimized} numbers, not the nets' {flat_gradient.numel()}")
        for scale in CHECK_GRADIENT_SCALES:
            moves, settings = [], []
            for step_function in (optimizer_step, None):
                param, twin = float64_optimizer(optimizer)
                before, gradient = param.detach().clone(), param.grad
                param.grad.copy_(flat_gradient * scale)
                if step_function is None:
                    fast_optimizer_step(param, twin, args.max_grad_norm)
                else:
                    with KeptState(step_function, {"args": args}) as watch:
                        step_function(param, twin, args)
                        kept = watch.changes()
                    if kept:
                        return f"optimizer_step keeps state between calls ({kept}), which the fast step does not"
                    if param.grad is not gradient:  # the nets' .grad are views of this one tensor: it must stay
                        return "optimizer_step replaces or removes the .grad of the flat parameter buffer " \
                               "(optimizer.zero_grad() sets it to None), which every net's .grad is a view of, so " \
                               "section 1's update cannot run as edited (the loop already zeroes that buffer in " \
                               "place before each autograd_gradients: drop the zero_grad or pass set_to_none=False)"
                moves.append(param.detach() - before)
                settings.append({key: value for key, value in twin.param_groups[0].items() if key != "params"})
            for key in sorted({*settings[0], *settings[1]}):  # e.g. a learning rate decayed after the step, which
                if not same_setting(settings[0].get(key), settings[1].get(key)):  # the fast step does not do
                    return (f"optimizer_step leaves the optimizer's {key} at {settings[0].get(key)}, the fast step "
                            f"at {settings[1].get(key)}")
            error = relative_error([moves[1]], [moves[0]])
            if not error <= FAST_PATH_TOLERANCE:
                return f"the fast optimizer step (clip, fused Adam) moves the parameters otherwise than " \
                       f"optimizer_step (max relative error {error:.1e})"
            self.worst["optimizer"] = max(self.worst["optimizer"], error)
        return None

    def update(self, actor: nn.Module, critic: nn.Module, flat: nn.Parameter, optimizer: torch.optim.Adam,
               minibatch: tuple, args: Any, step: int) -> tuple[torch.Tensor | None, dict | None]:
        """One minibatch step with the hand-written gradients (clipped, fused Adam); (None, None) if it raised or
        a check failed, after switching itself off (the caller then runs section 1's step). Checked first
        (`check_update`): every minibatch of the first update with each new optimizer (each Cascade iteration's
        first, a resumed run's first), then the last minibatch of every update (`step` tells the updates apart;
        the last is --update-epochs x --num-minibatches: an update that stops before it, by --target-kl or an edit
        of the loop, has the next update's first minibatch checked instead)."""
        update_step, index, every = self._minibatch
        expected_last = args.update_epochs * args.num_minibatches - 1
        if update_step == step:
            index += 1
            check = every or index == expected_last
        else:  # a new update; if the one before stopped before its last minibatch (--target-kl, a loop edit), it
            # went unchecked: this first minibatch is checked instead
            stopped_early = update_step is not None and index < expected_last
            index, every = 0, optimizer is not self._fully_checked
            self._fully_checked = optimizer
            check = every or stopped_early or expected_last == 0  # (one minibatch per update: it is the last)
        self._minibatch = (step, index, every)
        # and any minibatch whose nets' buffers changed since the latest check (a hack-safety hunt: observation
        # statistics kept in buffers, updated in the loop and read at a net's input, which the hand-written backward
        # of its first layer does not see, trained the update's unchecked minibatches on a wrong gradient)
        buffers = [b for net in (actor, critic) for b in net.buffers()]
        if moved(buffers, self._checked_buffers):
            check = True
        if check and self.definition is not None:
            self._checked_buffers = [b.detach().clone() for b in buffers]
            self.check_update(actor, critic, optimizer, minibatch, args, step)
            if not self.gradients:
                return None, None
        try:
            with torch.inference_mode():  # no autograd bookkeeping at all
                loss, parts = self.fast_gradients(actor, critic, minibatch, args)
                fast_optimizer_step(flat, optimizer, args.max_grad_norm)
            return loss, parts
        except Exception as exc:
            self.switch_off("gradients", f"the hand-written update raised {describe(exc)}", step)
            return None, None

    def switch_off(self, path: str, what: str, step: int) -> None:
        setattr(self, path, False)
        remedy = ("acting through act()" if path == "acting"
                  else "updating with autograd_gradients")
        message = (f"fast path check at global_step={step}: {what}; continuing by {remedy} (as --autograd). "
                   f"If section 1 was edited on purpose, this is expected; edit cascade_plumbing/fast.py to match it "
                   f"to get the speed back")
        self.messages.append(message)
        if self.announce is not None:
            self.announce(message, step)


def dtype_hint(exc: BaseException) -> str:
    """The remedy for an `act` that fails on the check's float64 copy because it converts the observation to float32
    (torch.Tensor(obs)), or '' if `exc` does not read as a dtype mismatch (an AttributeError, a typo: its own type and
    message say what went wrong)."""
    text = str(exc).lower()
    if isinstance(exc, (RuntimeError, TypeError)) and any(
            word in text for word in ("dtype", "scalar type", "double", "float")):
        return ("; the check needs act to keep the observation's dtype (torch.as_tensor(obs), not "
                "torch.Tensor(obs))")
    return ""


def describe(exc: BaseException) -> str:
    """`TypeName: first line of the message`, for a one-line warning."""
    text = str(exc).splitlines()[0][:160] if str(exc) else ""
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
