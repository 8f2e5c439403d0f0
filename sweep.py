"""Experiment grids: the paper's experiments as one command, on this machine or on a Ray cluster.

A sweep expands presets and/or command templates over env ids and seeds into runs, and executes
each run as a subprocess of one of our scripts (`--env-id`, `--seed`, `--exp-name`, `--track-dir`
added; with --track, the W&B flags: one group per sweep), with its log in `<sweep-dir>/logs/`. A run's
identity is its full command (tracking and the checkpoint cadence --scale adds aside): its folder is
`<sweep-dir>/runs/<env>__<label>__<seed>__<hash of the command>/`, and a run that exits 0 gets a
completion marker `<sweep-dir>/done/<same name>.json` (written last). Re-running a sweep skips marked
runs and restarts the others, resuming from their own checkpoint when one exists (a run folder without a
checkpoint, left by a run killed before its first one, is removed then); a re-run with other flags (or
another --scale) is another setup, so it starts new runs and never continues old ones. Failures are
reported at the end with their error line and log; they do not stop the other runs. Ctrl-C or SIGTERM stops
the running runs (each resumes on the next call) and ends the sweep with one line saying so (exit 130 / 143).

    python sweep.py --preset standard --envs Hopper-v4 --seeds 1 2 --scale 0.01
    python sweep.py --preset standard --envs Ant-v4 Walker2d-v4 --seeds 1 2 3 --backend ray --ray-address auto
    python sweep.py --command "cascade_ppo_continuous.py --n 3 --k 500000" --envs Hopper-v4 --seeds 1 2 --dry-run
    python plots/learning_curves.py --runs sweeps/standard/runs      # then plot (see docs/reproducing.md)
"""

from __future__ import annotations

import ast
import contextlib
import fcntl
import functools
import glob
import hashlib
import json
import math
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Literal

import tyro

from cascade_plumbing.errors import fail, parse_command_line, parse_error_line, unwrapped_errors
from cascade_plumbing.processes import run_dies_with_parent
from cascade_plumbing.tracking import PROGRESS_NAME, check_wandb, duration

ROOT = os.path.dirname(os.path.abspath(__file__))


@dataclass
class Args:
    preset: list[str] = field(default_factory=list)
    """named experiments of the paper to run (see --list-presets), e.g. `standard frozen`"""
    command: list[str] = field(default_factory=list)
    """command templates, each one quoted string: a script and its flags (e.g. "cascade_ppo_continuous.py --n 3")"""
    envs: list[str] = field(default_factory=lambda: ["Hopper-v4"])
    """env ids; every run of the grid is made for each"""
    seeds: list[str] = field(default_factory=lambda: ["1"])
    """seeds (integers); every run of the grid is made for each"""
    scale: float = 1.0
    """multiply every step count by this, e.g. 0.01 for a quick check: the budgets (--k, --total-timesteps, --cycle-steps), --learning-starts, --eval-every (at least 1000) and --checkpoint-every (at least 2048), the template's or the script's default; a PPO budget below one rollout is refused"""
    sweep_dir: str | None = None
    """folder for runs/, logs/ and done/ markers (default: sweeps/<presets or 'custom'>); on a cluster, a shared folder"""
    backend: Literal["local", "ray"] = "local"
    """local: a pool of worker processes on this machine; ray: Ray tasks on a cluster"""
    workers: int = max(os.cpu_count() or 1, 1)
    """local backend: runs at a time (default: the number of cores)"""
    ray_address: str = "auto"
    """ray backend: `auto` (the cluster this machine belongs to) or host:port of the head node"""
    cpus_per_run: float = 1.0
    """ray backend: CPUs reserved for each run"""
    python: str = sys.executable
    """python interpreter the runs use (on a cluster, one that exists on every node)"""
    dry_run: bool = False
    """print the commands, each with how far its run is (new, training now, or where it resumes), and exit"""
    list_presets: bool = False
    """print the presets and exit"""
    status_every: float = 30.0
    """seconds between progress lines (counts, then each running run's own progress line: steps, SPS, ETA)"""
    track: bool = False
    """log every run to Weights & Biases too (the scripts' --track), the runs of this sweep in one W&B group; not part of a run's identity, so a re-run with it resumes the unfinished runs"""
    wandb_project_name: str = "cascade"
    """the W&B project of the runs (with --track)"""
    wandb_entity: str | None = None
    """the W&B entity of the runs (with --track; default: your default entity)"""
    wandb_group: str | None = None
    """the W&B group of the runs (with --track; default: the sweep folder's name)"""


# ----------------------------------------------------------------------------------------------
# The paper's experiments (Schmöcker & Dockhorn, RLJ 2025: Section 4, Fig. 2-8; Appendices D-I, Fig. 9-16). Each
# entry: label, script, flags.
# Step counts (budgets, warm-ups, evaluation and checkpoint cadences) are scaled by --scale (scale_template).
# ----------------------------------------------------------------------------------------------
CASCADE = "cascade_ppo_continuous.py"
PPO = "ppo_baseline.py"
# Fig. 14 and 15 as the paper's code ran them (the scripts' defaults are its code where its Appendix H is silent or
# differs: alpha fixed at 0.2, 16-16 tanh DDPG nets with a 64-64 tanh critic and annealed LR, a restart (random
# warm-up, fresh targets) with each net, +-10 clipping)
SAC_RUNS = [
    ("cascade_sac", "cascade_sac.py", "--n 4 --k 500000"),
    ("sac", "cascade_sac.py", "--n 1 --k 2000000 --hidden-size 256"),
]
DDPG_RUNS = [
    ("cascade_ddpg", "cascade_ddpg.py", "--n 6 --k 1000000"),
    ("ddpg", "cascade_ddpg.py", "--n 1 --k 6000000 --hidden-size 64"),
]


def every_50k(entries: list[tuple[str, str, str]]) -> list[tuple[str, str, str]]:
    """The runs evaluated every 50k steps, as results/ runs them."""
    return [(label, script, f"{flags} --eval-every 50000") for label, script, flags in entries]


PRESETS: dict[str, tuple[str, list[tuple[str, str, str]]]] = {
    "standard": ("Fig. 2, 9: standard Cascade vs PPO (6M steps)", [
        ("cascade", CASCADE, "--n 6 --k 1000000"),
        ("ppo", PPO, "--total-timesteps 6000000"),
    ]),
    "reproduce": ("Fig. 2 at the paper's budget as we ran it (results/): standard Cascade vs PPO, eval every 50k", [
        ("cascade", CASCADE, "--n 6 --k 1000000 --eval-every 50000"),
        ("ppo", PPO, "--total-timesteps 6000000 --eval-every 50000"),
    ]),
    "ablations": ("Fig. 3, 4, 5, 10, 11, 12, 13 as results/ runs them (eval every 50k; standard Cascade is `reproduce`'s); "
                  "run with --envs Ant-v4 Walker2d-v4", every_50k([
        ("ppo_h16_cyclic", PPO, "--total-timesteps 6000000 --hidden-size 16 --lr-schedule cyclic --cycle-steps 1000000"),
        ("cascade_frozen", CASCADE, "--n 6 --k 1000000 --freeze-previous"),
        ("cascade_start_full", CASCADE, "--n 6 --k 1000000 --start-full"),
        ("cascade_fallback0.05", CASCADE, "--n 6 --k 1000000 --fallback-init 0.05"),
        ("cascade_fallback0.9", CASCADE, "--n 6 --k 1000000 --fallback-init 0.9"),
        ("cascade_n2", CASCADE, "--n 2 --k 3000000"),
        ("cascade_n4", CASCADE, "--n 4 --k 1500000"),
        ("cascade_global_lr", CASCADE, "--n 6 --k 1000000 --lr-schedule global"),
        ("cascade_nonorm", CASCADE, "--n 6 --k 1000000 --no-normalize"),
        ("cascade_frozen_nonorm", CASCADE, "--n 6 --k 1000000 --freeze-previous --no-normalize"),
    ])),
    "baselines": ("Fig. 3, 9: PPO over 2M..6M steps, and one 16-wide net with a cyclic LR (a fresh Adam each cycle, the paper's code)", [
        *[(f"ppo_{m}M", PPO, f"--total-timesteps {m}000000") for m in range(2, 7)],
        ("ppo_h16_cyclic", PPO, "--total-timesteps 6000000 --hidden-size 16 --lr-schedule cyclic --cycle-steps 1000000"),
    ]),
    "frozen": ("Fig. 4, 13: only the newest net trains, with and without normalization (raw values still clipped to ±10, the paper's code)", [
        ("cascade", CASCADE, "--n 6 --k 1000000"),
        ("cascade_frozen", CASCADE, "--n 6 --k 1000000 --freeze-previous"),
        ("cascade_nonorm", CASCADE, "--n 6 --k 1000000 --no-normalize"),
        ("cascade_frozen_nonorm", CASCADE, "--n 6 --k 1000000 --freeze-previous --no-normalize"),
    ]),
    "start-full": ("Fig. 5: the full 6-net stack from the start (one critic; Adam and LR cycle restart every 1M, the paper's code)", [
        ("cascade", CASCADE, "--n 6 --k 1000000"),
        ("cascade_start_full", CASCADE, "--n 6 --k 1000000 --start-full"),
    ]),
    "tiny": ("Fig. 8: 16 tiny base nets (one hidden layer of size 1)", [
        ("cascade_tiny_k500k", CASCADE, "--n 16 --k 500000 --hidden-size 1 --num-layers 1"),
        ("cascade_tiny_k1M", CASCADE, "--n 16 --k 1000000 --hidden-size 1 --num-layers 1"),
    ]),
    "k-sweep": ("Fig. 10: n = 2..8 nets within the same 6M steps", [
        (f"cascade_n{n}", CASCADE, f"--n {n} --k {6_000_000 // n}") for n in range(2, 9)
    ]),
    "fallback-init": ("Fig. 11: initial fallback 0.05, 0.5, 0.9", [
        (f"cascade_fallback{f}", CASCADE, f"--n 6 --k 1000000 --fallback-init {f}") for f in ("0.05", "0.5", "0.9")
    ]),
    "global-lr": ("Fig. 12: one LR decay over the whole run instead of cyclic", [
        ("cascade", CASCADE, "--n 6 --k 1000000"),
        ("cascade_global_lr", CASCADE, "--n 6 --k 1000000 --lr-schedule global"),
    ]),
    "discrete": ("Fig. 16: discrete Cascade vs discrete PPO on discretized envs (10M steps, normalized as the paper's code; "
                 "eval every 50k as results/)", [
        ("cascade_discrete", "cascade_ppo_discrete.py", "--n 10 --k 1000000 --eval-every 50000"),
        ("ppo_discrete", "ppo_baseline_discrete.py", "--total-timesteps 10000000 --eval-every 50000"),
    ]),
    "sac-ddpg": ("Fig. 14, 15: Cascade with SAC (2M) and DDPG (6M) vs their baselines, as the paper's code ran them",
                 [*SAC_RUNS, *DDPG_RUNS]),
    "ddpg": ("Fig. 15 as results/ runs it: Cascade-DDPG vs DDPG (6M steps, eval every 50k); run with --envs Hopper-v4 "
             "Walker2d-v4", every_50k(DDPG_RUNS)),
    "sac": ("Fig. 14 as results/ runs it: Cascade-SAC vs SAC (2M steps, eval every 50k); run with --envs Hopper-v4 "
            "HalfCheetah-v4", every_50k(SAC_RUNS)),
}
CONTINUOUS_SCRIPTS = (CASCADE, PPO, "cascade_sac.py", "cascade_ddpg.py")  # the discrete scripts take both kinds
# What --scale multiplies (a 0, "off", stays 0). The budgets: a PPO budget below one rollout is refused, not raised.
SCALED_BUDGETS = ("--k", "--total-timesteps", "--cycle-steps")
# the off-policy warm-up (uniform-random steps before updates, after each new net) scales with the budget it is part of
WARMUP_FLAG = "--learning-starts"
EVAL_FLAG = "--eval-every"  # so that a quick check keeps a learning curve
MIN_EVAL_EVERY = 1000  # ... of at most one evaluation per 1000 steps (each is --eval-episodes whole episodes)
CADENCE_FLAG = "--checkpoint-every"  # not part of a run's identity (a resume may change it)
MIN_CADENCE = 2048  # a checkpoint costs ~0.1-0.2 s: not more often than this
# a scaled template that leaves one of these at the script's default gets the default, scaled: (Args field, flag)
SCALED_DEFAULTS = (("k", "--k"), ("total_timesteps", "--total-timesteps"), ("learning_starts", WARMUP_FLAG),
                   ("eval_every", EVAL_FLAG))
# ... and this one where the template turns it on: the LR cycle of `--lr-schedule cyclic` (Fig. 3) divides the budget
CYCLE_DEFAULT = ("cycle_steps", "--cycle-steps", "--lr-schedule", "cyclic")
# the sweep sets these for each run itself
SWEEP_FLAGS = ("--env-id", "--seed", "--track-dir", "--resume", "--evaluate")


@dataclass
class Run:
    label: str
    script: str
    flags: list[str]
    env_id: str
    seed: int
    cadence: list[str] = field(default_factory=list)
    """--checkpoint-every for a scaled run whose template leaves the script's default (not part of its identity:
    it does not change what the run computes, and a resume may change it)"""
    written: list[str] | None = None
    """the flags as the template wrote them, where that differs from `flags` (`--k=300`): the identity sweeps made
    before flags were spelled one way gave the run (its folder there is used; see `as_in`)"""

    def as_in(self, sweep_dir: str) -> Run:
        """This run, or the same run under the identity of the template's own spelling where `sweep_dir` holds that
        one's folder or completion marker and not this one's (a sweep made before flags were spelled one way)."""
        if self.written is None:
            return self
        earlier = replace(self, flags=self.written, written=None)
        def made(run: Run) -> bool:
            return (os.path.exists(os.path.join(sweep_dir, "done", f"{run.run_id}.json"))
                    or os.path.isdir(os.path.join(sweep_dir, "runs", run.run_id)))
        return earlier if made(earlier) and not made(self) else self

    @property
    def setup_hash(self) -> str:
        """Digest of the run's full command (script, flags after scaling and in one spelling, env, seed): its
        identity."""
        command = shlex.join([self.script, *self.flags, "--env-id", self.env_id, "--seed", str(self.seed)])
        return hashlib.sha1(command.encode()).hexdigest()[:10]

    @property
    def run_id(self) -> str:
        return f"{self.env_id}__{self.label}__{self.seed}__{self.setup_hash}"

    def identity(self) -> dict:
        """What the completion marker records: which exact setup finished."""
        return {"run_id": self.run_id, "setup_hash": self.setup_hash, "script": self.script, "flags": self.flags,
                "env_id": self.env_id, "seed": self.seed}

    def fresh_command(self, python: str, track_dir: str, tracking: list[str]) -> list[str]:
        return [python, os.path.join(ROOT, self.script), *self.flags, "--env-id", self.env_id, "--seed",
                str(self.seed), "--exp-name", self.label, "--track-dir", track_dir, "--quiet", *self.cadence, *tracking]

    def command(self, python: str, runs_dir: str, tracking: list[str] = ()) -> list[str]:
        """The fresh run's command, or a resume of its latest checkpoint when one exists.

        Each setup logs into its own folder `<runs_dir>/<run_id>/`, so a checkpoint is only ever
        resumed by the exact command that started it; the resume also repeats every flag, so the
        script itself refuses a checkpoint whose saved settings differ."""
        track_dir = os.path.join(runs_dir, self.run_id)
        # a folder whose checkpoint.pt is gone but whose iteration_<i>.pt are there is resumed too: the script then
        # stops in one line naming the iteration file to continue from (a fault hunt: the sweep started a new run
        # beside it, the finished iterations unused)
        folders = os.path.join(glob.escape(track_dir), "*")
        checkpoints = sorted(glob.glob(os.path.join(folders, "checkpoint.pt"))
                             + glob.glob(os.path.join(folders, "iteration_*.pt")), key=os.path.getmtime)
        command = self.fresh_command(python, track_dir, list(tracking))
        if checkpoints:
            at = command.index("--track-dir")  # the resumed run continues in its own folder
            return [*command[:2], "--resume", os.path.dirname(checkpoints[-1]), *command[2:at], *command[at + 2 :]]
        return command


def tracking_flags(args: Args, sweep_dir: str) -> list[str]:
    """--track for every run, all in one W&B group; added after the identity flags, so it never changes a
    run's setup hash (tracking does not change what a run computes)."""
    if not args.track:
        return []
    flags = ["--track", "--wandb-project-name", args.wandb_project_name,
             "--wandb-group", args.wandb_group or os.path.basename(sweep_dir)]
    return flags + (["--wandb-entity", args.wandb_entity] if args.wandb_entity else [])


def flag_name(flag: str) -> str:
    """`--total_timesteps=5` -> `--total-timesteps`: the flag a token sets, spelled as the scripts' --help spells it
    (tyro accepts both spellings)."""
    name = flag.partition("=")[0]
    return "--" + name[2:].replace("_", "-") if name.startswith("--") else name


def canonical_flags(flags: list[str]) -> list[str]:
    """Flags in one spelling, `--k=300` -> `--k 300` and `--env_id` -> `--env-id` (tyro reads both alike): a run's
    identity is its command, so one setup written two ways in two sweeps into one folder is one run, not two."""
    out: list[str] = []
    for token in flags:
        if token.startswith("--"):
            name, eq, value = token.partition("=")
            out += [flag_name(name), value] if eq else [flag_name(name)]
        else:
            out.append(token)
    return out


def flag_value(flags: list[str], name: str) -> str | None:
    """The value a command's flags give `name` (`--k 100` or `--k=100`; the last one wins, as in the scripts)."""
    value = None
    for i, flag in enumerate(flags):
        if flag_name(flag) == name:
            eq, rest = flag.partition("=")[1:]
            value = rest if eq else (flags[i + 1] if i + 1 < len(flags) else None)
    return value


def set_flag_value(flags: list[str], name: str, value: str) -> None:
    """Set the value of `name` where `flag_value` reads it (its last occurrence), in place."""
    for i in reversed(range(len(flags))):
        if flag_name(flags[i]) == name:
            if "=" in flags[i]:
                flags[i] = f"{flags[i].partition('=')[0]}={value}"
            else:
                flags[i + 1] = value
            return
    raise KeyError(name)


def whole_lr_cycles(flags: list[str]) -> int:
    """How many LR cycles `--lr-schedule cyclic` fits in --total-timesteps, where it is a whole number of them (0
    otherwise): scaling keeps that number, so the last cycle is not cut short by rounding."""
    if flag_value(flags, "--lr-schedule") != "cyclic":
        return 0
    try:
        total, cycle = int(flag_value(flags, "--total-timesteps") or 0), int(flag_value(flags, "--cycle-steps") or 0)
    except ValueError:  # (not whole numbers: scale_template says so)
        return 0
    return total // cycle if cycle > 0 and total > 0 and total % cycle == 0 else 0


@functools.cache
def script_default(script: str, field: str) -> int | None:
    """The script's default of its Args field `field` (e.g. checkpoint_every), or None where it has no such flag
    (or its default is None)."""
    try:
        with open(os.path.join(ROOT, script)) as f:
            tree = ast.parse(f.read())
    except (OSError, SyntaxError):
        return None
    for node in tree.body:
        if isinstance(node, ast.ClassDef) and node.name == "Args":
            for item in node.body:
                if isinstance(item, ast.AnnAssign) and getattr(item.target, "id", None) == field:
                    try:
                        return ast.literal_eval(item.value)
                    except ValueError:
                        return None
    return None


def rollout_steps(script: str, flags: list[str]) -> int | None:
    """The env steps of one PPO rollout of `script` run with `flags` (--num-envs x --num-steps, the continuous
    scripts' default 2048 // num_envs each), or None for the off-policy scripts (and for values the script itself
    will refuse)."""
    if script_default(script, "num_minibatches") is None:
        return None
    try:
        num_envs = int(flag_value(flags, "--num-envs") or script_default(script, "num_envs") or 1)
        if num_envs < 1:
            return None
        num_steps = int(flag_value(flags, "--num-steps") or script_default(script, "num_steps") or max(2048 // num_envs, 1))
    except ValueError:
        return None
    return num_envs * num_steps if num_steps >= 1 else None


def replay_batch(script: str, flags: list[str]) -> tuple[int, int] | None:
    """For an off-policy script run with `flags`: (--batch-size, the iterations its replay buffer spans: --n with
    --keep-buffer, else 1); None for the PPO scripts (and for values the script itself will refuse)."""
    if script_default(script, "batch_size") is None or script_default(script, "num_minibatches") is not None:
        return None
    try:
        batch = int(flag_value(flags, "--batch-size") or script_default(script, "batch_size"))
        spans = int(flag_value(flags, "--n") or script_default(script, "n") or 1) if "--keep-buffer" in flags else 1
    except ValueError:
        return None
    return (batch, spans) if batch >= 1 and spans >= 1 else None


def scale_template(script: str, flags: list[str], scale: float,
                   template: str) -> tuple[list[str], list[str], float, tuple[float, float, str, int, int]]:
    """A template's flags at `scale`, the checkpoint cadence to add, the smallest scale its PPO budgets allow, and
    the PPO budget that rounding to whole rollouts moves most: (flags, cadence, smallest scale, (|relative change|,
    relative change, flag, steps, exact scaled steps)).

    At scale 1 the flags are the command as written. Otherwise every step count is multiplied by `scale`, where the
    template gives it and where it leaves the script's default (then added, scaled): the budgets (SCALED_BUDGETS),
    the off-policy warm-up, the evaluation cadence and, under `--lr-schedule cyclic`, the LR cycle (part of the run's identity: they change what it computes or
    logs), and the checkpoint cadence the sweep adds where the template leaves it (not part of the identity). A 0
    (off) stays 0. A PPO budget is rounded to the nearest whole number of rollouts (the script would round it down
    to them: at 0.001, discrete Cascade's 10 iterations of --k 1000 were 10 x 512 steps against its baseline's 9,728).
    The caller refuses a scale below the smallest one (a PPO budget below one rollout: raising it would break the
    equal budgets a figure compares), and one whose rounding moves a budget by more than MAX_ROUNDING."""
    if scale == 1:
        return list(flags), [], 0.0, (0.0, 0.0, "", 0, 0)
    out = list(flags)
    field_name, flag, switch, on = CYCLE_DEFAULT
    defaults = [*SCALED_DEFAULTS, *([(field_name, flag)] if flag_value(out, switch) == on else [])]
    for field_name, flag in defaults:
        default = script_default(script, field_name)
        if isinstance(default, int) and flag_value(out, flag) is None:
            out += [flag, str(default)]
    rollout = rollout_steps(script, out)
    smallest, rounding = 0.0, (0.0, 0.0, "", 0, 0)
    batch = replay_batch(script, out)
    cycles = whole_lr_cycles(out)

    def scaled(name: str, value: str) -> str:
        nonlocal smallest, rounding
        try:
            steps = int(value)
        except ValueError:
            fail(f"{name} {value} in '{template}' is not a whole number of steps; write it as one, e.g. {name} 1000000")
        new = int(round(steps * scale))
        if steps <= 0 or name == WARMUP_FLAG:
            return str(new)
        if name == EVAL_FLAG:  # a floor, but never above what the template asked for
            return str(max(new, min(MIN_EVAL_EVERY, steps)))
        if name == CADENCE_FLAG:
            return str(max(new, min(MIN_CADENCE, steps)))
        if batch and name == "--k":  # an off-policy iteration must hold a batch (--keep-buffer: the run's n of them,
            # each of the scaled --k rounded: hence whole rows per iteration)
            smallest = max(smallest, math.ceil(batch[0] / batch[1]) / steps)
        if rollout:
            smallest = max(smallest, rollout / steps)
            new = max(round(steps * scale / rollout), 1) * rollout
            change = new / (steps * scale) - 1
            rounding = max(rounding, (abs(change), change, name, new, int(round(steps * scale))))
        return str(new)

    for i, flag in enumerate(out):
        name, eq, value = flag_name(flag), *flag.partition("=")[1:]
        if name not in (*SCALED_BUDGETS, WARMUP_FLAG, EVAL_FLAG, CADENCE_FLAG):
            continue
        if eq:
            out[i] = f"{flag.partition('=')[0]}={scaled(name, value)}"
        elif i + 1 < len(out):
            out[i + 1] = scaled(name, out[i + 1])
    if cycles:  # rounded on their own, 6 cycles of 10,240 steps got a budget of 59,392: the last cycle cut short
        cycle = int(flag_value(out, "--cycle-steps"))
        set_flag_value(out, "--total-timesteps", str(cycles * cycle))
    cadence = []
    default = script_default(script, "checkpoint_every")
    if default and flag_value(out, CADENCE_FLAG) is None:
        # a scaled run left at the script's default would write no checkpoint before its end
        cadence = [CADENCE_FLAG, scaled(CADENCE_FLAG, str(default))]
    return out, cadence, smallest, rounding


MAX_ROUNDING = 0.1  # the most a PPO budget may move by rounding to whole rollouts (5 rollouts or more: at most 10%)


def scale_problem(templates: list[tuple[str, str, list[str]]], scale: float) -> tuple[str, float]:
    """What is wrong with `scale` for the (label, script, flags) `templates` ("" if nothing), and the smallest scale
    that gives every PPO budget one rollout."""
    scaled = [(scale_template(script, flags, scale, shlex.join([script, *flags])), shlex.join([script, *flags]))
              for _, script, flags in templates]
    smallest, template = max((result[2], template) for result, template in scaled)
    if smallest > scale:
        script = shlex.split(template)[0]
        least = "one PPO rollout" if rollout_steps(script, shlex.split(template)[1:]) else "one --batch-size of steps"
        return f"makes a budget of '{template}' less than {least}", smallest
    (change, _, flag, steps, exact), template = max((result[3], template) for result, template in scaled)
    if change > MAX_ROUNDING:
        return (f"gives '{template}' {flag} {steps} (whole PPO rollouts) instead of {exact}, {100 * change:.0f}% "
                "off, which would skew the budgets a figure compares"), smallest
    # each within 10%, but one rounded up and another down can still be further apart than that
    changes = sorted((result[3][1], result[3][2:4], template) for result, template in scaled)
    (low, (low_flag, low_steps), low_template), (high, (high_flag, high_steps), high_template) = changes[0], changes[-1]
    if high - low > MAX_ROUNDING:
        return (f"gives '{high_template}' {high_flag} {high_steps} and '{low_template}' "
                f"{low_flag or 'its budgets'} {low_steps or 'unrounded'} ({100 * high:+.0f}% and {100 * low:+.0f}% of "
                "their scaled values, in whole PPO rollouts), which would skew the budgets a figure compares"), smallest
    return "", smallest


def a_scale_that_works(templates: list[tuple[str, str, list[str]]], smallest: float) -> float:
    """The first scale of two significant figures from `smallest` up at which `scale_problem` finds nothing (the
    rounding's share shrinks as the budgets grow: found within a few hundred steps for any real template)."""
    scale = smallest_scale_that_works(smallest)
    for _ in range(10_000):
        if not scale_problem(templates, scale)[0]:
            break
        scale = float(f"{scale + 10 ** (math.floor(math.log10(scale)) - 1):.2g}")
    return scale


def smallest_scale_that_works(needed: float) -> float:
    """`needed` rounded up to two significant figures (0.002048 -> 0.0021): a scale to name in a message."""
    unit = 10 ** (math.floor(math.log10(needed)) - 1)
    return math.ceil(needed / unit - 1e-9) * unit


def expand(args: Args) -> list[Run]:
    """The grid: every (template, env, seed)."""
    try:
        seeds = [int(s) for s in args.seeds]
    except ValueError:
        fail(f"--seeds must be integers (got {' '.join(args.seeds)})")
    bad = [s for s in seeds if not 0 <= s < 2**32]
    if bad:
        fail(f"--seeds {bad[0]}: a seed must be a non-negative integer below 2**32 (numpy and gymnasium refuse others)")
    if not seeds or not args.envs:
        fail(f"nothing to run: {'--seeds' if not seeds else '--envs'} is given with no value")
    templates: list[tuple[str, str, list[str]]] = []
    for name in args.preset:
        if name not in PRESETS:
            fail(f"unknown preset '{name}'; choose from {', '.join(PRESETS)}")
        templates += [(label, script, shlex.split(flags)) for label, script, flags in PRESETS[name][1]]
    for i, template in enumerate(args.command):
        try:
            parts = shlex.split(template)
        except ValueError as exc:  # an unclosed quote
            fail(f"--command '{template}' cannot be read as a command line ({exc}); quote the whole template once")
        if parts and os.path.dirname(parts[0]):
            name = os.path.basename(parts[0])
            fail(f"--command '{template}': name one of the training scripts of the repository root, without a "
                 f"folder (e.g. {name if os.path.isfile(os.path.join(ROOT, name)) else CASCADE}): the sweep runs it "
                 f"from {ROOT}")
        if not parts or not parts[0].endswith(".py") or not os.path.isfile(os.path.join(ROOT, parts[0])):
            fail(f"unknown script in --command '{template}': expected one of our scripts, e.g. {CASCADE}")
        flags, label = parts[1:], f"{parts[0][:-3]}_{i + 1}"
        names = [flag_name(flag) for flag in flags]
        if "--exp-name" in names:  # the sweep sets --exp-name itself: it becomes the template's label
            at = names.index("--exp-name")
            if "=" in flags[at]:
                label, flags = flags[at].partition("=")[2], flags[:at] + flags[at + 1 :]
            elif at + 1 < len(flags):
                label, flags = flags[at + 1], flags[:at] + flags[at + 2 :]
            else:
                fail(f"--exp-name in '{template}' has no value; give the template's name after it")
        templates.append((label, parts[0], flags))
    if not (math.isfinite(args.scale) and args.scale > 0):
        fail(f"--scale must be positive (got {args.scale}); e.g. 0.01 for a quick check, 1 for the paper's budgets")
    if not templates:
        fail("nothing to run: give --preset NAME (see --list-presets) and/or --command TEMPLATE")
    scaled = []
    for label, script, flags in templates:
        template = shlex.join([script, *flags])
        for flag in flags:
            if flag_name(flag) in SWEEP_FLAGS:
                fail(f"'{template}' sets {flag_name(flag)}, which the sweep sets for each run itself: give "
                     "env ids with --envs and seeds with --seeds, and the sweep folder with --sweep-dir")
            if flag_name(flag) == "--no-quiet":  # (it was overridden by the --quiet put after it, silently)
                fail(f"'{template}' sets --no-quiet: the sweep runs every script with --quiet and shows each run's "
                     "progress in its own status lines; leave it out")
            if flag in ("-h", "--help"):
                fail(f"'{template}' asks for --help, which runs nothing: read the flags with `python {script} --help`")
        canonical = canonical_flags(flags)
        template_flags, cadence, _, _ = scale_template(script, canonical, args.scale, template)
        written = None if canonical == flags else scale_template(script, flags, args.scale, template)[0]
        scaled.append((label, script, template_flags, cadence, written))
    problem, smallest = scale_problem(templates, args.scale)
    if problem:
        works = a_scale_that_works(templates, max(smallest, args.scale))
        which = "the smallest that works" if smallest > args.scale else "the next one up that works"
        fail(f"--scale {args.scale:g} {problem}; use --scale {works:.2g} ({which}: every PPO budget at least one "
             "rollout, and in whole rollouts within 10% of its scaled value and of the others', and the steps a "
             "SAC/DDPG replay buffer holds at least one batch)")
    runs, seen = [], set()
    # env by env, seed by seed: the runs one figure panel compares finish together
    for env_id in args.envs:
        for seed in seeds:
            for label, script, flags, cadence, written in scaled:
                run = Run(label, script, flags, env_id, seed, cadence, written)
                if run.run_id not in seen:  # presets share some runs (e.g. standard Cascade), spellings one setup
                    seen.add(run.run_id)
                    runs.append(run)
    return runs


# ----------------------------------------------------------------------------------------------
# Executing a run: a subprocess, its log, and the completion marker written last
# ----------------------------------------------------------------------------------------------
def execute(command: list[str], log_path: str, marker_path: str, cwd: str, identity: dict | None = None,
            start: Callable | None = None) -> int | None:
    """Run `command` to its end, logging to `log_path`; its exit code. `start(command, log, cwd)` starts it
    (default: `launch`; the local backend's returns None once the sweep stops: then so does this)."""
    os.makedirs(os.path.dirname(log_path), exist_ok=True)
    with open(log_path, "a") as log:
        proc = (start or launch)(command, log, cwd)
        if proc is None:
            return None
        try:
            code = proc.wait()
        finally:
            RUNNING.discard(proc)
    if code == 0:
        os.makedirs(os.path.dirname(marker_path), exist_ok=True)
        tmp = f"{marker_path}.tmp"
        with open(tmp, "w") as f:
            json.dump({**(identity or {}), "command": command, "finished": time.time()}, f)
        os.replace(tmp, marker_path)
    return code


def launch(command: list[str], log, cwd: str) -> subprocess.Popen:
    """The run in a session of its own (a stop of the sweep reaches it from the sweep only), ending with the sweep:
    a sweep killed even by SIGKILL sends it SIGTERM (Linux), and it stops as when stopped (`stop_running`). A local run holds the
    sweep folder's lock too (`lock_sweep_dir`), so no other sweep starts there before it has ended."""
    log.write(f"$ {shlex.join(command)}\n")
    log.flush()
    return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, cwd=cwd, start_new_session=True,
                            pass_fds=LOCK_FD, preexec_fn=run_dies_with_parent(os.getpid()))


def launch_unless_stopping(command: list[str], log, cwd: str) -> subprocess.Popen | None:
    """Local backend: a run starts before the sweep stops (and is stopped with the others) or not at all."""
    with RUNNING_LOCK:
        if STOP:
            return None
        proc = launch(command, log, cwd)
        RUNNING.add(proc)
        return proc


RUNNING: set[subprocess.Popen] = set()
LOCK_FD: list[int] = []  # the sweep folder's lock (sweep.lock), held by the sweep and its local runs
RUNNING_LOCK = threading.Lock()
STOP: list[int] = []  # the signal that stops the sweep (SIGINT: Ctrl-C, SIGTERM: kill), once it came
# the exit of a run the sweep stopped: the scripts exit 128 + SIGTERM, or die by it before their handler is set
STOPPED_CODES = (128 + signal.SIGTERM, -signal.SIGTERM)


class Tracker:
    """Counts and a periodic progress line: done / running / failed / pending, ETA; after the sweep is stopped,
    the runs it stopped (not failures) and no more progress lines."""

    def __init__(self, total: int, parallel: int, every: float, running_label: str = "running"):
        self.total, self.parallel, self.every = total, max(parallel, 1), every
        self.running_label = running_label
        self.done = self.running = 0
        self.failed: list[tuple[Run, str, int]] = []
        self.stopped: list[Run] = []
        self.active: dict[str, Run] = {}  # started, not finished
        self.durations: list[float] = []
        self.runs_dir = ""  # where the runs' folders are (their progress lines), once the sweep knows it
        self.lock = threading.Lock()
        self.last = 0.0

    def started(self, run: Run) -> None:
        with self.lock:
            self.running += 1
            self.active[run.run_id] = run

    def finished(self, run: Run, code: int, log: str, seconds: float) -> None:
        with self.lock:
            self.running -= 1
            self.active.pop(run.run_id, None)
            if STOP and code in STOPPED_CODES:
                self.stopped.append(run)
                return
            if code == 0:
                self.done += 1
                self.durations.append(seconds)
            else:
                self.failed.append((run, log, code))
            print(f"{'done  ' if code == 0 else 'FAILED'} {run.run_id} ({seconds:.0f}s)", flush=True)
            self.report(force=True)

    def report(self, force: bool = False) -> None:
        if STOP or (not force and time.time() - self.last < self.every):
            return
        self.last = time.time()
        pending = self.total - self.done - len(self.failed) - self.running
        eta = "?"
        if self.durations:
            left = (pending + self.running) * (sum(self.durations) / len(self.durations)) / self.parallel
            # A duration, not a clock time; it can pass 24 h. A resumed run's duration counts only its last part.
            eta = duration(left)
        print(f"[sweep] {self.done} done, {self.running} {self.running_label}, {len(self.failed)} failed, {pending} pending "
              f"of {self.total} | ETA {eta}", flush=True)
        if self.runs_dir:  # how far each running run is: the progress line it keeps in its folder
            shown = list(self.active.values())
            for run in shown[:8]:
                try:  # (none yet: the run has just started; or its folder is being removed)
                    files = glob.glob(os.path.join(glob.escape(self.runs_dir), run.run_id, "*", PROGRESS_NAME))
                    with open(max(files, key=os.path.getmtime)) as f:
                        print(f"  {run.run_id}: {f.readline().strip()}", flush=True)
                except (ValueError, OSError):
                    continue
            if len(shown) > 8:
                print(f"  ... and {len(shown) - 8} more running", flush=True)


def run_local(todo: list[tuple[Run, list[str], str, str]], workers: int, tracker: Tracker) -> None:
    def one(item):
        run, command, log, marker = item

        def start(*launch_args):
            proc = launch_unless_stopping(*launch_args)
            if proc is not None:
                tracker.started(run)
            return proc

        begun = time.time()
        code = execute(command, log, marker, ROOT, run.identity(), start)
        if code is not None:
            tracker.finished(run, code, log, time.time() - begun)

    pool = ThreadPoolExecutor(max_workers=workers)
    futures = []
    try:
        futures += [pool.submit(one, item) for item in todo]
        while not all(f.done() for f in futures):
            time.sleep(0.5)
            tracker.report()
        for f in futures:
            f.result()
    except KeyboardInterrupt:
        for f in futures:
            f.cancel()
        stop_running()
        pool.shutdown(wait=True, cancel_futures=True)  # the stopped runs exit (after their one line)
        raise
    pool.shutdown()


def stop_running(hold_lock: bool = True) -> None:
    """SIGTERM to each running run (its main process, which ends its own worker processes): a PPO run stops at its
    last checkpoint, a SAC or DDPG run writes one at its next step first; a run whose final checkpoint is already
    being written finishes normally. `hold_lock`: False from a signal handler (the interrupted code may hold it)."""
    with RUNNING_LOCK if hold_lock else contextlib.nullcontext():
        for proc in list(RUNNING):
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)


def check_ray_address(address: str, timeout: float = 5.0) -> None:
    """A host:port that does not answer fails within `timeout` seconds, instead of hanging."""
    if address in ("auto", "local"):
        return
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        fail(f"--ray-address must be 'auto' or host:port (got '{address}')")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            pass
    except OSError as exc:
        fail(f"no Ray head answers at {address} ({exc.strerror or exc}); start one with `ray start --head` "
             "and pass the address it prints")


def run_ray(todo: list[tuple[Run, list[str], str, str]], args: Args, tracker: Tracker) -> None:
    try:
        import ray
    except ImportError:
        fail("the ray backend needs ray: pip install -r requirements.txt")
    check_ray_address(args.ray_address)
    try:
        ray.init(address=args.ray_address, log_to_driver=False, logging_level="ERROR")
    except Exception as exc:
        fail(f"cannot connect to Ray at {args.ray_address}: {type(exc).__name__}: {str(exc).splitlines()[0]}")
    remote = ray.remote(num_cpus=args.cpus_per_run, max_retries=0)(execute)
    pending = {}
    for run, command, log, marker in todo:
        pending[remote.remote(command, log, marker, ROOT, run.identity())] = (run, log, time.time())
        tracker.started(run)
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in ready:
                run, log, start = pending.pop(ref)
                try:
                    code = ray.get(ref)
                except Exception as exc:  # the task itself died (node lost, ...)
                    with open(log, "a") as f:
                        f.write(f"\nray task failed: {exc}\n")
                    code = -1
                tracker.finished(run, code, log, time.time() - start)
            tracker.report()
    except KeyboardInterrupt:
        for ref in pending:  # these runs end unfinished (counted as stopped, not failed)
            ray.cancel(ref, force=True)
        raise
    finally:
        ray.shutdown()


def interrupt(signum, frame):
    """Ctrl-C, SIGTERM or SIGHUP: the sweep stops. A repeated one while it stops its runs passes on to them: a SAC or DDPG
    run, which writes a checkpoint at its next step when stopped, then stops at once."""
    if STOP:
        stop_running(hold_lock=False)
        return
    STOP.append(signum)
    raise KeyboardInterrupt


def main() -> None:
    # Ctrl-C and `kill` stop the sweep cleanly, even when started in the background (where SIGINT
    # is inherited as ignored): running runs are stopped, finished ones keep their markers.
    signal.signal(signal.SIGINT, interrupt)
    signal.signal(signal.SIGTERM, interrupt)
    if signal.getsignal(signal.SIGHUP) == signal.SIG_DFL:  # a closed terminal (not under nohup)
        signal.signal(signal.SIGHUP, interrupt)
    try:
        sweep()
    except KeyboardInterrupt:  # stopped before any run started
        signum = STOP[-1] if STOP else signal.SIGINT
        print(f"[sweep] stopped by {signal.Signals(signum).name} before any run started", flush=True)
        sys.exit(128 + signum)


def check_envs(runs: list[Run]) -> None:
    """Each env id made once, up front: an unknown one, or one with discrete actions for a continuous script, is one
    line now instead of a failed run per seed and template later."""
    import gymnasium as gym

    from cascade_plumbing.envs import check_flat_observations, probe_spaces

    warnings.filterwarnings("ignore", message=".*is out of date.*")  # the paper's v4 tasks, as in the scripts

    for env_id in dict.fromkeys(run.env_id for run in runs):
        action_space, observation_space = probe_spaces(env_id)
        check_flat_observations(env_id, observation_space)  # what every script needs
        scripts = sorted({run.script for run in runs
                          if run.env_id == env_id and os.path.normpath(run.script) in CONTINUOUS_SCRIPTS})
        if scripts and not isinstance(action_space, gym.spaces.Box):
            fail(f"--envs {env_id} has a {type(action_space).__name__} action space, and {' and '.join(scripts)} "
                 f"{'needs' if len(scripts) == 1 else 'need'} a Box (continuous) one: drop it from --envs, or sweep "
                 "the discrete scripts on it")


def check_templates(todo: list[tuple[Run, list[str], str, str]]) -> None:
    """Each new run's command line parsed by its script's Args and checked by the script's own input checks (its
    `validate`, or `resolve` in the discrete scripts), once per template and env, before any run starts: a flag
    the script does not have, a value it refuses or a budget too small for it is one line now, instead of one
    failed run per seed and template at the end of the sweep."""
    import importlib
    import io

    # (torch: only when a sweep is run)
    from cascade_plumbing.runs import NEW_RUN_FLAGS, explicit_fields, refuse_idle_flags

    if ROOT not in sys.path:
        sys.path.insert(0, ROOT)
    checked = set()
    for run, command, _, _ in todo:
        if "--resume" in command[2:3] or (run.script, tuple(run.flags), run.env_id) in checked:
            continue  # a started run was checked when it started (and resumes with what it saved)
        checked.add((run.script, tuple(run.flags), run.env_id))
        template = shlex.join([run.script, *run.flags])
        module = importlib.import_module(run.script[: -len(".py")])
        check = getattr(module, "validate", None) or getattr(module, "resolve", None)
        if not hasattr(module, "Args") or check is None:
            fail(f"--command '{template}': {run.script} is not one of the training scripts (it has no Args and "
                 f"input checks); sweep one of them, e.g. {CASCADE}")
        argv = command[2:]  # the new run's command as it will run (tracking flags and cadence included)
        quiet = io.StringIO()
        try:
            with contextlib.redirect_stderr(quiet), contextlib.redirect_stdout(io.StringIO()), unwrapped_errors():
                script_args = tyro.cli(module.Args, args=argv)
        except SystemExit:
            said = quiet.getvalue().strip().splitlines()
            reason = parse_error_line(quiet.getvalue()) or (said[-1] if said else "refused")
            fail(f"'{template}': {run.script} does not accept it: {reason}")
        given = explicit_fields(module.Args, argv)
        try:
            refuse_idle_flags(script_args, given)
            NEW_RUN_FLAGS.update(given)  # (the idle checks that need the env, as run_main sets them)
            with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
                check(script_args)  # (warnings each run prints itself are not repeated here)
        except SystemExit as exc:
            fail(f"'{template}' on {run.env_id}: {str(exc).removeprefix('error: ')}")
        finally:
            NEW_RUN_FLAGS.clear()


def refuse_repeated_list_flags(argv: list[str]) -> None:
    """A list flag given twice (`--seeds 1 --seeds 2`) keeps only its last values in tyro: a grid silently smaller
    than the one asked for. Refused in one line; the values go after one flag."""
    for name in ("preset", "command", "envs", "seeds"):
        given = [token for token in argv if token.split("=")[0] == f"--{name}"]
        if len(given) > 1:
            example = "'cascade_sac.py --n 2' 'cascade_ddpg.py'" if name == "command" else "a b"
            fail(f"--{name} is given {len(given)} times, and only its last values would count; give all its values "
                 f"after one --{name}, e.g. --{name} {example}")


def refuse_idle_sweep_flags(args: Args, argv: list[str]) -> None:
    """A flag given that this sweep cannot act on is refused in one line (as the scripts refuse theirs): the user
    meant something the sweep would not do."""
    given = {token[2:].split("=")[0].replace("-", "_") for token in argv if token.startswith("--")}
    rules = [(name, "applies with --track only", "add --track")
             for name in ("wandb_project_name", "wandb_entity", "wandb_group") if not args.track]
    if args.backend == "local":
        rules += [(name, "applies to --backend ray only", "add --backend ray")
                  for name in ("ray_address", "cpus_per_run")]
    else:
        rules += [("workers", "applies to --backend local only (Ray places runs by --cpus-per-run)",
                   "use --cpus-per-run")]
    for name, why, instead in rules:
        if name in given:
            fail(f"--{name.replace('_', '-')} {getattr(args, name)} {why}; {instead}, or leave it out")


def sweep() -> None:
    args = parse_command_line(lambda: tyro.cli(Args, description=__doc__.split("\n\n")[0]))
    refuse_repeated_list_flags(sys.argv[1:])
    if args.sweep_dir is not None and not args.sweep_dir.strip():  # (`--sweep-dir "$DIR"` with DIR unset)
        fail("--sweep-dir is empty; pass a folder, or leave it out for sweeps/<presets>")
    if args.workers < 1:
        fail(f"--workers must be at least 1 (got {args.workers})")
    if not args.status_every > 0:
        fail(f"--status-every must be a positive number of seconds (got {args.status_every})")
    if args.backend == "ray" and not args.cpus_per_run >= 0:
        fail(f"--cpus-per-run must be >= 0 (got {args.cpus_per_run})")
    refuse_idle_sweep_flags(args, sys.argv[1:])
    if args.list_presets:
        for name, (what, entries) in PRESETS.items():
            print(f"{name:14s} {what} ({len(entries)} runs per env and seed)")
        return
    runs = expand(args)
    check_envs(runs)
    sweep_dir = args.sweep_dir or os.path.join("sweeps", "_".join(args.preset) or "custom")
    sweep_dir = os.path.abspath(sweep_dir)
    existing = sweep_dir  # its nearest existing ancestor must be a folder
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        fail(f"--sweep-dir {args.sweep_dir}: {existing} is a file, not a folder; pass a folder for the sweep")
    try:  # (else each run's own check named a --track-dir the user never gave; as that check, also with --dry-run)
        os.rmdir(tempfile.mkdtemp(dir=existing))
    except OSError as exc:
        fail(f"--sweep-dir {sweep_dir} cannot be made or written ({exc.strerror or exc} in {existing}); pass a "
             "writable folder for the sweep")
    if args.backend == "local" and shutil.which(args.python) is None:  # (on Ray it must exist on the nodes)
        fail(f"--python {args.python} is not an executable (a path, or a name on PATH); pass the interpreter the runs "
             "use (default: this one)")
    if args.backend == "local" and os.path.abspath(shutil.which(args.python) or "") != os.path.abspath(sys.executable):
        # another interpreter: it must import what the scripts need (a fault hunt: --python /bin/false ran, and each
        # run failed at the end with "exit 1" and no word of the interpreter)
        try:
            probe = subprocess.run([args.python, "-c", "import torch, gymnasium, tyro"], capture_output=True, text=True,
                                   timeout=300)
            problem = None if probe.returncode == 0 else ((probe.stderr.strip().splitlines() or [f"exit {probe.returncode}"])[-1])
        except (OSError, subprocess.TimeoutExpired) as exc:
            problem = str(exc)
        if problem:
            fail(f"--python {args.python} cannot run the scripts (importing torch, gymnasium and tyro: {problem[:200]}); "
                 "pass the interpreter of the environment the requirements are installed in (default: this one)")
    track_dir = os.path.join(sweep_dir, "runs")
    tracking = tracking_flags(args, sweep_dir)
    todo, skipped = [], 0
    runs = [run.as_in(sweep_dir) for run in runs]
    for run in runs:
        marker = os.path.join(sweep_dir, "done", f"{run.run_id}.json")
        if os.path.exists(marker):
            skipped += 1
            continue
        todo.append((run, run.command(args.python, track_dir, tracking),
                     os.path.join(sweep_dir, "logs", f"{run.run_id}.log"), marker))
    check_templates(todo)
    if args.dry_run:
        for run, command, _, _ in todo:
            print(f"# {run.run_id}: {how_far(command)}")
            print(shlex.join(command))
        print(f"# {len(todo)} runs to do, {skipped} already finished, in {sweep_dir}")
        return
    missing = sorted({run.script for run, *_ in todo if not os.path.isfile(os.path.join(ROOT, run.script))})
    if missing:
        fail(f"script(s) not found in {ROOT}: {', '.join(missing)}")
    if args.track and todo:
        check_wandb()  # what every run checks at its start, once here: one line, not a failed sweep
    LOCK_FD[:] = [lock_sweep_dir(sweep_dir)]  # before the folder is changed: no other sweep is using it
    removed = sum(remove_unresumable(os.path.join(track_dir, run.run_id)) for run, *_ in todo)
    print(f"[sweep] {len(runs)} runs in {sweep_dir}: {skipped} already finished, {len(todo)} to run "
          f"({args.backend} backend)" + (f"; removed {removed} run folder(s) without a checkpoint, left by runs "
                                         "killed before their first one" if removed else ""), flush=True)
    parallel = args.workers if args.backend == "local" else len(todo)
    # Ray schedules the tasks itself: submitted ones are running or waiting for a free CPU
    tracker = Tracker(len(todo), parallel, args.status_every,
                      "running" if args.backend == "local" else "running or queued on the cluster")
    tracker.runs_dir = track_dir
    try:
        if args.backend == "local":
            run_local(todo, args.workers, tracker)
        else:
            run_ray(todo, args, tracker)
    except KeyboardInterrupt:
        pass
    # the work is over: a stop from here on changes nothing (the summary is printed in full)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if signal.getsignal(signal.SIGHUP) is interrupt:
        signal.signal(signal.SIGHUP, signal.SIG_IGN)
    stopped = tracker.stopped + list(tracker.active.values())  # Ray: tasks cancelled while running or queued
    not_started = len(todo) - tracker.done - len(tracker.failed) - len(stopped)
    if STOP and (stopped or not_started):
        print(stop_line(STOP[-1], stopped, not_started, tracker, args.python, track_dir), flush=True)
        sys.exit(128 + STOP[-1])
    print(f"[sweep] finished: {tracker.done + skipped} of {len(runs)} runs done ({skipped} skipped), "
          f"{len(tracker.failed)} failed", flush=True)
    for run, log, code in tracker.failed:
        print(f"  FAILED {run.run_id} (exit {code}): {last_line(log)}; log: {log}")
    if tracker.failed:
        sys.exit(1)


def last_line(log: str) -> str:
    """The last non-empty line of a run's log: the one-line error a script stops with (shortened)."""
    try:
        with open(log, "rb") as f:
            f.seek(max(os.path.getsize(log) - 4096, 0))
            lines = [line.rstrip() for line in f.read().decode(errors="replace").splitlines() if line.strip()]
    except OSError:
        return "(no log)"
    # a parse error: why, not its box (read with the lines' indentation, which tells a flag from its help)
    line = parse_error_line("\n".join(lines)) or (lines[-1].strip() if lines else "(empty log)")
    return line if len(line) <= 300 else line[:297] + "..."


def stop_line(signum: int, stopped: list[Run], not_started: int, tracker: Tracker, python: str, track_dir: str) -> str:
    """The one line of a stopped sweep: which runs it stopped and where each continues on the next call."""
    where = []
    for run in stopped:
        command = run.command(python, track_dir)
        if "--resume" in command:
            where.append(f"{run.run_id} (resumes from {command[command.index('--resume') + 1]})")
        else:
            where.append(f"{run.run_id} (starts over: no checkpoint yet)")
    parts = [f"stopped {len(stopped)} run(s): {', '.join(where)}" if stopped else "stopped no run"]
    if not_started:
        parts.append(f"{not_started} not started")
    parts.append(f"{tracker.done} done, {len(tracker.failed)} failed")
    return (f"[sweep] stopped by {signal.Signals(signum).name}: {'; '.join(parts)}; the same command continues "
            "the unfinished runs")


def lock_sweep_dir(sweep_dir: str) -> int:
    """An exclusive lock on `<sweep_dir>/sweep.lock` (flock; the file holds the sweep's pid), held until this sweep
    and the runs it started have all ended (each run inherits the descriptor): a second sweep on the same folder
    would remove a live run's folder or train the same run twice. Returns the descriptor; refused in one line."""
    os.makedirs(sweep_dir, exist_ok=True)
    path = os.path.join(sweep_dir, "sweep.lock")
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.read(fd, 64).decode(errors="replace").strip()
        os.close(fd)
        if holder.isdigit() and alive(int(holder)):
            fail(f"another sweep (pid {holder}) is using {sweep_dir}; wait for it to end, or stop it (kill {holder}) "
                 "and run this again")
        fail(f"the runs of an ended sweep{f' (pid {holder})' if holder else ''} are still stopping in {sweep_dir}; "
             "run this again once they have ended")
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def how_far(command: list[str]) -> str:
    """For --dry-run: how far the run of `command` is. A new run (or one training now towards its first
    checkpoint); a run training now (its run folder locked by another process), with the progress line it keeps;
    or where a stopped run resumes (its checkpoint's step)."""
    if "--resume" not in command:
        track_dir = command[command.index("--track-dir") + 1] if "--track-dir" in command else None
        for run_dir in sorted(glob.glob(os.path.join(glob.escape(track_dir), "*__*__*__*"))) if track_dir else ():
            holder = lock_holder(run_dir)
            if holder is not None:
                return training_now(run_dir, holder) or f"training now (pid {holder}), before its first checkpoint"
        return "new run"
    run_dir = command[command.index("--resume") + 1]
    holder = lock_holder(run_dir)
    line = holder and training_now(run_dir, holder)
    if line:
        return line
    import torch  # (only here: a dry run of new runs needs none)

    path = os.path.join(run_dir, "checkpoint.pt")
    if not os.path.exists(path):
        return (f"cannot resume {run_dir} by itself: its checkpoint.pt is gone; the run will stop naming the "
                "iteration_<i>.pt beside it to continue from")
    try:
        saved = torch.load(path, map_location="cpu", weights_only=False)
        step, saved_args = saved["global_step"], saved["args"]
    except Exception:  # noqa: BLE001 - the run itself says what is wrong with its checkpoint when it resumes
        return f"resumes from {run_dir} (its checkpoint cannot be read here; the run will say why)"
    total = saved_args.get("total_timesteps") or saved_args.get("n", 0) * saved_args.get("k", 0)
    when = time.strftime("%Y-%m-%d %H:%M", time.localtime(os.path.getmtime(path)))
    at = f"global_step {step:,}{f' of {total:,}' if total else ''} (its checkpoint of {when})"
    return f"training now (pid {holder}); its last checkpoint is at {at}" if holder else f"stopped; resumes at {at}"


def lock_holder(run_dir: str) -> str | None:
    """The pid (as its run.lock says it) of the process training in `run_dir` now, or None where none is."""
    with contextlib.suppress(OSError):
        fd = os.open(os.path.join(run_dir, "run.lock"), os.O_RDWR)
        try:
            fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # (released with the close below: nothing is held)
        except OSError:
            return os.read(fd, 64).decode(errors="replace").strip() or "?"
        finally:
            os.close(fd)
    return None


def training_now(run_dir: str, holder: str) -> str | None:
    """A run training now, with the progress line it keeps in its folder (None for a run that keeps none)."""
    with contextlib.suppress(OSError), open(os.path.join(run_dir, PROGRESS_NAME)) as f:
        return f"training now (pid {holder}): {f.readline().strip()}"
    return None


def remove_unresumable(track_dir: str) -> int:
    """Remove the run folders in a setup's folder that hold no checkpoint (a run killed before its first one):
    a new start makes its own, and plots would read their partial logs. Returns how many were removed."""
    removed = 0
    for folder in glob.glob(os.path.join(glob.escape(track_dir), "*__*__*__*")):
        if os.path.isdir(folder) and folder.rsplit("__", 1)[1].isdigit() and \
                not glob.glob(os.path.join(glob.escape(folder), "*.pt")):
            shutil.rmtree(folder, ignore_errors=True)
            removed += 1
    return removed


if __name__ == "__main__":
    main()
