"""Scene dicts from element sets load, render, and survive a save/load round trip unchanged."""

import numpy as np

import mi_lidar
from mi_lidar.core.elements import ElementTable
from mi_lidar.scene.dicts import EllipsoidElements, MeshElements, save_scene, scene_dict


def element_sets():
    rng = np.random.default_rng(1)
    grid = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0), indexing="ij"), -1).reshape(-1, 2)
    vertices = np.c_[grid * 2 - 4, np.zeros(len(grid))]
    i, j = np.meshgrid(np.arange(4), np.arange(4), indexing="ij")
    a, b, c, d = i * 5 + j, (i + 1) * 5 + j, (i + 1) * 5 + j + 1, i * 5 + j + 1
    faces = np.r_[np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    ground = MeshElements(
        vertices=vertices,
        faces=faces,
        p_hit=rng.uniform(0.5, 1, len(faces)),
        label=np.ones(len(faces)),
        range_sigma=np.full(len(faces), 0.02),
    )
    n = 6
    bushes = EllipsoidElements(
        centers=rng.uniform(-3, 3, (n, 3)) + [0, 0, 4],
        scales=rng.uniform(0.2, 0.5, (n, 3)),
        quaternions=np.tile([0, 0, 0.3826834, 0.9238795], (n, 1)),
        p_hit=rng.uniform(0.2, 0.6, n),
        label=np.full(n, 5),
        extent=2.5,
    )
    return {"ground": ground, "bushes": bushes}


def table_arrays(scene):
    table = ElementTable.from_scene(scene)
    order = np.argsort(table.shape_ids)
    return table, order


def test_dict_and_saved_xml_give_the_same_elements(tmp_path):
    sets = element_sets()
    from_dict = mi_lidar.load_scene(scene_dict(sets))
    path = save_scene(tmp_path / "fitted.xml", sets)
    from_xml = mi_lidar.load_scene(path)
    a, b = ElementTable.from_scene(from_dict), ElementTable.from_scene(from_xml)
    assert sorted(a.shape_ids) == sorted(b.shape_ids) == ["bushes", "ground"]

    def by_shape(table, name):
        k = table.shape_ids.index(name)
        start = sum(table.element_counts[:k])
        sl = slice(start, start + table.element_counts[k])
        return {f: np.asarray(getattr(table, f))[sl] for f in ("p_hit", "range_sigma", "label", "kind")}

    for name in ("bushes", "ground"):
        x, y = by_shape(a, name), by_shape(b, name)
        for field in x:
            np.testing.assert_allclose(x[field], y[field], rtol=1e-6, equal_nan=True)
    np.testing.assert_allclose(np.sort(np.asarray(a.ellipsoid_data)), np.sort(np.asarray(b.ellipsoid_data)), rtol=1e-5)


def test_saved_scene_renders_identically(tmp_path):
    sets = element_sets()
    pose = np.eye(4)
    pose[2, 3] = 8.0
    pose[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]  # sensor x (forward) points down (-z)
    a = mi_lidar.simulate(mi_lidar.load_scene(scene_dict(sets)), "raster", poses=pose, seed=4)
    b = mi_lidar.simulate(mi_lidar.load_scene(save_scene(tmp_path / "s.xml", sets)), "raster", poses=pose, seed=4)
    assert a.hit.mean() > 0.3
    np.testing.assert_array_equal(a.hit, b.hit)
    np.testing.assert_allclose(a.ranges, b.ranges, rtol=1e-5, equal_nan=True)
