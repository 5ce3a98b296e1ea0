"""Strict JSON: how every JSON file and JSON printout of mi-lidar is written.

Python's ``json`` writes ``NaN``, ``Infinity`` and ``-Infinity`` for non-finite floats. They are not JSON
(RFC 8259): JavaScript's ``JSON.parse``, Go's ``encoding/json``, Rust's ``serde_json`` and many dashboards
reject the whole file. Here a non-finite number is written as ``null``, which in mi-lidar's files means
*undefined or not measured*: the NLL of the misses of a log that has none, the range error of a group without
returns, the maximum range of a log without a no-return value. Finite numbers are written as before, digit for
digit. Readers that need a number back use :func:`nan_for_null`.
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
    if isinstance(value, (np.ndarray, np.floating)):
        value = value.tolist()
    if isinstance(value, float):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_or_null(v, default) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_null(v, default) for v in value]
    if value is None or isinstance(value, (str, int)) or default is None:
        return value
    return finite_or_null(default(value))


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
