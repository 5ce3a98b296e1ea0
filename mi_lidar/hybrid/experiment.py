"""The evaluation of thesis table 4.3 on synthetic worlds: one training and two test scenes.

Training scene: the hybrid model is fitted to the even scans and both it and the neighbour
simulator (database = even scans) are evaluated at the odd scans. Test scenes (other seeds and
layouts): the annotation comes from the test log's labels, the ground mesh is fitted to the test
log's ground points, objects are training-scene primitives. Two opaque baselines get the same
annotation and ground: the thesis's mesh-model simulator (per object the stock generator model
of its class with the closest box, :mod:`.mesh_models`) and a box-surface simulator (a closed
surface scaled to each annotated box, more generous than the thesis's). The test scenes of ours
and of the mesh-model baseline are written with range-image and top-view PNG previews. Also
reported: ground segmentation accuracy (threshold tuned on the training log) and automatic
segmentation + size-classifier accuracy on the tests.

Every simulation is :func:`mi_lidar.simulate` on the written scene's elements (the product's
own core, via :func:`.simulation.simulate_log`). Besides all rays, the metrics are also reported
on the *object rays* (the real or the simulated return is on an object class) and on the other
rays (ground, grass, misses). With ``tune_scans > 0`` the parameters are first tuned
(:mod:`.tune`) on the first ``tune_scans`` scans of the training log.

Run ``python -m mi_lidar.hybrid.experiment OUT_DIR [TUNE_SCANS [MAX_EVALS]]``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from mi_lidar.core.strict_json import dumps, write_json
from mi_lidar.hybrid.baselines import NeighborSimulator, box_surface_scene, mesh_model_scene
from mi_lidar.hybrid.classes import GROUND_CLASSES, OBJECT_CLASSES
from mi_lidar.hybrid.commands import render_previews, write_scene_together
from mi_lidar.hybrid.compose import annotation_from_segments, compose_scene, save_annotation
from mi_lidar.hybrid.evaluate import observation_metrics
from mi_lidar.hybrid.fit import FitParams, fit_model, world_rays
from mi_lidar.hybrid.ground import ground_features, tune_threshold
from mi_lidar.hybrid.mesh_models import MeshModelLibrary
from mi_lidar.hybrid.primitives import PrimitiveLibrary, extract_primitives
from mi_lidar.hybrid.segments import (
    SizeClassifier,
    euclidean_segments,
    majority_label,
    segment_features,
    segments_from_labels,
)
from mi_lidar.hybrid.simulation import simulate_log
from mi_lidar.hybrid.true_sensor import SensorSpec, path_poses, render_log
from mi_lidar.hybrid.tune import tune_parameters
from mi_lidar.hybrid.world import WorldSpec, make_world

SCENES = {
    "train": (11, WorldSpec(length=100, width=50)),
    "test1": (22, WorldSpec(length=120, width=50, object_density=1.5, n_patches=3)),
    "test2": (33, WorldSpec(length=90, width=60, object_density=1.0, n_patches=1, relief=1.8)),
}


def make_log(name: str, spacing: float = 1.5, sensor: SensorSpec | None = None):
    """World and true-sensor log of scene ``name`` (a key of ``SCENES``)."""
    seed, spec = SCENES[name]
    world = make_world(seed, spec)
    return world, render_log(world, path_poses(world, spacing, sensor), sensor, seed=seed)


def score(model, log, seed: int) -> dict:
    """Table 4.3 metrics of ``model`` simulated at the rays of ``log``: all, object and other rays."""
    o, d = world_rays(log)
    sim, sim_label = simulate_log(model, log, seed)
    real = np.where(log.hit, log.ranges, np.nan)
    on_object = np.isin(log.attributes["label"], OBJECT_CLASSES) | np.isin(sim_label, OBJECT_CLASSES)
    return {
        "all": observation_metrics(real, sim, o, d),
        "object_rays": observation_metrics(real, sim, o, d, mask=on_object),
        "other_rays": observation_metrics(real, sim, o, d, mask=~on_object),
    }


def _write(model, out: Path, name: str, log) -> Path:
    return write_scene_together(model, out / f"{name}.xml", log=log)[0]


def run(
    out_dir, params: FitParams | None = None, say=lambda message: None, tune_scans: int = 0, max_evals: int = 20
) -> dict:
    """Run the whole evaluation, write scenes, library, annotations and ``results.json`` to ``out_dir``.

    Args:
        out_dir: output folder. params: fitting parameters. say: callback receiving stage messages.
        tune_scans: tune the parameters on this many first training scans first (0: no tuning).
        max_evals: tuning budget (fits).
    """
    out = Path(out_dir)
    params = params or FitParams()
    results = {"timings": {}}
    t0 = time.perf_counter()
    _, train_log = make_log("train")
    results["timings"]["train_log"] = time.perf_counter() - t0
    # ---- ground segmentation threshold tuned on the training labels
    pts = train_log.points_world()[train_log.hit]
    truth = np.isin(train_log.attributes["label"][train_log.hit], GROUND_CLASSES)
    phi = ground_features(pts, params.ground)
    params.ground.phi_thresh, acc = tune_threshold(phi, truth)
    results["ground_segmentation"] = {"phi_thresh": params.ground.phi_thresh, "train_accuracy": acc}
    if tune_scans > 0:
        say("tuning")
        t0 = time.perf_counter()
        tuned = tune_parameters(train_log.select(slice(0, tune_scans)), params, max_evals)
        params = tuned.params
        results["timings"]["tuning"] = time.perf_counter() - t0
        results["tuning"] = {
            "initial": tuned.initial,
            "best": tuned.best,
            "evaluations": len(tuned.history),
            "phi_thresh": params.ground.phi_thresh,
            "clusters_per_point": params.clusters.clusters_per_point,
            "extent": params.extent,
            "max_edge": params.surface.max_edge,
            "max_residual": params.max_residual,
        }
    say("training scene")
    even, odd = train_log.select(slice(0, None, 2)), train_log.select(slice(1, None, 2))
    t0 = time.perf_counter()
    fit = fit_model(even, params)
    results["timings"]["fit_train_even"] = time.perf_counter() - t0
    results["fit_timings"] = fit.timings
    results["train_model"] = {
        "triangles": len(fit.model.ground),
        "ellipsoids": len(fit.model.ellipsoids),
        **fit.model.info,
    }
    _write(fit.model, out / "train_scene", "train", odd)
    t0 = time.perf_counter()
    results["train"] = {"ours": score(fit.model, odd, 1)}
    results["timings"]["simulate_train"] = time.perf_counter() - t0
    o, d = world_rays(odd)
    nb = NeighborSimulator(even.points_world()[even.hit], d_perp=0.3).simulate(o, d, max_range=params.max_range)
    real = np.where(odd.hit, odd.ranges, np.nan)
    results["train"]["neighbor"] = {"all": observation_metrics(real, nb.reshape(real.shape), o, d)}
    say("primitives")
    full = fit_model(train_log, params)
    labels = train_log.attributes["label"].ravel()[full.ray_index]
    inst = train_log.attributes["instance"].ravel()[full.ray_index]
    segs = segments_from_labels(full.points, labels, inst)
    library = PrimitiveLibrary(extract_primitives(full.model, full.points, segs, train_log.poses, source="train"))
    library.save(out / "library")
    library.preview(out / "library_preview.png")
    results["library"] = {
        c: int(sum(1 for p in library.primitives if p.class_name == c))
        for c in sorted({p.class_name for p in library.primitives})
    }
    mesh_models = MeshModelLibrary.generate()
    mesh_models.preview(out / "mesh_models_preview.png")
    results["mesh_models"] = {
        "models": len(mesh_models),
        "triangles": int(sum(len(m.faces) for m in mesh_models.models)),
    }
    clf = SizeClassifier().fit(
        np.stack([segment_features(full.points[s.index]) for s in segs]), np.array([s.label for s in segs])
    )
    # ---- test scenes
    for name in ("test1", "test2"):
        say(name)
        _, log = make_log(name)
        ground_fit = fit_model(log, params, ground_only=True)
        labels = log.attributes["label"].ravel()[ground_fit.ray_index]
        inst = log.attributes["instance"].ravel()[ground_fit.ray_index]
        truth = np.isin(labels, GROUND_CLASSES)
        segs = segments_from_labels(ground_fit.points, labels, inst)
        objects = annotation_from_segments(ground_fit.points, segs, log.poses)
        save_annotation(out / f"{name}_annotation.json", objects, ground_fit.model.ground)
        ours = compose_scene(objects, library, ground_fit.model.ground, params.extent)
        render_previews(_write(ours, out / f"{name}_scene", name, log), log.poses)
        base = mesh_model_scene(objects, ground_fit.model.ground, mesh_models, sigma=0.05)
        render_previews(_write(base, out / f"{name}_mesh_models", name, log), log.poses)
        auto = euclidean_segments(ground_fit.points[~ground_fit.is_ground])
        ng_labels = labels[~ground_fit.is_ground]
        scored = [
            (
                clf.predict(segment_features(ground_fit.points[~ground_fit.is_ground][s.index]))[0],
                majority_label(s, ng_labels),
            )
            for s in auto
        ]
        scored = [(p, t) for p, t in scored if t in OBJECT_CLASSES]
        results[name] = {
            "ours": score(ours, log, 2),
            "mesh_models": score(base, log, 3),
            "box_surfaces": score(box_surface_scene(objects, ground_fit.model.ground, sigma=0.05), log, 4),
            "mesh_models_used": len(set(base.info["models"])),
            "ground_segmentation_accuracy": float(np.mean(ground_fit.is_ground == truth)),
            "objects": len(objects),
            "auto_segments": len(scored),
            "auto_classification_accuracy": float(np.mean([p == t for p, t in scored])) if scored else float("nan"),
        }
    write_json(out / "results.json", results, default=float)
    return results


if __name__ == "__main__":
    args = sys.argv[1:]
    print(
        dumps(
            run(
                args[0] if args else "hybrid_experiment",
                say=lambda m: print(m, file=sys.stderr, flush=True),
                tune_scans=int(args[1]) if len(args) > 1 else 0,
                max_evals=int(args[2]) if len(args) > 2 else 20,
            ),
            indent=1,
            default=float,
        )
    )
