"""Scene XML in world coordinates far from the origin, loaded at a local origin.

A georeferenced scene places its shapes with ``<transform name="to_world">`` (``translate x="500012"
y="4000031"``). Mitsuba composes and applies that transform in float32 (0.25 m steps at 4e6 m), so
the XML is rewritten before Mitsuba reads it: each top-level element's ``to_world`` is evaluated in
float64, the local origin (:func:`mi_lidar.core.frames.local_origin` of the elements' positions) is
subtracted, and the result goes back as one ``<matrix>``; a shape placed by its own points instead
(a ``sphere``'s ``center``, a ``cylinder``'s ``p0`` and ``p1``, without a ``to_world``) gets them
moved the same way. The loader records the origin with the
scene (:func:`mi_lidar.core.frames.set_scene_origin`) so that poses are moved into the same frame
and outputs back out of it.

Supported transform steps: ``translate``, ``scale``, ``rotate``, ``matrix`` and ``lookat``, with
numbers or ``$name`` parameters. A file that uses anything else is loaded as written, and
:func:`mi_lidar.scene.loading.load_scene` refuses it if its geometry ends up far from the origin.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import numpy as np

from mi_lidar.core.errors import SceneError
from mi_lidar.core.frames import MAX_COORDINATE_M, local_origin

PLACED = ("shape", "sensor", "emitter")  # top-level elements whose to_world is moved to the local frame
PLACING_POINTS = ("center", "p0", "p1")  # points that place a shape without a to_world (sphere, cylinder), moved too


class UnsupportedTransform(SceneError):
    """A ``to_world`` step this module does not evaluate (:func:`rebase_xml` then loads the file as written)."""


def _numbers(text: str | None, parameters: dict[str, str]) -> list[float]:
    if text is None:
        raise UnsupportedTransform("to_world: a transform step lacks a value; give its numbers")
    text = re.sub(r"\$(\w+)", lambda m: parameters.get(m.group(1), m.group(0)), text)
    try:
        return [float(v) for v in text.replace(",", " ").split()]
    except ValueError as exc:
        raise UnsupportedTransform(f"to_world: {text!r} is not a list of numbers") from exc


def _vector(step: ET.Element, parameters: dict[str, str], default: float, name: str = "value") -> np.ndarray:
    """An ``x y z`` step value: the ``value`` attribute (one number is uniform) or ``x``, ``y``, ``z``."""
    if name in step.attrib:
        values = _numbers(step.attrib[name], parameters)
        if len(values) == 1:
            values *= 3
        if len(values) != 3:
            raise UnsupportedTransform(f"to_world: {step.attrib[name]!r} has not 1 or 3 numbers")
        return np.array(values)
    return np.array([_numbers(step.attrib.get(axis, str(default)), parameters)[0] for axis in "xyz"])


def _rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    """(4, 4) right-handed rotation by ``degrees`` about ``axis`` (Rodrigues), as Mitsuba builds it: the axis is
    not normalized (a non-unit axis scales and shears as it does in Mitsuba)."""
    angle = np.radians(degrees)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    matrix = np.eye(4)
    matrix[:3, :3] = np.cos(angle) * np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * np.outer(axis, axis)
    return matrix


def _look_at(step: ET.Element, parameters: dict[str, str]) -> np.ndarray:
    """Mitsuba's ``lookat``: columns left, up, direction and the origin."""
    origin, target, up = (np.array(_numbers(step.attrib.get(k), parameters)) for k in ("origin", "target", "up"))
    direction = (target - origin) / np.linalg.norm(target - origin)
    left = np.cross(up, direction)
    left /= np.linalg.norm(left)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = left, np.cross(direction, left), direction, origin
    return matrix


def to_world_matrix(transform: ET.Element, parameters: dict[str, str]) -> np.ndarray:
    """The (4, 4) float64 matrix of a ``<transform>`` element (steps applied in order: each left-multiplies).

    Raises:
        UnsupportedTransform: a step other than those of the module docstring, or a value that is not numbers.
    """
    with np.errstate(invalid="ignore", over="ignore"):  # inf steps make NaNs, refused by the caller, not warned
        return _compose(transform, parameters)


def _compose(transform: ET.Element, parameters: dict[str, str]) -> np.ndarray:
    matrix = np.eye(4)
    for step in transform:
        if step.tag == "translate":
            change = np.eye(4)
            change[:3, 3] = _vector(step, parameters, 0.0)
        elif step.tag == "scale":
            change = np.diag([*_vector(step, parameters, 1.0), 1.0])
        elif step.tag == "rotate":
            axis = _vector(step, parameters, 0.0)
            change = _rotation(axis, _numbers(step.attrib.get("angle"), parameters)[0])
        elif step.tag == "matrix":
            values = _numbers(step.attrib.get("value"), parameters)
            if len(values) == 9:
                change = np.eye(4)
                change[:3, :3] = np.reshape(values, (3, 3))
            elif len(values) == 16:
                change = np.reshape(values, (4, 4))
            else:
                raise UnsupportedTransform(f"to_world: matrix {step.attrib.get('value')!r} has not 9 or 16 numbers")
        elif step.tag == "lookat":
            change = _look_at(step, parameters)
        else:
            raise UnsupportedTransform(
                f"to_world: step <{step.tag}> is not one of translate, scale, rotate, matrix, lookat"
            )
        matrix = change @ matrix
    return matrix


def _check_shape_place(element: ET.Element, what: str, values: np.ndarray) -> None:
    """Refuse a top-level shape placed by a non-finite number (Mitsuba drops such a shape without a word) or a
    position beyond :data:`~mi_lidar.core.frames.MAX_COORDINATE_M` (a misread number). Sensors check their own pose.

    Args:
        element: the ``<shape>`` element.
        what: ``"to_world"`` or the placing point's name (``"center"``, ``"p0"``).
        values: its (4, 4) matrix or (3,) point.
    """
    if element.tag != "shape":
        return
    name = f"shape {element.attrib.get('id', element.attrib.get('type', ''))!r}"
    position = values[:3, 3] if values.ndim == 2 else values
    if not np.isfinite(values).all():
        shown = "" if values.ndim == 2 else f" ({values.tolist()})"
        raise SceneError(
            f"{name}: its {what} holds a non-finite number (NaN or inf){shown}; Mitsuba would drop the shape without "
            "a word: fix the transform or point"
        )
    if np.abs(position).max() > MAX_COORDINATE_M:
        raise SceneError(
            f"{name}: its {what} places it at {position.tolist()} m, beyond {MAX_COORDINATE_M:.0e} m (farther than any "
            "Earth-fixed coordinate): a misread number; fix the transform or point"
        )


def matrix_value(matrix: np.ndarray) -> str:
    """A (4, 4) matrix as an XML ``<matrix value>``, each entry in the shortest text that reads back exactly."""
    return " ".join(repr(float(v)) for v in np.asarray(matrix, dtype=np.float64).ravel())


def rebase_xml(text: str, parameters: dict[str, str] | None = None) -> tuple[str, np.ndarray] | None:
    """Rewrite a scene XML whose elements sit far from the origin into a local frame.

    Args:
        text: the scene XML.
        parameters: values of its ``<default>`` parameters given by the caller (they override the file's).

    Returns:
        ``(xml, origin)``: the rewritten XML and the local origin (3,) m in the world, or None when
        every top-level ``to_world`` stays within :data:`~mi_lidar.core.frames.NEAR_M` of the origin
        or uses a step this module does not evaluate (the file is then loaded as written).

    Raises:
        SceneError: a top-level shape placed by a non-finite number or beyond 1e8 m (:func:`_check_shape_place`).
    """
    try:
        root = ET.fromstring(text)
    except ET.ParseError:
        return None  # Mitsuba reports the syntax error with its own words
    values = {d.attrib["name"]: d.attrib.get("value", "") for d in root.iter("default") if "name" in d.attrib}
    values.update(parameters or {})
    placed, points = [], []
    try:
        for element in root:
            if element.tag not in PLACED:
                continue
            transform = element.find("transform[@name='to_world']")
            if transform is not None:
                placed.append((transform, to_world_matrix(transform, values)))
                _check_shape_place(element, "to_world", placed[-1][1])
            elif element.tag == "shape":  # a sphere's centre, a cylinder's ends: the points are world positions
                for point in element.findall("point"):
                    if point.attrib.get("name") in PLACING_POINTS:
                        points.append((point, _vector(point, values, 0.0)))
                        _check_shape_place(element, point.attrib["name"], points[-1][1])
    except (UnsupportedTransform, ValueError, ZeroDivisionError):
        return None
    if not placed and not points:
        return None
    origin = local_origin(np.array([matrix[:3, 3] for _, matrix in placed] + [p for _, p in points]))
    if not np.any(origin):  # every element within NEAR_M of the origin
        return None
    for transform, matrix in placed:
        matrix = matrix.copy()
        matrix[:3, 3] -= origin
        for step in list(transform):
            transform.remove(step)
        ET.SubElement(transform, "matrix", value=matrix_value(matrix))
    for point, position in points:
        for key in ("value", "x", "y", "z"):
            point.attrib.pop(key, None)
        point.attrib.update({axis: repr(float(v)) for axis, v in zip("xyz", position - origin)})
    return ET.tostring(root, encoding="unicode"), origin
