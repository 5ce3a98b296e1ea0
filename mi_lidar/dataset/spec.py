"""The dataset spec: scenes, trajectories, the sensor rig, frame count and seed, validated by pydantic.

A spec is a YAML (``.yaml``/``.yml``) or TOML (``.toml``) file; relative paths in it are relative to
the spec's folder. See ``docs/datasets.md`` for every field and ``examples/datasets/`` for worked
specs. :func:`load_spec` raises :class:`~mi_lidar.core.errors.SpecError` naming every bad field.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from mi_lidar.core.errors import MiLidarError, SpecError, describe_invalid, parser_message, unreadable
from mi_lidar.core.frames import MAX_COORDINATE_M
from mi_lidar.core.params import MAX_DISTANCE_M, MAX_SIGMA_M, parse_calls
from mi_lidar.core.patterns import is_pattern_file
from mi_lidar.core.strict_json import dumps

MAX_FRAMES = 1_000_000  # KITTI names frames with 6 digits (000000.bin ... 999999.bin)
MAX_IMAGE_SIDE = 8192  # pixels, and samples per pixel below: the limits of `camera-lidar`
MAX_SPP = 4096
MAX_ANGLE_DEG = 360.0  # a mount angle beyond a turn is a unit slip or a misread number
Position = Annotated[float, Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)]  # m: beyond is no place on Earth
Angle = Annotated[float, Field(ge=-MAX_ANGLE_DEG, le=MAX_ANGLE_DEG)]


class Strict(BaseModel):
    """A spec section: unknown keys are errors (a typo never passes silently), and so are NaN and infinite numbers."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def rotation_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """(3, 3) rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (angles in rad)."""
    cr, sr, cp, sp, cy, sy = (
        math.cos(roll),
        math.sin(roll),
        math.cos(pitch),
        math.sin(pitch),
        math.cos(yaw),
        math.sin(yaw),
    )
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1.0]])
    ry = np.array([[cp, 0, sp], [0, 1.0, 0], [-sp, 0, cp]])
    rx = np.array([[1.0, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


class Mount(Strict):
    """Where a sensor sits on the vehicle: sensor-to-ego transform (ego: x forward, y left, z up, m).

    Either ``xyz`` (m) and ``rpy_deg`` (roll, pitch, yaw about x, y, z; degrees), or a 4x4 row-major
    ``matrix`` (then ``xyz`` and ``rpy_deg`` must stay unset).
    """

    xyz: tuple[Position, Position, Position] = (0.0, 0.0, 0.0)
    rpy_deg: tuple[Angle, Angle, Angle] = (0.0, 0.0, 0.0)
    matrix: tuple[tuple[float, float, float, float], ...] | None = None

    @model_validator(mode="after")
    def _one_form(self):
        if self.matrix is not None:
            if len(self.matrix) != 4:
                raise ValueError(f"matrix has {len(self.matrix)} rows; give 4 rows of 4 numbers (row-major 4x4)")
            if self.xyz != (0.0, 0.0, 0.0) or self.rpy_deg != (0.0, 0.0, 0.0):
                raise ValueError("give either matrix or xyz/rpy_deg, not both")
            m = np.asarray(self.matrix)
            if not (np.allclose(m[3], [0, 0, 0, 1]) and np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-4)):
                raise ValueError("matrix is not a rigid transform (orthonormal rotation, last row 0 0 0 1)")
        return self

    def to_matrix(self) -> np.ndarray:
        """(4, 4) sensor-to-ego transform."""
        if self.matrix is not None:
            return np.asarray(self.matrix, dtype=np.float64)
        m = np.eye(4)
        m[:3, :3] = rotation_rpy(*np.radians(self.rpy_deg))
        m[:3, 3] = self.xyz
        return m


class LidarSpec(Strict):
    """One Lidar of the rig: firing pattern, mount and sensor model (the integrator's syntax)."""

    name: str = "lidar"
    pattern: str = "vlp16"
    mount: Mount = Mount(xyz=(0.0, 0.0, 1.8))
    density: str = Field("gaussian", description="return density, e.g. 'np_reg(file=sensor.npz)'")
    effects: str = Field("", description="effects, e.g. 'range_noise(sigma0=0.01)'")
    range_sigma: float = Field(0.02, ge=0, le=MAX_SIGMA_M)  # m; beyond, a misread number (core.params)
    min_range: float = Field(0.5, ge=0, le=MAX_DISTANCE_M)
    max_range: float = Field(100.0, gt=0, le=MAX_DISTANCE_M)
    max_segments: int = Field(16, ge=1, le=256)


class CameraSpec(Strict):
    """One pinhole camera: image size (pixels), horizontal field of view (deg) and mount.

    With ``xyz``/``rpy_deg`` the camera looks along the mount's x axis (image right = mount -y,
    image down = mount -z); a ``matrix`` mount is the OpenCV optical frame (x right, y down, z forward)
    to ego, as nuScenes' ``cam2ego``.
    """

    name: str
    width: int = Field(640, ge=8, le=MAX_IMAGE_SIDE)
    height: int = Field(360, ge=8, le=MAX_IMAGE_SIDE)
    fov_deg: float = Field(70.0, gt=1, lt=179)
    mount: Mount = Mount(xyz=(0.0, 0.0, 1.6))


class NuScenesRig(Strict):
    """Cameras (and the Lidar mount) from a nuScenes calibration pickle (``cam2img``, ``cam2ego``, ``lidar2ego``).

    ``image_scale`` shrinks the 1600x900 images (0.25 gives 400x225); the field of view comes from the
    focal length and the principal point from ``cam2img`` (nuScenes' lie 8-51 px from the image centre).
    """

    file: Path
    cameras: list[str] = ["CAM_FRONT"]
    image_scale: float = Field(0.25, gt=0, le=1)


class RigSpec(Strict):
    """The sensor rig: Lidars (points of all are merged in the first Lidar's frame) and cameras."""

    lidars: list[LidarSpec] = Field(min_length=1)
    cameras: list[CameraSpec] = []
    nuscenes: NuScenesRig | None = None

    @model_validator(mode="after")
    def _names(self):
        names = [s.name for s in self.lidars] + [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"sensor names must be unique; got {names}")
        if not self.cameras and self.nuscenes is None:
            raise ValueError("the rig has no camera: add cameras: [...] or nuscenes: {file: ..., cameras: [...]}")
        return self


class Trajectory(Strict):
    """The ego path: a polyline of waypoints (m); frames are spread evenly along it, heading = tangent.

    ``follow_ground`` sets the ego height on the scene's ground mesh (hybrid scenes); otherwise the
    waypoint's z (default 0) is the ego height.
    """

    waypoints: list[tuple[Position, ...]] = Field(min_length=2)
    follow_ground: bool = True

    @field_validator("waypoints")
    @classmethod
    def _distinct(cls, value):
        for i, w in enumerate(value):
            if len(w) not in (2, 3):
                raise ValueError(f"waypoint {i} has {len(w)} numbers; give [x, y] or [x, y, z] (m)")
        xy = np.asarray([w[:2] for w in value], float)
        if np.any(np.linalg.norm(np.diff(xy, axis=0), axis=1) < 1e-6):
            raise ValueError("consecutive waypoints must differ in x or y")
        return value


class XmlObject(Strict):
    """A labelled object of an XML scene: its class and the shape ids it is made of (one 3D box)."""

    class_name: str = Field(alias="class", pattern=r"^\S+$")  # the first word of a KITTI label_2 line
    shapes: list[str] = Field(min_length=1)


class RandomObjects(Strict):
    """Objects drawn from the primitive library's classes along the trajectory (thesis ch. 4.3)."""

    classes: list[str] = Field(min_length=1)
    count: int = Field(30, ge=1)
    lateral: tuple[float, float] = Field((4.0, 15.0), description="distance from the path, min and max (m)")

    @field_validator("classes")
    @classmethod
    def _known(cls, value):
        from mi_lidar.hybrid.classes import class_id

        for name in value:
            class_id(name)
        return value

    @field_validator("lateral")
    @classmethod
    def _range(cls, value):
        if not 0 <= value[0] < value[1]:
            raise ValueError(f"lateral must be (min, max) with 0 <= min < max (m); got {value}")
        return value


class SceneSpec(Strict):
    """One scene of the dataset: an XML file, an annotation filled from a library, or random objects."""

    name: str
    frames: int = Field(ge=1, le=MAX_FRAMES)
    trajectory: Trajectory
    xml: Path | None = None
    parameters: dict[str, str] = {}
    objects: list[XmlObject] = []
    labels: dict[int, str] = {}
    annotation: Path | None = None
    library: Path | None = None
    random: RandomObjects | None = None
    ground: Path | None = None
    variants: int = Field(1, ge=1)

    @model_validator(mode="after")
    def _one_source(self):
        sources = [k for k in ("xml", "annotation", "random") if getattr(self, k) is not None]
        if len(sources) != 1:
            raise ValueError(f"give exactly one of xml, annotation or random; got {sources or 'none'}")
        if self.xml is None and self.library is None:
            raise ValueError(f"{sources[0]} scenes need library: (a primitive library folder)")
        if self.xml is not None and (self.library is not None or self.ground is not None):
            raise ValueError("library and ground belong to annotation or random scenes, not xml")
        if self.variants > self.frames:
            raise ValueError(f"variants ({self.variants}) exceeds frames ({self.frames})")
        if self.variants > 1 and self.random is None:
            raise ValueError("variants > 1 needs random: objects (other scenes are fixed)")
        return self


class OutputSpec(Strict):
    """What is written per frame besides the KITTI files."""

    spp: int = Field(16, ge=1, le=MAX_SPP, description="camera samples per pixel")
    overlays: bool = False
    semantic_ids: dict[str, Annotated[int, Field(ge=0, le=0xFFFF)]] = Field(
        {}, description="class name -> SemanticKITTI label id (16 bits), over the defaults"
    )


class DatasetSpec(Strict):
    """A whole dataset: ``frames`` is the sum of the scenes' frames; frame ``k`` depends on ``seed`` and ``k`` only."""

    name: str = "dataset"
    seed: int = Field(0, ge=0)
    rig: RigSpec
    scenes: list[SceneSpec] = Field(min_length=1)
    output: OutputSpec = OutputSpec()
    base_dir: Path = Path(".")
    source: dict = {}

    @model_validator(mode="after")
    def _unique_scenes(self):
        names = [s.name for s in self.scenes]
        if len(set(names)) != len(names):
            raise ValueError(f"scene names must be unique; got {names}")
        if self.frames > MAX_FRAMES:
            raise ValueError(
                f"the scenes' frames add up to {self.frames:,}; KITTI names frames with 6 digits, so a dataset holds "
                f"at most {MAX_FRAMES:,}: split it into several datasets"
            )
        return self

    @property
    def frames(self) -> int:
        """Total number of frames."""
        return sum(s.frames for s in self.scenes)

    @property
    def digest(self) -> str:
        """SHA-256 of the spec as written (what resume compares)."""
        return hashlib.sha256(dumps(self.source, sort_keys=True).encode()).hexdigest()

    def resolve(self, path: Path | str) -> Path:
        """A spec path made absolute against the spec's folder."""
        return (self.base_dir / Path(path)).resolve()

    def locate(self, frame: int) -> tuple[int, int, int, int]:
        """``(scene index, variant, index within the variant, frames of the variant)`` of frame ``frame``.

        A scene's frames are split into ``variants`` contiguous runs, each covering the whole path.
        """
        if not 0 <= frame < self.frames:
            raise SpecError(f"frame {frame} out of range 0..{self.frames - 1}")
        first = 0
        for index, scene in enumerate(self.scenes):
            if frame < first + scene.frames:
                local = frame - first
                bounds = np.linspace(0, scene.frames, scene.variants + 1).round().astype(int)
                variant = int(np.searchsorted(bounds, local, side="right") - 1)
                return index, variant, local - int(bounds[variant]), int(bounds[variant + 1] - bounds[variant])
            first += scene.frames
        raise AssertionError("unreachable")


def read_spec_file(path: Path) -> dict:
    """The raw mapping of a YAML or TOML spec file."""
    if not path.is_file():
        raise SpecError(f"{path}: no such spec file")
    suffix = path.suffix.lower()
    try:
        if suffix in (".yaml", ".yml"):
            from ruamel.yaml import YAML

            data = YAML(typ="safe").load(path.read_text())
        elif suffix == ".toml":
            try:
                import tomllib
            except ModuleNotFoundError:  # Python 3.10
                import tomli as tomllib
            data = tomllib.loads(path.read_text())
        else:
            raise SpecError(f"{path}: unknown spec format {suffix!r}; write the spec as .yaml, .yml or .toml")
    except SpecError:
        raise
    except PermissionError as exc:
        raise unreadable(path, "spec", SpecError) from exc
    except Exception as exc:
        raise SpecError(f"{path}: cannot parse the spec: {parser_message(exc)}") from exc
    if not isinstance(data, dict):
        raise SpecError(f"{path}: the spec must be a mapping of fields (name, seed, rig, scenes, output)")
    return data


def load_spec(path: str | Path, source: dict | None = None) -> DatasetSpec:
    """Read and validate a dataset spec.

    Args:
        path: the spec file (``.yaml``, ``.yml`` or ``.toml``); relative paths inside it are taken
            from its folder.
        source: the already-read mapping (skips reading ``path``; used to rebuild a spec from a manifest).

    Raises:
        SpecError: missing or unparsable file, unknown or invalid fields (every one is listed), a
            referenced file that does not exist, a Lidar pattern or sensor model that cannot be built, or a
            nuScenes file that does not read.
    """
    path = Path(path)
    data = read_spec_file(path) if source is None else source
    try:
        spec = DatasetSpec.model_validate({**data, "base_dir": path.resolve().parent, "source": data})
    except ValidationError as exc:
        raise SpecError(
            describe_invalid(exc.errors(), f"{path}: invalid dataset spec:", "See docs/datasets.md for every field.")
        ) from None
    missing = [(where, file) for where, file in _referenced_files(spec) if not spec.resolve(file).exists()]
    if missing:
        lines = [f"{where}: {file} ({spec.resolve(file)}){_what(spec, where)}" for where, file in missing]
        raise SpecError(
            f"{path}: referenced files do not exist (paths in a spec are relative to its folder, {spec.base_dir}):\n  "
            + "\n  ".join(lines)
            + _how_to_make(path, spec, missing)
        )
    from mi_lidar.dataset.rig import check_lidars, check_nuscenes  # the rig module builds on this one

    problems = check_lidars(spec) + check_nuscenes(spec)
    if problems:
        raise SpecError(f"{path}: the rig cannot be built:\n  " + "\n  ".join(problems))
    return spec


def _referenced_files(spec: DatasetSpec) -> list[tuple[str, Path]]:
    files = []
    for i, scene in enumerate(spec.scenes):
        for key in ("xml", "annotation", "library", "ground"):
            value = getattr(scene, key)
            if value is not None:
                files.append((f"scenes.{i}.{key}", value))
    for i, lidar in enumerate(spec.rig.lidars):
        if is_pattern_file(lidar.pattern):
            files.append((f"rig.lidars.{i}.pattern", lidar.pattern))
        files.extend((f"rig.lidars.{i}.density", file) for file in density_files(lidar.density))
    if spec.rig.nuscenes is not None:
        files.append(("rig.nuscenes.file", spec.rig.nuscenes.file))
    return files


def density_files(density: str) -> list[str]:
    """The ``file=`` names of a return density in the integrator's syntax: ``["sensor.npz"]`` for
    ``np_reg(file=sensor.npz)``; empty when the text does not parse (building the density names that mistake).
    """
    files = []

    def note(name: str, **values) -> None:
        if "file" in values:
            files.append(str(values["file"]))

    try:
        parse_calls(density, note, "density")
    except MiLidarError:
        return []
    return files


SCENE_FILES = {"xml": "scene XML", "annotation": "annotation", "library": "primitive library", "ground": "ground mesh"}
LIDAR_FILES = {"pattern": "firing pattern", "density": "density file"}


def _what(spec: DatasetSpec, where: str) -> str:
    """``", the primitive library of scene 'forest'"`` for ``scenes.1.library``, ``", the density file of Lidar
    'top'"`` for ``rig.lidars.0.density``; ``""`` for the nuScenes file."""
    parts = where.split(".")
    if parts[0] == "scenes":
        return f", the {SCENE_FILES[parts[2]]} of scene {spec.scenes[int(parts[1])].name!r}"
    if parts[:2] == ["rig", "lidars"]:
        return f", the {LIDAR_FILES[parts[3]]} of Lidar {spec.rig.lidars[int(parts[2])].name!r}"
    return ""


def _header_setup(path: Path) -> tuple[str, list[str]]:
    """The setup note of a spec's header comment: its sentence and its ``mi-lidar`` commands, in order.

    The header is the comment block that opens the file; its commands are the comment lines that start
    with ``mi-lidar`` (the spec's own ``mi-lidar dataset`` line left out), and its sentence is the comment
    line just above the first of them. ``("", [])`` when the file has no such header or cannot be read.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return "", []
    header = []
    for line in text.splitlines():
        if not line.startswith("#"):
            break
        header.append(line.lstrip("#").strip())
    first = next((i for i, line in enumerate(header) if line.startswith("mi-lidar ")), None)
    if first is None:
        return "", []
    commands = [line for line in header[first:] if line.startswith("mi-lidar ") and line.split()[1] != "dataset"]
    return (header[first - 1] if first else ""), commands


def _names(command: str, target: Path) -> bool:
    """Whether a header command names ``target``: one of its relative paths is the tail of ``target``."""
    return any(
        not word.startswith("-") and "/" in word and target.parts[-len(Path(word).parts) :] == Path(word).parts
        for word in command.split()
    )


def _how_to_make(path: Path, spec: DatasetSpec, missing: list[tuple[str, Path]]) -> str:
    """What to run to make the missing files: the setup commands of the spec's header when one of them names a
    missing file, else for a missing primitive library or density file the verb that makes one; "" otherwise."""
    note, commands = _header_setup(path)
    if any(_names(c, spec.resolve(file)) for c in commands for _, file in missing):
        return f"\nThe spec's header says: {note or 'make them with'}\n  " + "\n  ".join(commands)
    libraries = [spec.resolve(file) for where, file in missing if where.endswith(".library")]
    densities = [spec.resolve(file) for where, file in missing if where.endswith(".density")]
    verbs = []
    if libraries:
        verbs.append(f"Make a primitive library with `mi-lidar primitives extract LOG --library {libraries[0]}`.")
    if densities:
        verbs.append(f"Fit a density file with `mi-lidar fit-sensor LOG SCENE.xml --out {densities[0]}`.")
    return "".join(f"\n{verb}" for verb in verbs)
