"""Loading scenes (XML files or dicts) with clear errors, and reading their Lidar settings."""

from __future__ import annotations

import os
import re
from pathlib import Path

import mitsuba as mi
import numpy as np

from mi_lidar.core.errors import MiLidarError, SceneError
from mi_lidar.core.frames import COORDINATES_DOC, check_float32, set_scene_origin
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.scene.cylinders import mesh_cylinders
from mi_lidar.scene.rebase import rebase_xml
from mi_lidar.scene.stray_text import check_stray_text


def bundled_scene(name: str) -> Path:
    """Path of a bundled example scene, e.g. ``"offroad.xml"``.

    Installed from a wheel the scenes are package data (``mi_lidar/scenes_xml``); in a source
    checkout they are the repository's ``scenes_xml`` folder.

    Raises:
        SceneError: No bundled scene of that name.
    """
    package = Path(__file__).resolve().parents[1]
    folders = (package / "scenes_xml", package.parent / "scenes_xml")
    for folder in folders:
        if (folder / name).is_file():
            return folder / name
    raise SceneError(f"{name}: no such bundled scene in {' or '.join(str(f) for f in folders)}")


def load_scene(source, optimize: bool = False, **parameters):
    """Load a Mitsuba scene from an XML path or a scene dict.

    Args:
        source: path of a scene XML, or a dict for ``mi.load_dict``.
        optimize: let Mitsuba merge meshes that share a material into one unnamed mesh (faster to
            build). Off by default, so every shape keeps its declared id: ``elements.<id>.*`` names
            every shape of the file and shape ids tell objects apart.
        parameters: values for the XML's ``<default>`` parameters (``$name``).

    Mitsuba's parallel loading is off (``parallel=False``): with it, loading a bundled scene rarely
    failed with ``failed to instantiate shape plugin of type "cube": basic_string::_M_create``. We saw
    this 3 times, including 1 failure in about 95 runs of ``mi-lidar demo``. Each time the shape's
    ``lidar_material`` (a Python plugin) was built on Mitsuba's loader threads. We could not reproduce
    it on demand. Serial loading costs 0.1 s on a 1M-triangle mesh (0.55 -> 0.65 s) and is faster for
    many small shapes (600 shapes with a ``lidar_material``: 0.06 s against 0.08 s).

    Every ``cylinder`` is loaded as a triangle mesh of the same tube (Mitsuba 3.9.1's own cylinder test
    misses thin poles far from the sensor: :mod:`mi_lidar.scene.cylinders`).

    A file whose shapes and sensors are placed far from the origin (a georeferenced ``translate``)
    is loaded at a local origin (:mod:`mi_lidar.scene.rebase`); :func:`mi_lidar.core.frames.scene_origin`
    gives that origin, and :func:`mi_lidar.simulate` moves poses into the scene's frame and its log
    back out of it.

    Raises:
        SceneError: the file is missing, malformed, holds stray text (:mod:`mi_lidar.scene.stray_text`: Mitsuba
            ignores it, and an element typed without its ``<`` is lost), or names an unknown plugin or property;
            the message keeps Mitsuba's explanation and names the file. Or the geometry reaches
            coordinates where float32 keeps more than 1 mm (e.g. a PLY of UTM vertices): the
            message names the coordinate and how to move the scene near the origin.
    """
    where = "scene dict" if isinstance(source, dict) else str(source)
    origin = np.zeros(3)
    try:
        if isinstance(source, dict):
            config = _parser_config(optimize=False)
            scene = _instantiate(config, mi.parser.parse_dict(config, source))
        else:
            path = Path(source)
            if not path.is_file():
                raise SceneError(f"{path}: no such scene file")
            values = {k: str(v) for k, v in parameters.items()}
            scene, origin = _load_file(path, optimize, values)
    except MiLidarError:
        raise
    except Exception as exc:
        raise SceneError(f"{where}: could not load the scene: {loader_message(exc)}") from exc
    box = scene.bbox()
    check_float32(
        [box.min, box.max],
        where,
        "vertex coordinates",
        "Move the scene near the origin: write mesh vertices relative to a local origin and place each shape "
        'there with <transform name="to_world"><translate .../></transform>, which mi-lidar reads in float64 '
        f"(see {COORDINATES_DOC})",
        SceneError,
    )
    set_scene_origin(scene, origin)
    return scene


def _load_file(path: Path, optimize: bool, values: dict[str, str]):
    """Load a scene file, at a local origin when its elements are placed far from the world's (:mod:`.rebase`).

    Returns:
        ``(scene, origin)``: the scene and the world position (m) of its frame's origin.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        text = ""  # Mitsuba's loader reports an unreadable file in its own words
    outside = check_stray_text(text, str(path)) if text else None
    try:
        rebased = rebase_xml(text, values)
    except SceneError as exc:  # a shape placed by a NaN or far off: name the file
        raise SceneError(f"{path}: {exc}") from exc
    config = _parser_config(optimize)
    resolver = mi.file_resolver()
    saved = [resolver[i] for i in range(len(resolver))]
    resolver.prepend(mi.filesystem.path(os.fspath(path.resolve().parent)))  # assets relative to the file
    try:
        if rebased is None:
            state, origin = mi.parser.parse_file(config, os.fspath(path), **values), np.zeros(3)
        else:
            state, origin = mi.parser.parse_string(config, rebased[0], **values), rebased[1]
        if outside is not None:  # text before or after the root element, which Mitsuba's parser skipped
            raise SceneError(outside)
        return _instantiate(config, state), origin
    finally:
        resolver.clear()
        for folder in saved:
            resolver.append(folder)


def _parser_config(optimize: bool):
    """Mitsuba's parser settings of ``mi.load_file(..., parallel=False, optimize=optimize)``."""
    config = mi.parser.ParserConfig(mi.variant())
    config.parallel = False
    config.merge_equivalent = config.merge_meshes = optimize
    return config


def _instantiate(config, state):
    """The scene of a parsed file or dict, made as ``mi.load_file`` makes it, with its cylinders as meshes
    (:mod:`mi_lidar.scene.cylinders`: Mitsuba 3.9.1's own cylinder misses thin poles far away)."""
    mi.parser.transform_all(config, state)
    mesh_cylinders(state)
    return mi.parser.instantiate(config, state)


PYTHON_TRACEBACK = "Traceback (most recent call last):"
LOADER_HINTS = (  # (text in Mitsuba's message, what to do), for the messages that do not say it
    (
        'plugin "lidar" is of type "sensor"',
        'the integrator is called `lidar_integrator`: write <integrator type="lidar_integrator">',
    ),
    (
        "incompatible sizes! (sizes: 0",
        "a mesh without faces gives this: give the shape at least one triangle, or remove it",
    ),
    (
        "didn't have normals at construction",
        "a mesh without vertices gives this: give the shape at least one triangle, or remove it",
    ),
)


def loader_message(exc: Exception) -> str:
    """Mitsuba's error on loading a scene, on one line: where in the file, the plugin, and the cause.

    A Python plugin (``lidar``, ``lidar_integrator``, ``lidar_material``) that refuses a value raises an error
    naming it; Mitsuba passes it on as the text of the whole Python traceback. The traceback is replaced by the
    error's own message, the C++ source locations (``[parser.cpp:1718]``) is dropped, line breaks are folded, and
    a hint is added where Mitsuba's words do not say what to do (:data:`LOADER_HINTS`).
    """
    text = str(exc)
    if isinstance(exc, UnicodeDecodeError):  # Mitsuba quoted bytes of a binary file that are not UTF-8
        text = exc.object.decode("utf-8", "backslashreplace")
    if PYTHON_TRACEBACK in text:
        context = text.split(PYTHON_TRACEBACK, 1)[0]
        trace = text.rsplit(PYTHON_TRACEBACK, 1)[1].splitlines()
        end = max((i for i, line in enumerate(trace) if line.startswith("  File ")), default=-1) + 1
        while end < len(trace) and trace[end][:1].isspace():  # the last frame's source line and markers
            end += 1
        text = context + re.sub(r"^[\w.]+: ", "", "\n".join(trace[end:]))
    text = " ".join(re.sub(r"\[[\w.]+\.(?:cpp|h):\d+\] ", "", text).split())
    hints = [hint for found, hint in LOADER_HINTS if found in text]
    return "; ".join([text, *hints])


def use_density(scene, spec: str | None):
    """Make ``spec`` the return density of ``scene``'s ``lidar_integrator`` (None leaves the scene as it is).

    The same as writing ``<string name="density" value="SPEC"/>`` in the scene's integrator, for a
    density fitted after the scene was written (``mi-lidar fit-sensor``): every path that renders,
    simulates or scores the scene then uses it.

    Args:
        scene: a loaded scene.
        spec: a density of the catalog with its settings, e.g. ``"np_reg(file=sensor.npz)"``,
            ``"physics(k=1e-4)"``; file names are relative to the working directory.

    Returns:
        ``scene``.

    Raises:
        SceneError: the scene has no ``lidar_integrator`` to carry the density.
        ParameterError: ``spec`` names no density of the catalog or a bad setting (named).
    """
    if spec is None:
        return scene
    from mi_lidar.core.densities import parse_density

    integrator = _lidar_integrator(scene, f"--density {spec!r}")
    integrator.density = parse_density(spec, resolve=lambda name: os.fspath(Path(name).resolve()))
    return scene


def use_effects(scene, spec: str | None):
    """Add the effects ``spec`` to those of ``scene``'s ``lidar_integrator`` (None leaves the scene as it is).

    The same as appending them to the integrator's ``effects`` string in the XML: every path that
    renders, simulates or scores the scene then applies them (``mi-lidar simulate --effect``: a log
    with an effect the scene's model lacks).

    Args:
        scene: a loaded scene.
        spec: effects of the catalog with their settings, e.g. ``"incidence_dropout(gamma=2)"``.

    Returns:
        ``scene``.

    Raises:
        SceneError: the scene has no ``lidar_integrator`` to carry the effects.
        ParameterError: ``spec`` names no effect of the catalog, or a bad setting (named).
    """
    if spec is None:
        return scene
    from mi_lidar.core.effects import parse_effects

    integrator = _lidar_integrator(scene, f"--effect {spec!r}")
    integrator.effects = [*integrator.effects, *parse_effects(spec)]
    return scene


def _lidar_integrator(scene, what: str):
    """The scene's ``lidar_integrator``; SceneError naming ``what`` needed it when the scene has another."""
    from mi_lidar.plugins.lidar_integrator import LidarIntegrator

    integrator = scene.integrator()
    if not isinstance(integrator, LidarIntegrator):
        raise SceneError(
            f"{what}: the scene's integrator is {type(integrator).__name__}, not a lidar_integrator; "
            'add <integrator type="lidar_integrator"/> to the scene'
        )
    return integrator


def scene_lidar_sensor(scene):
    """The scene's first ``lidar`` sensor, or None."""
    from mi_lidar.plugins.lidar_sensor import LidarSensor

    return next((s for s in scene.sensors() if isinstance(s, LidarSensor)), None)


def scene_sensor_model(scene) -> tuple[SensorModel, np.ndarray]:
    """The sensor model and (4, 4) pose given by the scene's ``lidar`` sensor and integrator.

    Scenes without a ``lidar`` sensor give the default model and the identity pose.
    """
    from mi_lidar.plugins.lidar_integrator import LidarIntegrator

    sensor = scene_lidar_sensor(scene)
    integrator = scene.integrator()
    if sensor is not None and isinstance(integrator, LidarIntegrator):
        return integrator.sensor_model(sensor), sensor.to_world_matrix
    model = SensorModel()
    if sensor is not None:
        model = SensorModel(range_sigma=sensor.range_sigma, min_range=sensor.min_range, max_range=sensor.max_range)
        return model, sensor.to_world_matrix
    if isinstance(integrator, LidarIntegrator):
        model = SensorModel(
            max_segments=integrator.max_segments,
            effects=integrator.effects,
            density=integrator.density,
            intensity=integrator.intensity,
        )
    return model, np.eye(4)
