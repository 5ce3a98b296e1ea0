"""Strict JSON: how every JSON file and JSON printout of mi-lidar is written.

Python's ``json`` writes ``NaN``, ``Infinity`` and ``-Infinity`` for non-finite floats. They are not JSON
(RFC 8259): JavaScript's ``JSON.parse``, Go's ``encoding/json``, Rust's ``serde_json`` and many dashboards
reject the whole file. Here a non-finite number is written as ``null``, which in mi-lidar's files means
*undefined or not measured*: the NLL of the misses of a log that has none, the range error of a group without
returns, the maximum range of a log without a no-return value. Finite numbers are written as before, digit for
digit. Readers that need a number back use :func:`nan_for_null`.

JSON embedded in other files (the header of a log or density ``.npz``, an EXR header attribute, a bag's sensor
message) holds values a reader needs back exactly: a sensor without a far end has ``max_range`` inf. There
:func:`dumps_exact` writes the same strict JSON and lists each non-finite number, by its JSON pointer (RFC 6901),
under the key :data:`NON_FINITE` of the top-level object, and :func:`loads_exact` puts them back::

    {"sensor": {"max_range": null}, "$non_finite": {"/sensor/max_range": "inf"}}
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mi_lidar.core.atomic import atomic_write_text

NON_FINITE = "$non_finite"  # the key of an object written by dumps_exact that lists its non-finite numbers
NON_FINITE_TEXT = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}  # how they are named there


def finite_or_null(value: Any, default: Callable[[Any], Any] | None = None) -> Any:
    """``value`` with every non-finite number replaced by None (JSON ``null``).

    Mappings, lists and tuples are walked (tuples become lists, as JSON has them); numpy arrays become
    (nested) lists and numpy floating scalars Python floats, so float32 and float64 arrays and scalars are
    covered; finite floats keep their value bit for bit.

    Args:
        value: a JSON-like value.
        default: called on any other object (e.g. ``float`` for numpy integers or Dr.Jit scalars); its result
            is walked in turn. None: the object is left for ``json`` to refuse (``TypeError``).

    Returns:
        A value ``json.dumps(..., allow_nan=False)`` writes.
    """
    return _walk(value, default, None, "")


def _walk(value: Any, default: Callable[[Any], Any] | None, found: dict[str, str] | None, pointer: str) -> Any:
    """:func:`finite_or_null` of ``value`` (at JSON pointer ``pointer``), naming each non-finite number in ``found``
    (``{pointer: "inf" | "-inf" | "nan"}``) when it is a dict."""
    if isinstance(value, (np.ndarray, np.floating)):
        value = value.tolist()
    if isinstance(value, float):
        if math.isfinite(value):
            return float(value)
        if found is not None:
            found[pointer] = repr(value)
        return None
    if isinstance(value, dict):
        return {k: _walk(v, default, found, f"{pointer}/{_escape(str(k))}") for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_walk(v, default, found, f"{pointer}/{i}") for i, v in enumerate(value)]
    if value is None or isinstance(value, (str, int)) or default is None:
        return value
    return _walk(default(value), default, found, pointer)


def _escape(key: str) -> str:
    """``key`` as one step of a JSON pointer (RFC 6901: ``~`` is ``~0``, ``/`` is ``~1``)."""
    return key.replace("~", "~0").replace("/", "~1")


def dumps(
    value: Any, indent: int | None = None, sort_keys: bool = False, default: Callable[[Any], Any] | None = None
) -> str:
    """Strict JSON text of ``value`` (:func:`finite_or_null`; ``indent`` and ``sort_keys`` as in ``json.dumps``).

    Raises:
        TypeError: an object JSON does not know and ``default`` does not convert.
    """
    return json.dumps(finite_or_null(value, default), indent=indent, sort_keys=sort_keys, allow_nan=False)


def write_json(
    path: str | os.PathLike,
    value: Any,
    indent: int | None = 1,
    sort_keys: bool = False,
    default: Callable[[Any], Any] | None = None,
) -> Path:
    """Write :func:`dumps` of ``value`` to ``path`` atomically (:func:`~mi_lidar.core.atomic.atomic_write_text`).

    Returns:
        ``path`` as a Path.
    """
    return atomic_write_text(path, dumps(value, indent=indent, sort_keys=sort_keys, default=default))


def nan_for_null(value: Any) -> Any:
    """``value`` read from a JSON file of numbers with every None (``null``) back to NaN; mappings and lists walked."""
    if value is None:
        return math.nan
    if isinstance(value, dict):
        return {k: nan_for_null(v) for k, v in value.items()}
    if isinstance(value, list):
        return [nan_for_null(v) for v in value]
    return value


def dumps_exact(value: dict, default: Callable[[Any], Any] | None = None, sort_keys: bool = False) -> str:
    """Strict JSON text of the object ``value`` that :func:`loads_exact` reads back exactly, non-finite numbers too.

    Each non-finite number is written as null (:func:`finite_or_null`) and named, by its JSON pointer, under the
    key :data:`NON_FINITE` (``{"/sensor/max_range": "inf"}``), which is written only when there is one.

    Args:
        value: a mapping (``default`` as in :func:`finite_or_null`, ``sort_keys`` as in ``json.dumps``).

    Raises:
        TypeError: ``value`` is not a mapping, or holds an object JSON does not know and ``default`` does not convert.
        ValueError: ``value`` has a key :data:`NON_FINITE` of its own.
    """
    if not isinstance(value, dict):
        raise TypeError(f"dumps_exact writes an object (a dict), not a {type(value).__name__}")
    if NON_FINITE in value:
        raise ValueError(f"the key {NON_FINITE!r} is reserved: it lists the non-finite numbers of the object")
    found: dict[str, str] = {}
    text = _walk(value, default, found, "")
    return json.dumps({**text, NON_FINITE: found} if found else text, sort_keys=sort_keys, allow_nan=False)


def loads_exact(text: str | bytes) -> Any:
    """The value of JSON ``text`` written by :func:`dumps_exact`, its listed non-finite numbers put back.

    Text written before (``NaN`` and ``Infinity`` as Python's ``json`` writes them) reads as it did.

    Raises:
        ValueError: ``text`` is not JSON, or its :data:`NON_FINITE` list is not one of pointers to nulls of the
            object, each named ``"inf"``, ``"-inf"`` or ``"nan"``.
    """
    value = json.loads(text)
    if not isinstance(value, dict) or NON_FINITE not in value:
        return value
    listed = value.pop(NON_FINITE)
    if not isinstance(listed, dict):
        raise ValueError(f"{NON_FINITE} holds a {type(listed).__name__}; expected an object of JSON pointers")
    for pointer, name in listed.items():
        if not isinstance(name, str) or name not in NON_FINITE_TEXT or not pointer.startswith("/"):
            raise ValueError(f"{NON_FINITE}: {pointer!r}: {name!r} is not a JSON pointer to 'inf', '-inf' or 'nan'")
        *path, last = [step.replace("~1", "/").replace("~0", "~") for step in pointer[1:].split("/")]
        try:
            parent = value
            for step in path:
                parent = parent[int(step) if isinstance(parent, list) else step]
            key = int(last) if isinstance(parent, list) else last
            null = parent[key] is None
        except (KeyError, IndexError, TypeError, ValueError):
            null = False
        if not null:
            raise ValueError(f"{NON_FINITE}: {pointer!r} does not point to a null of the object")
        parent[key] = NON_FINITE_TEXT[name]
    return value
