"""Every command's ``--help`` as a user reads it in an 80-column terminal: no option name split or cut,
no help text cut short, no type or default beside a flag (``--force``, not ``--force <bool>``), plain
words instead of Python types (``MODEL ...``, not ``<list[str]>``), and the examples on lines a user can copy."""

import re
import subprocess
import sys

import pytest
import typer.main

from mi_lidar.cli import app

from .conftest import REPO
from .terminal import assert_whole, invoke_at_80


def commands(group, path=()):
    """``(words, command)`` of every command under ``group``, groups included (``primitives``, ``primitives list``)."""
    for name, command in group.commands.items():
        yield (*path, name), command
        if hasattr(command, "commands"):
            yield from commands(command, (*path, name))


ROOT = typer.main.get_command(app)
COMMANDS = [((), ROOT), *commands(ROOT)]
FENCE = re.compile(r"^```\n(.*?)^```", re.S | re.M)


def example_lines(command) -> list[str]:
    """The lines of the fenced example blocks of a command's docstring, as written (continuations included)."""
    text = "\n".join(line.strip() for line in (command.help or "").splitlines())
    return [line for block in FENCE.findall(text) for line in block.splitlines() if line]


@pytest.mark.parametrize("words, command", COMMANDS, ids=[" ".join(w) or "mi-lidar" for w, _ in COMMANDS])
def test_help_is_readable_at_80_columns(words, command):
    result = invoke_at_80([*words, "--help"])
    assert result.exit_code == 0, result.stdout
    text = result.stdout
    names = [name for param in command.params for name in (*param.opts, *param.secondary_opts) if name[0] == "-"]
    split = [n for n in names if not re.search(rf"(?<![\w-]){re.escape(n)}(?![\w-])", text)]
    assert not split, f"option names split across lines or cut: {split}\n{text}"
    assert_whole(text, "Show this message and exit.", *example_lines(command))
    assert "<bool>" not in text and "[default: False]" not in text, f"a flag shows a type or default\n{text}"
    python_types = re.findall(r"<(?:str|int|float|list\[\w+\])>", text)
    assert not python_types, f"Python types in the type column: {python_types}\n{text}"


def test_every_verb_has_examples_that_fit():
    verbs = [(words, command) for words, command in COMMANDS if words and not hasattr(command, "commands")]
    assert verbs and all(example_lines(command) for _, command in verbs)
    too_long = [line for _, command in verbs for line in example_lines(command) if len(line) > 76]
    assert not too_long, too_long


EXAMPLES = sorted((REPO / "examples").glob("0*.py"))


@pytest.mark.parametrize("script", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_example_help_prints_its_docstring_and_runs_nothing(script, tmp_path):
    """``python examples/0N_*.py --help`` ran the whole example (up to 5 min) into a folder named ``--help``."""
    run = lambda flag: subprocess.run([sys.executable, script, flag], cwd=tmp_path, capture_output=True, text=True)  # noqa: E731
    help_run, typo_run = run("--help"), run("--hepl")
    assert help_run.returncode == 0 and f"Run:  python examples/{script.name}" in help_run.stdout, help_run
    assert typo_run.returncode == 2 and "unrecognized arguments: --hepl" in typo_run.stderr, typo_run
    assert not any(tmp_path.iterdir()), f"{script.name} wrote {sorted(tmp_path.iterdir())}"
