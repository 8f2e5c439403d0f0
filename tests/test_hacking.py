"""Copy-and-hack safety of the two PPO scripts: an edit of section 1 (the math) takes effect, through the
fast paths or through autograd after a one-line warning, never silently wrong; the unmodified scripts
keep their fast paths; --autograd gives the fast path's results up to float rounding."""

import importlib.util
import logging
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

import cascade_plumbing.fast as fast_paths
import cascade_ppo_continuous as cpc
import ppo_baseline as pb
from helpers import ROOT, error_line_in_process, only_run_dir, read_scalars

TINY = dict(num_steps=256, num_minibatches=4, update_epochs=2, eval_every=0, checkpoint_every=0, quiet=True)


def final_parameters(run_dir):
    checkpoint = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)
    return {f"{part}.{k}": v for part in ("actor", "critic") for k, v in checkpoint[part].items()}


def assert_close_parameters(a, b, tol):
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=0.0, atol=tol, msg=key)


FEWER_MINIBATCHES = dict(num_minibatches=8, update_epochs=4)  # 32 checks, not 320, in each fully checked update


@pytest.mark.parametrize("module,budget", [(cpc, dict(n=2, k=4096)),
                                           (cpc, dict(n=3, k=4096, fallback_init=0.999999, **FEWER_MINIBATCHES)),
                                           (cpc, dict(n=2, k=4096, freeze_previous=True, **FEWER_MINIBATCHES)),
                                           (pb, dict(total_timesteps=8192))])
def test_unmodified_script_keeps_its_fast_paths(module, budget, tmp_path):
    """The float64 checks pass on every rollout and update of a real run (the default settings), by many orders
    of magnitude, also with saturated fallbacks (--fallback-init 0.999999: the hand-written dL/dz must not
    compute 1 - l as a difference, which loses six digits; section 1's forward does, and float64 keeps ten) and
    frozen nets (with fewer minibatches: every check still runs)."""
    result = module.train(module.Args(env_id="Hopper-v4", eval_every=0, track_dir=str(tmp_path), quiet=True,
                                      **budget))
    fast = result["fast_paths"]
    assert fast.acting and fast.gradients and fast.messages == []
    assert 0 < fast.worst["gradients"] < fast_paths.FAST_PATH_TOLERANCE * 1e-3, fast.worst
    assert fast.worst["acting"] < fast_paths.FAST_PATH_TOLERANCE * 1e-3, fast.worst
    # every action of every rollout against section 1's forward (float32 both): rounding, far below the threshold
    assert 0 < fast.worst["rollout"] < fast_paths.ROLLOUT_TOLERANCE * 0.1, fast.worst
    # the loss's parts (relative to at least PARTS_SCALE) and the optimizer step, checked with the gradients
    assert 0 < fast.worst["parts"] < fast_paths.FAST_PATH_TOLERANCE * 1e-2, fast.worst
    assert fast.worst["optimizer"] < fast_paths.FAST_PATH_TOLERANCE * 1e-3, fast.worst


@pytest.mark.parametrize("module,budget", [(cpc, dict(n=2, k=1024)), (cpc, dict(n=2, k=1024, freeze_previous=True)),
                                           (pb, dict(total_timesteps=2048))])
def test_autograd_path_gives_the_fast_paths_results(module, budget, tmp_path):
    results = {}
    for autograd in (False, True):
        args = module.Args(env_id="Hopper-v4", autograd=autograd, track_dir=str(tmp_path / str(autograd)),
                           **TINY, **budget)
        results[autograd] = module.train(args)
    assert not results[True]["fast_paths"].acting and not results[True]["fast_paths"].gradients
    for net in ("actor", "critic"):
        fast, slow = results[False][net].state_dict(), results[True][net].state_dict()
        for key in fast:
            torch.testing.assert_close(slow[key], fast[key], rtol=1e-4, atol=1e-5, msg=key)


# Edits made the CleanRL way, in a copy of the script: (old text, new text) pairs of section 1.
EDITS = {
    # a hack-safety hunt (2026-12-07): the critic's input statistics in a buffer, updated in the loop once per update:
    # the hand-written backward fed the raw observation to the first layer for an update's unchecked minibatches
    "critic input statistics": [("            self.biases.append(nn.Parameter(bias[0]))\n        self._refresh()",
                                 "            self.biases.append(nn.Parameter(bias[0]))\n"
                                 "        self.register_buffer(\"in_mean\", torch.zeros(sizes[0]))\n        self._refresh()"),
                                ("        *layers, last = self.layers\n        for weight, bias in layers:",
                                 "        *layers, last = self.layers\n        x = x - self.in_mean\n"
                                 "        for weight, bias in layers:"),
                                ("            run.update_done(global_step, optimizer, parts,",
                                 "            critic.in_mean.copy_(b_obs.mean(0))\n"
                                 "            run.update_done(global_step, optimizer, parts,")],
    # ... and act() counting its calls in a buffer of the actor (read by no forward): changed on the check's copy only
    "act counter": [("        self.fallback_init = fallback_init\n",
                     "        self.fallback_init = fallback_init\n"
                     "        self.register_buffer(\"calls\", torch.zeros(()))\n"),
                    ("    with torch.inference_mode():\n        mean, log_std, _, _ = actor(torch.as_tensor(obs, device=",
                     "    actor.calls.add_(1)\n"
                     "    with torch.inference_mode():\n        mean, log_std, _, _ = actor(torch.as_tensor(obs, device=")],
    # ... and dropout in training only, with the loop acting in eval mode: a twin copied in train mode was reused by
    # the acting check of the same step (a false alarm, acting switched off)
    "dropout while training": [("            hidden = torch.tanh(stacked_affine(hidden, self.trainable(weight, 0), "
                                "self.trainable(bias, 0)))",
                                "            hidden = nn.functional.dropout(torch.tanh(stacked_affine(hidden, "
                                "self.trainable(weight, 0), self.trainable(bias, 0))), 0.1, self.training)"),
                               ("            check_obs = np.concatenate(",
                                "            actor.eval()\n            check_obs = np.concatenate("),
                               ("            batch = (b_obs, b_actions, b_logprobs, b_advantages, b_returns, b_values)",
                                "            actor.train()\n"
                                "            batch = (b_obs, b_actions, b_logprobs, b_advantages, b_returns, b_values)")],
    # a fault hunt (2026-12-07): what the update leaves besides the gradients and the step, which the fast update
    # silently ignored in the off-policy scripts: a learning rate decayed after the step, running statistics in a buffer
    "lr decay in optimizer_step": [("    nn.utils.clip_grad_norm_([flat_params], args.max_grad_norm)\n    optimizer.step()\n",
                                    "    nn.utils.clip_grad_norm_([flat_params], args.max_grad_norm)\n    optimizer.step()\n"
                                    "    for group in optimizer.param_groups:\n        group[\"lr\"] *= 0.99\n")],
    # the same settings written otherwise (a list for Adam's tuple): the fast step keeps on, as off-policy's does
    "betas rewritten in optimizer_step": [("    nn.utils.clip_grad_norm_([flat_params], args.max_grad_norm)\n    optimizer.step()\n",
                                           "    nn.utils.clip_grad_norm_([flat_params], args.max_grad_norm)\n    optimizer.step()\n"
                                           "    for group in optimizer.param_groups:\n"
                                           "        group[\"betas\"] = [float(beta) for beta in group[\"betas\"]]\n")],
    "buffer statistics": [("        self.fallback_init = fallback_init\n",
                           "        self.fallback_init = fallback_init\n"
                           "        self.register_buffer(\"obs_mean\", torch.zeros(obs_dim))\n"),
                          ("        grads = torch.autograd.grad(loss, params, allow_unused=True)",
                           "        grads = torch.autograd.grad(loss, params, allow_unused=True)\n"
                           "        actor.obs_mean.lerp_(obs.mean(0), 0.01)")],
    "loss term": [("loss = pg_loss - args.ent_coef * entropy_loss + v_loss * args.vf_coef",
                   "loss = pg_loss - args.ent_coef * entropy_loss + v_loss * args.vf_coef + 0.01 * mean.pow(2).mean()")],
    "relu base nets": [("hidden = torch.tanh(stacked_affine(", "hidden = torch.relu(stacked_affine(")],
    "relu mlp": [("x = torch.tanh(torch.addmm(bias, x, weight))", "x = torch.relu(torch.addmm(bias, x, weight))")],
    "softmax gating": [("        contribution = contributions(fallback)  # w_i [n, B]",
                        "        contribution = torch.softmax(torch.cat([fallback_logit.new_zeros(1, obs.shape[0]), "
                        "fallback_logit]), 0)")],
    # a review (2026-12-03): the fallback rule, written once in `forward`, reaches the policy (not only the logs)
    "fallback temperature": [("        fallback = torch.sigmoid(fallback_logit)  # l_i, nets 2..n",
                              "        fallback = torch.sigmoid(fallback_logit / 2)")],
    # issue 27's three classes, with edits of our own:
    # 1. a term added to the objective where autograd computes it (not in ppo_loss): pull the log-stds to 1
    "objective term": [("        grads = torch.autograd.grad(loss, params, allow_unused=True)",
                        "        loss = loss + (log_std - 1.0).pow(2).mean()\n"
                        "        grads = torch.autograd.grad(loss, params, allow_unused=True)")],
    # 2. another policy distribution: heavier-tailed Laplace noise of the same scale; rollouts must sample it
    "laplace policy": [("    return Normal(mean, log_std.exp(), validate_args=False)",
                        "    return torch.distributions.Laplace(mean, log_std.exp(), validate_args=False)")],
    # 3. a shape change of the nets: each base net reads the observation and its square (2 * obs_dim inputs)
    "squared features": [("        hidden = obs  # every base net reads the same observation",
                          "        hidden = torch.cat([obs, obs * obs], -1)"),
                         ("        dims = [obs_dim] + [hidden_size] * num_layers",
                          "        dims = [2 * obs_dim] + [hidden_size] * num_layers"),
                         ("        dims = [self.obs_dim] + [self.hidden_size] * self.num_layers",
                          "        dims = [2 * self.obs_dim] + [self.hidden_size] * self.num_layers")],
    # found by a review (2026-12-03): edits that only matter once the policy has moved, or outside the gradient
    "policy clip range": [("torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)",
                           "torch.clamp(ratio, 1 - 0.001, 1 + 0.001)")],
    "value clip range": [("torch.clamp(value - old_value, -args.clip_coef, args.clip_coef)",
                          "torch.clamp(value - old_value, -0.001, 0.001)")],
    "kl penalty": [("loss = pg_loss - args.ent_coef * entropy_loss + v_loss * args.vf_coef",
                    "loss = pg_loss - args.ent_coef * entropy_loss + v_loss * args.vf_coef"
                    " + 0.1 * ((ratio - 1) - logratio).mean()")],
    "adamw": [("return torch.optim.Adam([flat_params], lr=learning_rate, eps=1e-5, fused=True)",
               "return torch.optim.AdamW([flat_params], lr=learning_rate, eps=1e-5, weight_decay=0.1, fused=True)")],
    "no gradient clip": [("    nn.utils.clip_grad_norm_([flat_params], args.max_grad_norm)\n", "")],
    "truncated noise": [("return action_distribution(mean, log_std).sample()",
                         "return mean + log_std.exp() * torch.randn_like(mean).clamp(-2.5, 2.5)")],
    # a second review (2026-12-03): an edit that draws random numbers; CleanRL's float32 conversion in `act`
    "noisy observations in the loss": [("        mean, log_std, _, _ = actor(obs)\n",
                                        "        obs = obs + 0.01 * torch.randn_like(obs)\n"
                                        "        mean, log_std, _, _ = actor(obs)\n")],
    "float32 observations in act": [("actor(torch.as_tensor(obs, device=actor.log_std.device))",
                                     "actor(torch.Tensor(obs).to(actor.log_std.device))")],
    # a third review (2026-12-04): a parameter the hand-written update does not know of (here a learned shift of
    # the mean, zero at first, so the acting check cannot see it before it moves) must train, not keep a zero
    # gradient; and CleanRL's habit of accumulating with loss.backward() must give autograd_gradients' gradients
    "new parameter": [("        self.log_std = nn.Parameter(torch.empty(0, act_dim))\n",
                       "        self.log_std = nn.Parameter(torch.empty(0, act_dim))\n"
                       "        self.shift = nn.Parameter(torch.zeros(act_dim))\n"),
                      ("        mean = (contribution[..., None] * means).sum(0)  # C_n = sum_i w_i b_i",
                       "        mean = (contribution[..., None] * means).sum(0) + self.shift")],
    "new parameter (baseline)": [("        self.log_std = nn.Parameter(torch.zeros(1, act_dim))\n",
                                  "        self.log_std = nn.Parameter(torch.zeros(1, act_dim))\n"
                                  "        self.shift = nn.Parameter(torch.zeros(1, act_dim))\n"),
                                 ("        mean = self.mean_net(obs, hidden)\n",
                                  "        mean = self.mean_net(obs, hidden) + self.shift\n")],
    "backward": [("        grads = torch.autograd.grad(loss, params, allow_unused=True)",
                  "        loss.backward()"),
                 ("    for param, grad in zip(params, grads):\n"
                  "        param.grad.copy_(grad) if grad is not None else param.grad.zero_()\n", "")],
    # a probe of the checks (2026-12-04): a gradient hook (the check's deep copies dropped it, and the hand-written
    # update never applies one), an optimizer step hook (the kernel call skipped it, the check's copy too), and
    # epsilon-greedy exploration in act from numpy's random numbers (the check restored numpy's stream)
    "gradient hook": [("                self._replace(name, nn.Parameter(new))",
                       "                hooked = nn.Parameter(new)\n"
                       "                hooked.register_hook(lambda g: g.clamp(-1e-3, 1e-3))\n"
                       "                self._replace(name, hooked)")],
    "gradient hook (baseline)": [("        self.log_std = nn.Parameter(torch.zeros(1, act_dim))\n",
                                  "        self.log_std = nn.Parameter(torch.zeros(1, act_dim))\n"
                                  "        self.log_std.register_hook(lambda g: g.clamp(-1e-3, 1e-3))\n")],
    "optimizer step hook": [("    return torch.optim.Adam([flat_params], lr=learning_rate, eps=1e-5, fused=True)",
                             "    optimizer = torch.optim.Adam([flat_params], lr=learning_rate, eps=1e-5, fused=True)\n"
                             "    optimizer.register_step_post_hook(lambda opt, args, kwargs: [\n"
                             "        p.data.mul_(1 - group['lr'] * 0.1) for group in opt.param_groups for p in group['params']])\n"
                             "    return optimizer")],
    "epsilon-greedy act": [("        mean, log_std, _, _ = actor(torch.as_tensor(obs, device=actor.log_std.device))",
                            "        if np.random.rand() < 0.1:\n"
                            "            return np.random.uniform(-1, 1, (len(obs), actor.act_dim)).astype(np.float32)\n"
                            "        mean, log_std, _, _ = actor(torch.as_tensor(obs, device=actor.log_std.device))")],
    # a researcher's probe (2026-12-05): parameter groups with their own learning rates, which the LR schedule had
    # overwritten with --learning-rate at every update (in --autograd runs too)
    "critic learning rate": [("return torch.optim.Adam([flat_params], lr=learning_rate, eps=1e-5, fused=True)",
                              'return torch.optim.Adam([{"params": actor.parameters()}, {"params": '
                              'critic.parameters(), "lr": 1e-3}], lr=learning_rate, eps=1e-5)')],
    # logged only (--ent-coef 0): the logged entropy must be section 1's
    "entropy per dimension": [("entropy_loss = dist.entropy().sum(1).mean()", "entropy_loss = dist.entropy().mean()")],
}
CASES = [  # script, edit, the parts the warnings must name (in order)
    ("cascade_ppo_continuous.py", "loss term", ["computes another loss than autograd_gradients"]),
    ("cascade_ppo_continuous.py", "relu base nets", ["draws other actions than act()", "gradient of actor.hidden"]),
    ("cascade_ppo_continuous.py", "softmax gating", ["draws other actions than act()", "gradient of actor.fallback"]),
    ("cascade_ppo_continuous.py", "fallback temperature", ["draws other actions than act()",
                                                           "gradient of actor.fallback"]),
    ("cascade_ppo_continuous.py", "objective term", ["computes another loss than autograd_gradients"]),
    ("cascade_ppo_continuous.py", "laplace policy", ["draws other actions than act()",
                                                     "computes another loss than autograd_gradients"]),
    ("cascade_ppo_continuous.py", "squared features", ["numpy acting path fails on this actor (ValueError"]),
    ("ppo_baseline.py", "loss term", ["computes another loss than autograd_gradients"]),
    ("ppo_baseline.py", "relu mlp", ["draws other actions than act()", "gradient of actor.mean_net"]),
    ("ppo_baseline.py", "objective term", ["computes another loss than autograd_gradients"]),
    ("ppo_baseline.py", "laplace policy", ["draws other actions than act()",
                                           "computes another loss than autograd_gradients"]),
    *[(script, edit, expected) for script in ("cascade_ppo_continuous.py", "ppo_baseline.py") for edit, expected in [
        ("policy clip range", ["computes another loss than autograd_gradients"]),
        ("value clip range", ["computes another loss than autograd_gradients"]),
        ("kl penalty", ["autograd_gradients"]),
        ("adamw", []),  # the fast path steps any optimizer but torch's plain fused Adam with its step()
        ("no gradient clip", ["moves the parameters otherwise than optimizer_step"]),
        ("truncated noise", ["draws other actions than act()"]),
        ("entropy per dimension", ["computes another 'entropy' than autograd_gradients"]),
        ("critic learning rate", ["the hand-written update cannot follow this edit"]),
    ]],
]
LOGGED_ONLY = {"entropy per dimension": "losses/entropy"}  # edits that change a logged value, not the parameters
CASES += [
    ("cascade_ppo_continuous.py", "new parameter", ["gradient of actor.shift", "draws other actions than act()"]),
    ("ppo_baseline.py", "new parameter (baseline)", ["gradient of actor.shift", "draws other actions than act()"]),
    # the same gradients as autograd.grad: nothing to switch off, and --autograd (which zeroes .grad before each
    # minibatch, as CleanRL's zero_grad) must not accumulate them over minibatches
    *[(script, "backward", []) for script in ("cascade_ppo_continuous.py", "ppo_baseline.py")],
    ("cascade_ppo_continuous.py", "gradient hook", ["has a gradient hook"]),
    ("ppo_baseline.py", "gradient hook (baseline)", ["has a gradient hook"]),
    *[(script, "optimizer step hook", []) for script in ("cascade_ppo_continuous.py", "ppo_baseline.py")],
    ("cascade_ppo_continuous.py", "epsilon-greedy act", ["act() draws from numpy's or Python's global random"]),
    ("cascade_ppo_continuous.py", "noisy observations in the loss", ["autograd_gradients"]),
    # no change of the math: the numpy path is switched off, saying why, and the run is act()'s
    ("cascade_ppo_continuous.py", "float32 observations in act", ["needs act to keep the observation's dtype"]),
    ("cascade_ppo_continuous.py", "lr decay in optimizer_step", ["optimizer_step leaves the optimizer's lr at"]),
    ("cascade_ppo_continuous.py", "betas rewritten in optimizer_step", []),
    ("cascade_ppo_continuous.py", "buffer statistics", ["autograd_gradients changes the buffer actor.obs_mean"]),
    ("cascade_ppo_continuous.py", "critic input statistics", ["the hand-written gradient of critic.weights.0"]),
    ("cascade_ppo_continuous.py", "dropout while training", ["computes another loss than autograd_gradients"]),
    ("cascade_ppo_continuous.py", "act counter", ["act() changes the buffer actor.calls"]),
]
# nothing to compare with the unedited result: a new shape or parameter (equal to its --autograd twin is the check),
# or the same math written otherwise
NO_EFFECT = {"squared features", "float32 observations in act", "new parameter", "new parameter (baseline)",
             "backward", "betas rewritten in optimizer_step", "buffer statistics", "critic input statistics", "act counter"}


TINY_ARGS = dict(env_id="Hopper-v4", **TINY)
# |switched run - its --autograd twin| allowed in each parameter: float rounding, measured at most 1.2e-7 after the
# 4 updates of BUDGET_ARGS (2026-12-03), far below the smallest effect of an edit (~1.5e-5)
ROUNDING = 2e-6
BUDGET_ARGS = {"cascade_ppo_continuous.py": dict(n=2, k=512), "ppo_baseline.py": dict(total_timesteps=1024)}  # 4 updates each


def import_copy(path):
    """The edited copy as a module of its own (in-process: a subprocess per run would cost ~4 s of start-up)."""
    name = f"edited_{os.path.basename(os.path.dirname(path))}_{os.path.splitext(os.path.basename(path))[0]}"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while the file runs
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module


def edited_copy(script, edits, folder):
    """`script` with each (old, new) text replaced (old must occur exactly once), as a module of its own."""
    source = open(os.path.join(ROOT, script)).read()
    for old, new in edits:
        assert source.count(old) == 1, f"the edit's line is not in {script} exactly once: {old}"
        source = source.replace(old, new)
    copy = folder / script
    copy.write_text(source)
    return import_copy(str(copy))


def train_copy(module, script, track_dir, **extra):
    """Train `module` (`script` or an edited copy) on the tiny budget; its final parameters, from its checkpoint,
    and the warnings of its fast-path checks."""
    result = module.train(module.Args(**TINY_ARGS, **BUDGET_ARGS[script], track_dir=str(track_dir), **extra))
    (run_dir,) = os.listdir(track_dir)
    return final_parameters(os.path.join(track_dir, run_dir)), result["fast_paths"].messages


def logged(track_dir, tag):
    return [value for _, value in read_scalars(only_run_dir(track_dir))[tag]]


@pytest.fixture(scope="module")
def unedited(tmp_path_factory):
    """Final parameters of each unedited script on the tiny budget."""
    out = {}
    for script, module in (("cascade_ppo_continuous.py", cpc), ("ppo_baseline.py", pb)):
        out[script], warnings = train_copy(module, script, tmp_path_factory.mktemp(script.replace(".", "_")) / "runs")
        assert warnings == [], warnings  # the unedited script keeps its fast paths
    return out


@pytest.mark.parametrize("script,edit,expected", CASES, ids=[f"{s[:-3]}-{e}" for s, e, _ in CASES])
def test_an_edit_of_section_1_is_never_silently_wrong(script, edit, expected, unedited, tmp_path, capsys):
    module = edited_copy(script, EDITS[edit], tmp_path)
    capsys.readouterr()
    switched_params, _ = train_copy(module, script, tmp_path / "fast")
    stderr = capsys.readouterr().err
    assert "Traceback" not in stderr, stderr  # a fast path that raises is a failed check
    warnings = [line for line in stderr.splitlines() if line.startswith("warning: fast path check")]
    assert len(warnings) == len(expected), stderr
    for line, part in zip(warnings, expected):
        assert part in line and "continuing by" in line, line
    edited, _ = train_copy(module, script, tmp_path / "autograd", autograd=True)
    # the edit takes effect exactly as autograd computes it (up to float rounding)...
    assert_close_parameters(switched_params, edited, ROUNDING)
    if edit in LOGGED_ONLY:  # the run logs what section 1 computes (the unedited script logs something else)
        tag = LOGGED_ONLY[edit]
        fast_log, autograd_log = logged(tmp_path / "fast", tag), logged(tmp_path / "autograd", tag)
        torch.testing.assert_close(torch.tensor(fast_log), torch.tensor(autograd_log), rtol=1e-4, atol=1e-5)
        train_copy(importlib.import_module(script[:-3]), script, tmp_path / "unedited")
        unedited_log = logged(tmp_path / "unedited", tag)
        assert abs(fast_log[-1] - unedited_log[-1]) > 1e-3 * abs(unedited_log[-1]), (fast_log, unedited_log)
    # ...and it does change the result: by far more than that rounding, and by more than ROUNDING, so that a run
    # that missed the edit (the unedited result) fails the comparison above (the smallest effects, ~1.5e-5, are
    # the first loss term's and the KL penalty's, small at first; a shape change is a change by construction)
    elif edit not in NO_EFFECT:
        rounding = max((switched_params[k] - edited[k]).abs().max().item() for k in edited)
        effect = max((edited[k] - unedited[script][k]).abs().max().item() for k in edited)
        assert effect > max(10 * rounding, 3 * ROUNDING), (effect, rounding)


COPY_FLAGS = ["--env-id", "InvertedPendulum-v4", "--num-steps", "256", "--num-minibatches", "4", "--update-epochs", "1",
              "--eval-every", "0", "--checkpoint-every", "0", "--quiet"]
COPY_BUDGET = {"cascade_ppo_continuous.py": ["--n", "1", "--k", "256"], "ppo_baseline.py": ["--total-timesteps", "256"]}


@pytest.mark.parametrize("script", ["cascade_ppo_continuous.py", "ppo_baseline.py"])
def test_a_copy_in_the_repository_root_runs_and_names_its_runs(script, tmp_path):
    """`cp cascade_ppo_continuous.py my_idea.py` in the repository root runs as is, and its runs are named after
    the copy (the default --exp-name is the file name), so plots/ keeps them apart from the original's."""
    name = f"my_idea_{os.getpid()}"
    copy = os.path.join(ROOT, f"{name}.py")
    shutil.copy(os.path.join(ROOT, script), copy)
    try:
        proc = subprocess.run([sys.executable, copy, *COPY_FLAGS, *COPY_BUDGET[script], "--track-dir", str(tmp_path)],
                              capture_output=True, text=True, cwd=ROOT, timeout=300)
    finally:
        os.remove(copy)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (run_dir,) = os.listdir(tmp_path)
    assert run_dir.startswith(f"InvertedPendulum-v4__{name}__1__"), run_dir


def test_a_copy_elsewhere_runs_once_the_package_is_installed(tmp_path):
    """A copy in any other folder imports the shared plumbing from the installed package (`pip install -e .`, which
    `pip install -r requirements.txt` does): it trains, from that folder, with nothing else copied."""
    shutil.copy(os.path.join(ROOT, "cascade_ppo_continuous.py"), tmp_path / "mine.py")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([sys.executable, str(tmp_path / "mine.py"), *COPY_FLAGS, "--n", "1", "--k", "256",
                           "--track-dir", str(tmp_path / "runs")], capture_output=True, text=True, cwd=tmp_path,
                          timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (run_dir,) = os.listdir(tmp_path / "runs")
    assert "__mine__" in run_dir
    help_text = subprocess.run([sys.executable, str(tmp_path / "mine.py"), "--help"], capture_output=True, text=True,
                               cwd=tmp_path, timeout=120, env=env)
    assert help_text.returncode == 0 and "--autograd" in help_text.stdout
    # the copy's run, resumed or evaluated by the original (the same checkpoint format), would go on with the
    # original's code: refused in one line that names the copy
    run_path = str(tmp_path / "runs" / run_dir)
    for flag in ("--resume", "--evaluate"):
        line = error_line_in_process("cascade_ppo_continuous.py", flag, run_path)
        assert line.startswith(f"error: {run_path}/checkpoint.pt was written by mine.py, not cascade_ppo_continuous.py")
        assert line.endswith(f"python mine.py {flag} {run_path}/checkpoint.pt"), line


def test_a_non_finite_loss_of_section_1_stops_the_run_as_autograd_would(tmp_path, capsys):
    """A term that is NaN in section 1 (the mean of the empty fallback tensor of a one-net stack) must stop the run
    with the non-finite guard's line, as --autograd does, not train on with the hand-written (finite) loss."""
    module = edited_copy("cascade_ppo_continuous.py", [(
        "        grads = torch.autograd.grad(loss, params, allow_unused=True)",
        "        loss = loss + 0.01 * actor(obs)[2].mean()\n"
        "        grads = torch.autograd.grad(loss, params, allow_unused=True)")], tmp_path)
    for autograd in (False, True):
        capsys.readouterr()
        with pytest.raises(SystemExit) as stopped:
            train_copy(module, "cascade_ppo_continuous.py", tmp_path / f"runs_{autograd}", autograd=autograd)
        assert "the loss became non-finite at global_step=256 (iteration 1, update 1)" in str(stopped.value), \
            stopped.value
        warnings = [line for line in capsys.readouterr().err.splitlines() if "fast path check" in line]
        assert warnings == ([] if autograd else [warnings[0]])
        assert autograd or "autograd_gradients gives a non-finite loss or gradient" in warnings[0]


@pytest.mark.parametrize("script", ["cascade_ppo_continuous.py", "ppo_baseline.py"])
def test_a_new_part_of_the_loss_can_be_logged(script, tmp_path):
    """A diagnostic added to ppo_loss's parts (here CleanRL's k3 estimate of the KL) is logged, as `losses/k3`, as
    section 1 computes it: the hand-written update does not compute it, so the check hands the run to
    autograd_gradients before the loop reads it."""
    module = edited_copy(script, [('"ratio": ratio}', '"ratio": ratio, "k3": ((ratio - 1) - logratio).mean()}')],
                         tmp_path)
    _, messages = train_copy(module, script, tmp_path / "fast")
    assert len(messages) == 1 and "returns a part 'k3'" in messages[0], messages
    train_copy(module, script, tmp_path / "autograd", autograd=True)
    fast_log, autograd_log = logged(tmp_path / "fast", "losses/k3"), logged(tmp_path / "autograd", "losses/k3")
    assert len(fast_log) >= 4 and all(value > 0 for value in fast_log)  # every update; the KL estimate is positive
    torch.testing.assert_close(torch.tensor(fast_log), torch.tensor(autograd_log), rtol=1e-3, atol=1e-9)


def test_an_update_stopped_early_is_checked_all_the_same(tmp_path, monkeypatch):
    """With --target-kl every update stops after its first epoch, before the minibatch the late check waits for:
    the next update's first minibatch is checked instead, so no update but the run's last goes unchecked."""
    checked = []
    check = fast_paths.FastPaths.check_update
    monkeypatch.setattr(fast_paths.FastPaths, "check_update",
                        lambda self, *a: checked.append(a[-1]) or check(self, *a))
    result = cpc.train(cpc.Args(**TINY_ARGS, n=1, k=2048, target_kl=1e-12, track_dir=str(tmp_path)))
    assert result["fast_paths"].messages == []
    updates = list(range(256, 2049, 256))  # global_step of each update
    assert sorted(set(checked)) == updates  # each update's (early) end is checked at the next update's start...
    assert checked.count(256) == 4  # ...and the first update, on its 4 minibatches (one epoch): all of them


@pytest.mark.parametrize("script", ["cascade_ppo_continuous.py", "ppo_baseline.py"])
def test_zero_grad_that_drops_the_gradient_buffer_is_named_not_silent(script, tmp_path, capsys):
    """CleanRL's `optimizer.zero_grad()`, added after the step: it sets the flat buffer's .grad, which every net's
    .grad is a view of, to None, so section 1's next step would have no gradient. The fast path's check says so
    in its line, and neither path trains on without gradients: the run stops at the loop's next zeroing."""
    module = edited_copy(script, [("    optimizer.step()\n", "    optimizer.step()\n    optimizer.zero_grad()\n")],
                         tmp_path)
    for autograd in (False, True):
        capsys.readouterr()
        with pytest.raises(AttributeError, match="NoneType"):
            train_copy(module, script, tmp_path / f"runs_{autograd}", autograd=autograd)
        warnings = [line for line in capsys.readouterr().err.splitlines() if "fast path check" in line]
        assert len(warnings) == (0 if autograd else 1), warnings
        assert autograd or "optimizer_step replaces or removes the .grad of the flat parameter buffer" in warnings[0]


def test_torch_random_numbers_drawn_in_the_rollout_loop_are_named(tmp_path, capsys):
    """An edit of the rollout loop that draws from torch's RNG (sensor noise on the observations): the numpy path
    draws a rollout's action noise at its first step, so the draws come in another order than act()'s step by step.
    The first such rollout is named in one warning line and every later one acts through act(), as --autograd."""
    module = edited_copy("cascade_ppo_continuous.py", [(
        "next_obs = next_obs.astype(np.float32)",
        "next_obs = (next_obs + 0.01 * torch.randn(next_obs.shape).numpy()).astype(np.float32)")], tmp_path)
    capsys.readouterr()
    _, messages = train_copy(module, "cascade_ppo_continuous.py", tmp_path / "runs")
    assert len(messages) == 1 and "fast path check at global_step=0" in messages[0], messages
    assert "the rollout drew from torch's random numbers" in messages[0], messages[0]


ONE_MINIBATCH = dict(env_id="Hopper-v4", num_steps=256, num_minibatches=1, update_epochs=1, eval_every=0,
                     checkpoint_every=0, quiet=True)
ONE_MINIBATCH_BUDGET = {"cascade_ppo_continuous.py": dict(n=1, k=1024), "ppo_baseline.py": dict(total_timesteps=1024)}


@pytest.mark.parametrize("script", ["cascade_ppo_continuous.py", "ppo_baseline.py"])
def test_one_minibatch_per_update_is_checked_at_every_update(script, tmp_path, capsys):
    """With --num-minibatches 1 --update-epochs 1 an update's one minibatch is also its last, so every update is
    checked (a probe, 2026-12-04: only each optimizer's first was). The edit matters only once the policy has moved
    (a penalty on log-stds beyond 1e-4, zero at the start), so the first update's check cannot see it."""
    module = edited_copy(script, [("loss = pg_loss - args.ent_coef * entropy_loss + v_loss * args.vf_coef",
                                   "loss = pg_loss - args.ent_coef * entropy_loss + v_loss * args.vf_coef"
                                   " + 10.0 * torch.relu(log_std.abs().max() - 1e-4)")], tmp_path)
    finals = {}
    for autograd in (False, True):
        track_dir = tmp_path / f"runs_{autograd}"
        capsys.readouterr()
        result = module.train(module.Args(**ONE_MINIBATCH, **ONE_MINIBATCH_BUDGET[script], track_dir=str(track_dir),
                                          autograd=autograd))
        finals[autograd] = final_parameters(only_run_dir(track_dir))
        if not autograd:
            assert any("computes another loss than autograd_gradients" in m for m in result["fast_paths"].messages), \
                result["fast_paths"].messages
    assert_close_parameters(finals[False], finals[True], ROUNDING)


def test_a_resumed_actor_keeps_its_saved_frozen_count_through_an_edited_freeze_below(tmp_path):
    """The checkpoint holds the frozen count freeze_below set; a resume restores that count as saved, not through
    freeze_below again (a probe: an edit of freeze_below was applied twice after a resume)."""
    module = edited_copy("cascade_ppo_continuous.py", [("        self.num_frozen = num_frozen\n",
                                                        "        self.num_frozen = max(num_frozen - 1, 0)\n")], tmp_path)
    result = module.train(module.Args(**TINY_ARGS, n=3, k=256, freeze_previous=True, track_dir=str(tmp_path / "runs")))
    assert result["actor"].num_frozen == 1  # the edit: net 3 trains with net 2 at the end, only net 1 is frozen
    checkpoint = module.load_checkpoint(only_run_dir(tmp_path / "runs"))
    assert module.actor_from_checkpoint(checkpoint).num_frozen == 1


@pytest.mark.parametrize("module", [cpc, pb], ids=["cascade_ppo_continuous", "ppo_baseline"])
def test_the_fast_paths_stay_off_on_a_gpu(module):
    """On a GPU, act() samples from the CUDA generator, which the numpy acting path (torch's CPU generator) cannot
    reproduce: --cuda runs section 1 only (tests/test_cuda.py checks a real --cuda run). On the CPU the fast paths
    are on unless --autograd."""
    cpu = torch.device("cpu")
    assert module.make_fast_paths(module.Args(), cpu).acting
    assert not module.make_fast_paths(module.Args(autograd=True), cpu).acting
    fast = module.make_fast_paths(module.Args(cuda=True), torch.device("cuda"))
    assert not fast.acting and not fast.gradients
    assert module.make_fast_paths(module.Args(), cpu).gradients


def test_an_act_drawing_one_numpy_number_mid_stream_switches_acting_off():
    """numpy's key array changes only every 624 draws: the acting check compares numpy's whole state, so a single
    draw by act() is seen wherever the stream stands (here one number after seeding, not at a regeneration)."""
    actor = cpc.CascadeActor(3, 2, 4, 2, 0.5)
    actor.add_base_net()

    def act(actor, obs):
        np.random.rand()
        return cpc.act(actor, obs)

    np.random.seed(0)
    np.random.rand()  # the stream stands mid-block: the next draw moves only numpy's position
    fast = cpc.make_fast_paths(cpc.Args(), torch.device("cpu"))
    fast.acting_function(act, actor, np.zeros((2, 3), np.float32), 0, 4)
    assert not fast.acting and "act() draws from numpy's or Python's global random numbers" in fast.messages[0]


STATEFUL_ACTS = {  # act() edits that keep state between calls, on the actor or in a global of the script
    "sticky actions": [("        return sample_action(mean, log_std).cpu().numpy()\n",
                        "        action = sample_action(mean, log_std).cpu().numpy()\n"
                        "        previous = getattr(actor, 'previous_action', None)\n"
                        "        if previous is not None and previous.shape == action.shape:\n"
                        "            action = np.where(np.arange(len(action))[:, None] % 2 == 0, previous, action)\n"
                        "        actor.previous_action = action\n"
                        "        return action\n")],
    "correlated noise": [("def act(actor: CascadeActor, obs: np.ndarray) -> np.ndarray:\n",
                          "previous_noise = None\n\n\ndef act(actor: CascadeActor, obs: np.ndarray) -> np.ndarray:\n"
                          "    global previous_noise\n"),
                         ("        return sample_action(mean, log_std).cpu().numpy()\n",
                          "        noise = torch.randn_like(mean)\n"
                          "        if previous_noise is not None:\n"
                          "            noise = 0.8 * previous_noise + 0.6 * noise\n"
                          "        previous_noise = noise\n"
                          "        return (mean + log_std.exp() * noise).cpu().numpy()\n")],
}


@pytest.mark.parametrize("edit", list(STATEFUL_ACTS))
def test_an_act_that_keeps_state_between_calls_switches_acting_off(edit, unedited, tmp_path, capsys):
    """A researcher's probe (2026-12-05): the acting check called act() once, on a fresh copy of the actor, so an
    act() keeping state on the actor was never seen (the run acted as the unedited script), and one keeping it in
    a global was seen late and kept the check's batch (a crash at the next step). The check now names the state,
    leaves nothing behind, and the run acts through act() from its first step, as --autograd does."""
    module = edited_copy("cascade_ppo_continuous.py", STATEFUL_ACTS[edit], tmp_path)
    capsys.readouterr()
    switched, messages = train_copy(module, "cascade_ppo_continuous.py", tmp_path / "fast")
    assert "Traceback" not in capsys.readouterr().err
    assert len(messages) == 1 and "fast path check at global_step=0" in messages[0], messages
    named = {"sticky actions": "it sets actor.previous_action", "correlated noise": "it sets global previous_noise"}
    assert f"act() keeps state between calls ({named[edit]})" in messages[0], messages[0]
    if hasattr(module, "previous_noise"):
        module.previous_noise = None  # the next run starts afresh, as a new process would
    edited, _ = train_copy(module, "cascade_ppo_continuous.py", tmp_path / "autograd", autograd=True)
    assert_close_parameters(switched, edited, ROUNDING)
    effect = max((edited[k] - unedited["cascade_ppo_continuous.py"][k]).abs().max().item() for k in edited)
    assert effect > 3 * ROUNDING, effect


def test_the_acting_check_sees_state_kept_inside_a_container():
    """State that act() keeps inside a mutable object (not a rebinding the check can name) shows in its second call
    on the same observations, which then differs from the numpy path's."""
    actor = cpc.CascadeActor(3, 2, 4, 2, 0.5)
    actor.add_base_net()
    memory = {}

    def act(actor, obs):
        action = cpc.act(actor, obs)
        if "previous" in memory:
            action = memory["previous"]
        memory["previous"] = action
        return action

    fast = cpc.make_fast_paths(cpc.Args(), torch.device("cpu"))
    fast.acting_function(act, actor, np.zeros((2, 3), np.float32), 0, 4)
    assert not fast.acting and "act() keeps state between calls (its second call" in fast.messages[0]


STATEFUL_UPDATES = {  # edits of the checked update functions that keep state between calls
    "clip range schedule": ([("    obs, actions, old_logprob, advantages, returns, old_value = minibatch\n",
                              "    obs, actions, old_logprob, advantages, returns, old_value = minibatch\n"
                              "    args.clip_coef = args.clip_coef * 0.99\n")],
                            "autograd_gradients keeps state between calls (it sets args.clip_coef)"),
    "step counter": ([("    nn.utils.clip_grad_norm_([flat_params], args.max_grad_norm)\n",
                       "    global steps_taken\n"
                       "    steps_taken = globals().get('steps_taken', 0) + 1\n"
                       "    nn.utils.clip_grad_norm_([flat_params], args.max_grad_norm * 0.99 ** steps_taken)\n")],
                     "optimizer_step keeps state between calls (it sets global steps_taken)"),
}


@pytest.mark.parametrize("edit", list(STATEFUL_UPDATES))
def test_an_update_that_keeps_state_between_calls_switches_the_hand_written_update_off(edit, unedited, tmp_path):
    """A researcher's probe (2026-12-05, of the off-policy scripts): a schedule kept in `args` by the checked
    functions, or a counter in a global, ran only inside the checks (and moved the run's own args there). Now the
    check names it, undoes what its own call set, and the run updates through section 1 from that minibatch on,
    as --autograd does."""
    edits, named = STATEFUL_UPDATES[edit]
    module = edited_copy("cascade_ppo_continuous.py", edits, tmp_path)
    switched, messages = train_copy(module, "cascade_ppo_continuous.py", tmp_path / "fast")
    assert len(messages) == 1 and named in messages[0], messages
    module.__dict__.pop("steps_taken", None)  # the next run starts afresh, as a new process would
    edited, _ = train_copy(module, "cascade_ppo_continuous.py", tmp_path / "autograd", autograd=True)
    assert_close_parameters(switched, edited, ROUNDING)
    effect = max((edited[k] - unedited["cascade_ppo_continuous.py"][k]).abs().max().item() for k in edited)
    assert effect > 3 * ROUNDING, effect


LOG = logging.getLogger("cascade-tests")  # deepcopy returns a logger itself; its attribute graph has cycles
STATS = {"mean": torch.zeros(3)}  # running statistics in a global dict
NAN_BUFFER = torch.full((2,), float("nan"))


def reads_globals():
    LOG.debug("acting")
    return STATS["mean"].sum() + NAN_BUFFER.nan_to_num().sum()


def keeps_statistics():
    STATS["mean"].add_(1.0)
    STATS["count"] = 1


def test_the_checks_leave_globals_that_nothing_changed_as_they_are():
    """A review (2026-12-05): watching a function's globals hung on a logger (its attribute graph has cycles),
    emptied it on restoring, put deep copies in place of unchanged objects (so a tensor shared with the rest of the
    run no longer was), and read a NaN buffer as changed. Unchanged globals are now named nowhere and left alone."""
    shared = STATS["mean"]
    watch = fast_paths.KeptState(reads_globals, {})
    reads_globals()
    assert watch.changes() == ""
    watch.restore()
    assert STATS["mean"] is shared and LOG.disabled is False
    LOG.debug("still a working logger")


def test_the_checks_put_changed_contents_back_in_place():
    """Changed contents go back as they were: the same objects in the same places, values copied back in place."""
    shared = STATS["mean"]
    watch = fast_paths.KeptState(keeps_statistics, {})
    keeps_statistics()
    assert watch.changes() == "it sets the contents of global STATS"
    watch.restore()
    assert STATS["mean"] is shared and torch.equal(shared, torch.zeros(3)) and "count" not in STATS


def test_an_act_that_raises_is_named_by_its_own_exception():
    """An act() that fails for a reason of its own (here an attribute the actor does not have) is reported with that
    exception's type and message, not as a dtype problem (the remedy for a float32 conversion of the observation)."""
    actor = cpc.CascadeActor(3, 2, 4, 2, 0.5)
    actor.add_base_net()

    def act(actor, obs):
        return cpc.sample_action(*actor(torch.as_tensor(obs))[:2]).numpy() * actor.action_scale

    fast = cpc.make_fast_paths(cpc.Args(), torch.device("cpu"))
    fast.acting_function(act, actor, np.zeros((2, 3), np.float32), 0, 4)
    assert not fast.acting
    (message,) = fast.messages
    assert "act() raised AttributeError: 'CascadeActor' object has no attribute 'action_scale'" in message, message
    assert "dtype" not in message, message


SQUASHED_POLICY = {  # a tanh-squashed Gaussian through torch's TransformedDistribution: its .mean is not defined
    "cascade_ppo_continuous.py": "    return Normal(mean, log_std.exp(), validate_args=False)",
    "ppo_baseline.py": "    return Normal(mean, log_std.exp(), validate_args=False)",
}


@pytest.mark.parametrize("script", list(SQUASHED_POLICY))
def test_deterministic_evaluation_of_a_distribution_without_a_mean_ends_in_one_line(script, tmp_path, capsys):
    """`--evaluate <run> --deterministic` acts with the distribution's mean; a copy whose distribution has no
    closed-form mean (torch's TransformedDistribution raises NotImplementedError) ended in a traceback. It now stops
    with one line naming the reason and what to do, and a non-zero exit; without --deterministic it evaluates."""
    module = edited_copy(script, [(SQUASHED_POLICY[script],
                                   "    return torch.distributions.TransformedDistribution(Normal(mean, log_std.exp(), "
                                   "validate_args=False), [torch.distributions.transforms.TanhTransform(cache_size=1)])")],
                         tmp_path)
    unedited_module = importlib.import_module(script[:-3])
    train_copy(unedited_module, script, tmp_path / "runs")
    run_dir = only_run_dir(tmp_path / "runs")
    with pytest.raises(SystemExit) as stopped:
        module.evaluate_saved(module.Args(evaluate=run_dir, deterministic=True, eval_episodes=1, quiet=True))
    message = str(stopped.value)
    assert message.startswith("error: --deterministic acts with the mean") and "\n" not in message, message
    assert "NotImplementedError" in message and "evaluate without --deterministic" in message, message
    assert "define the mean in section 1" in message, message
    result = module.evaluate_saved(module.Args(evaluate=run_dir, eval_episodes=1, quiet=True))
    assert np.isfinite(result["returns"]).all()


# Edits that act on some observations only, which the acting check at a rollout's start (the next observation and 8
# of the previous rollout's) did not see for many rollouts: the numpy path acted on the unedited policy meanwhile.
PARTIAL_EDITS = {  # edit, threshold on max |obs| of a rollout from which it acts
    "observation clip": ([("        hidden = obs  # every base net reads the same observation",
                           "        hidden = obs.clamp(-5.0, 5.0)  # every base net reads the clipped observation")],
                         5.0),
    "wider policy on large observations": ([(
        "        log_std = contribution.T @ log_stds  # the same sum for the per-net log-std vectors",
        "        log_std = contribution.T @ log_stds + 0.5 * (obs.abs().amax(1, keepdim=True) > 4.5)")], 4.5),
}


@pytest.mark.parametrize("edit", list(PARTIAL_EDITS))
def test_an_edit_acting_on_some_observations_only_is_caught_at_the_first_rollout_it_acts_in(edit, tmp_path,
                                                                                            monkeypatch):
    """An issue: clipping the observations to ±5 in base_nets was not followed by the numpy acting path, and the
    acting check, which saw ~9 observations per rollout, missed it for eight rollouts. Every action of a rollout is
    now compared with section 1's forward over the rollout's observations (which the loop computes anyway): the
    first rollout with an observation the edit acts on switches acting off, saying that rollout acted on the numpy
    path; no later rollout does."""
    edits, threshold = PARTIAL_EDITS[edit]
    module = edited_copy("cascade_ppo_continuous.py", edits, tmp_path)
    rollouts = []  # (global_step at the rollout's end, max |obs| in it)
    rollout_done = fast_paths.FastPaths.rollout_done
    monkeypatch.setattr(fast_paths.FastPaths, "rollout_done", lambda self, act, actor, obs, *rest: (
        rollouts.append((rest[-1], float(obs.abs().max()))), rollout_done(self, act, actor, obs, *rest))[1])
    _, messages = train_copy(module, "cascade_ppo_continuous.py", tmp_path / "fast")
    first = next(step for step, largest in rollouts if largest > threshold)
    assert len(messages) == 1, messages
    assert f"fast path check at global_step={first}: the rollout from global_step={first - 256} acted through the " \
           "numpy path" in messages[0], messages[0]
    assert "draws other actions than act()" in messages[0] and "continuing by acting through act()" in messages[0]


def test_the_script_file_of_an_args_class_without_one_is_empty():
    """A review: an Args class defined in a notebook's cell (or `python -c`) has no source file, and the checkpoint's
    record of the script that wrote it raised there, at the run's first checkpoint. It is "" (not checked)."""
    import cascade_sac
    from cascade_plumbing.runs import script_file

    assert script_file(cascade_sac.Args) == "cascade_sac.py"
    cell = type("Args", (), {"__module__": "a_notebook_cell_that_is_no_module"})
    assert script_file(cell) == ""


def test_an_error_of_section_1_itself_is_named_as_the_edits(tmp_path, capsys):
    """A hack-safety hunt: a critic layer frozen with requires_grad_(False) while autograd_gradients differentiates
    every parameter makes section 1 itself raise (as --autograd does); the warning before that error blamed the
    hand-written update ("cannot follow this edit"). Now it names section 1's own error."""
    module = edited_copy("cascade_ppo_continuous.py", [(
        "    return TanhMLP([obs_dim, 64, 64, 1], [math.sqrt(2), math.sqrt(2), 1.0])",
        "    critic = TanhMLP([obs_dim, 64, 64, 1], [math.sqrt(2), math.sqrt(2), 1.0])\n"
        "    critic.weights[0].requires_grad_(False)\n    return critic")], tmp_path)
    with pytest.raises(RuntimeError, match="does not require grad"):
        train_copy(module, "cascade_ppo_continuous.py", tmp_path / "runs")
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning: fast path check")]
    assert len(warnings) == 1 and "autograd_gradients (section 1) itself raised RuntimeError" in warnings[0], warnings
    assert "an error of the edit, which --autograd meets too" in warnings[0]
