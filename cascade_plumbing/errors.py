"""The one way a script stops on bad input or a failed operation: one line, non-zero exit."""

from __future__ import annotations

import contextlib
import io
import math
import os
import re
import sys
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

T = TypeVar("T")


def fail(message: str) -> None:
    """Stop with a one-line error and a non-zero exit code."""
    raise SystemExit(f"error: {message}")


def parse_command_line(parse: Callable[[], T]) -> T:
    """`parse()` (a `tyro.cli` call), with tyro's parse errors (a box of a dozen lines) as one line: what is wrong,
    the flag tyro suggests, and where the help is (`error: ...; see <script> --help`, exit 2). --help is as tyro
    prints it; anything else tyro says (a warning) goes out unchanged."""
    said = io.StringIO()
    try:
        with contextlib.redirect_stderr(said), unwrapped_errors(asks_for_help=bool({"-h", "--help"} & set(sys.argv))):
            return parse()
    except SystemExit as exc:
        line = parse_error_line(said.getvalue()) if exc.code else None
        if line is None:
            raise
        text = ANSI.sub("", said.getvalue())
        said = io.StringIO()
        said.write(text[: text.rfind("\n", 0, error_start(text)) + 1])  # what came before the error
        said.write(f"error: {line.rstrip('.')}; see {sys.argv[0]} --help\n")
        raise SystemExit(2) from None
    finally:
        sys.stderr.write(said.getvalue())
        sys.stderr.flush()


@contextlib.contextmanager
def unwrapped_errors(asks_for_help: bool = False) -> Iterator[None]:
    """tyro draws its errors to the terminal's width: a narrow one wraps a flag's line, and the wrapped part reads as
    another flag. While parsing, a wide "terminal" (COLUMNS) keeps each line whole, unless the command asks for
    --help (printed for the real terminal)."""
    if asks_for_help:
        yield
        return
    saved = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "1000"
    try:
        yield
    finally:
        if saved is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = saved


ANSI = re.compile(r"\x1b\[[0-9;]*m")  # tyro colours its errors on a terminal
BOX = ("\u2502", "\u256d", "\u2570")  # a box's left border: side, top, bottom


def error_start(text: str) -> int:
    """Where tyro's error box (its top border; in plain form, its title before the first rule) starts in `text`."""
    top = text.rfind("\u256d")
    if top >= 0:
        return top
    rule = re.search(r"^[ \t]*-{4,}[ \t]*$", text, flags=re.M)
    if rule is None:
        return len(text)
    title_end = text.rfind("\n", 0, rule.start())  # the newline that ends the title's line
    return text.rfind("\n", 0, max(title_end, 0)) + 1


def parse_error_line(text: str) -> str | None:
    """The parse error tyro printed at the end of `text`, in one line (None if `text` ends otherwise).

    tyro draws it as a box (or as plain text with dashed rules): a title, then sections split by rules, the last one
    "For full helptext, ...". A section is a sentence (wrapped over lines: joined), or a heading that ends in ":"
    over indented entries: the flags (or values) first, each with its help indented further, then maybe a note
    (less indented: a sentence). "Perhaps you meant:" becomes "(did you mean --x?)", naming the subcommand a flag
    belongs to; "Argument helptext:" (the help of the flag named before) is left out."""
    raw = [line for line in ANSI.sub("", text).splitlines() if line.strip()]
    lines = [line.rstrip().rstrip("\u2502\u256e\u256f").rstrip() for line in raw]  # (a box's right border)
    lines = [line.lstrip()[1:] if line.lstrip()[:1] in BOX else line for line in lines]
    ends = [i for i, line in enumerate(lines) if line.strip().startswith("For full helptext")]
    if not ends or ends[-1] < len(lines) - 4:
        return None

    def rule(line: str) -> bool:
        return len(line.strip()) > 3 and set(line.strip()) <= {"-", "\u2500"}

    def indent(line: str) -> int:
        return len(line) - len(line.lstrip())

    window = range(max(ends[-1] - 80, 0), ends[-1])
    tops = [i for i in window if raw[i].strip().startswith("\u256d")]  # a box: its title is in the top border
    starts = tops[-1:] or [i for i in window if rule(lines[i])][:1]  # plain: the title, then a rule
    if not starts:
        return None
    content = lines[starts[0] + 1 : ends[-1]]
    margin = min((indent(line) for line in content if line.strip() and not rule(line)), default=0)  # (box: 1, plain: 2)
    sections: list[list[str]] = [[]]
    for line in content:
        if rule(line):
            sections.append([])
        else:
            sections[-1].append(line[margin:])
    said: list[list[str]] = []  # per section: what is wrong, then a note
    for section in sections:
        section = [line for line in section if line.strip()]
        # the heading: the section's unindented lines up to its first indented one (a long one wraps: joined)
        head = next((i for i, line in enumerate(section) if indent(line) > 0), len(section))
        if head == 0:
            continue
        heading, entries = " ".join(line.strip() for line in section[:head]), section[head:]
        if heading == "Argument helptext:":
            continue
        if not (heading.endswith(":") and entries):
            said.append([" ".join([heading, *(entry.strip() for entry in entries)])])
            continue
        # a heading over indented entries: the entries at the first one's indentation are the flags (or values),
        # each followed by its help; what is less indented after them is a note
        depth = indent(entries[0])
        flags: list[str] = []
        note: list[str] = []
        for entry in entries:
            if note or indent(entry) < depth:
                note.append(entry.strip())
            elif indent(entry) == depth:
                flags.append(entry.split()[0].rstrip(","))  # (`--x, --no-x` of a boolean flag: --x)
            elif entry.strip().startswith("in ") and entry.strip().endswith(" --help") and flags:
                flags[-1] += f" of {entry.strip()[3:-7]}"  # a suggestion from another subcommand
        if heading == "Perhaps you meant:" and said:
            said[-1][0] += f" (did you mean {' or '.join(dict.fromkeys(flags))}?)"
        else:
            said.append([f"{heading} {', '.join(flags)}", *note])
    return "; ".join(" ".join(parts) for parts in said) or None


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
