"""`--cuda` on a real GPU: every script trains with its nets on the GPU, a GPU run resumes exactly on the GPU, its
checkpoints evaluate on the CPU, and the GPU computes the same policy (and PPO gradient) as the CPU.

Skipped where torch sees no GPU (CI has none): run `pytest tests/test_cuda.py` on a GPU machine. There, the last
test (`--cuda` without a GPU says so) is the one skipped.
"""

import copy
import importlib
import os
import shutil

import numpy as np
import pytest
import torch

from helpers import cli_in_process, copy_checkpoint_when, resume_from, run_script

needs_gpu = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (torch sees none)")

PPO = dict(num_steps=256, num_minibatches=4, update_epochs=2, eval_every=512, eval_episodes=2, checkpoint_every=512)
OFF_POLICY = dict(env_id="Hopper-v4", n=2, k=400, learning_starts=100, batch_size=32, eval_every=200,
                  eval_episodes=2)
# script: (its settings for a 2048-step run, or 800 for SAC/DDPG; which saved checkpoint to resume from)
RUNS = {
    "cascade_ppo_continuous": (dict(env_id="Hopper-v4", n=2, k=1024, **PPO), lambda c: c["global_step"] == 512),
    "ppo_baseline": (dict(env_id="Hopper-v4", total_timesteps=2048, **PPO), lambda c: c["global_step"] == 512),
    # 4 envs: a rollout is 1024 steps
    "cascade_ppo_discrete": (dict(env_id="CartPole-v1", n=2, k=1024, **PPO), lambda c: c["global_step"] == 1024),
    "ppo_baseline_discrete": (dict(env_id="CartPole-v1", total_timesteps=2048, **PPO),
                              lambda c: c["global_step"] == 1024),
    "cascade_sac": (OFF_POLICY, lambda c: c["global_step"] == 400),
    "cascade_ddpg": (OFF_POLICY, lambda c: c["global_step"] == 400),
}


def assert_same_parameters(a: torch.nn.Module, b: torch.nn.Module) -> None:
    for (name, x), y in zip(a.state_dict().items(), b.state_dict().values()):
        torch.testing.assert_close(x, y, rtol=0, atol=0, msg=name)


@needs_gpu
@pytest.mark.parametrize("name", list(RUNS))
def test_gpu_run_resumes_exactly_and_evaluates_on_the_cpu(name, tmp_path, capsys, monkeypatch):
    module = importlib.import_module(name)
    settings, resume_point = RUNS[name]
    args = module.Args(cuda=True, quiet=True, track_dir=str(tmp_path / "a"), **settings)
    with copy_checkpoint_when(module, resume_point, tmp_path / "mid.pt"):
        full = module.train(args)
    assert {p.device.type for p in full["actor"].parameters()} == {"cuda"}
    # the checkpoint holds the GPU's random stream: the resumed run draws what the uninterrupted one drew
    assert "torch_cuda" in module.load_checkpoint(str(tmp_path / "mid.pt"))["rng"]
    resumed = resume_from(module, tmp_path / "mid.pt", tmp_path / "b")
    assert_same_parameters(full["actor"], resumed["actor"])
    # again in a fresh process, where CUDA starts with the resumed run: the restored stream must outlive start-up
    os.makedirs(tmp_path / "c")
    shutil.copy(tmp_path / "mid.pt", tmp_path / "c" / "checkpoint.pt")
    proc = run_script(f"{name}.py", "--resume", tmp_path / "c", "--quiet")
    assert proc.returncode == 0, proc.stderr[-2000:]
    final = module.load_checkpoint(str(tmp_path / "c"))["actor"]
    for key, value in full["actor"].state_dict().items():
        torch.testing.assert_close(final[key], value.cpu(), rtol=0, atol=0, msg=key)
    # --evaluate (always on the CPU) of a GPU run's checkpoint, as on a machine without a GPU
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    code, out, error = cli_in_process(capsys, f"{name}.py", "--evaluate", full["run_dir"], "--eval-episodes", "2")
    assert code == 0 and " over 2 " in out, (out, error)


@needs_gpu
@pytest.mark.parametrize("name", ["cascade_ppo_continuous", "cascade_ppo_discrete", "cascade_sac", "cascade_ddpg"])
def test_gpu_and_cpu_compute_the_same_policy(name, tmp_path):
    """The final nets of a short GPU run, rebuilt from its checkpoint on each device: same forward outputs."""
    module = importlib.import_module(name)
    settings, _ = RUNS[name]
    full = module.train(module.Args(cuda=True, quiet=True, track_dir=str(tmp_path), **settings))
    checkpoint = module.load_checkpoint(full["run_dir"])
    on_cpu, on_gpu = module.actor_from_checkpoint(checkpoint, "cpu"), module.actor_from_checkpoint(checkpoint, "cuda")
    assert on_cpu.size == on_gpu.size == 2
    obs = torch.as_tensor(np.random.default_rng(0).normal(size=(64, on_cpu.obs_dim)), dtype=torch.float32)
    with torch.no_grad():
        for a, b in zip(on_cpu(obs), on_gpu(obs.cuda())):
            torch.testing.assert_close(b.cpu(), a, rtol=1e-4, atol=1e-5)


@needs_gpu
def test_gpu_and_cpu_compute_the_same_ppo_gradient():
    """Section 1's loss and autograd gradient of the flagship on one minibatch, on each device."""
    import cascade_ppo_continuous as cpc

    torch.manual_seed(0)
    actor = cpc.CascadeActor(11, 3, 16, 2, 0.5)
    for _ in range(3):
        actor.add_base_net()
    critic = cpc.make_critic(11)
    batch = 64
    obs = torch.randn(batch, 11)
    with torch.no_grad():
        mean, log_std, _, _ = actor(obs)
        actions = cpc.sample_action(mean, log_std)
        old_logprob = cpc.action_distribution(mean, log_std).log_prob(actions).sum(1) + 0.1 * torch.randn(batch)
    minibatch = (obs, actions, old_logprob, torch.randn(batch), torch.randn(batch), torch.randn(batch))
    grads = {}
    for device in ("cpu", "cuda"):
        a, c = copy.deepcopy(actor).to(device), copy.deepcopy(critic).to(device)
        params = [*a.parameters(), *c.parameters()]
        for p in params:
            p.grad = torch.zeros_like(p)
        loss, _ = cpc.autograd_gradients(a, c, params, tuple(t.to(device) for t in minibatch), cpc.Args())
        grads[device] = [loss.cpu()] + [p.grad.cpu().clone() for p in params]
    assert any(g.abs().sum() > 0 for g in grads["cpu"][1:])
    for g_cpu, g_gpu in zip(grads["cpu"], grads["cuda"]):
        torch.testing.assert_close(g_gpu, g_cpu, rtol=1e-3, atol=1e-5)


@needs_gpu
@pytest.mark.parametrize("name", ["cascade_ppo_continuous", "ppo_baseline"])
def test_a_gpu_run_trains_without_the_fast_paths(name, tmp_path, monkeypatch):
    """The fast paths are CPU-only: train() hands make_fast_paths the GPU it chose, and they stay off."""
    module = importlib.import_module(name)
    made = []
    monkeypatch.setattr(module, "make_fast_paths",
                        lambda *a, make=module.make_fast_paths: made.append(make(*a)) or made[-1])
    settings, _ = RUNS[name]
    module.train(module.Args(cuda=True, quiet=True, track_dir=str(tmp_path), **{**settings, "eval_every": 0}))
    assert len(made) == 1 and not made[0].gradients and not made[0].acting


TINY = {  # one update each
    "cascade_ppo_continuous": dict(env_id="Hopper-v4", n=1, k=256, num_steps=256, num_minibatches=4),
    "ppo_baseline": dict(env_id="Hopper-v4", total_timesteps=256, num_steps=256, num_minibatches=4),
    "cascade_ppo_discrete": dict(env_id="CartPole-v1", n=1, k=256, num_steps=64, num_minibatches=4),
    "ppo_baseline_discrete": dict(env_id="CartPole-v1", total_timesteps=256, num_steps=64, num_minibatches=4),
    "cascade_sac": dict(env_id="Hopper-v4", n=1, k=150, learning_starts=100, batch_size=32),
    "cascade_ddpg": dict(env_id="Hopper-v4", n=1, k=150, learning_starts=100, batch_size=32),
}


@needs_gpu
@pytest.mark.parametrize("name", ["cascade_sac", "cascade_ddpg"])
def test_an_off_policy_gpu_run_trains_without_the_fast_paths(name, tmp_path):
    """The off-policy fast paths (numpy on the weights) are CPU-only too: a --cuda run updates and acts through the
    scripts' own functions."""
    module = importlib.import_module(name)
    result = module.train(module.Args(cuda=True, quiet=True, track_dir=str(tmp_path), eval_every=0, **TINY[name]))
    assert not result["fast_path"].on and not result["fast_path"].acting


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine where torch sees no GPU")
@pytest.mark.parametrize("name", list(TINY))
def test_cuda_without_a_gpu_says_so_and_runs_on_the_cpu(name, tmp_path, capsys):
    module = importlib.import_module(name)
    result = module.train(module.Args(cuda=True, quiet=True, eval_every=0, track_dir=str(tmp_path), **TINY[name]))
    assert {p.device.type for p in result["actor"].parameters()} == {"cpu"}
    warning = "warning: --cuda: torch sees no GPU here"
    assert capsys.readouterr().err.count(warning) == 1
