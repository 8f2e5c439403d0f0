"""Export finished runs to small JSON files (`results/per_run/<run_name>.json`) that the plots read like run folders.

A run folder holds megabytes of TensorBoard events and checkpoints; the committed results need only what
the paper's figures and tables use. Per run, one JSON file with:

- every evaluation (`eval/*`), member return (`members/*`) and fallback std (`cascade/fallback_std/*`);
- the per-update scalars the figures read (`cascade/fallback/*`, `cascade/contribution/*`,
  `cascade/fallback_product`, `cascade/size`, the parameter counts, `charts/SPS`) at each evaluation step
  (the last value logged at or before it);
- the hyperparameters the run logged, the exact command (from the sweep's completion marker when the
  run was made by sweep.py), the code commit, and the training time from the final checkpoint.

Only runs that reached their planned budget are exported (`--allow-incomplete` to override). Then every
plot script accepts the folder: `python plots/learning_curves.py --runs results/per_run`.

    python plots/export_results.py --runs sweeps/reproduce/runs --out results/per_run --commit d274905
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # for `python plots/<script>.py`
from plots import common  # noqa: E402

FULL_TAGS = ("eval/", "members/", "cascade/fallback_std/")
SAMPLED_TAGS = ("cascade/fallback/", "cascade/contribution/", "cascade/fallback_product", "cascade/size",
                "cascade/parameters", "charts/parameters", "charts/SPS")


@dataclass
class Args:
    runs: list[str] = field(default_factory=lambda: ["runs"])
    """folders searched (at any depth) for run folders"""
    out: str = "results/per_run"
    """folder the JSON files are written to (one per run, named like the run folder)"""
    commit: str | None = None
    """code commit the runs were made with (default: this repository's HEAD)"""
    allow_incomplete: bool = False
    """also export runs that stopped before their planned budget"""
    overwrite: bool = False
    """rewrite JSON files that already exist"""


def planned_steps(hparams: dict[str, str]) -> int | None:
    """The steps the run does, from its logged settings: whole rollout batches of n*k (Cascade scripts:
    k // batch per iteration) or of total_timesteps (baselines: `cascade_plumbing.ppo.baseline_updates`, the
    scripts' own count); n*k env steps for SAC and DDPG (one env, no
    rollouts: their settings have a warm-up, learning_starts, and no num_steps)."""
    try:
        if "learning_starts" in hparams and "num_steps" not in hparams:
            return int(hparams["n"]) * int(hparams["k"])
        batch = int(hparams["num_envs"]) * int(hparams["num_steps"])
        if "total_timesteps" in hparams:  # the baselines' own count (under a cyclic LR: whole cycles, then the rest)
            from cascade_plumbing.ppo import baseline_updates

            cyclic = hparams.get("lr_schedule") == "cyclic"
            settings = SimpleNamespace(total_timesteps=int(hparams["total_timesteps"]), lr_schedule=hparams.get(
                "lr_schedule"), cycle_steps=int(hparams["cycle_steps"]) if cyclic else None)
            return baseline_updates(settings, batch) * batch
        return int(hparams["n"]) * (int(hparams["k"]) // batch) * batch
    except (KeyError, ValueError):
        return None


def sampled(series: common.Series, at: np.ndarray) -> dict:
    """The last value logged at or before each step of `at` (steps before the first value are left out)."""
    index = np.searchsorted(series.steps, at, side="right") - 1
    keep = index >= 0
    index = index[keep]
    return {"steps": at[keep].tolist(), "values": series.values[index].tolist(),
            "wall_times": series.wall_times[index].tolist()}


def whole(series: common.Series) -> dict:
    return {"steps": series.steps.tolist(), "values": series.values.tolist(), "wall_times": series.wall_times.tolist()}


def sweep_command(run_dir: str) -> list[str] | None:
    """sweep.py keeps each setup in runs/<run_id>/<run_name>/ and writes done/<run_id>.json with the command."""
    setup = os.path.dirname(os.path.abspath(run_dir))
    marker = os.path.join(os.path.dirname(os.path.dirname(setup)), "done", os.path.basename(setup) + ".json")
    if os.path.isfile(marker):
        with open(marker) as f:
            return json.load(f).get("command")
    return None


def training_seconds(run_dir: str) -> float | None:
    """Training time from the final checkpoint (it excludes the time a killed run spent stopped)."""
    path = os.path.join(run_dir, "checkpoint.pt")
    if not os.path.isfile(path):
        return None
    import torch

    return float(torch.load(path, map_location="cpu", weights_only=False).get("elapsed", float("nan")))


def export(run: common.Run, commit: str | None) -> dict:
    eval_steps = run.series("eval/episodic_return").steps
    scalars = {}
    for tag, series in run.scalars.items():
        if tag.startswith(FULL_TAGS):
            scalars[tag] = whole(series)
        elif tag.startswith(SAMPLED_TAGS):
            scalars[tag] = sampled(series, eval_steps)
    return {"format": "cascade-results/1", "name": run.name, "hparams": run.hparams,
            "command": sweep_command(run.path), "commit": commit, "seconds": training_seconds(run.path),
            "final_step": run.last_step(), "scalars": scalars}


def main(args: Args) -> list[str]:
    commit = args.commit
    if commit is None:
        head = subprocess.run(["git", "-C", os.path.dirname(os.path.abspath(__file__)), "rev-parse", "HEAD"],
                              capture_output=True, text=True)
        commit = head.stdout.strip() or None
    found = [path for path in common.find_run_dirs(args.runs) if not path.endswith(".json")]  # (.json: exported)
    if not found:
        common.fail(f"no run folders (named like a run, holding TensorBoard event files) under {' '.join(args.runs)}")
    by_name: dict[str, str] = {}
    for path in found:  # one file per run name: a second folder of the same name would overwrite the first
        other = by_name.setdefault(os.path.basename(path), path)
        if other != path:
            common.fail(f"two run folders are named {os.path.basename(path)} ({other} and {path}); export them "
                        "one at a time into different --out folders")
    os.makedirs(args.out, exist_ok=True)
    written, kept = [], 0
    try:
        for path in found:
            target = os.path.join(args.out, os.path.basename(path) + ".json")
            if os.path.exists(target) and not args.overwrite:
                common.note(f"skipped {path}: {target} exists (--overwrite replaces it)")
                kept += 1
                continue
            run = common.read_run(path)
            planned = planned_steps(run.hparams)
            if "eval/episodic_return" not in run.scalars:
                common.note(f"skipped {path}: no evaluations logged")
                continue
            final = int(run.scalars["eval/episodic_return"].steps.max())
            if planned is not None and final < planned and not args.allow_incomplete:
                common.note(f"skipped {path}: evaluated up to step {final:,} of {planned:,} (unfinished)")
                continue
            tmp = f"{target}.tmp"
            with open(tmp, "w") as f:
                json.dump(export(run, commit), f, separators=(",", ":"))
            os.replace(tmp, target)
            written.append(target)
    finally:  # also when a later run stops the export: what was written is said
        common.report(written)
    if not written and not kept:
        common.fail(f"nothing exported from {' '.join(args.runs)}: no run there has finished and logged evaluations "
                    "(see the notes above; --allow-incomplete exports unfinished runs)")
    return written


if __name__ == "__main__":
    main(common.parse_cli(Args, __doc__.split("\n\n")[0]))
