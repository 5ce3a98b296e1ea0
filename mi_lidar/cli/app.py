"""The ``mi-lidar`` Typer application, its console and its one error handler.

Every verb module (:mod:`mi_lidar.cli.render`, ``convert``, ``hybrid``, ``loop``, ``calibrate``)
registers its commands on :data:`app`. A command raises; it never prints an error itself: the
application's group catches :class:`~mi_lidar.core.errors.MiLidarError`, ``ValueError`` and
``OSError`` from any command, prints one line ``error: <message>`` and exits with code 2, the
code of click's own usage errors. Messages say what was wrong and what to do.
"""

from __future__ import annotations

import contextlib
import os
import time

import typer
from rich.console import Console
from typer.core import TyperGroup

from mi_lidar.core.errors import MiLidarError

console = Console()
USER_ERRORS = (MiLidarError, ValueError, OSError)


class FriendlyGroup(TyperGroup):
    """A command group that turns user errors raised by any of its commands into one-line messages."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except USER_ERRORS as exc:
            console.print(f"[bold red]error:[/] {exc}", soft_wrap=True, highlight=False)
            raise typer.Exit(code=2) from None


app = typer.Typer(
    name="mi-lidar",
    cls=FriendlyGroup,
    help="Lidar simulation on Mitsuba 3: render scans from XML scenes, simulate logs, convert real sensor data, "
    "compare, diagnose and calibrate sensor models.",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode="markdown",
)


def throttled_progress(every: float = 5.0):
    """A ``progress(done, total, label)`` callback that logs at most every ``every`` seconds (and at the end)."""
    last = [0.0]

    def progress(done: int, total: int, label: str) -> None:
        now = time.perf_counter()
        if now - last[0] > every or done == total:
            console.log(f"{label}: {done}/{total}")
            last[0] = now

    return progress


def versions() -> dict[str, str]:
    """Versions of mi-lidar, Mitsuba, Dr.Jit, the active variant and the LLVM library."""
    import drjit as dr
    import mitsuba as mi

    from mi_lidar import __version__

    llvm = os.environ.get("DRJIT_LIBLLVM_PATH", "system default")
    with contextlib.suppress(RuntimeError):  # the backend reports no version before it is initialised
        llvm = "{}.{}.{} ({})".format(*dr.detail.llvm_version(), llvm)
    return {
        "mi-lidar": __version__,
        "Mitsuba": mi.__version__,
        "Dr.Jit": dr.__version__,
        "variant": str(mi.variant()),
        "LLVM": llvm,
    }


def _version_callback(value: bool):
    if value:
        for name, version in versions().items():
            console.print(f"{name:9s} {version}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(
        False,
        "--version",
        callback=_version_callback,
        is_eager=True,
        help="Print the versions of mi-lidar, Mitsuba, Dr.Jit, the variant and LLVM.",
    ),
):
    """Lidar simulation for robot application development."""
