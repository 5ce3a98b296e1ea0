"""The README and docs/*.md cannot go stale: their command blocks are checked against the CLI and run.

Fenced blocks tagged ``bash`` are shell commands, ``python`` blocks are Python (the python blocks
of one page form one session); other tags (``text``, ``xml``) are not run. The fast test checks
every ``mi-lidar`` command line against the CLI (verb and options exist) and runs the README's
blocks verbatim; the slow test runs every block of every page verbatim, in file order (README, then
docs/ by name). Blocks run in one temporary folder holding links to ``scenes_xml``, ``examples`` and
``../shared/data``, so later commands read what earlier ones wrote.
Lines running ``make`` are not run (they are the targets that run this suite). Blocks that read
``../shared/data`` are skipped when it is absent.
"""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import typer.main

from mi_lidar.cli import app

from .conftest import REPO, SHARED_DATA

DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)


def blocks(language: str) -> list[tuple[str, str]]:
    """``(where, text)`` of every fenced block tagged ``language``, in documentation order."""
    found = []
    for path in DOCS:
        text = path.read_text(encoding="utf-8")
        for match in FENCE.finditer(text):
            if match.group(1) == language:
                line = text[: match.start()].count("\n") + 1
                found.append((f"{path.relative_to(REPO)}:{line}", match.group(2)))
    return found


def command_lines(block: str) -> list[list[str]]:
    """The ``mi-lidar`` invocations of a shell block as argument lists (comments dropped)."""
    commands = []
    for line in block.replace("\\\n", " ").splitlines():
        for part in re.split(r"&&|;", line.split(" #")[0]):
            words = shlex.split(part, comments=True)
            if words and words[0] == "mi-lidar":
                commands.append(words[1:])
    return commands


def test_documentation_has_runnable_blocks():
    assert len(blocks("bash")) >= 3 and len(blocks("python")) >= 4
    assert sum(len(command_lines(b)) for _, b in blocks("bash")) >= 15


def test_every_documented_command_exists_with_its_options():
    root = typer.main.get_command(app)
    problems = []
    for where, block in blocks("bash"):
        for words in command_lines(block):
            command, rest = root, list(words)
            while rest and hasattr(command, "commands") and rest[0] in command.commands:
                command = command.commands[rest.pop(0)]
            if command is root and rest and not rest[0].startswith("-"):
                problems.append(f"{where}: unknown verb {rest[0]!r}")
                continue
            known = {name for param in command.params for name in (*param.opts, *param.secondary_opts)}
            known |= {"--help"}
            for word in rest:
                option = word.split("=")[0]
                if option.startswith("-") and option not in known and not re.fullmatch(r"-\d.*", option):
                    problems.append(f"{where}: `mi-lidar {' '.join(words[:2])}` has no option {option}")
    assert not problems, "\n".join(problems)


def run_verbatim(pages: list[Path], tmp_path: Path) -> list[str]:
    """Run every block of ``pages`` verbatim, in documentation order, in one folder under ``tmp_path``.

    Returns:
        Where the blocks that read ``../shared/data`` are, when it is absent (not run).
    """
    work = tmp_path / "work"
    work.mkdir()
    for folder in ("scenes_xml", "examples"):  # the README runs from a checkout: its scenes and example specs
        (work / folder).symlink_to(REPO / folder)
    have_data = SHARED_DATA.is_dir()
    if have_data:
        (tmp_path / "shared").mkdir()
        (tmp_path / "shared" / "data").symlink_to(SHARED_DATA)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    on_pages = lambda where: REPO / where.split(":")[0] in pages
    # The python blocks of one page are one session (later blocks use earlier names): one run each.
    sessions: dict[str, tuple[str, str]] = {}
    for where, block in filter(lambda wb: on_pages(wb[0]), blocks("python")):
        page = where.split(":")[0]
        first, text = sessions.get(page, (where, ""))
        sessions[page] = (first, text + block)
    runs = [("bash", w, b) for w, b in blocks("bash") if on_pages(w)]
    runs += [("python", w, b) for w, b in sessions.values()]
    runs.sort(key=lambda run: (DOCS.index(REPO / run[1].split(":")[0]), int(run[1].split(":")[1])))
    assert runs, f"no runnable blocks on {pages}"
    skipped = []
    for language, where, block in runs:
        if "../shared/data" in block and not have_data:
            skipped.append(where)
            continue
        if language == "bash":
            script = "set -e\n" + "\n".join(line for line in block.splitlines() if not line.startswith("make "))
            command = ["bash", "-c", script]
        else:
            command = [sys.executable, "-c", block]
        result = subprocess.run(command, cwd=work, env=env, capture_output=True, text=True)
        assert result.returncode == 0, f"{where}:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return skipped


def test_every_readme_block_runs_verbatim(tmp_path):
    skipped = run_verbatim([REPO / "README.md"], tmp_path)
    assert len(skipped) <= 1, f"only the real-data block may need ../shared/data: {skipped}"


@pytest.mark.slow
def test_every_block_runs_verbatim(tmp_path):
    skipped = run_verbatim(DOCS, tmp_path)
    if skipped:
        pytest.skip(f"blocks reading ../shared/data skipped (absent): {skipped}")
