"""Exception types of mi-lidar.

Every error names the offending value and says what to do about it. All derive from
:class:`MiLidarError` so callers can catch the family at once.
"""

import tokenize
import zipfile
import zlib


class MiLidarError(Exception):
    """Base class of every error raised by mi-lidar."""


class MiLidarWarning(UserWarning):
    """Base class of the warnings of mi-lidar: the input is usable but worse than it looks; the CLI prints them."""


class CoarseCoordinatesWarning(MiLidarWarning):
    """Coordinates were stored in float32 where float32 keeps them more coarsely than a millimetre."""


class TruncatedLogWarning(MiLidarWarning):
    """A log ends in the middle of a record (a logger stopped mid-write): the complete records before it were read."""


class TimeOrderWarning(MiLidarWarning):
    """A log's timestamps step back by more than clock jitter (concatenated logs?): time windows misjudge which scans
    are neighbours."""


class DuplicateScanWarning(MiLidarWarning):
    """A log repeats scans exactly (the same returns at the same pose; a line written twice, or a stalled driver): the
    copies were dropped, so that no copy of a test scan trains a model."""


class EqualTimesWarning(MiLidarWarning):
    """A log's scans all have one timestamp (a converter that wrote no times?): time windows cannot tell its scans
    apart, so every scan counts as recent."""


class NoReturnValueWarning(MiLidarWarning):
    """A no-return value given for a log disagrees with the log: returns it holds are read as no-returns, or its
    no-return codes as returns."""


class BeamAnglesWarning(MiLidarWarning):
    """A log's beam angles are a guess: its lines do not give them, and its beam count is not one whose angles are
    known."""


class SetupError(MiLidarError):
    """The environment cannot run mi-lidar (missing LLVM, scalar variant, ...)."""


class ParameterError(MiLidarError, ValueError):
    """A plugin, pattern or effect parameter is out of range or unknown."""


class FitError(ParameterError):
    """A fit cannot take its next step: its loss, or the gradient of some of its parameters, is not finite."""


class PatternError(ParameterError):
    """A firing pattern name or table is invalid."""


class PoseError(ParameterError):
    """A sensor pose is not finite or not a rigid transform."""


class SceneError(MiLidarError):
    """A scene file cannot be loaded or holds invalid elements."""


class LogFormatError(MiLidarError):
    """A log or scan file is unreadable, truncated, empty or of an unknown version."""


class CalibrationError(MiLidarError, ValueError):
    """A calibration request cannot be fitted: no parameter matches, the log and scene disagree, or the loss
    diverges."""


class SpecError(MiLidarError, ValueError):
    """A run specification (e.g. a dataset spec file) is missing, malformed or inconsistent."""


class SensorMismatchError(MiLidarError, ValueError):
    """A log was recorded by another sensor than the scene's (beam count, field of view or range scale)."""


def unreadable(path, what: str = "file", error: type[MiLidarError] | None = None) -> MiLidarError:
    """The error for a file the process may not read: what happened and the two ways out.

    Args:
        path: The file.
        what: Its role in the message ("log", "file", "spec").
        error: The exception type of the reader's other errors (default :class:`LogFormatError`).
    """
    return (error or LogFormatError)(
        f"{path}: cannot read the {what} (permission denied); make it readable (chmod a+r {path}) or copy it to a "
        "file you may read"
    )


def parser_message(exc: Exception) -> str:
    """A parser's error on one line: ``line L, column C: problem`` for YAML parsers' marked errors (ruamel spreads
    them over several lines with a drawing of the spot), else the message with its line breaks folded."""
    mark, problem = getattr(exc, "problem_mark", None), getattr(exc, "problem", None)
    if mark is not None and problem:
        return f"line {mark.line + 1}, column {mark.column + 1}: {problem}"
    return " ".join(str(exc).split())


def describe_invalid(items: list[dict], header: str, footer: str = "") -> str:
    """One message listing every problem of a validated document, one line each.

    Args:
        items: pydantic's ``ValidationError.errors()``: dicts with ``loc``, ``msg`` and ``input``.
        header: the first line (the file and what it should be).
        footer: a last line saying where the fields are documented ("" for none).
    """
    lines = [header]
    for item in items:
        where = ".".join(str(p) for p in item["loc"]) or "(top level)"
        got = item.get("input")
        shown = "" if isinstance(got, (dict, list)) else f" (got {got!r})"
        lines.append(f"  {where}: {item['msg']}{shown}")
    return "\n".join(lines + ([footer] if footer else []))


# What numpy's .npy / .npz parsing raises on damaged files (a mangled header reaches ``ast`` and
# ``tokenize``, a huge shape overflows; a damaged deflate stream raises ``zlib.error``, a damaged zip
# directory can claim a zip version or compression that ``zipfile`` does not implement).
NUMPY_FILE_ERRORS = (
    zipfile.BadZipFile,
    zlib.error,
    ValueError,
    OSError,
    EOFError,
    OverflowError,
    UnicodeDecodeError,
    SyntaxError,
    tokenize.TokenError,
    NotImplementedError,
)
# ... and what reading a named member of an ``.npz`` archive adds: ``KeyError`` when the member is missing.
NPZ_MEMBER_ERRORS = (*NUMPY_FILE_ERRORS, KeyError)


def numpy_file_problem(exc: Exception) -> str:
    """What a numpy load error (one of :data:`NPZ_MEMBER_ERRORS`) says about the file, for a message.

    numpy reads a file that starts as neither an ``.npy`` array nor a zip archive as a pickle, and refuses it
    advising to "load it unsafely using the `allow_pickle=` keyword": for random bytes or another format, it
    is said so instead. Other errors are named with their type.
    """
    if isinstance(exc, ValueError) and "pickled" in str(exc):
        return "its first bytes are neither a numpy .npy header nor a zip archive: damaged, or another format"
    return f"{type(exc).__name__}: {exc}"
