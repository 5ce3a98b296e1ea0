"""The calibration parameter namespace: every fittable quantity of a scene and sensor model, by name.

Names (select them with ``fnmatch`` globs, for example ``elements.*.p_hit`` or ``sensor.*``):

====================================  =====================  ======================  ===========
name                                  values                 unit                    optimized as
====================================  =====================  ======================  ===========
``elements.<shape>.p_hit``            one per element        probability             logit
``elements.<shape>.range_sigma``      one per triangle       m                       log
``classes.<label>.range_sigma``       one per class          m                       log
``elements.<shape>.centers``          3 per ellipsoid        m                       value
``elements.<shape>.scales``           3 per ellipsoid        m                       log
``terrain.<shape>.heights``           one per mesh vertex    m (z)                   value
``sensor.elevation_offset``           one per beam           rad                     value
``sensor.azimuth_offset``             one per beam           rad                     value
``sensor.range_bias``                 one per beam           m                       value
``sensor.range_scale``                one                    1                       value
``sensor.extrinsics``                 rx ry rz tx ty tz      rad, m (sensor frame)   value
``effects.<effect>.<parameter>``      as the effect's        the effect's            value
``density.<density>.<parameter>``     as the density's       the density's           value
====================================  =====================  ======================  ===========

The ``sensor.*`` names are the effects ``beam_offsets``, ``range_bias``, ``range_scale`` and
``extrinsics``; selecting one adds its effect at identity when the model lacks it. Values are
clipped to their bounds after every optimizer step.
"""

from __future__ import annotations

import copy
import dataclasses
import fnmatch
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.effects import make_effect
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import CalibrationError
from mi_lidar.core.fitting import FitVariable
from mi_lidar.core.scene_shapes import ELLIPSOID_STRIDE
from mi_lidar.core.segment import ELLIPSOID
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.core.smoothing import inflation

P_EPS = 1e-4  # hit probabilities are kept in [P_EPS, 1 - P_EPS] so that their logits stay finite
MIN_SCALE = 1e-3  # m: smallest ellipsoid scale and range sigma

# sensor name -> (effect name, effect parameters, unit, default learning rate, changes the trace)
SENSOR_EFFECTS = {
    "sensor.elevation_offset": ("beam_offsets", ("elevation",), "rad", 2e-4, True),
    "sensor.azimuth_offset": ("beam_offsets", ("azimuth",), "rad", 2e-4, True),
    "sensor.range_bias": ("range_bias", ("bias",), "m", 1e-3, False),
    "sensor.range_scale": ("range_scale", ("scale",), "1", 2e-4, False),
    "sensor.extrinsics": ("extrinsics", ("rx", "ry", "rz", "tx", "ty", "tz"), "rad, m", 1e-3, True),
}
EFFECT_ORDER = ("beam_offsets", "extrinsics", "range_scale", "range_bias")  # firing table, pose, then ranges


@dataclass
class Parameter:
    """One named parameter (a flat array of values).

    Attributes:
        name: its name in the namespace.
        family: ``p_hit``, ``range_sigma``, ``class_sigma``, ``centers``, ``scales``, ``heights``,
            ``sensor``, ``effect`` or ``density``.
        initial: (n,) initial natural values.
        transform: ``"value"``, ``"log"`` or ``"logit"``: the optimized variable is the natural
            value, its log or its logit.
        lower, upper: bounds of the natural values (clipped after every step).
        lr: default Adam learning rate of the optimized variable.
        unit: unit of the natural values.
        geometric: changing it moves what rays meet, so rays are re-traced at every step.
        target: ``(array name, index)`` for table arrays, or ``(effect name, keys)`` for effects.
        per_beam: one value per beam of the log's sensor (a per-beam effect parameter).
    """

    name: str
    family: str
    initial: np.ndarray
    transform: str
    lower: float
    upper: float
    lr: float
    unit: str
    geometric: bool
    target: tuple = field(default=())
    per_beam: bool = False

    def variable(self, initial: np.ndarray, lr: float) -> FitVariable:
        """The fitter's view of this parameter, starting at natural values ``initial`` with step ``lr``."""
        return FitVariable(self.name, initial, lower=self.lower, upper=self.upper, scale=lr, transform=self.transform)


def _range_sigma(name: str, family: str, start, elements) -> Parameter:
    """A range-sigma parameter: fitted through its log within [MIN_SCALE, 10] m, started at ``start`` (m, raised
    to MIN_SCALE), written to the table's ``range_sigma`` at ``elements`` (indices or a mask)."""
    return Parameter(
        name, family, np.maximum(start, MIN_SCALE), "log", MIN_SCALE, 10.0, 0.02, "m", False, ("range_sigma", elements)
    )


class ParameterSpace:
    """All parameters of a scene and sensor model, and the differentiable model built from their values.

    Args:
        scene: the loaded Mitsuba scene.
        model: its sensor model.
        n_beams: beams of the log's sensor (length of the per-beam parameters).
    """

    def __init__(self, scene, model: SensorModel, n_beams: int):
        self.scene = scene
        self.table = ElementTable.from_scene(scene)
        self.model = model
        self.n_beams = int(n_beams)
        self.params: dict[str, Parameter] = {}
        self._add_elements()
        self._add_sensor()

    # ------------------------------------------------------------------ namespace
    def _add(self, parameter: Parameter) -> None:
        self.params[parameter.name] = parameter

    def _add_elements(self) -> None:
        t = self.table
        p_hit, sigma, label = np.asarray(t.p_hit), np.asarray(t.range_sigma), np.asarray(t.label)
        kind, e_index = np.asarray(t.kind), np.asarray(t.ellipsoid_index)
        data = np.asarray(t.ellipsoid_data).reshape(-1, ELLIPSOID_STRIDE)
        vertices = np.asarray(t.vertex_positions).reshape(-1, 3)
        offset = 0
        for k, (shape_id, count) in enumerate(zip(t.shape_ids, t.element_counts)):
            elements = np.arange(offset, offset + count, dtype=np.uint32)
            offset += count
            self._add(
                Parameter(
                    f"elements.{shape_id}.p_hit",
                    "p_hit",
                    p_hit[elements],
                    "logit",
                    P_EPS,
                    1 - P_EPS,
                    0.1,
                    "probability",
                    False,
                    ("p_hit", mi.UInt32(elements)),
                )
            )
            if t.shape_kinds[k] == "ellipsoids":
                e = e_index[elements].astype(np.uint32)
                for name, first, transform, lr, low in (
                    ("centers", 0, "value", 0.01, -np.inf),
                    ("scales", 3, "log", 0.02, MIN_SCALE),
                ):
                    index = (e[:, None] * ELLIPSOID_STRIDE + first + np.arange(3, dtype=np.uint32)).ravel()
                    self._add(
                        Parameter(
                            f"elements.{shape_id}.{name}",
                            name,
                            data[e, first : first + 3].ravel(),
                            transform,
                            low,
                            np.inf,
                            lr,
                            "m",
                            True,
                            ("ellipsoid_data", mi.UInt32(index)),
                        )
                    )
                continue
            values = np.where(np.isnan(sigma[elements]), self.model.range_sigma, sigma[elements])
            self._add(_range_sigma(f"elements.{shape_id}.range_sigma", "range_sigma", values, mi.UInt32(elements)))
            if t.vertex_offset[k] >= 0:
                v = np.arange(t.vertex_offset[k], t.vertex_offset[k] + t.vertex_counts[k], dtype=np.uint32)
                self._add(
                    Parameter(
                        f"terrain.{shape_id}.heights",
                        "heights",
                        vertices[v, 2],
                        "value",
                        -np.inf,
                        np.inf,
                        0.005,
                        "m",
                        True,
                        ("vertex_positions", mi.UInt32(3 * v + 2)),
                    )
                )
        surfaces = kind != ELLIPSOID
        for value in np.unique(label[surfaces]):
            members = surfaces & (label == value)
            current = sigma[members]
            start = float(np.nanmean(current)) if np.any(~np.isnan(current)) else self.model.range_sigma
            self._add(_range_sigma(f"classes.{int(value)}.range_sigma", "class_sigma", [start], mi.Bool(members)))

    def _effect(self, name: str):
        return next((e for e in self.model.effects if e.name == name), None)

    def _add_sensor(self) -> None:
        for name, (effect_name, keys, unit, lr, geometric) in SENSOR_EFFECTS.items():
            effect = self._effect(effect_name) or make_effect(effect_name)
            spec = effect.specs[keys[0]]
            if spec.per_beam:
                values = np.asarray(effect.params[keys[0]], np.float64)
                initial = values[np.minimum(np.arange(self.n_beams), values.size - 1)]
            else:
                initial = np.array([float(np.asarray(effect.params[k])[0]) for k in keys])
            self._add(
                Parameter(
                    name,
                    "sensor",
                    initial,
                    "value",
                    spec.fit_bound,
                    spec.upper,
                    lr,
                    unit,
                    geometric,
                    (effect_name, keys),
                    per_beam=spec.per_beam,
                )
            )
        sensor_effects = {v[0] for v in SENSOR_EFFECTS.values()}
        parts = [("effects", "effect", e) for e in self.model.effects if e.name not in sensor_effects]
        for prefix, family, part in parts + [("density", "density", self.model.density)]:
            for key in part.fitted_names():
                spec = part.specs[key]
                self._add(
                    Parameter(
                        f"{prefix}.{part.name}.{key}",
                        family,
                        np.asarray(part.params[key], np.float64),
                        "value",
                        spec.fit_bound,
                        spec.upper,
                        part.fit_scale(key) * 0.1,
                        spec.unit,
                        False,
                        (part.name, (key,)),
                        per_beam=spec.per_beam,
                    )
                )

    def select(self, globs: list[str]) -> list[str]:
        """Names matched by ``fnmatch`` globs, in namespace order.

        Raises:
            CalibrationError: a glob matches nothing (the message lists the available names).
        """
        if not globs:
            raise CalibrationError("no parameters selected; pass at least one --params GLOB, e.g. 'elements.*.p_hit'")
        chosen = []
        for glob in globs:
            matches = [n for n in self.params if fnmatch.fnmatchcase(n, glob)]
            if not matches:
                raise CalibrationError(f"--params {glob!r} matches no parameter; available: {', '.join(self.params)}")
            chosen += [m for m in matches if m not in chosen]
        return [n for n in self.params if n in chosen]

    # ------------------------------------------------------------------ building
    def calibration_model(self, names: list[str]) -> SensorModel:
        """The sensor model with the effects that ``names`` need, added at identity in canonical order."""
        needed = {self.params[n].target[0] for n in names if n in SENSOR_EFFECTS}
        present = {e.name for e in self.model.effects}
        extra = [make_effect(e) for e in EFFECT_ORDER if e in needed and e not in present]
        return dataclasses.replace(self.model, effects=list(self.model.effects) + extra)

    def build(self, values: dict[str, mi.Float], model: SensorModel) -> tuple[ElementTable, SensorModel]:
        """The table and model with natural ``values`` (name -> array, may carry gradients) applied.

        Args:
            values: natural values of some parameters; the others keep their current values.
            model: the calibration model (:meth:`calibration_model`); it is not modified.
        """
        arrays = {}
        effects = {e.name: copy.copy(e) for e in model.effects}
        density = copy.copy(model.density)
        for part in [*effects.values(), density]:
            part.params = dict(part.params)
        for name, value in values.items():
            par = self.params[name]
            if par.family == "density":
                density.params[par.target[1][0]] = value
                continue
            if par.family in ("sensor", "effect"):
                effect, keys = par.target
                if len(keys) == 1:
                    effects[effect].params[keys[0]] = value
                else:
                    for i, key in enumerate(keys):
                        effects[effect].params[key] = dr.gather(mi.Float, value, mi.UInt32(i))
                continue
            array_name, index = par.target
            array = arrays.get(array_name, getattr(self.table, array_name))
            if par.family == "class_sigma":
                array = dr.select(index, value, array)  # a broadcast: its gradient is a sum over fixed blocks
            else:
                array = mi.Float(array)
                dr.scatter(array, value, index)
            arrays[array_name] = array
        return self.table.replaced(**arrays), dataclasses.replace(
            model, effects=[effects[e.name] for e in model.effects], density=density
        )

    def push_geometry(self, table: ElementTable) -> None:
        """Write ``table``'s vertex positions and ellipsoid data into the Mitsuba scene (for tracing).

        A smoothed table (``table.smoothing > 0``) is written with its ellipsoids inflated by the
        traced margin of :func:`~mi_lidar.core.smoothing.inflation`. The arrays are handed over
        in aligned memory: unaligned numpy slices compile other variants of the trace kernels.
        """
        params = mi.traverse(self.scene)
        vertices = np.asarray(dr.detach(table.vertex_positions))
        data = np.asarray(dr.detach(table.ellipsoid_data))
        if table.smoothing > 0:
            data = data.reshape(-1, ELLIPSOID_STRIDE).copy()
            data[:, 3:6] = inflation(data[:, 3:6], table.smoothing, np.asarray(table.ellipsoid_extent))
            data = data.ravel().astype(np.float32)
        e_offset = 0
        for k, shape_id in enumerate(self.table.shape_ids):
            if self.table.vertex_offset[k] >= 0:
                first = self.table.vertex_offset[k]
                mesh = vertices[3 * first : 3 * (first + self.table.vertex_counts[k])]
                params[f"{shape_id}.vertex_positions"] = mi.Float(aligned(mesh))
            elif self.table.shape_kinds[k] == "ellipsoids":
                n = ELLIPSOID_STRIDE * self.table.element_counts[k]
                params[f"{shape_id}.data"] = mi.Float(aligned(data[e_offset : e_offset + n]))
                e_offset += n
        params.update()
