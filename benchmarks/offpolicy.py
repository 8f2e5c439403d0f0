"""Update cost and training throughput of cascade_sac.py and cascade_ddpg.py on this machine (issue 30).

Each configuration runs `train` of its script in a fresh subprocess (so peak memory is its own) with the
script's own nets, optimizers and update function. The run is cut short: the nets are stacked without
waiting for updates (`--no-restart-on-new-net --keep-buffer`, k = --k; the update function is skipped
until the last net is stacked), evaluation is off. A baseline (n = 1) runs as many steps as its Cascade
(4 x --k for SAC, 6 x --k for DDPG, as one iteration) and is measured over the same steps: the cost of an
env step and of the logging changes as the policy learns (a Hopper that falls at once is cheaper to
simulate than one that hops), so windows at different points of training are not comparable (measured:
the DDPG baseline made ~400 steps/s over steps 225-525 of a run, ~285 over steps 750-2500). Measured,
once the full stack is updated:

- steps/s of the training loop (env step, acting, sampling, update, bookkeeping) over --updates steps;
- ms per update split into parts, by calling the script's update function on the live objects with its
  delays arranged so that only some parts run: critic (critic only), actor (critic + the actor's
  `policy_frequency` updates, less the critic; per env step), alpha (the same with --autotune, less
  without; SAC only, not in the total: alpha is fixed by default), targets (SAC: with the target update,
  less without; DDPG: the script's soft_update of both targets, per env step), sampling (buffer.sample);
- peak RSS of the process;
- the arithmetic of the script's own update (`sac_update`, `ddpg_update`): the self time of its torch compute
  kernels (matmuls, activations and their backward, the fused Adam) under torch.profiler, per update (the
  profiler slows the rest, not the kernels); what no removal of per-operation overhead can go below with these
  kernels on this CPU. The fast path (the default; `--autograd` also measures the scripts without it) does the
  same arithmetic in numpy, which the profiler does not see, and can go below it;
- products: the fast update's matrix products alone (numpy, the same operands, back to back), per update: a lower
  bound for this update's products (this tree with its fast paths on; nan otherwise);
- the env's own limit: steps/s of the same wrapped training env with random actions (`env_sps`).

`--cleanrl DIR --cleanrl-python PY` also times whole processes, interleaved: the SAC baseline
(`cascade_sac.py --n 1 --hidden-size 256 --autotune --obs-reward-clip 0`, CleanRL's hyperparameters) against
CleanRL's own `cleanrl/sac_continuous_action.py` from a CleanRL checkout DIR (its file is run as is, with its
own dependencies in the venv of PY; nothing of it is copied here), --whole-random uniform-random steps then
--whole-updates steps with updates, `--threads` torch threads each (OMP_NUM_THREADS for CleanRL).

    python benchmarks/offpolicy.py                        # Hopper-v4, all four configurations
    python benchmarks/offpolicy.py --env-id HalfCheetah-v4 --configs sac_baseline ddpg_baseline
    python benchmarks/offpolicy.py --autograd             # with and without the fast path, interleaved
    python benchmarks/offpolicy.py --ref HEAD~1           # this tree and an older commit, interleaved
    python benchmarks/offpolicy.py --cuda                 # the nets on a GPU (compare with a CPU run on that machine)
    python benchmarks/offpolicy.py --configs sac_baseline --cleanrl ../cleanrl --cleanrl-python ../cleanrl/.venv/bin/python

`--ref REV` also runs every configuration from an older commit (exported to a temp folder), interleaved with
the current ones, and prints the ratios (median and range over the repeats), so changes are judged side by
side on a loaded machine. The update functions' signatures must be the same in both trees.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass

import tyro

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@dataclass
class Args:
    env_id: str = "Hopper-v4"
    """environment to train on (Hopper-v4; HalfCheetah-v4 as an option)"""
    configs: tuple[str, ...] = ("cascade_sac", "sac_baseline", "cascade_ddpg", "ddpg_baseline")
    """configurations to measure"""
    k: int = 1000
    """steps per iteration of the shortened run (the last net's iteration holds warm-up and measured updates)"""
    warmup: int = 50
    """updates of the full stack before measuring"""
    updates: int = 800
    """measured training steps (each with one update; a short window is at the mercy of one slow episode)"""
    calls: int = 40
    """update calls per part and round for the split"""
    rounds: int = 3
    """rounds of the split (the parts interleaved; each part's median over rounds)"""
    repeats: int = 2
    """runs per configuration (and per tree with --ref); the table shows medians"""
    threads: int = 1
    """torch threads (--torch-threads of the scripts)"""
    cuda: bool = False
    """the nets on the GPU (the scripts' --cuda): timings wait for the GPU, the floor is its kernels' busy time"""
    ref: str | None = None
    """also measure every configuration at this git revision, side by side"""
    autograd: bool = False
    """also measure every configuration with the scripts' --autograd (their own update, no fast path), side by side"""
    only_autograd: bool = False
    """internal: this worker runs with the script's --autograd"""
    json: bool = False
    """print the results as JSON instead of a table"""
    cleanrl: str | None = None
    """a CleanRL checkout: also time whole processes of the SAC baseline and CleanRL's sac_continuous_action.py"""
    cleanrl_python: str = sys.executable
    """the interpreter (of a venv with CleanRL's dependencies) that runs CleanRL's file"""
    whole_random: int = 3000
    """whole-process timing: uniform-random steps before updates start (--learning-starts of both)"""
    whole_updates: int = 5000
    """whole-process timing: steps with updates after the random ones"""
    worker: str | None = None
    """internal: run one configuration and print its JSON result"""
    root: str = ROOT
    """internal: the folder the worker imports the scripts from"""


CONFIGS = {  # script, its arguments
    "cascade_sac": ("cascade_sac", dict(n=4, hidden_size=128)),
    "sac_baseline": ("cascade_sac", dict(n=1, hidden_size=256)),
    "cascade_ddpg": ("cascade_ddpg", dict(n=6, hidden_size=16)),
    "ddpg_baseline": ("cascade_ddpg", dict(n=1, hidden_size=64)),
}
ITERATIONS = {"cascade_sac": 4, "cascade_ddpg": 6}  # every configuration of a script runs this many x --k steps
PARTS = ("sampling", "critic", "actor", "targets", "alpha")


class Stop(Exception):
    pass


def synchronize() -> None:
    """Wait for the GPU's queued work (--cuda): its calls return before their kernels finish."""


def timed(fn, calls: int) -> float:
    """ms per call of fn()."""
    synchronize()
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    synchronize()
    return (time.perf_counter() - start) / calls * 1e3


def split_sac(script, update_function, a: Args, update_args: tuple, buffer) -> dict:
    args, _, _, *objects = update_args
    pf = args.policy_frequency
    never = 10**9  # a delay that never comes round: that part is skipped
    plain = dataclasses.replace(args, target_network_frequency=never, autotune=False)
    with_targets = dataclasses.replace(plain, target_network_frequency=1)
    tuned = dataclasses.replace(plain, autotune=True)
    device = update_args[2][0].device

    def update(run_args, step):
        return lambda: update_function(run_args, step, buffer.sample(args.batch_size, device), *objects)

    variants = {"sampling": lambda: buffer.sample(args.batch_size, device), "critic": update(plain, 1),
                "critic+targets": update(with_targets, 1), "critic+actor": update(plain, pf),
                "critic+actor+alpha": update(tuned, pf)}
    ms = measure_variants(variants, a)
    critic = ms["critic"] - ms["sampling"]
    return {"sampling": ms["sampling"], "critic": critic, "actor": (ms["critic+actor"] - ms["critic"]) / pf,
            "targets": ms["critic+targets"] - ms["critic"],
            "alpha": (ms["critic+actor+alpha"] - ms["critic+actor"]) / pf}


def split_ddpg(script, update_function, a: Args, update_args: tuple, buffer) -> dict:
    args, _, batch, actor, target_actor, qf, qf_target, *_ = update_args
    pf = args.policy_frequency
    device = batch[0].device

    def update(step):
        return lambda: update_function(args, step, buffer.sample(args.batch_size, device), *update_args[3:])

    def targets():
        script.soft_update(target_actor, actor, args.tau)
        script.soft_update(qf_target, qf, args.tau)

    variants = {"sampling": lambda: buffer.sample(args.batch_size, device), "critic": update(1),
                "critic+actor+targets": update(pf), "targets": targets}
    ms = measure_variants(variants, a)
    return {"sampling": ms["sampling"], "critic": ms["critic"] - ms["sampling"],
            "actor": (ms["critic+actor+targets"] - ms["critic"] - ms["targets"]) / pf,
            "targets": ms["targets"] / pf, "alpha": float("nan")}


def measure_variants(variants: dict, a: Args) -> dict:
    rounds: dict[str, list[float]] = {name: [] for name in variants}
    for fn in variants.values():  # warm-up (first-call costs, optimizer state)
        timed(fn, 3)
    for _ in range(a.rounds):
        for name, fn in variants.items():
            rounds[name].append(timed(fn, a.calls))
    return {name: statistics.median(values) for name, values in rounds.items()}


COMPUTE_KERNELS = {  # the arithmetic of an update: matmuls, activations and their backward, the fused Adam
    "aten::mm", "aten::bmm", "aten::addmm", "aten::baddbmm", "aten::tanh", "aten::tanh_backward", "aten::relu",
    "aten::clamp_min", "aten::threshold_backward", "aten::sigmoid", "aten::sigmoid_backward", "aten::exp",
    "aten::_fused_adam_",
}


def arithmetic_floor(update_calls: list, rounds: int = 10, cuda: bool = False) -> float:
    """ms per update spent inside compute kernels (self time under torch.profiler) over `rounds` passes of
    `update_calls` (one pass: the updates of `policy_frequency` consecutive steps). With `cuda`: the time the
    GPU spends in all of its kernels (a GPU update is bound by launching them, not by this)."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities) as prof:
        for _ in range(rounds):
            for call in update_calls:
                call()
        synchronize()
    if cuda:
        # kernels only: not the copies of the sampled batch to the GPU, nor the GPU-side copies of annotated ranges
        # (Optimizer.step's record_function), which would count the Adam kernels twice
        kernel_us = sum(e.self_device_time_total for e in prof.key_averages()
                        if e.device_type == DeviceType.CUDA and not e.is_user_annotation
                        and not e.key.startswith(("Memcpy", "Memset")))
    else:
        kernel_us = sum(e.self_cpu_time_total for e in prof.key_averages() if e.key in COMPUTE_KERNELS)
    return kernel_us / 1e3 / (rounds * len(update_calls))


def median_of_measured(values: list[float]) -> float:
    """The median of the values that were measured (nan: not measured in that run)."""
    measured = [v for v in values if not math.isnan(v)]
    return statistics.median(measured) if measured else math.nan


def products_time(update_calls: list, rounds: int = 20) -> float:
    """ms per update of the fast update's matrix products alone: the operands of every `matmul` of one pass of
    `update_calls` (recorded as they are, transposed views included), multiplied again back to back by numpy.
    A lower bound for this update's products (numpy, one thread, warm caches). The calls step the live nets and
    optimizers once more each, which does not matter: the run stops right after."""
    import cascade_plumbing.fast_offpolicy as kernels

    recorded: list[tuple] = []
    product = kernels.matmul

    def recording(a, b):
        recorded.append((a, b))
        return product(a, b)

    kernels.matmul = recording
    try:
        for call in update_calls:
            call()
    finally:
        kernels.matmul = product
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        for a, b in recorded:
            product(a, b)
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1e3 / len(update_calls)


def env_limit(env_id: str, clip: float, steps: int = 3000) -> float:
    """steps/s of the scripts' training env (the same wrappers) with uniform random actions."""
    from cascade_plumbing.envs import make_env, make_vector_env

    envs = make_vector_env([make_env(env_id, clip=clip)])
    envs.reset(seed=0)
    envs.single_action_space.seed(0)
    actions = [envs.single_action_space.sample()[None] for _ in range(steps)]
    start = time.perf_counter()
    for action in actions:
        envs.step(action)
    elapsed = time.perf_counter() - start
    envs.close()
    return steps / elapsed


def run_worker(config: str, a: Args) -> dict:
    sys.path.insert(0, a.root)
    import importlib

    import torch

    if a.cuda:
        if not torch.cuda.is_available():
            sys.exit("error: --cuda: torch sees no GPU here")
        global synchronize
        synchronize = torch.cuda.synchronize
    script_name, extra = CONFIGS[config]
    script = importlib.import_module(script_name)
    assert os.path.dirname(os.path.abspath(script.__file__)) == os.path.abspath(a.root), script.__file__
    n = extra["n"]
    update_name = "sac_update" if script_name == "cascade_sac" else "ddpg_update"
    update = getattr(script, update_name)
    k = a.k * ITERATIONS[script_name] // n  # the same run length for a Cascade and its baseline
    first_measured = k - a.k  # step in the last iteration: the last --k steps of the run for every configuration
    if a.only_autograd:
        extra = {**extra, "autograd": True}
    args = script.Args(env_id=a.env_id, k=k, learning_starts=a.k // 4, keep_buffer=True,
                       restart_on_new_net=False, eval_every=0, eval_members=False, quiet=True,
                       torch_threads=a.threads, cuda=a.cuda, track_dir=tempfile.mkdtemp(prefix="offpolicy_"), **extra)
    assert a.warmup + a.updates + 1 < a.k, "--k must exceed --warmup + --updates"
    state: dict = {}
    marks: list[float] = []

    def on_iteration_start(s: dict) -> None:
        state["buffer"] = s["buffer"]

    def run_update(*update_args):
        """The update as the run makes it: the fast path's (the scripts' section 2, when it is on), else the
        script's own; for the split, outside the run's checks."""
        fast = state.get("fast")
        if fast is not None and fast.on:
            with torch.no_grad():
                return fast.fast_update(*update_args)
        return update(*update_args)

    def measured_update(*update_args, through=None):
        if update_args[3].size < n or update_args[1] < first_measured:  # not yet the run's last --k steps
            return {"alpha": update_args[8]} if script_name == "cascade_sac" else {}
        out = through(*update_args) if through is not None else update(*update_args)
        synchronize()
        marks.append(time.perf_counter())
        if len(marks) == a.warmup + a.updates + 1:
            # the window closes here; the split below calls the update again, not this function
            state["sps"] = a.updates / (marks[-1] - marks[a.warmup])
            setattr(script, update_name, update)
            splitter = split_sac if script_name == "cascade_sac" else split_ddpg
            state["parts"] = splitter(script, run_update, a, update_args, state["buffer"])
            args, device = update_args[0], update_args[2][0].device
            fast = state.get("fast")
            # the fast update's products (numpy): this tree's, with its fast paths on
            if fast is not None and fast.on and not a.cuda and os.path.abspath(a.root) == ROOT:
                def fast_call(step):
                    with torch.no_grad():
                        fast.fast_update(args, step, state["buffer"].sample(args.batch_size, device), *update_args[3:])
                state["products"] = products_time([
                    (lambda step=step: fast_call(step)) for step in range(args.policy_frequency)])
            # the arithmetic of the script's own update: torch.profiler does not see the fast path's numpy kernels
            state["floor"] = arithmetic_floor([
                (lambda step=step: update(args, step, state["buffer"].sample(args.batch_size, device), *update_args[3:]))
                for step in range(args.policy_frequency)], cuda=a.cuda)
            raise Stop
        return out

    if hasattr(script, "make_fast_paths"):  # the update goes through the fast path's update(definition, ...)
        make_fast_paths = script.make_fast_paths

        class Measured:
            def __init__(self, fast):
                self.fast = fast

            def update(self, definition, *update_args, step=0):
                return measured_update(*update_args, through=lambda *u: self.fast.update(definition, *u, step=step))

            def act(self, *act_args, **kwargs):
                return self.fast.act(*act_args, **kwargs)

        def measured_fast_path(*make_args):
            state["fast"] = make_fast_paths(*make_args)
            return Measured(state["fast"])

        script.make_fast_paths = measured_fast_path
    else:  # an older tree (--ref): the loop calls the update function by its name
        setattr(script, update_name, measured_update)
    try:
        script.train(args, on_iteration_start=on_iteration_start)
    except Stop:
        pass
    fast = state.get("fast")
    sps = state["sps"]
    parts = state["parts"]
    total = sum(v for k, v in parts.items() if k != "alpha")
    return {"config": config, "sps": sps, "parts_ms": parts, "update_ms": total, "floor_ms": state["floor"],
            "products_ms": state.get("products", math.nan),
            "fast_path": None if fast is None else fast.on,
            "env_sps": env_limit(a.env_id, args.obs_reward_clip), "torch": torch.__version__,
            "device": torch.cuda.get_device_name() if a.cuda else "cpu",
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def export(rev: str) -> str:
    root = tempfile.mkdtemp(prefix="offpolicy_ref_")
    archive = subprocess.run(["git", "-C", ROOT, "archive", rev], capture_output=True)
    if archive.returncode != 0:
        sys.exit(f"error: cannot export --ref {rev}: {archive.stderr.decode().strip()}")
    subprocess.run(["tar", "-x", "-C", root], input=archive.stdout, check=True)
    return root


def timed_process(cmd: list[str], env: dict, cwd: str) -> tuple[float, float]:
    """Wall-clock and CPU seconds (user + system) of one whole process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if out.returncode != 0:
        sys.exit(f"error: {' '.join(cmd[:2])} failed:\n{out.stderr[-3000:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def against_cleanrl(a: Args) -> dict:
    """Whole processes, interleaved: the SAC baseline and CleanRL's sac_continuous_action.py, same
    hyperparameters (CleanRL's: alpha autotuned, no clipping), --threads torch threads each."""
    cleanrl_file = os.path.join(a.cleanrl, "cleanrl", "sac_continuous_action.py")
    if not os.path.isfile(cleanrl_file):
        sys.exit(f"error: no {cleanrl_file}; --cleanrl takes the root of a CleanRL checkout")
    total, folder = a.whole_random + a.whole_updates, tempfile.mkdtemp(prefix="offpolicy_whole_")
    ours = [sys.executable, os.path.join(ROOT, "cascade_sac.py"), "--env-id", a.env_id, "--n", "1",
            "--hidden-size", "256", "--k", str(total), "--learning-starts", str(a.whole_random), "--autotune",
            "--obs-reward-clip", "0", "--eval-every", "0", "--quiet", "--torch-threads", str(a.threads),
            "--track-dir", folder]
    theirs = [a.cleanrl_python, cleanrl_file, "--env-id", a.env_id, "--total-timesteps", str(total),
              "--learning-starts", str(a.whole_random), "--no-cuda"]
    env = {**os.environ, "OMP_NUM_THREADS": str(a.threads), "MKL_NUM_THREADS": str(a.threads)}
    times: dict[str, list[tuple[float, float]]] = {"sac_baseline": [], "cleanrl": []}
    for repeat in range(a.repeats):
        times["sac_baseline"].append(timed_process(ours, env, ROOT))
        times["cleanrl"].append(timed_process(theirs, {**env, "PYTHONPATH": a.cleanrl}, folder))
        if not a.json:
            print(f"  whole process, repeat {repeat + 1}/{a.repeats}: sac_baseline {times['sac_baseline'][-1][0]:.1f} s, "
                  f"CleanRL {times['cleanrl'][-1][0]:.1f} s", file=sys.stderr)
    ratios = [c[0] / o[0] for o, c in zip(times["sac_baseline"], times["cleanrl"])]
    return {name: {"wall_s": statistics.median(w for w, _ in t), "cpu_s": statistics.median(c for _, c in t),
                   "all_wall_s": [w for w, _ in t]} for name, t in times.items()} | {
        "speedup": statistics.median(ratios), "speedup_range": [min(ratios), max(ratios)]}


def main() -> None:
    a = tyro.cli(Args)
    if a.worker:
        print(json.dumps(run_worker(a.worker, a)))
        return
    unknown = [c for c in a.configs if c not in CONFIGS]
    if unknown:
        sys.exit(f"error: unknown --configs {unknown} (known: {', '.join(CONFIGS)})")
    trees = [("this", ROOT)] + ([("autograd", ROOT)] if a.autograd else []) + ([("ref", export(a.ref))] if a.ref else [])
    runs = [(c, tree, root) for c in a.configs for tree, root in trees]
    results: dict[tuple[str, str], list[dict]] = {(c, t): [] for c, t, _ in runs}
    for repeat in range(a.repeats):
        for config, tree, root in runs:  # interleaved, so slow drifts of the machine hit every config alike
            cmd = [sys.executable, os.path.abspath(__file__), "--worker", config, "--root", root]
            for name in ("env_id", "k", "warmup", "updates", "calls", "rounds", "threads"):
                cmd += [f"--{name.replace('_', '-')}", str(getattr(a, name))]
            cmd += ["--cuda"] if a.cuda else []
            cmd += ["--only-autograd"] if tree == "autograd" else []
            # the scripts from `root`, the package too (PYTHONPATH precedes the editable install)
            env = {**os.environ, "PYTHONPATH": root}
            out = subprocess.run(cmd, capture_output=True, text=True, cwd=root, env=env)
            if out.returncode != 0:
                sys.exit(f"error: {config} ({tree}) failed:\n{out.stderr[-3000:]}")
            r = json.loads(out.stdout.strip().splitlines()[-1])
            results[(config, tree)].append(r)
            if not a.json:
                print(f"  repeat {repeat + 1}/{a.repeats} {config} ({tree}): {r['sps']:.0f} steps/s, "
                      f"{r['update_ms']:.2f} ms/update", file=sys.stderr)
    summary = {}
    for (config, tree), rs in results.items():
        summary[f"{config}@{tree}"] = {
            "sps": statistics.median(r["sps"] for r in rs), "all_sps": [r["sps"] for r in rs],
            "update_ms": statistics.median(r["update_ms"] for r in rs),
            "all_update_ms": [r["update_ms"] for r in rs],
            "parts_ms": {p: statistics.median(r["parts_ms"][p] for r in rs) for p in PARTS},
            "floor_ms": statistics.median(r["floor_ms"] for r in rs),
            "products_ms": median_of_measured([r.get("products_ms", math.nan) for r in rs]),
            "env_sps": statistics.median(r["env_sps"] for r in rs),
            "peak_rss_mb": statistics.median(r["peak_rss_mb"] for r in rs)}
    ratios = {}
    for other in [tree for tree, _ in trees[1:]]:
        for config in a.configs:
            this, them = results[(config, "this")], results[(config, other)]
            sps = [t["sps"] / r["sps"] for t, r in zip(this, them)]  # pairs run next to each other
            upd = [r["update_ms"] / t["update_ms"] for t, r in zip(this, them)]
            ratios[f"{config} / {a.ref if other == 'ref' else '--autograd'}"] = {
                "sps": statistics.median(sps), "sps_range": [min(sps), max(sps)],
                "update_speedup": statistics.median(upd), "update_speedup_range": [min(upd), max(upd)]}
    whole = against_cleanrl(a) if a.cleanrl else {}
    meta = dataclasses.asdict(a) | {"cpus": os.cpu_count(), "python": sys.version.split()[0],
                                    "load_avg": os.getloadavg()}
    if a.json:
        print(json.dumps({"meta": meta, "results": summary, "ratios": ratios, "whole_process": whole}, indent=2))
        return
    print(f"\n{a.env_id}: median of {a.repeats} runs; {a.updates} training steps with updates after {a.warmup} "
          f"warm-up updates; split from {a.rounds} x {a.calls} calls per part; {a.threads} torch thread(s); "
          f"{'nets on the GPU (' + results[runs[0][:2]][0]['device'] + '), floor = GPU kernel time; ' if a.cuda else ''}"
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs\n")
    print("| configuration | tree | steps/s | env alone, steps/s | ms/update | autograd kernels | products | sampling | "
          "critic | actor | targets | (alpha) | peak RSS MB |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for key, r in summary.items():
        config, tree = key.split("@")
        p = r["parts_ms"]
        label = {"ref": a.ref, "autograd": "this tree, --autograd"}.get(tree, "this tree")
        print(f"| {config} | {label} | {r['sps']:.0f} | {r['env_sps']:.0f} | {r['update_ms']:.2f} | {r['floor_ms']:.2f} | "
              f"{r['products_ms']:.2f} | "
              + " | ".join(f"{p[name]:.2f}" for name in PARTS) + f" | {r['peak_rss_mb']:.0f} |")
    for pair, q in ratios.items():
        config, other = pair.split(" / ")
        print(f"{config}: this tree / {other}: steps/s x{q['sps']:.2f} [{q['sps_range'][0]:.2f}, "
              f"{q['sps_range'][1]:.2f}], update speed x{q['update_speedup']:.2f} "
              f"[{q['update_speedup_range'][0]:.2f}, {q['update_speedup_range'][1]:.2f}]")
    if whole:
        print(f"\nWhole processes, {a.whole_random} random + {a.whole_updates} update steps, {a.threads} thread(s), "
              f"median of {a.repeats}: SAC baseline {whole['sac_baseline']['wall_s']:.1f} s "
              f"({whole['sac_baseline']['cpu_s']:.1f} s CPU), CleanRL {whole['cleanrl']['wall_s']:.1f} s "
              f"({whole['cleanrl']['cpu_s']:.1f} s CPU): x{whole['speedup']:.2f} "
              f"[{whole['speedup_range'][0]:.2f}, {whole['speedup_range'][1]:.2f}] in wall-clock")


if __name__ == "__main__":
    main()
