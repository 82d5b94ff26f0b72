"""The documentation stays true to the code: every `mcsplat` command line shown in README.md and docs/*.md parses
with the command's own parser (a renamed or removed option fails here, not in a reader's terminal), every relative
link of README.md, docs/*.md and benchmarks/README.md leads to a file of the repository, and the README stays short
enough to read from top to bottom."""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
COMMAND_PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINKED_PAGES = [*COMMAND_PAGES, ROOT / "benchmarks" / "README.md"]
README_MAX_LINES = 300

FENCE = re.compile(r"^(```|~~~)")
# A command line: `mcsplat ...` (or a path ending in /mcsplat), after an optional `$ ` prompt, or `-m mcsplat ...`
# inside a torchrun line. Console output such as `mcsplat: error: ...` has no space after the name and is skipped.
COMMAND = re.compile(r"^(?:\$ )?(?:(?:\S*/)?mcsplat\s|torchrun\s.*\s-m\s+mcsplat\s)")
INLINE_CODE = re.compile(r"`+[^`]*`+")
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE = re.compile(r"^\s*\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)", re.M)
HTML_LINK = re.compile(r"""(?:src|href)=["']([^"']+)["']""")
EXTERNAL = re.compile(r"^(?:[a-z][a-z0-9+.-]*:|//)", re.I)


def page_id(page: Path) -> str:
    return str(page.relative_to(ROOT))


def fenced_blocks(text: str) -> list[tuple[str, list[str]]]:
    """(info string, lines) of every fenced code block."""
    blocks, inside, info, lines = [], None, "", []
    for line in text.splitlines():
        stripped = line.strip()
        if inside is None:
            fence = FENCE.match(stripped)
            if fence:
                inside, info, lines = fence.group(1), stripped[3:].strip(), []
        elif stripped.startswith(inside):
            blocks.append((info, lines))
            inside = None
        else:
            lines.append(line)
    return blocks


def command_lines(lines: list[str]) -> list[str]:
    """The mcsplat command lines of a code block, continuation lines (ending in a backslash) joined."""
    joined, pending = [], ""
    for line in lines:
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        joined.append((pending + line).strip())
        pending = ""
    return [line for line in joined if COMMAND.match(line)]


def mcsplat_argv(line: str) -> list[str]:
    """The arguments after `mcsplat` (the program's name, or torchrun's `-m mcsplat`), comments dropped."""
    words = shlex.split(line.removeprefix("$ "), comments=True)
    for index, word in enumerate(words):
        if word == "mcsplat" or word.endswith("/mcsplat"):
            return words[index + 1:]
    raise AssertionError(f"no mcsplat in {line!r}")


def documented_commands(page: Path) -> list[str]:
    text = page.read_text()
    return [line for info, lines in fenced_blocks(text) if info in ("", "sh", "bash", "shell", "console")
            for line in command_lines(lines)]


def parse(argv: list[str]) -> str | None:
    """None when `mcsplat ARGV` parses (as cli.main parses it, without running anything), else tyro's message."""
    import tyro

    from mcsplat import cli

    output = io.StringIO()
    try:
        with contextlib.redirect_stdout(output), contextlib.redirect_stderr(output):
            tyro.extras.subcommand_cli_from_dict(cli.COMMANDS, prog="mcsplat", description=cli.DESCRIPTION,
                                                 args=argv)
    except SystemExit as exc:
        return " ".join(output.getvalue().split()) or f"exit status {exc.code}"
    return None


def test_the_pages_show_command_lines():
    """The test below has something to check: the README's main path and the docs' examples are code blocks."""
    assert len(documented_commands(ROOT / "README.md")) >= 8
    assert sum(len(documented_commands(page)) for page in COMMAND_PAGES) >= 40


@pytest.mark.parametrize("page", COMMAND_PAGES, ids=page_id)
def test_every_documented_command_line_parses(page):
    failures = []
    for line in documented_commands(page):
        problem = parse(mcsplat_argv(line))
        if problem is not None:
            failures.append(f"{line}\n    {problem}")
    assert not failures, f"{page_id(page)}: command lines the CLI refuses:\n" + "\n".join(failures)


@pytest.mark.parametrize("page", COMMAND_PAGES, ids=page_id)
def test_command_lines_sit_in_fenced_blocks(page):
    """An indented code block is not read by the test above: a command there could rot unseen."""
    text = "\n".join(line for _, lines in fenced_blocks(page.read_text()) for line in lines)
    outside = [line for line in page.read_text().splitlines()
               if line.startswith("    ") and COMMAND.match(line.strip()) and line not in text]
    assert not outside, f"{page_id(page)}: put these in a ``` block:\n" + "\n".join(outside)


def test_a_refused_option_is_caught():
    """The parse above really checks options: an unknown one is refused, a known one accepted."""
    assert parse(["train", "data/lego_demo", "--budget", "10m"]) is None
    assert parse(["train", "data/lego_demo", "--no-such-option", "1"]) is not None
    assert parse(["export", "runs/demo", "--format", "no-such-format"]) is not None


def prose(text: str) -> str:
    """The page without its fenced code blocks and inline code, where brackets are not links."""
    kept, inside = [], None
    for line in text.splitlines():
        stripped = line.strip()
        if inside is None and FENCE.match(stripped):
            inside = stripped[:3]
        elif inside is not None and stripped.startswith(inside):
            inside = None
        elif inside is None:
            kept.append(INLINE_CODE.sub("", line))
    return "\n".join(kept)


def heading_anchors(page: Path) -> set[str]:
    """GitHub's anchors of a page's headings: lower case, punctuation dropped, spaces as hyphens."""
    anchors = set()
    for line in prose(page.read_text()).splitlines():
        if line.startswith("#"):
            title = line.lstrip("#").strip().lower()
            anchors.add(re.sub(r"[^\w\- ]", "", title).replace(" ", "-"))
    return anchors


def relative_links(page: Path) -> list[str]:
    text = prose(page.read_text())
    targets = LINK.findall(text) + REFERENCE.findall(text) + HTML_LINK.findall(text)
    return [target for target in targets if not EXTERNAL.match(target)]


@pytest.mark.parametrize("page", LINKED_PAGES, ids=page_id)
def test_every_relative_link_leads_to_a_file_of_the_repository(page):
    broken = []
    for target in relative_links(page):
        path_part, _, anchor = target.partition("#")
        path = (page.parent / path_part).resolve() if path_part else page
        if not path.is_relative_to(ROOT) or not path.exists():
            broken.append(f"{target} (no such file in the repository)")
        elif anchor and path.suffix == ".md" and anchor not in heading_anchors(path):
            broken.append(f"{target} (no heading #{anchor} in {path.relative_to(ROOT)})")
    assert not broken, f"{page_id(page)}: broken links:\n" + "\n".join(broken)


def test_the_readme_is_read_top_to_bottom():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; move details into docs/"


def test_the_readme_keeps_the_test_command():
    """CI (.ci/run) runs the README's test command: `make test`."""
    blocks = fenced_blocks((ROOT / "README.md").read_text())
    assert any(line.split("#")[0].strip() == "make test" for _, lines in blocks for line in lines)
