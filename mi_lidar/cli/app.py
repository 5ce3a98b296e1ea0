"""The ``mi-lidar`` Typer application, its console and its one error handler.

Every verb module (:mod:`mi_lidar.cli.render`, ``convert``, ``hybrid``, ``loop``, ``calibrate``)
registers its commands on :data:`app`. A command raises; it never prints an error itself: the
application's group catches :class:`~mi_lidar.core.errors.MiLidarError`, ``ValueError`` and
``OSError`` from any command, prints one line ``error: <message>`` and exits with code 2, the
code of click's own usage errors. Messages say what was wrong and what to do. SIGTERM ends a command with its
clean-up, as Ctrl-C does (exit code 143).

Help stays readable in an 80-column terminal (``tests/test_cli_help.py``): a number option's metavar is
``N`` (integer) or ``X`` (real) so the type column stays narrow, a flag has one name (``--force``, not
``--force/--no-force``), a verb with many options groups them in panels (``rich_help_panel``), and the
examples are fenced blocks whose lines fit 76 columns.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import sys
import threading
import warnings
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape
from typer.core import TyperGroup

from mi_lidar.core.errors import MiLidarError, MiLidarWarning

console = Console()
USER_ERRORS = (MiLidarError, ValueError, OSError)


def given_value(args: list[str], param) -> str | None:
    """The text given for option ``param`` in the command line ``args`` (``--seed -1`` or ``--seed=-1``), or None.

    The last one when the option is repeated: the value click keeps.
    """
    for i, token in reversed(list(enumerate(args))):
        for opt in getattr(param, "opts", ()):
            if token == opt and i + 1 < len(args):
                return args[i + 1]
            if token.startswith(opt + "="):
                return token[len(opt) + 1 :]
    return None


def usage_error_line(exc, args: list[str]) -> str:
    """One line for a usage error (click's, vendored by Typer): the value given, what is wrong, where to look."""
    message = exc.format_message().rstrip(".")
    param = getattr(exc, "param", None)
    value = None if param is None else given_value(args, param)
    if value is not None and value.strip().lower().lstrip("+-") == "nan":
        # the range check compares and reports a bound ('Input should be less than or equal to 1')
        message = f"Invalid value for '{param.opts[0]}': {value!r} is not a number; give one in {number_range(param)}"
    elif value is not None:
        message = f"{message} (got {value!r})"
    command = exc.ctx.command_path if exc.ctx is not None else "mi-lidar"
    return f"{message}; see `{command} --help`"


def number_range(param) -> str:
    """The range of a number option as ``--help`` prints it (``0.005<=x<=1.0``; ``x`` alone when unbounded)."""
    low, high = getattr(param, "min", None), getattr(param, "max", None)
    return ("" if low is None else f"{low}<=") + "x" + ("" if high is None else f"<={high}")


NUMBER_METAVARS = {"int": "N", "float": "X"}  # Python types -> the app's number metavars


def plain_metavars(params: list) -> list:
    """``params`` with a plain word in the type column of ``--help`` where Typer would print a Python type.

    Typer's rich help writes ``<bool>`` beside a flag that takes no value (``--force``, ``--help``),
    ``<str>`` or ``<list[str]>`` beside a text option and ``<float>`` beside a number. A flag gets an
    empty metavar (what the plain help prints), a number ``N`` or ``X`` as everywhere in the app, and a
    text value its own name in capitals (``--model`` -> ``MODEL``), with ``...`` when it may repeat.
    Metavars the commands set, paths (``<file>``, ``<dir>``) and choices stay. Returns ``params``.
    """
    for param in params:
        if param.metavar is not None:
            continue
        if getattr(param, "is_flag", False):
            param.metavar = ""
            continue
        descriptor = getattr(param, "type_descriptor", None)
        if descriptor is None or descriptor.is_path or descriptor.is_choice:
            continue
        bare = param.bare_type()
        many = bare.startswith("list[")
        bare = bare.removeprefix("list[").removesuffix("]")
        word = NUMBER_METAVARS.get(bare) or (param.name.upper() if bare == "str" and param.name else None)
        if word:
            param.metavar = word + (" ..." if many else "")
    return params


@contextlib.contextmanager
def _terminated_as_exit():
    """Within the block, SIGTERM (``kill``, ``timeout``, a CI job cancelled) raises ``SystemExit(143)`` in the main
    thread, so that the clean-up of a command runs as for Ctrl-C: a run's new output folder is removed while it holds
    no file, a staged report or scene and a temporary file are removed (:mod:`mi_lidar.core.atomic`). By default
    SIGTERM ended the process at once and left them behind. A second SIGTERM ends the process at once."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def exit_on(signum, frame):
        signal.signal(signum, signal.SIG_DFL)
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, exit_on)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class FriendlyGroup(TyperGroup):
    """A command group that turns user errors raised by any of its commands into one-line messages.

    Bad command-line values (click's usage errors: a value out of range, a missing option) and the
    errors a command raises (:data:`USER_ERRORS`) both print ``error: <message>`` and exit with 2.
    Its own options and its commands' show plain words, not Python types, in ``--help`` (:func:`plain_metavars`).
    """

    def get_params(self, ctx):
        return plain_metavars(super().get_params(ctx))

    def get_command(self, ctx, cmd_name):
        command = super().get_command(ctx, cmd_name)
        if command is not None:
            plain_metavars(command.get_params(ctx))
        return command

    def invoke(self, ctx):
        args = list(ctx.args)
        with warnings.catch_warnings(), _terminated_as_exit():  # restore the filters, the printer and the handler
            warnings.simplefilter("always", MiLidarWarning)
            warnings.showwarning = _show_warning
            return self._invoke(ctx, args)

    def _invoke(self, ctx, args: list[str]):
        try:
            return super().invoke(ctx)
        except typer.TyperException as exc:
            if getattr(exc, "exit_code", None) != 2 or not hasattr(exc, "format_message"):
                raise  # typer.Exit, typer.Abort: not errors of the user's input
            fail(usage_error_line(exc, args))
        except OSError as exc:
            fail(os_error_line(exc))
        except USER_ERRORS as exc:
            fail(str(exc))


# The handler sees the error, not the operation that raised it: a denied access is worded for a read and a write alike.
PERMISSION_FIX = (
    "check the permissions: reading a file needs read access to it, writing one needs write access to its folder; "
    "or choose another path"
)
OS_ERROR_FIXES = {
    errno.EACCES: PERMISSION_FIX,
    errno.EPERM: PERMISSION_FIX,
    errno.EROFS: "the file system is read-only: choose a folder on a writable disk",
    errno.ENOTDIR: "a part of the path is a file, not a folder: choose another path",
    errno.EISDIR: "the path is a folder: give a file name",
    errno.EEXIST: "a file of that name is in the way of the folder: give another path, or move the file",
    errno.ENOENT: "check the path",
    errno.ENOSPC: "the disk is full: free space or choose another disk",
    errno.EDQUOT: "your disk quota is used up: free space or choose another disk",
    errno.EFBIG: "the file is larger than the file system or the process's limit (ulimit -f) allows: choose another "
    "disk or raise the limit",
    errno.EIO: "the write failed (a full disk, a file size limit, a failing disk): check the space (df) and "
    "`ulimit -f`, or choose another disk",
}


def os_error_line(exc: OSError) -> str:
    """One line for a failed file operation: the path, what the system said, and what to do."""
    if exc.errno not in OS_ERROR_FIXES or not exc.filename:
        return str(exc)
    return f"{exc.filename}: {exc.strerror[:1].lower()}{exc.strerror[1:]}; {OS_ERROR_FIXES[exc.errno]}"


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Print mi-lidar's warnings as ``warning: <message>`` lines; others as Python prints them."""
    if issubclass(category, MiLidarWarning):
        warn([str(message)])
    else:
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def warn(messages: list[str]) -> None:
    """Print each message as one ``warning: <message>`` line (its text as written, never read as markup)."""
    for message in messages:
        console.print(f"warning: {message}", highlight=False, markup=False)


def say(text: str) -> None:
    """Print a verdict written in the reports' Markdown: ``**name**`` in bold on a terminal (plain in a log),
    everything else as written (never read as rich markup)."""
    parts = escape(text).split("**")
    console.print("".join(f"[bold]{p}[/bold]" if i % 2 else p for i, p in enumerate(parts)), highlight=False)


def fail(message: str) -> None:
    """Print ``error: <message>`` on one line and exit with code 2."""
    console.print(f"[bold red]error:[/] {escape(message)}", soft_wrap=True, highlight=False, markup=True)
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


MAX_STEPS = 100_000  # the most Adam steps a verb takes: minutes to hours; more is a typo, not a plan


def density_option():
    """The ``--density`` option of the verbs that simulate or score a scene (see :func:`mi_lidar.scene.use_density`)."""
    return typer.Option(
        None,
        "--density",
        help="Return density to use instead of the scene's, e.g. `np_reg(file=sensor.npz)` from `fit-sensor`, "
        "or `physics(k=1e-4)`.",
    )


def force_option(verb: str):
    """The ``--force`` flag of the verbs that refuse a log whose sensor does not match the scene's."""
    return typer.Option(False, "--force", help=f"{verb} even when the log's sensor does not match the scene's.")


def log_argument():
    """The LOG argument of the verbs that take ``LOG SCENE`` (``compare``, ``diagnose``, ``fit-sensor``): a scene
    XML given first is refused saying which argument is which (the reader only knew '.xml' was not a log's)."""

    def not_a_scene(ctx: typer.Context, log: Path) -> Path:
        if log.suffix.lower() == ".xml":
            raise typer.BadParameter(
                f"{log} is a scene XML: the first argument is the log, the second the scene "
                f"(`{ctx.command_path} LOG SCENE.xml ...`)"
            )
        return log

    return typer.Argument(..., help="Measured log (any format `convert` reads).", exists=True, callback=not_a_scene)


def carmen_log_argument():
    """The LOG argument of the verbs that read a planar CARMEN log (``benchmark-planar``, ``evaluate-apps``)."""
    return typer.Argument(
        ...,
        help="A SLAM-corrected CARMEN log (`.log`, `.clf` or `.log.gz`) with FLASER or ROBOTLASER1 lines.",
        exists=True,
        dir_okay=False,
    )


def max_range_option():
    """The ``--max-range`` option of the verbs that read a planar CARMEN log."""
    return typer.Option(
        None,
        "--max-range",
        metavar="X",
        min=0.1,
        max=10_000.0,
        help="The sensor's no-return value (m, at most 10 km: the longest range the models take); default: detected "
        "from the log.",
    )


def carmen_message_option():
    """The ``--message`` option of the verbs that read a planar CARMEN log."""
    return typer.Option(
        None,
        "--message",
        metavar="NAME",
        help="The laser lines to read: FLASER, RLASER, ROBOTLASER1 or ROBOTLASER2; default: FLASER when the log "
        "has any, else ROBOTLASER1.",
    )


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
