"""Shared plumbing of the plot scripts: find run folders, read their TensorBoard logs, group them over seeds.

A run folder is `<env_id>__<exp_name>__<seed>__<timestamp>` (what every training script of this
repository writes) holding TensorBoard event files. Runs are grouped by (env, experiment): each
figure draws one panel per env and one curve per experiment, averaged over the experiment's seeds.
Everything that goes wrong (no matching runs, a missing scalar, a run whose folder name and logged
settings disagree) stops with a one-line `error: ...` naming what was looked for and what was found.
"""

from __future__ import annotations

import csv
import difflib
import math
import os
import re
import sys
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, NoReturn

import numpy as np

RUN_NAME = re.compile(r"^(?P<env>.+?)__(?P<exp>.+)__(?P<seed>-?\d+)__(?P<time>\d+)$")
HPARAMS_TAG = "hyperparameters/text_summary"

# Okabe & Ito's colourblind-safe palette (yellow last: it is hard to see on white).
OKABE_ITO = ["#0072B2", "#D55E00", "#009E73", "#E69F00", "#56B4E9", "#CC79A7", "#000000", "#F0E442"]

DEFAULT_LABELS = {
    "cascade_ppo_continuous": "Cascade",
    "ppo_baseline": "PPO",
    "cascade_ppo_discrete": "Cascade (discrete)",
    "ppo_baseline_discrete": "PPO (discrete)",
}

# Settings that do not change what a run learns: runs differing only in these are the same experiment.
NOT_SETTINGS = {
    "seed", "exp_name", "track_dir", "quiet", "torch_threads", "torch_deterministic", "cuda", "resume",
    "evaluate", "deterministic", "members", "capture_video", "checkpoint_every", "eval_in_worker",
    "track", "wandb_project_name", "wandb_entity", "wandb_group",
}


def fail(message: str) -> NoReturn:
    """Stop with a one-line error and a non-zero exit code."""
    raise SystemExit(f"error: {message}")


def note(message: str) -> None:
    """A one-line remark on stderr that does not stop the script."""
    print(f"note: {message}", file=sys.stderr)


def nearest_first(name: str, names: Sequence[str]) -> list[str]:
    """`names` with the ones most like `name` (difflib's close matches, then the same `prefix/`) first."""
    close = difflib.get_close_matches(name, names, n=3, cutoff=0.6)
    prefix = name.split("/")[0] + "/"
    return close + [n for n in names if n.startswith(prefix) and n not in close] + \
        [n for n in names if not n.startswith(prefix) and n not in close]


def short_list(items: Iterable[str], limit: int = 12) -> str:
    items = list(items)
    more = f", … ({len(items) - limit} more)" if len(items) > limit else ""
    return ", ".join(items[:limit]) + more if items else "nothing"


# ----------------------------------------------------------------------------------------------
# Reading runs
# ----------------------------------------------------------------------------------------------
@dataclass
class Series:
    """One logged scalar of one run, in the order it was logged."""

    steps: np.ndarray
    values: np.ndarray
    wall_times: np.ndarray

    def by_step(self) -> dict[int, float]:
        """step -> value; a step logged twice keeps its last value."""
        return {int(s): float(v) for s, v in zip(self.steps, self.values)}

    def last(self, window: int = 1) -> float:
        """Mean of the last `window` values (one per step)."""
        values = list(self.by_step().values())
        return float(np.mean(values[-window:]))


@dataclass
class Run:
    """One run folder: its name parts, its logged hyperparameters and its scalars."""

    path: str
    env_id: str
    exp_name: str
    seed: int
    timestamp: int
    hparams: dict[str, str] = field(default_factory=dict)
    scalars: dict[str, Series] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)  # of an exported run (results/): command, commit, seconds

    @property
    def name(self) -> str:
        name = os.path.basename(self.path)
        return name[: -len(".json")] if name.endswith(".json") else name

    def series(self, tag: str) -> Series:
        if tag not in self.scalars:
            fail(f"run {self.path} does not log '{tag}' (it logs: {short_list(nearest_first(tag, sorted(self.scalars)))})")
        return self.scalars[tag]

    def last_step(self) -> int:
        return max((int(s.steps.max()) for s in self.scalars.values() if len(s.steps)), default=0)


def parse_run_name(name: str) -> tuple[str, str, int, int] | None:
    """(env_id, exp_name, seed, timestamp) of a run folder name (or of an exported run file's path: its
    `.json` and folders are ignored), or None if it is not one."""
    name = os.path.basename(name)
    name = name[: -len(".json")] if name.endswith(".json") else name
    match = RUN_NAME.match(name)
    if match is None:
        return None
    return match["env"], match["exp"], int(match["seed"]), int(match["time"])


def has_event_files(folder: str) -> bool:
    return any(f.startswith("events.out.tfevents") for f in os.listdir(folder))


def find_run_dirs(roots: Sequence[str]) -> list[str]:
    """Every folder under `roots` (at any depth) that is named like a run and holds event files, and every
    exported run `<run_name>.json` (plots/export_results.py; the committed results/per_run/)."""
    found = []
    for root in roots:
        if os.path.isfile(root):  # one exported run file is that run; another file is no runs folder
            if root.endswith(".json") and parse_run_name(os.path.basename(root)[:-5]):
                found.append(root)
                continue
            fail(f"--runs '{root}' is a file, not a runs folder; pass the folder that holds the run folders or the "
                 "exported run files (<run_name>.json)")
        if not os.path.isdir(root):
            fail(f"runs folder '{root}' does not exist")
        # normpath: a run folder given with a trailing slash would otherwise have an empty basename
        for folder, _dirs, files in os.walk(os.path.normpath(root)):
            if parse_run_name(os.path.basename(folder)) and has_event_files(folder):
                found.append(folder)
            if os.path.basename(folder) == "done" and os.path.isdir(os.path.join(os.path.dirname(folder), "runs")):
                continue  # sweep.py's completion markers, <run_id>.json: named like a run when the hash is all digits
            found += [os.path.join(folder, f) for f in files if f.endswith(".json") and parse_run_name(f[:-5])]
    return sorted(found)


def read_exported_run(path: str) -> Run:
    """A run exported by plots/export_results.py: its scalars, settings and metadata."""
    import json

    try:
        with open(path) as f:
            data = json.load(f)
        env_id, exp_name, seed, timestamp = parse_run_name(path)
        run = Run(path, env_id, exp_name, seed, timestamp, hparams=data["hparams"])
        for tag, series in data["scalars"].items():
            run.scalars[tag] = Series(np.array(series["steps"], dtype=np.int64),
                                      np.array(series["values"], dtype=np.float64),
                                      np.array(series["wall_times"], dtype=np.float64))
            if not len(run.scalars[tag].steps) == len(run.scalars[tag].values) == len(run.scalars[tag].wall_times):
                raise ValueError(f"{tag} holds {len(series['steps'])} steps and {len(series['values'])} values")
            if tag == "eval/episodic_return" and not len(series["steps"]):  # (export writes evaluated runs only)
                raise ValueError(f"{tag} is empty")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        fail(f"cannot read exported run {path} ({type(exc).__name__}: {exc}); re-export it with plots/export_results.py")
    run.meta = {key: data.get(key) for key in ("command", "commit", "seconds", "final_step")}
    # as for a run folder, the file name decides the panel, the curve and the seed: a copied or renamed file (a
    # Walker2d run under Hopper's name, one seed saved as two) is refused, not averaged in (a results-pipeline hunt)
    name = os.path.basename(path)[: -len(".json")]
    if data.get("name", name) != name:
        fail(f"exported run {path} holds the run {data['name']}: a renamed or copied file would count a run under "
             "another name; re-export the run, or give the file its own name back")
    check_name_against_settings(run, "exported run")
    return run


def check_name_against_settings(run: Run, what: str) -> None:
    """The env, experiment and seed a run's name gives are those it logged (one line if not)."""
    for key, from_name in (("env_id", run.env_id), ("exp_name", run.exp_name), ("seed", str(run.seed))):
        logged = run.hparams.get(key)
        if logged is not None and logged != from_name:
            fail(f"{what} {run.path} is named for {key}={from_name} but the run logged {key}={logged}; "
                 "a renamed or copied run would mix runs of different settings into one panel: give it its own name back")


def parse_hparams(text: str) -> dict[str, str]:
    """The `|param|value|` Markdown table the training scripts log as text."""
    hparams = {}
    for line in text.splitlines():
        cells = line.strip().strip("|").split("|")
        if len(cells) == 2 and cells[0] not in ("param", "-"):
            hparams[cells[0]] = cells[1]
    return hparams


def read_run(path: str) -> Run:
    """Every scalar and the hyperparameter table of one run folder (resumed runs: TensorBoard's purge applies),
    or of an exported run file."""
    if path.endswith(".json"):
        return read_exported_run(path)
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    env_id, exp_name, seed, timestamp = parse_run_name(os.path.basename(path))
    acc = EventAccumulator(path, size_guidance={"scalars": 0, "tensors": 0})
    acc.Reload()
    tags = acc.Tags()
    run = Run(path, env_id, exp_name, seed, timestamp)
    for tag in tags.get("scalars", []):
        events = acc.Scalars(tag)
        run.scalars[tag] = Series(np.array([e.step for e in events], dtype=np.int64),
                                  np.array([e.value for e in events], dtype=np.float64),
                                  np.array([e.wall_time for e in events], dtype=np.float64))
    if HPARAMS_TAG in tags.get("tensors", []):
        text = acc.Tensors(HPARAMS_TAG)[0].tensor_proto.string_val[0].decode()
        run.hparams = parse_hparams(text)
    # the folder name decides the panel and the curve: it must agree with what the run logged
    check_name_against_settings(run, "run folder")
    return run


# ----------------------------------------------------------------------------------------------
# Selecting and grouping runs
# ----------------------------------------------------------------------------------------------
def parse_cli(args_type: type, description: str) -> Any:
    """A tool's command line, parsed (tyro) and checked before anything is read or written (`check_cli`)."""
    import tyro

    from cascade_plumbing.errors import parse_command_line

    args = parse_command_line(lambda: tyro.cli(args_type, description=description))
    check_cli(args)
    return args


def check_cli(args: Any) -> None:
    """What a command line names, in one line each: --out must be a folder that can be made and written, --name a
    file name, and each env, experiment and label experiment named must have runs. A typo in one of several names
    would otherwise leave it out of the figure silently. (`plots/reproduce.py`, which draws whatever runs are
    there, passes its names to the tools directly.)"""
    out = getattr(args, "out", None)
    if isinstance(out, str):
        existing = os.path.abspath(out)
        while not os.path.exists(existing):
            existing = os.path.dirname(existing)
        if not os.path.isdir(existing):
            fail(f"--out {out}: {existing} is a file, not a folder; pass a folder for the output")
        try:  # a real probe, nothing left behind: os.access says yes to root on a read-only or virtual file system
            os.rmdir(tempfile.mkdtemp(dir=existing))
        except OSError as exc:
            fail(f"--out {out}: {existing} cannot be written ({exc.strerror or exc}); pass a folder you can write to")
    name = getattr(args, "name", None)
    if isinstance(name, str) and (not name.strip() or "/" in name or os.sep in name):
        fail(f"--name {name!r}: give a file name without a folder (the files go to --out)")
    columns = getattr(args, "columns", None)
    if isinstance(columns, int) and columns < 1:
        fail(f"--columns must be at least 1 (got {columns})")
    baseline = getattr(args, "baseline", None)
    asked_baseline = baseline if baseline != getattr(type(args), "baseline", None) else None  # named, not the default
    runs = getattr(args, "runs", None)
    asked = {"--envs": tuple(getattr(args, "envs", ()) or ()), "--experiments": tuple(getattr(args, "experiments", ()) or ()),
             "--labels": tuple(label.split("=", 1)[0] for label in getattr(args, "labels", ()) or () if "=" in label)}
    if runs is None or not (any(asked.values()) or asked_baseline):
        return
    found = [parse_run_name(d) for d in find_run_dirs([runs] if isinstance(runs, str) else runs)]
    if not found:
        return  # select_runs says so, with what it looked for
    present = {"--envs": sorted({f[0] for f in found}), "--experiments": sorted({f[1] for f in found})}
    present["--labels"] = present["--experiments"]
    labels = parse_labels(getattr(args, "labels", ()) or ())  # (the default display names included)
    if asked_baseline and asked_baseline not in present["--experiments"] + [labels.get(e, e) for e in present["--experiments"]]:
        fail(f"--baseline {asked_baseline}: no runs of that experiment or label under {runs if isinstance(runs, str) else short_list(runs)} "
             f"(there are: {short_list(nearest_first(asked_baseline, present['--experiments']))}); fix the name")
    for flag, names in asked.items():
        for name in names:
            if name not in present[flag]:
                kind = "env" if flag == "--envs" else "experiment"
                fail(f"{flag} {name}: no runs of that {kind} under {short_list(runs) if not isinstance(runs, str) else runs} "
                     f"(there are: {short_list(nearest_first(name, present[flag]))}); fix or drop the name")


def parse_labels(labels: Sequence[str]) -> dict[str, str]:
    """`EXP=LABEL` pairs on top of the default display names."""
    mapping = dict(DEFAULT_LABELS)
    for item in labels:
        if "=" not in item:
            fail(f"--labels takes EXP=LABEL pairs (got '{item}')")
        exp, label = item.split("=", 1)
        mapping[exp] = label
    return mapping


def describe(runs: Sequence[Run]) -> str:
    """`Hopper-v4/ppo_baseline (2 seeds), ...` for error messages."""
    counts: dict[str, int] = {}
    for run in runs:
        key = f"{run.env_id}/{run.exp_name}"
        counts[key] = counts.get(key, 0) + 1
    return short_list(f"{key} ({n} run{'s' if n > 1 else ''})" for key, n in sorted(counts.items()))


def evaluation_protocol(runs: Sequence[Run]) -> str:
    """How the runs were evaluated, from their logged settings: `every 50k steps, 10 episodes each`."""
    every = sorted({r.hparams.get("eval_every", "?") for r in runs})
    episodes = sorted({r.hparams.get("eval_episodes", "?") for r in runs})
    steps = " / ".join(format_steps(int(e)) if e.isdigit() else e for e in every)
    return f"every {steps} steps, {' / '.join(episodes)} episodes each" + (" (the runs differ)" if
                                                                           len(every) > 1 or len(episodes) > 1 else "")


def final_score(run: Run, tag: str, window: int) -> float:
    """A run's final score: the mean of its last `window` values of `tag`. A run with fewer values is an error (the
    mean of a whole run is no final score)."""
    series = run.series(tag)
    logged = len(series.by_step())
    if logged < window:
        fail(f"--final-window {window}: {run.name} logs only {logged} value{'s' if logged != 1 else ''} of '{tag}'; "
             f"pass at most {logged}")
    return series.last(window)


def group_label(run: Run, labels: dict[str, str], split_by: Sequence[str]) -> str:
    label = labels.get(run.exp_name, run.exp_name)
    extra = [f"{key}={run.hparams[key]}" for key in split_by if key in run.hparams]
    return f"{label} ({', '.join(extra)})" if extra else label


@dataclass
class Selection:
    """The runs a figure draws, grouped by (env, experiment label), each group's runs sorted by seed."""

    groups: dict[tuple[str, str], list[Run]]
    envs: list[str]
    labels: list[str]  # experiment labels in display order (their colours follow this order)

    def color(self, label: str) -> str:
        return OKABE_ITO[self.labels.index(label) % len(OKABE_ITO)]

    def in_env(self, env: str) -> list[tuple[str, list[Run]]]:
        return [(label, runs) for (e, label), runs in self.groups.items() if e == env]


def select_runs(
    roots: Sequence[str],
    envs: Sequence[str] = (),
    experiments: Sequence[str] = (),
    split_by: Sequence[str] = (),
    labels: Sequence[str] = (),
    tags: Sequence[str] = (),
    complete_only: bool = False,
) -> Selection:
    """Read the runs of `experiments` on `envs` (empty: all found) that log every one of `tags`.

    Experiments named explicitly must log the tags (or it is an error); otherwise runs that do not
    log them are left out with a note (e.g. baseline runs in a fallback figure).
    """
    names = {exp for exp in experiments}
    label_map = parse_labels(labels)
    all_dirs = find_run_dirs(roots)
    where = ", ".join(roots)
    if not all_dirs:
        fail(f"no run folders (named <env_id>__<exp_name>__<seed>__<timestamp>, holding TensorBoard event files) "
             f"under {where}")
    found = [parse_run_name(d) for d in all_dirs]
    chosen = [d for d, (env, exp, _, _) in zip(all_dirs, found)
              if (not envs or env in envs) and (not names or exp in names)]
    if not chosen:
        listed = describe([Run(d, env, exp, seed, ts) for d, (env, exp, seed, ts) in zip(all_dirs, found)])
        wanted = f"experiment(s) {short_list(experiments) if experiments else '(any)'} on env(s) " \
                 f"{short_list(envs) if envs else '(any)'}"
        fail(f"no runs of {wanted} under {where} (found: {listed})")
    runs = [read_run(d) for d in chosen]
    damaged = [r for r in runs if not any(len(series.steps) for series in r.scalars.values())]
    for r in damaged:
        note(f"left out {r.path}: it holds no scalars (an empty or damaged event file)")
    runs = [r for r in runs if r not in damaged]
    if not runs:
        fail(f"every run found under {where} is empty or damaged")

    for tag in tags:
        missing = [r for r in runs if tag not in r.scalars]
        if not missing:
            continue
        if len(missing) == len(runs):
            logged = sorted({t for r in runs for t in r.scalars})
            fail(f"no run logs '{tag}' (looked in {describe(runs)} under {where}; they log: "
                 f"{short_list(nearest_first(tag, logged))})")
        explicit = [r for r in missing if r.exp_name in names]
        if explicit:
            r = explicit[0]
            fail(f"run {r.path} of experiment {r.exp_name} does not log '{tag}' "
                 f"(it logs: {short_list(nearest_first(tag, sorted(r.scalars)))})")
        note(f"left out {describe(missing)}: no '{tag}' logged")
        runs = [r for r in runs if tag in r.scalars]

    # a setting no run records would split nothing, silently (a typo): refused; tyro's dashed spelling is accepted
    split_by = [key.replace("-", "_") for key in split_by]
    recorded = sorted({key for run in runs for key in run.hparams})
    for key in split_by:
        if key not in recorded:
            fail(f"--split-by {key}: no run records that setting (they record: "
                 f"{short_list(nearest_first(key, recorded))}); fix the name")
    groups: dict[tuple[str, str], list[Run]] = {}
    for run in runs:
        groups.setdefault((run.env_id, group_label(run, label_map, split_by)), []).append(run)
    for key, members in groups.items():
        groups[key] = drop_duplicate_seeds(sorted(members, key=lambda r: (r.seed, r.timestamp)))
        warn_if_settings_differ(key, groups[key], split_by)
        groups[key] = check_complete(key, groups[key], complete_only)
    groups = {key: members for key, members in groups.items() if members}

    env_order = [e for e in envs if any(k[0] == e for k in groups)] or sorted({k[0] for k in groups})
    # default order (and so colours): Cascade, PPO, then the rest alphabetically
    known = list(DEFAULT_LABELS)
    exp_order = list(experiments) or sorted({r.exp_name for r in runs},
                                            key=lambda e: (known.index(e) if e in known else len(known), e))
    label_order = sorted({k[1] for k in groups},
                         key=lambda lab: (min(exp_order.index(r.exp_name) for k, rs in groups.items()
                                              if k[1] == lab for r in rs), lab))
    ordered = {(e, lab): groups[(e, lab)] for e in env_order for lab in label_order if (e, lab) in groups}
    return Selection(ordered, env_order, label_order)


def check_complete(key: tuple[str, str], runs: list[Run], complete_only: bool) -> list[Run]:
    """Name every run that stops before the others of its (env, experiment), with the step it stops at (an
    unfinished run, or a damaged event file); with `complete_only` (final scores) leave it out."""
    last = max(r.last_step() for r in runs)
    for r in runs:
        if r.last_step() < last:
            what = "left out of the final scores" if complete_only else "kept (its curve ends early)"
            hint = " (--allow-incomplete keeps it)" if complete_only else ""
            note(f"{r.path} stops at step {r.last_step():,} while other runs of {key[0]}/{key[1]} reach "
                 f"{last:,} (unfinished or a damaged event file): {what}{hint}")
    return [r for r in runs if r.last_step() == last] if complete_only else runs


def drop_duplicate_seeds(runs: list[Run]) -> list[Run]:
    """Two runs of the same seed (a relaunch) would count one seed twice: keep the longer (then newer) one."""
    by_seed: dict[int, Run] = {}
    for run in runs:
        kept = by_seed.get(run.seed)
        if kept is None:
            by_seed[run.seed] = run
            continue
        if (run.last_step(), run.timestamp) > (kept.last_step(), kept.timestamp):
            by_seed[run.seed], kept, run = run, run, kept  # keep the new one, drop the old
        differ = sorted(k for k in set(kept.hparams) | set(run.hparams)
                        if k not in NOT_SETTINGS and kept.hparams.get(k) != run.hparams.get(k))
        why = f"; they differ in {', '.join(differ)}: give them different --exp-name" if differ else ""
        note(f"two runs of {run.env_id}/{run.exp_name} seed {run.seed}: using {kept.name}, not {run.name}{why}")
    return [by_seed[s] for s in sorted(by_seed)]


def warn_if_settings_differ(key: tuple[str, str], runs: list[Run], split_by: Sequence[str]) -> None:
    keys = sorted({k for r in runs for k in r.hparams} - NOT_SETTINGS)
    for name in keys:
        values = sorted({r.hparams.get(name, "(unset)") for r in runs})
        if len(values) > 1:
            note(f"runs of {key[0]}/{key[1]} differ in {name} ({', '.join(values)}) and are averaged together; "
                 f"give them different --exp-name or pass --split-by {name}")


# ----------------------------------------------------------------------------------------------
# Statistics over seeds
# ----------------------------------------------------------------------------------------------
def stack_seeds(runs: Sequence[Run], tag: str, curve: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Steps logged by every run and the values there: steps [T], values [runs, T].

    Steps that only some runs reached (a run still going or killed) are left out, with a note. For a `curve`, a
    group whose runs share at most one step (while some log more) is an error naming the short run: its line would
    be drawn empty.
    """
    per_run = [r.series(tag).by_step() for r in runs]
    common = sorted(set.intersection(*(set(p) for p in per_run)))
    if curve and len(common) < 2 and max(len(p) for p in per_run) >= 2:
        shortest = min(zip(runs, per_run), key=lambda rp: (len(rp[1]), max(rp[1], default=-1)))
        reach = f"stops at step {max(shortest[1]):,}" if shortest[1] else "logs none"
        shared = f"only step {common[0]:,}" if common else "no step"
        fail(f"the runs {short_list(r.name for r in runs)} share {shared} of '{tag}' ({shortest[0].name} {reach}; "
             "or do they log it at different steps?): leave the short run out of --runs, or tell the runs apart "
             "with --split-by / --exp-name")
    for run, p in zip(runs, per_run):
        extra = len(p) - len(common)
        if extra:
            note(f"{run.name}: {extra} step(s) of '{tag}' not logged by every seed of its group are left out "
                 f"(the curve ends at step {common[-1] if common else 0})")
    values = np.array([[p[s] for s in common] for p in per_run], dtype=np.float64).reshape(len(runs), len(common))
    return np.array(common, dtype=np.int64), values


def mean_sem(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard error (std with ddof=1 over sqrt(n)) over axis 0; the error is 0 for one seed."""
    mean = values.mean(0)
    if values.shape[0] < 2:
        return mean, np.zeros_like(mean)
    return mean, values.std(0, ddof=1) / math.sqrt(values.shape[0])


def net_added_steps(run: Run) -> list[int]:
    """Steps where `cascade/size` grew, i.e. where a base net was added (not the bottom net at step 0)."""
    if "cascade/size" not in run.scalars:
        return []
    series = run.scalars["cascade/size"]
    grew = np.flatnonzero(np.diff(series.values) > 0) + 1
    return [int(series.steps[i]) for i in grew]


def fallback_nets(runs: Sequence[Run], prefix: str = "cascade/fallback/net_") -> list[int]:
    """The net indices i for which some run logs `<prefix>i`, sorted."""
    return sorted({int(t[len(prefix):]) for r in runs for t in r.scalars if t.startswith(prefix)})


def fmt(mean: float, sem: float | None, digits: int) -> str:
    """`0.96 ± 0.01` (just `0.96` for one seed)."""
    if mean is None or (isinstance(mean, float) and math.isnan(mean)):
        return "–"
    return f"{mean:.{digits}f}" if sem is None else f"{mean:.{digits}f} ± {sem:.{digits}f}"


# ----------------------------------------------------------------------------------------------
# Figures and tables
# ----------------------------------------------------------------------------------------------
def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed), with readable defaults."""
    os.environ.pop("MPLBACKEND", None)  # (the backend is Agg whatever it names; a bad name failed the import)
    try:
        import matplotlib
    except ImportError:
        fail("matplotlib is not installed; install the project's requirements: pip install -r requirements.txt")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({
        "font.size": 10, "axes.titlesize": 11, "axes.labelsize": 10, "legend.fontsize": 9,
        "axes.spines.top": False, "axes.spines.right": False, "axes.grid": True, "grid.alpha": 0.25,
        "pdf.fonttype": 42, "savefig.dpi": 150,
    })
    return plt


def format_steps(x: float, _pos: int | None = None) -> str:
    """Tick labels for env steps: 0, 500k, 1M, 1.5M."""
    if abs(x) >= 1e6:
        return f"{x / 1e6:g}M"
    if abs(x) >= 1e3:
        return f"{x / 1e3:g}k"
    return f"{x:g}"


def panels(plt, count: int, columns: int = 3, width: float = 4.2, height: float = 3.2, sharex: bool = False):
    """A figure with `count` panels in up to `columns` columns; returns (figure, flat list of the used axes)."""
    columns = max(1, min(columns, count))
    rows = math.ceil(count / columns)
    fig, axes = plt.subplots(rows, columns, figsize=(width * columns, height * rows + 0.6), squeeze=False,
                             layout="constrained", sharex=sharex)
    flat = list(axes.flat)
    for ax in flat[count:]:
        ax.set_visible(False)
    return fig, flat[:count]


def steps_axis(ax) -> None:
    from matplotlib.ticker import FuncFormatter

    ax.xaxis.set_major_formatter(FuncFormatter(format_steps))
    ax.set_xlabel("environment steps")


def figure_legend(fig, axes) -> None:
    """One legend for the whole figure, below the panels, each label once."""
    entries: dict[str, object] = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            entries.setdefault(label, handle)
    if entries:
        # as many columns as fit the figure's width (about 6 points per character plus the line sample)
        width = fig.get_figwidth() * 72
        ncol = max(1, min(len(entries), int(width // (6 * max(map(len, entries)) + 45))))
        fig.legend(list(entries.values()), list(entries), loc="outside lower center", ncol=ncol, frameon=False)


def save_figure(fig, out: str, stem: str) -> list[str]:
    """Write `<out>/<stem>.png` and `.pdf`; returns their paths. No creation date in the PDF, so rebuilding
    unchanged results rewrites identical files (a clean `git status`)."""
    os.makedirs(out, exist_ok=True)
    paths = [os.path.join(out, f"{stem}.{ext}") for ext in ("png", "pdf")]
    for path in paths:
        fig.savefig(path, metadata={"CreationDate": None} if path.endswith(".pdf") else None)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return paths


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def write_text(out: str, name: str, text: str) -> str:
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, name)
    with open(path, "w") as f:
        f.write(text)
    return path


def write_csv(out: str, name: str, headers: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    """Full-precision numbers behind a figure or table (what the tests and further analysis read)."""
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, name)
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(headers)
        writer.writerows([repr(float(c)) if isinstance(c, float) else c for c in row] for row in rows)
    return path


def report(paths: Sequence[str]) -> None:
    for path in paths:
        print(f"wrote {path}")
