"""The spread of the learning tests' scores over many seeds, with learning intact and broken.

Runs each check of `tests/learning_checks.py` (the exact configurations the tests use) for the given
seeds, with the learning rate as configured and with it set to 0 ("broken": the policy never changes),
appending one JSON line per run to `--out` (so a stopped measurement keeps what it finished), then
prints, per check, the score the test asserts on: min / median / max over seeds, next to the test's
threshold. A portable threshold sits far below the intact minimum and far above the broken maximum.

    python benchmarks/learning_spread.py --seeds 1 2 3 4 5 6 7 8 9 10 --broken-seeds 1 2 3
    python benchmarks/learning_spread.py --summary-only --out benchmarks/learning_spread.jsonl
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np
import torch
import tyro

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests"))
import learning_checks  # noqa: E402


@dataclass
class Args:
    checks: list[str] = field(default_factory=lambda: list(learning_checks.CHECKS))
    """which checks to run (names in tests/learning_checks.py)"""
    seeds: list[int] = field(default_factory=lambda: list(range(1, 11)))
    """seeds with learning intact"""
    broken_seeds: list[int] = field(default_factory=lambda: [1, 2, 3])
    """seeds with the learning rate set to 0"""
    out: str = "learning_spread.jsonl"
    """JSON-lines file the results are appended to (one line per run)"""
    summary_only: bool = False
    """only print the summary of what `--out` holds"""


def summarize(path: str) -> None:
    rows = [json.loads(line) for line in open(path)]
    for name in learning_checks.CHECKS:
        score, threshold = learning_checks.SCORES[name]
        for broken in (False, True):
            scores = [score(r["curve"]) for r in rows if r["check"] == name and r["broken"] == broken]
            if not scores:
                continue
            seeds = sorted(r["seed"] for r in rows if r["check"] == name and r["broken"] == broken)
            secs = np.mean([r["seconds"] for r in rows if r["check"] == name and r["broken"] == broken])
            print(f"{name:32s} {'broken' if broken else 'intact'}: {len(scores):2d} seeds {seeds}, "
                  f"score min {min(scores):8.1f} median {np.median(scores):8.1f} max {max(scores):8.1f} "
                  f"(threshold {threshold}; {sum(s >= threshold for s in scores)} pass; {secs:.0f} s/run)")


def main() -> None:
    args = tyro.cli(Args, description=__doc__.split("\n\n")[0])
    torch.set_num_threads(1)
    if not args.summary_only:
        jobs = [(name, seed, False) for seed in args.seeds for name in args.checks]
        jobs += [(name, seed, True) for seed in args.broken_seeds for name in args.checks]
        for name, seed, broken in jobs:
            with tempfile.TemporaryDirectory() as track_dir:
                start = time.time()
                curve = learning_checks.CHECKS[name](seed, track_dir, broken)
                row = dict(check=name, seed=seed, broken=broken, curve=curve, seconds=time.time() - start)
            with open(args.out, "a") as f:
                f.write(json.dumps(row) + "\n")
            print(f"{name} seed {seed}{' broken' if broken else ''}: {[round(v) for _, v in curve]}", flush=True)
    summarize(args.out)


if __name__ == "__main__":
    main()
