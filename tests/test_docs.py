"""The documentation stays true: every relative link and `#anchor` in README.md and docs/*.md resolves (anchors by
GitHub's slug rules), the README stays short and links every page of docs/, and every `--flag` the docs name exists
in the `--help` of the tool it belongs to.

Which tool a flag belongs to: the last tool named before it in the same line of a code block (a quoted part of a
command, as `sweep.py --command "..."`, has its own), or in the same paragraph, list item or table row of the text;
where none is named, the scripts the page's title names (docs/sac_ddpg.md: cascade_sac.py and cascade_ddpg.py), and
on a page whose title names none, any of the six training scripts. Tools: every script of the repository with a
command line (its `--help`, with each subcommand's), and pip, pytest, TensorBoard, W&B and Ray (the short lists below).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from dataclasses import dataclass

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
README_MAX_LINES = 120
TRAINING_SCRIPTS = ("cascade_ppo_continuous.py", "ppo_baseline.py", "cascade_ppo_discrete.py",
                    "ppo_baseline_discrete.py", "cascade_sac.py", "cascade_ddpg.py")
TOOL_FOLDERS = ("", "plots", "benchmarks", "tests")
# the flags of other programs that the docs use (their --help is not ours to run: checked against this list)
EXTERNAL_FLAGS = {"pip": set(), "pytest": {"--maxprocesses"}, "tensorboard": {"--logdir"}, "wandb": set(),
                  "ray": {"--head", "--port", "--address"}}

FENCE = re.compile(r"^\s{0,3}(```|~~~)")
HEADING = re.compile(r"^\s{0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
NEW_UNIT = re.compile(r"^\s*(?:[-*+]|\d+[.)])\s|^\s{0,3}#|^\s*\|")  # a list item, a heading or a table row
CODE_SPAN = re.compile(r"(`+)(.+?)(?<!`)\1(?!`)", re.S)
LINK = re.compile(r"!?\[((?:[^\[\]]|\[[^\]]*\])*)\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)", re.M)
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9]*(?:-[a-z0-9]+)*")
SCRIPT = re.compile(r"(?<![\w.-])((?:[\w.-]+/)*[\w-]+\.py)\b")
# another program, where a command starts: `ray start`, `.venv/bin/pip install`, `python -m pytest`, `... && wandb sync`
EXTERNAL = re.compile(r"(?:^|(?<=[/;|&(])|(?<=[;|&(] )|(?<=-m ))(" + "|".join(EXTERNAL_FLAGS) + r")(?=\s)", re.M)
QUOTED = re.compile(r"\"[^\"]*\"")


# ---- reading Markdown -----------------------------------------------------------------------------------------

@dataclass
class Unit:
    """A paragraph, list item, table row or heading of the text (`code` False), or one line of a code block."""
    text: str
    line: int
    code: bool


def units(markdown: str) -> list[Unit]:
    """The page cut into the units a flag's tool is looked for in; a code block's lines continued by `\\` join."""
    result: list[Unit] = []
    fence, current = None, None
    for number, line in enumerate(markdown.splitlines(), 1):
        opening = FENCE.match(line)
        if fence:
            if opening and opening.group(1) == fence:
                fence = None
            elif result and result[-1].code and result[-1].text.endswith("\\"):
                result[-1].text = result[-1].text[:-1] + " " + line
            else:
                result.append(Unit(line, number, True))
            continue
        if opening:
            fence, current = opening.group(1), None
        elif not line.strip():
            current = None
        elif current is None or NEW_UNIT.match(line) or HEADING.match(current.text):
            current = Unit(line, number, False)
            result.append(current)
        else:
            current.text += "\n" + line
    return result


def masked(text: str) -> str:
    """The text with its code spans blanked out (a link inside `...` is no link)."""
    return CODE_SPAN.sub(lambda m: " " * len(m.group(0)), text)


def github_slug(heading: str) -> str:
    """GitHub's anchor of a heading: the rendered text lowercased, punctuation dropped (but - and _), spaces to -."""
    text = LINK.sub(lambda m: m.group(1), heading)  # a link or image: its text
    text = CODE_SPAN.sub(lambda m: m.group(2), text)
    text = re.sub(r"<[^>]+>", "", text).replace("*", "")
    return "".join(c for c in text.lower() if c.isalnum() or c in "-_ ").replace(" ", "-")


def anchors(markdown: str) -> set[str]:
    """Every heading's anchor, duplicates numbered -1, -2, ... as GitHub numbers them."""
    seen: dict[str, int] = {}
    result = set()
    for unit in units(markdown):
        heading = None if unit.code else HEADING.match(unit.text)
        if heading:
            slug = github_slug(heading.group(2))
            count = seen.get(slug, 0)
            seen[slug] = count + 1
            result.add(slug if count == 0 else f"{slug}-{count}")
    return result


def doc_pages(root: str) -> list[str]:
    """README.md and docs/*.md, relative to root."""
    docs = os.path.join(root, "docs")
    return ["README.md"] + sorted(os.path.join("docs", name) for name in os.listdir(docs) if name.endswith(".md"))


def read(root: str, page: str) -> str:
    with open(os.path.join(root, page), encoding="utf-8") as f:
        return f.read()


# ---- links ----------------------------------------------------------------------------------------------------

def link_targets(markdown: str) -> list[tuple[int, str]]:
    """(line, target) of every inline link, image and reference definition outside code."""
    targets = []
    for unit in units(markdown):
        if unit.code:
            continue
        text = masked(unit.text)
        for match in LINK.finditer(text):
            targets.append((unit.line + text.count("\n", 0, match.start()), match.group(2)))
        for match in REFERENCE.finditer(text):
            targets.append((unit.line + text.count("\n", 0, match.start()), match.group(1)))
    return targets


def link_problems(root: str, pages: list[str]) -> list[str]:
    """Each relative link of the pages whose file, or whose #anchor in a Markdown file, does not exist."""
    problems, anchors_of = [], {}
    root = os.path.realpath(root)
    for page in pages:
        for line, target in link_targets(read(root, page)):
            where = f"{page}:{line}: ({target})"
            if not target or re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
                continue
            path, _, anchor = target.partition("#")
            file = os.path.realpath(os.path.join(root, os.path.dirname(page), path)) if path else \
                os.path.join(root, page)
            if not file.startswith(root + os.sep) or not os.path.exists(file):
                problems.append(f"{where}: no such file in the repository")
            elif anchor:
                if not file.endswith(".md"):
                    problems.append(f"{where}: an anchor into a file that is not Markdown")
                    continue
                if file not in anchors_of:
                    with open(file, encoding="utf-8") as f:
                        anchors_of[file] = anchors(f.read())
                if anchor not in anchors_of[file]:
                    problems.append(f"{where}: no heading with the anchor #{anchor} in {os.path.relpath(file, root)}")
    return problems


# ---- flags ----------------------------------------------------------------------------------------------------

def tools_of_repository(root: str) -> list[str]:
    """The scripts with a command line: those of the repository's top level, plots/, benchmarks/ and tests/ that
    run as programs."""
    tools = []
    for folder in TOOL_FOLDERS:
        for name in sorted(os.listdir(os.path.join(root, folder))):
            path = os.path.join(folder, name)
            if name.endswith(".py") and not name.startswith("test_") and '__name__ == "__main__"' in read(root, path):
                tools.append(path)
    return tools


HELP_COLLECTOR = r"""
import contextlib, io, json, re, runpy, sys

def help_text(path, argv):
    out = io.StringIO()
    sys.argv = [path, *argv, "--help"]
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        try:
            runpy.run_path(path, run_name="__main__")
        except SystemExit:
            pass
    return out.getvalue()

texts = {}
for path in json.loads(sys.argv[1]):
    text = help_text(path, [])
    subcommands = re.search(r"\{([\w,-]+)\}", text.partition("\n")[0])  # tyro's usage line: {a,b,c}
    names = subcommands.group(1).split(",") if subcommands else []
    texts[path] = [text] + [help_text(path, [name]) for name in names]
print(json.dumps(texts))
"""


def flags_in_help(text: str) -> set[str]:
    """The flags an argparse/tyro help lists: those at the start of an option line, before its description."""
    flags = set()
    for line in text.splitlines():
        option = line.strip().strip("│|").strip()
        if option.startswith("-"):
            flags |= set(FLAG.findall(re.split(r"\s{2,}", option)[0]))
    return flags


def collect_help_flags(root: str, tools: list[str]) -> dict[str, set[str]]:
    """Each tool's flags from its `--help` (and its subcommands'), all run in one fresh interpreter (~10 s)."""
    env = {**os.environ, "COLUMNS": "200", "PYTHONPATH": root}
    out = subprocess.run([sys.executable, "-c", HELP_COLLECTOR, json.dumps(tools)], cwd=root, env=env,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    texts = json.loads(out.stdout.strip().splitlines()[-1])
    for tool in tools:
        assert all("usage:" in text for text in texts[tool]), f"no --help from {tool}: {texts[tool]}"
    return {tool: set().union(*map(flags_in_help, texts[tool])) for tool in tools}


def tool_named(name: str, tools: list[str]) -> str | None:
    """The tool a script name means (`learning_curves.py` is plots/learning_curves.py), None if it is none of ours."""
    if name in tools:
        return name
    matches = [tool for tool in tools if os.path.basename(tool) == os.path.basename(name)]
    return matches[0] if len(matches) == 1 and "/" not in name else None


def mentions(text: str, code: bool, tools: list[str]) -> list[tuple[int, str, str]]:
    """(position, "tool" or "flag", name) of the tools and flags named in the text, in order."""
    found = [(m.start(), "flag", m.group(0)) for m in FLAG.finditer(text)]
    for match in SCRIPT.finditer(text):
        tool = tool_named(match.group(1), tools)
        if tool:
            found.append((match.start(), "tool", tool))
    if code:
        found += [(m.start(), "tool", m.group(1)) for m in EXTERNAL.finditer(text)]
    return sorted(found)


def flags_with_tools(markdown: str, tools: list[str], default: tuple[str, ...]) -> list[tuple[int, str, tuple]]:
    """(line, flag, the tools it may belong to) for every flag the page names."""
    result = []
    for unit in units(markdown):
        pieces = [(unit.text, unit.code)]
        if not unit.code:  # the text and its code spans, in order, each searched for the tools it names
            text = LINK.sub(lambda m: m.group(0)[:-len(m.group(2)) - 1] + " " * len(m.group(2)) + ")", unit.text)
            pieces, at = [], 0
            for span in CODE_SPAN.finditer(text):
                pieces += [(text[at:span.start()], False), (span.group(2), True)]
                at = span.end()
            pieces.append((text[at:], False))
        context = default
        for text, code in pieces:
            before = context
            quoted = [(m.start(), m.group(0)) for m in QUOTED.finditer(text)] if code else []
            outer = QUOTED.sub(lambda m: " " * len(m.group(0)), text) if code else text
            parts = sorted([(at, "quote", part) for at, part in quoted] + mentions(outer, code, tools))
            for _, kind, name in parts:
                if kind == "tool":
                    context = (name,)
                elif kind == "flag":
                    result.append((unit.line, name, context))
                else:  # a quoted command: its own tool, else the one around it
                    inner = context
                    for _, inner_kind, inner_name in mentions(name, code, tools):
                        if inner_kind == "tool":
                            inner = (inner_name,)
                        else:
                            result.append((unit.line, inner_name, inner))
            if context[0] in EXTERNAL_FLAGS:  # another program's flags end with its command
                context = before
    return result


def page_default_tools(markdown: str, tools: list[str]) -> tuple[str, ...]:
    """The scripts a page's title names (a page about them), else the training scripts."""
    title = next((u.text for u in units(markdown) if not u.code and HEADING.match(u.text)), "")
    named = tuple(tool for tool in (tool_named(m.group(1), tools) for m in SCRIPT.finditer(title)) if tool)
    return named or TRAINING_SCRIPTS


def flag_problems(root: str, pages: list[str], help_flags: dict[str, set[str]]) -> list[str]:
    """Each flag the pages name that no tool it may belong to has."""
    known = {**help_flags, **EXTERNAL_FLAGS}
    tools = list(help_flags)
    problems = []
    for page in pages:
        markdown = read(root, page)
        for line, flag, candidates in flags_with_tools(markdown, tools, page_default_tools(markdown, tools)):
            if not any(flag in known.get(tool, set()) for tool in candidates):
                problems.append(f"{page}:{line}: {flag} is not a flag of {' or '.join(candidates)}")
    return problems


# ---- the tests ------------------------------------------------------------------------------------------------

def test_github_slugs():
    """The anchors GitHub gives these headings (its slugger: punctuation dropped, spaces kept as hyphens)."""
    assert github_slug("Tracking with W&B, and videos of training") == "tracking-with-wb-and-videos-of-training"
    assert github_slug("`--autograd`: section 1 alone") == "--autograd-section-1-alone"
    assert github_slug("The baseline: `ppo_baseline.py`") == "the-baseline-ppo_baselinepy"
    assert github_slug("Fig. 11: the initial fallback (and Fig. 6, 7, Table 1)") == \
        "fig-11-the-initial-fallback-and-fig-6-7-table-1"
    assert github_slug("See [the paper](https://example.org) *now*") == "see-the-paper-now"
    assert anchors("# A\n## Measured\ntext\n## Measured\n```\n# not a heading\n```\n## Measured") == \
        {"a", "measured", "measured-1", "measured-2"}


def test_every_link_and_anchor_resolves():
    problems = link_problems(ROOT, doc_pages(ROOT))
    assert not problems, "\n".join(problems)


def test_a_broken_link_or_anchor_is_found(tmp_path):
    os.makedirs(tmp_path / "docs")
    (tmp_path / "docs" / "page.md").write_text("# Page\n## A section\n[back](../README.md#the-title)\n")
    (tmp_path / "README.md").write_text(
        "# The title\n"
        "[fine](docs/page.md#a-section) and [fine too](#the-title), `[not a link](nowhere.md)`\n"
        "[no file](docs/missing.md) [no anchor](docs/page.md#b-section)\n"
        "- [no anchor here](#nothing) ![no image](results/x.png)\n\n"
        "[ref]: docs/gone.md\n")
    problems = link_problems(str(tmp_path), doc_pages(str(tmp_path)))
    assert [p.split(": (")[1].split(")")[0] for p in problems] == \
        ["docs/missing.md", "docs/page.md#b-section", "#nothing", "results/x.png", "docs/gone.md"], problems


def test_readme_is_short_and_links_every_page():
    readme = read(ROOT, "README.md")
    assert len(readme.splitlines()) <= README_MAX_LINES, "README.md is for five minutes: move the details to docs/"
    linked = {os.path.normpath(target.partition("#")[0]) for _, target in link_targets(readme)}
    missing = [page for page in doc_pages(ROOT)[1:] if page not in linked]
    assert not missing, f"README.md links no {missing}"
    assert "<!-- test-command" in readme, ".ci/run reads the test command after this marker"


@pytest.fixture(scope="module")
def help_flags():
    return collect_help_flags(ROOT, tools_of_repository(ROOT))


def test_every_flag_the_docs_name_exists(help_flags):
    assert set(TRAINING_SCRIPTS) <= set(help_flags)
    assert {"--env-id", "--no-normalize", "--help"} <= help_flags["cascade_ppo_continuous.py"]
    assert {"--table2", "--checkpoint", "--allow-incomplete"} - help_flags["plots/analyze.py"] == {"--table2"}
    problems = flag_problems(ROOT, doc_pages(ROOT), help_flags)
    assert not problems, "\n".join(problems)


def test_a_made_up_flag_is_found(tmp_path):
    help_flags = {**{script: {"--n"} for script in TRAINING_SCRIPTS}, "cascade_sac.py": {"--autotune", "--n"},
                  "sweep.py": {"--seeds", "--command"}}
    os.makedirs(tmp_path / "docs")
    (tmp_path / "README.md").write_text("# Title\n")
    (tmp_path / "docs" / "sac.md").write_text(
        "# SAC: `cascade_sac.py`\n"
        "`--autotune` and `--made-up` on this page are cascade_sac.py's;\n"
        "`cascade_ddpg.py --n 2 --autotune` is not.\n\n"
        "| row | `sweep.py --seeds 1` |\n"
        "| next row | `--seeds` |\n"
        "```bash\n"
        "python sweep.py --command \"cascade_sac.py --autotune --seeds 1\" --seeds 1 \\\n"
        "  --autotune\n"
        ".venv/bin/python -m pytest -n 0 --maxprocesses 4 --made-up-too\n"
        "```\n")
    problems = flag_problems(str(tmp_path), doc_pages(str(tmp_path)), help_flags)
    assert [p.split(": ", 1)[1] for p in problems] == [
        "--made-up is not a flag of cascade_sac.py",
        "--autotune is not a flag of cascade_ddpg.py",
        "--seeds is not a flag of cascade_sac.py",
        "--seeds is not a flag of cascade_sac.py",
        "--autotune is not a flag of sweep.py",
        "--made-up-too is not a flag of pytest",
    ], problems
