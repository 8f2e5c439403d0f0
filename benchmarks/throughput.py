"""Training throughput of the scripts, next to the env's own limit, on this machine.

Each configuration runs in a fresh subprocess (so peak memory is its own), a few times; the table
shows medians. Steps/s are measured between the end of the warm-up updates and the end of the last
update, so start-up (imports, env creation, the first-call costs) is excluded.

    python benchmarks/throughput.py                      # Ant-v4
    python benchmarks/throughput.py --env-id HalfCheetah-v4 --json
    python benchmarks/throughput.py --ref e22f4b3 --configs env_random ppo cascade6 ppo_autograd cascade6_autograd

`--ref REV` also runs PPO and Cascade from an older commit (exported to a temp folder), interleaved
with the current ones, so a code change is judged by ratios measured side by side.
"""

from __future__ import annotations

import json
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
BATCH = 2048


@dataclass
class Args:
    env_id: str = "Ant-v4"
    """environment to measure"""
    updates: int = 10
    """measured PPO updates per run (10 x 2048 steps spans two evaluations at the paper's 10k protocol)"""
    warmup: int = 1
    """updates run before measuring starts"""
    repeats: int = 3
    """runs per configuration; the table shows the median"""
    num_envs_parallel: int = 2
    """also measure Cascade with this many envs stepped in parallel processes (0 to skip)"""
    configs: tuple[str, ...] = ("env_random", "ppo", "cascade6", "cascade6_eval", "cascade6_parallel", "ppo_autograd",
                                "cascade6_autograd")
    """configurations to measure (env_random and ppo are always included: the ratios need them)"""
    ref: str | None = None
    """also measure ppo and cascade6 at this git revision, side by side (e.g. the commit before a change)"""
    json: bool = False
    """print the results as JSON instead of a table"""
    worker: str | None = None
    """internal: run one configuration and print its JSON result"""
    root: str = ROOT
    """internal: the folder the worker imports the scripts from"""


CONFIGS = {
    "env_random": "(a) wrapped env, random actions (the limit)",
    "ppo": "(b) ppo_baseline.py defaults",
    "cascade6": "(c) Cascade, 6-net stack",
    "cascade6_eval": "(d) Cascade, 6-net stack, eval every 10k (10 episodes)",
    "cascade6_parallel": "(e) Cascade, 6-net stack, envs in parallel processes",
    "ppo_autograd": "(f) ppo_baseline.py --autograd (no fast paths)",
    "cascade6_autograd": "(g) Cascade, 6-net stack, --autograd (no fast paths)",
}


class Stop(Exception):
    pass


def measure_training(script, args, updates: int, warmup: int) -> float:
    """Steps/s of `script.train(args)` between the end of update `warmup` and of update `warmup+updates`."""
    marks: list[tuple[float, int]] = []

    def record(self, step, sps, *rest, **kw):
        marks.append((time.perf_counter(), step))
        if len(marks) == warmup + updates:
            raise Stop

    progress = getattr(script, "Progress", None)  # a script of an older commit has its own
    if progress is None:
        from cascade_plumbing.tracking import Progress as progress
    progress.update = record
    try:
        script.train(args)
    except Stop:
        pass
    (t0, s0), (t1, s1) = marks[warmup - 1], marks[-1]
    return (s1 - s0) / (t1 - t0)


def run_worker(config: str, a: Args) -> dict:
    sys.path.insert(0, a.root)
    import numpy as np
    import torch

    torch.set_num_threads(1)
    track = tempfile.mkdtemp(prefix="throughput_")
    total = (a.warmup + a.updates) * BATCH
    common = dict(env_id=a.env_id, eval_every=0, quiet=True, checkpoint_every=0, track_dir=track)
    if config == "env_random":
        import ppo_baseline

        envs = ppo_baseline.make_vector_env(ppo_baseline.Args(env_id=a.env_id))
        envs.reset(seed=0)
        rng = np.random.default_rng(0)
        space = envs.envs[0].unwrapped.action_space  # ClipAction widens the wrapped space to ±inf
        actions = rng.uniform(space.low, space.high, size=(a.updates * BATCH, 1, *space.shape)).astype(np.float32)
        for action in actions[:1000]:
            envs.step(action)
        start = time.perf_counter()
        for action in actions:
            envs.step(action)
        sps = len(actions) / (time.perf_counter() - start)
    elif config in ("ppo", "ppo_autograd"):
        import ppo_baseline

        if config == "ppo_autograd":
            common.update(autograd=True)
        sps = measure_training(ppo_baseline, ppo_baseline.Args(total_timesteps=total, **common), a.updates, a.warmup)
    else:
        import cascade_ppo_continuous as cpc

        extra = dict(n=6, k=total, start_full=True, eval_members=False)
        if config == "cascade6_eval":
            common.update(eval_every=10_000, eval_episodes=10)
        if config == "cascade6_parallel":
            extra.update(num_envs=a.num_envs_parallel, num_steps=BATCH // a.num_envs_parallel)
        if config == "cascade6_autograd":
            extra.update(autograd=True)
        sps = measure_training(cpc, cpc.Args(**common, **extra), a.updates, a.warmup)
    # The training process itself (Linux reports KiB). Not RUSAGE_CHILDREN: short-lived helper forks
    # (ctypes' library lookup) would report the parent's size again; worker processes are listed apart.
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"config": config, "sps": sps, "peak_rss_mb": peak_mb}


def main() -> None:
    a = tyro.cli(Args)
    if a.worker:
        print(json.dumps(run_worker(a.worker, a)))
        return
    configs = [c for c in CONFIGS if (c in a.configs or c in ("env_random", "ppo"))
               and (c != "cascade6_parallel" or a.num_envs_parallel > 1)]
    roots = {c: ROOT for c in configs}
    if a.ref:  # the scripts of an older commit, exported to a temp folder
        ref_root = tempfile.mkdtemp(prefix="throughput_ref_")
        archive = subprocess.run(["git", "-C", ROOT, "archive", a.ref], capture_output=True)
        if archive.returncode != 0:
            sys.exit(f"error: cannot export --ref {a.ref}: {archive.stderr.decode().strip()}")
        subprocess.run(["tar", "-x", "-C", ref_root], input=archive.stdout, check=True)
        for c in ("ppo", "cascade6"):
            CONFIGS[f"{c}@ref"] = f"{CONFIGS[c]} @ {a.ref}"
            roots[f"{c}@ref"] = ref_root
            configs.insert(configs.index(c) + 1, f"{c}@ref")
    results: dict[str, list[dict]] = {c: [] for c in configs}
    for repeat in range(a.repeats):
        for config in configs:  # interleaved, so slow drifts of the machine hit every config alike
            cmd = [sys.executable, __file__, "--worker", config.split("@")[0], "--env-id", a.env_id, "--updates",
                   str(a.updates), "--warmup", str(a.warmup), "--num-envs-parallel", str(max(a.num_envs_parallel, 1)),
                   "--root", roots[config]]
            out = subprocess.run(cmd, capture_output=True, text=True, cwd=roots[config])
            if out.returncode != 0:
                sys.exit(f"error: {config} failed:\n{out.stderr[-2000:]}")
            results[config].append(json.loads(out.stdout.strip().splitlines()[-1]))
            if not a.json:
                print(f"  repeat {repeat + 1}/{a.repeats} {config}: {results[config][-1]['sps']:.0f} steps/s",
                      file=sys.stderr)
    summary = {c: {"sps": statistics.median(r["sps"] for r in runs),
                   "peak_rss_mb": statistics.median(r["peak_rss_mb"] for r in runs),
                   "all_sps": [r["sps"] for r in runs]} for c, runs in results.items()}
    limit, ppo = summary["env_random"]["sps"], summary["ppo"]["sps"]
    for c in summary:
        summary[c]["vs_limit"] = summary[c]["sps"] / limit
        summary[c]["vs_ppo"] = summary[c]["sps"] / ppo
    if "cascade6_eval" in summary:
        summary["eval_wallclock_ratio"] = summary["cascade6"]["sps"] / summary["cascade6_eval"]["sps"]
    meta = {"env_id": a.env_id, "updates": a.updates, "warmup": a.warmup, "repeats": a.repeats, "ref": a.ref,
            "cpus": os.cpu_count(), "python": sys.version.split()[0]}
    if a.json:
        print(json.dumps({"meta": meta, "results": summary}, indent=2))
        return
    print(f"\n{a.env_id}: median of {a.repeats} runs, {a.updates} x {BATCH} steps after {a.warmup} warm-up update(s)\n")
    print("| configuration | steps/s | vs limit (a) | vs PPO (b) | peak RSS MB |")
    print("|---|---:|---:|---:|---:|")
    for c in configs:
        r = summary[c]
        print(f"| {CONFIGS[c]} | {r['sps']:.0f} | {r['vs_limit']:.2f} | {r['vs_ppo']:.2f} | {r['peak_rss_mb']:.0f} |")
    if "eval_wallclock_ratio" in summary:
        print(f"\nwall-clock with evaluation / without: {summary['eval_wallclock_ratio']:.2f}x")
    if a.ref:
        for c in ("ppo", "cascade6"):
            print(f"{c}: this tree / {a.ref} = {summary[c]['sps'] / summary[c + '@ref']['sps']:.3f}")
    print("\ntargets (issue 4):")
    checks = [
        ("PPO >= 0.5x the env limit", summary["ppo"]["vs_limit"], 0.5, ">="),
        ("Cascade (6 nets) >= 0.9x PPO", summary["cascade6"]["vs_ppo"], 0.9, ">="),
        ("wall-clock with evaluation <= 1.25x without", summary.get("eval_wallclock_ratio", float("nan")), 1.25, "<="),
        ("peak memory of Cascade <= 600 MB", summary["cascade6"]["peak_rss_mb"], 600, "<="),
    ]
    for name, value, bound, op in checks:
        met = value >= bound if op == ">=" else value <= bound
        print(f"  {'met    ' if met else 'NOT met'}  {name}: {value:.2f}")


if __name__ == "__main__":
    main()
