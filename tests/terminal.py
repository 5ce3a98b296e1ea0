"""The command line as a user reads it in an 80-column terminal (the default of many terminals and CI logs)."""

from typer.testing import CliRunner

from mi_lidar.cli import app

WIDTH = 80


def invoke_at_80(args, **kwargs):
    """Run ``mi-lidar ARGS`` as in an 80-column terminal.

    rich sizes its tables from ``COLUMNS`` (else from the real terminal), not from click's
    ``terminal_width``: both are set, so the tables are laid out at 80 columns whatever runs the tests.
    """
    env = {"COLUMNS": str(WIDTH), **kwargs.pop("env", {})}
    return CliRunner().invoke(app, [str(a) for a in args], terminal_width=WIDTH, env=env, **kwargs)


def assert_whole(text: str, *figures: str) -> None:
    """No cell of ``text`` is cut short with an ellipsis, and every one of ``figures`` appears whole."""
    assert "\u2026" not in text, text
    for figure in figures:
        assert figure in text, (figure, text)
