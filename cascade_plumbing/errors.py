"""The one way a script stops on bad input or a failed operation: one line, non-zero exit."""

from __future__ import annotations

import math
from typing import Any


def fail(message: str) -> None:
    """Stop with a one-line error and a non-zero exit code."""
    raise SystemExit(f"error: {message}")


# The ranges of the scripts' real-valued settings (each applies where a script has the setting): a value outside
# its range would train until the non-finite guard stops the run, or silently do something else (a negative
# exploration noise is the same noise). A learning rate of 0 is allowed: a run that must not learn (a control).
RANGES = {
    "learning_rate": (lambda v: v >= 0, "must be >= 0"),
    "policy_lr": (lambda v: v >= 0, "must be >= 0"),
    "q_lr": (lambda v: v >= 0, "must be >= 0"),
    "gamma": (lambda v: 0 <= v <= 1, "must lie in [0, 1]"),
    "gae_lambda": (lambda v: 0 <= v <= 1, "must lie in [0, 1]"),
    "clip_coef": (lambda v: v > 0, "must be > 0"),
    "ent_coef": (lambda v: v >= 0, "must be >= 0"),
    "vf_coef": (lambda v: v >= 0, "must be >= 0"),
    "max_grad_norm": (lambda v: v > 0, "must be > 0"),
    "target_kl": (lambda v: v > 0, "must be > 0 (or left unset: no early stop)"),
    "tau": (lambda v: 0 < v <= 1, "must lie in (0, 1]"),
    "alpha": (lambda v: v >= 0, "must be >= 0"),
    "exploration_noise": (lambda v: v >= 0, "must be >= 0"),
    "adam_eps": (lambda v: v > 0, "must be > 0"),
    "obs_reward_clip": (lambda v: v >= 0, "must be >= 0 (0: no clipping)"),
    "fallback_init": (lambda v: 0 < v < 1, "must lie strictly between 0 and 1"),
}


def check_ranges(args: Any, ranges: dict = RANGES) -> None:
    """Every real-valued setting of `args` (a script's Args) finite, and each in its range (`ranges`: name ->
    (test, what it must be)); the first that is not is refused in one line naming the flag and the value."""
    values = vars(args)
    for name, value in values.items():
        if isinstance(value, float) and not math.isfinite(value):
            fail(f"--{name.replace('_', '-')} must be a finite number (got {value})")
    for name, (valid, must) in ranges.items():
        value = values.get(name)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and not valid(value):
            fail(f"--{name.replace('_', '-')} {must} (got {value})")
