"""Thin cylinders far from the sensor are met where they are (a workaround for Mitsuba 3.9.1's cylinder test).

Mitsuba 3.9.1's analytic ``cylinder`` solves its quadratic in float32 from the ray's origin in the unit
cylinder's frame, where the origin lies ``D / radius`` units from the axis: ``C = ox^2 + oy^2 - 1`` and the
discriminant lose everything once ``(D / radius)^2`` nears ``1 / eps`` (:mod:`mi_lidar.scene.cylinders`).
:func:`mi_lidar.load_scene` therefore loads every ``cylinder`` as a triangle mesh of the same tube.

Each case is one cylinder (length 2 m) at a random orientation, D m from the sensor, and 20,000 rays through
points drawn uniformly inside 0.95 of its radius (seed 7), traced by the tracer's
:func:`~mi_lidar.core.trace.next_intersection` and compared with a float64 closed form. Measured with
Mitsuba's cylinder (the code before), rays missed or met more than 1 mm off: radius 2 cm: 0.09 % at 10 m,
74 % at 30 m, 98 % at 120 m (51 % missed); 5 cm: 30 % at 30 m, 99 % at 250 m (60 % missed); 10 cm: 4.1 %
at 30 m, 97 % at 250 m (9.8 % missed); 13 of the 15 cases failed. Measured with the mesh: none missed, at
most 1 ray in 20,000 off by more than 1 mm (it slipped between two facets), medians 0.01-0.05 mm.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import mi_lidar
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import SceneError
from mi_lidar.core.trace import next_intersection
from mi_lidar.scene.cylinders import MAX_NORMAL_ERROR, SAGITTA, facet_count

N_RAYS, LENGTH, SEED = 20_000, 2.0, 7
RANGE_TOLERANCE = 1e-3  # m: a ray met further than this from the float64 surface counts as wrong
WRONG_BOUND = 0.001  # fraction of the rays aimed inside the cylinder that miss it or are off by RANGE_TOLERANCE
MEDIAN_TOLERANCE = 1e-4  # m: median range error (the facets lie within 0.1 mm of the cylinder)


def cylinder(radius: float, distance: float, seed: int = SEED):
    """One cylinder ``(p0, p1)`` about ``distance`` m away and N_RAYS unit directions from the origin into it."""
    rng = np.random.default_rng(seed)
    center = np.array([distance, 0.3, 0.2])
    axis = Rotation.random(random_state=seed).apply([0.0, 0.0, 1.0])
    p0, p1 = center - axis * LENGTH / 2, center + axis * LENGTH / 2
    u = np.cross(axis, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    rho, phi = 0.95 * radius * np.sqrt(rng.uniform(size=N_RAYS)), rng.uniform(0, 2 * np.pi, N_RAYS)
    along = rng.uniform(0.02, 0.98, N_RAYS) * LENGTH
    targets = p0 + along[:, None] * axis + (rho * np.cos(phi))[:, None] * u + (rho * np.sin(phi))[:, None] * v
    directions = (targets / np.linalg.norm(targets, axis=1, keepdims=True)).astype(np.float32).astype(np.float64)
    return p0, p1, directions / np.linalg.norm(directions, axis=1, keepdims=True)


def exact_range(p0, p1, radius: float, directions) -> np.ndarray:
    """(N,) float64 distance from the origin to the open cylinder along unit ``directions``, m (inf: none)."""
    axis = (p1 - p0) / np.linalg.norm(p1 - p0)
    o, d = -p0 - (-p0 @ axis) * axis, directions - np.outer(directions @ axis, axis)  # across the axis
    a = np.sum(d * d, 1)
    closest = -(d @ o) / a  # the ray's closest approach to the axis: no cancellation
    gap = np.sum((o + closest[:, None] * d) ** 2, 1)
    half = np.sqrt(np.maximum(radius**2 - gap, 0.0) / a)
    met = np.full(len(directions), np.inf)
    for t in (closest + half, closest - half):  # the nearer root last: it wins where both are on the cylinder
        along = (t[:, None] * directions - p0) @ axis
        on = (gap <= radius**2) & (t >= 0) & (along >= 0) & (along <= np.linalg.norm(p1 - p0))
        met = np.where(on, t, met)
    return met


def pole(p0, p1, radius: float) -> dict:
    point = mi.ScalarPoint3f
    return {"type": "cylinder", "p0": point(*p0), "p1": point(*p1), "radius": radius}


def traced_ranges(scene, directions) -> tuple[np.ndarray, np.ndarray]:
    """``(valid, range)`` of the tracer's first intersection from the origin, m."""
    origin = mi.Point3f(np.zeros((3, len(directions)), np.float32))
    direction = mi.Vector3f(np.ascontiguousarray(directions.T.astype(np.float32)))
    si, valid, _ = next_intersection(scene, ElementTable.from_scene(scene), origin, origin, direction, 1000.0)
    return np.asarray(valid), np.asarray(dr.dot(si.p - origin, direction), np.float64)


@pytest.mark.parametrize("distance", [10.0, 30.0, 60.0, 120.0, 250.0])
@pytest.mark.parametrize("radius", [0.02, 0.05, 0.1])
def test_rays_aimed_inside_a_thin_far_cylinder_meet_it_at_its_surface(radius, distance):
    p0, p1, directions = cylinder(radius, distance)
    truth = exact_range(p0, p1, radius, directions)
    assert np.isfinite(truth).all()  # every ray aimed inside crosses the wall (none leaves through an open end)
    scene = mi_lidar.load_scene({"type": "scene", "pole": pole(p0, p1, radius)})
    valid, met_at = traced_ranges(scene, directions)
    error = np.where(valid, np.abs(met_at - truth), np.inf)
    wrong = np.mean(error > RANGE_TOLERANCE)
    assert wrong <= WRONG_BOUND, f"{1 - valid.mean():.2%} missed, {wrong:.2%} missed or off by > 1 mm"
    assert np.median(error) < MEDIAN_TOLERANCE


def test_analytic_cylinders_still_miss_in_this_mitsuba():
    """The workaround is needed: Mitsuba's own cylinder misses most rays aimed inside a 5 cm pole 250 m away.
    When this fails, Mitsuba's cylinder test is exact and :mod:`mi_lidar.scene.cylinders` can go."""
    p0, p1, directions = cylinder(0.05, 250.0)
    valid, _ = traced_ranges(mi.load_dict({"type": "scene", "pole": pole(p0, p1, 0.05)}), directions)
    assert 1.0 - valid.mean() > 0.3


def analytic_and_mesh(shape: dict):
    """Mitsuba's own cylinder and mi-lidar's mesh of ``shape`` (a cylinder dict), each alone in a scene."""
    return mi.load_dict({"type": "scene", "pole": shape}), mi_lidar.load_scene({"type": "scene", "pole": shape})


@pytest.mark.parametrize("radius", [0.02, 0.15, 1.0, 10.0])
def test_a_cylinder_loads_as_a_mesh_on_mitsubas_surface(radius):
    turn = mi.ScalarTransform4f().rotate(list(np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)), 40.0)
    to_world = mi.ScalarTransform4f().translate([3.0, -2.0, 1.0]) @ turn
    analytic, meshed = analytic_and_mesh({**pole([0, 0, -1], [0.5, 0, 2], radius), "to_world": to_world})
    mesh = meshed.shapes()[0]
    n = facet_count(radius)
    assert isinstance(mesh, mi.Mesh) and mesh.id() == "pole" and mesh.face_count() == 2 * n
    assert radius * (1 - np.cos(np.pi / n)) <= SAGITTA and 180.0 / n <= MAX_NORMAL_ERROR
    matrix = np.asarray(mi.traverse(analytic.shapes()[0])["to_world"].matrix, np.float64).reshape(4, 4)
    vertices = np.asarray(mesh.vertex_positions_buffer(), np.float64).reshape(-1, 3)
    local = (vertices - matrix[:3, 3]) @ np.linalg.inv(matrix[:3, :3]).T  # the unit tube: radius 1, z 0 or 1
    float32 = 4 * np.spacing(np.float32(np.abs(vertices).max()))  # m: a few roundings of the coordinates
    np.testing.assert_allclose(np.hypot(local[:, 0], local[:, 1]) * radius, radius, atol=float32)
    np.testing.assert_allclose(np.sort(local[:, 2])[[0, n, n + 1, -1]], [0, 0, 1, 1], atol=1e-6)


def test_the_camera_sees_the_same_open_tube():
    """Rays 3 m away meet the mesh where they meet Mitsuba's cylinder (to SAGITTA), with Mitsuba's texture
    coordinates and shading normal at the point met; the geometric normal (what Lidar rays use) is the facet's,
    within MAX_NORMAL_ERROR. There are no end caps: a ray that enters the open end meets the inside of the wall,
    one along the axis meets nothing."""
    radius = 0.3
    analytic, meshed = analytic_and_mesh(pole([0, 0, 0], [0, 0, 1], radius))
    rng = np.random.default_rng(SEED)
    start = np.c_[rng.uniform(-3, 3, (N_RAYS, 2)), np.full(N_RAYS, 3.0)]  # above the open top end
    target = np.c_[0.25 * rng.normal(size=(N_RAYS, 2)), rng.uniform(0, 1, N_RAYS)]
    ray = mi.Ray3f(mi.Point3f(start.T.astype(np.float32)), mi.Vector3f(dr.normalize(mi.Vector3f((target - start).T))))
    a, m = analytic.ray_intersect(ray), meshed.ray_intersect(ray)
    both = np.asarray(a.is_valid() & m.is_valid())
    assert np.mean(np.asarray(a.is_valid()) != np.asarray(m.is_valid())) < 0.001 and both.mean() > 0.5
    assert np.mean(both & (np.asarray(dr.dot(a.n, ray.d)) > 0)) > 0.05  # through the open end onto the inner wall
    x, y, z = np.asarray(m.p, np.float64)[:, both]
    assert np.abs(np.hypot(x, y) - radius).max() <= SAGITTA + 1e-6  # m: the facets lie inside the tube
    u = np.arctan2(y, x) / (2 * np.pi) % 1.0  # Mitsuba's (phi / 2 pi, z) at the point met
    uv = np.asarray(m.uv, np.float64)[:, both]
    assert np.abs((uv[0] - u + 0.5) % 1.0 - 0.5).max() < 1e-3 and np.abs(uv[1] - z).max() < 1e-5
    outward = np.c_[x, y, np.zeros_like(x)] / np.hypot(x, y)[:, None]
    for normal, bound in ((m.sh_frame.n, 0.05), (m.n, MAX_NORMAL_ERROR + 0.01)):  # degrees
        degrees = np.degrees(np.arccos(np.clip(np.sum(np.asarray(normal, np.float64)[:, both].T * outward, 1), -1, 1)))
        assert degrees.max() < bound
    along = mi.Ray3f(mi.Point3f(0, 0, 3), mi.Vector3f(0, 0, -1))
    assert not analytic.ray_intersect(along).is_valid()[0] and not meshed.ray_intersect(along).is_valid()[0]


def test_the_mesh_keeps_the_shapes_material_label_and_orientation(tmp_path):
    xml = tmp_path / "pole.xml"
    shape = """<shape type="cylinder" id="pole"><point name="p0" x="2" y="0" z="0"/><point name="p1" x="2" y="0" z="3"/>
        <float name="radius" value="0.1"/>{flip}
        <bsdf type="lidar_material"><float name="p_hit" value="0.4"/><integer name="label" value="3"/></bsdf></shape>"""
    normal_x = []
    for flip in ("", '<boolean name="flip_normals" value="true"/>'):
        xml.write_text(f'<scene version="3.0.0">{shape.format(flip=flip)}</scene>')
        scene = mi_lidar.load_scene(xml)
        table = ElementTable.from_scene(scene)
        assert table.shape_ids == ["pole"] and table.element_counts == [2 * facet_count(0.1)]
        assert np.all(np.asarray(table.label) == 3) and np.allclose(np.asarray(table.p_hit), 0.4)
        si = scene.ray_intersect(mi.Ray3f(mi.Point3f(0, 0.01, 1), mi.Vector3f(1, 0, 0)))
        normal_x.append(float(si.n.x[0]))
    assert normal_x[0] < -0.99 and normal_x[1] > 0.99  # outward (towards the ray's origin), then flipped


@pytest.mark.parametrize(
    ("extra", "named"),
    [
        ('<float name="radiuss" value="2"/>', '"radiuss"'),
        ('<sampler type="independent"/>', "Sampler"),
        ('<float name="radius" value="0"/>', "radius 0 m"),
        ('<point name="p0" x="0" y="0" z="1"/>', "length nan m"),
    ],
)
def test_a_bad_cylinder_is_refused_naming_what_is_wrong(tmp_path, extra, named):
    xml = tmp_path / "pole.xml"
    xml.write_text(f'<scene version="3.0.0"><shape type="cylinder" id="pole">{extra}</shape></scene>')
    with pytest.raises(SceneError, match=named):
        mi_lidar.load_scene(xml)
