"""The loop in one call: a log with a hidden effect, its diagnosis, and the error before and after."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from mi_lidar.core.effects import parse_effects
from mi_lidar.loop.compare import compare, group_name
from mi_lidar.loop.diagnose import diagnose
from mi_lidar.scene.loading import bundled_scene, load_scene, scene_sensor_model
from mi_lidar.scene.simulation import simulate

HIDDEN = "incidence_dropout(gamma=2)"
CANDIDATES = ["range_dropout", "incidence_dropout", "label_dropout", "outliers"]
F1_NOTE = (
    "F1 may fall while the model gets better: it compares one simulated draw with the log ray by ray. "
    "A model that always returns scores 2q/(1+q) = {always:.3f} at the measured hit rate q = {q:.3f} without "
    "predicting a single miss; the right dropout draws its misses independently of the log's, so it agrees "
    "on fewer rays although its hit rate now matches. The NLL and the hit rate are the measures to read."
)


def make_hidden_log(hidden: str = HIDDEN, n_scans: int = 24, seed: int = 1):
    """Simulate ``n_scans`` scans of the bundled room with effects ``hidden`` the default model lacks.

    Returns:
        ``(scene, model, log)``: the scene, the default model (without ``hidden``) and the log.
    """
    scene = load_scene(bundled_scene("indoor_planar.xml"))
    model, pose = scene_sensor_model(scene)
    rng = np.random.default_rng(0)
    poses = np.repeat(pose[None], n_scans, 0)
    poses[:, 0, 3] += rng.uniform(-3, 3, n_scans)
    poses[:, 1, 3] += rng.uniform(-2, 2, n_scans)
    true = dataclasses.replace(model, effects=parse_effects(hidden))
    return scene, model, simulate(scene, poses=poses, model=true, seed=seed)


def ranking_lines(candidates) -> list[str]:
    """The ranking of diagnose's first round as text: one line per candidate (name, held-out gain in nats
    per ray, added parameters, BIC change, significance), names in one column; 80 columns for names of
    up to 32 characters."""
    width = max((len(c.name) for c in candidates), default=0)
    return ["Ranking (held-out NLL gain per ray, k added parameters, BIC change):"] + [
        f"  {i + 1}. {c.name:{width}s} {c.test_gain:+7.4f} k={c.k:<2d} dBIC {c.delta_bic:+8.1f} "
        f"{'significant' if c.significant else '-'}"
        for i, c in enumerate(candidates)
    ]


def print_plain(text: str) -> None:
    """Print a line written in the reports' Markdown without its bold markers (``**name**`` reads ``name``)."""
    print(text.replace("**", ""))


def run_demo(
    out: str | Path | None = None, hidden: str = HIDDEN, candidates: list[str] | None = CANDIDATES, echo=print_plain
) -> dict:
    """Run compare -> diagnose -> compare on a log with a hidden effect and print the story.

    Args:
        out: folder for the two comparison reports and the diagnosis (nothing written when None).
        hidden: effects hidden in the log.
        candidates: effects diagnose tries (None: the whole catalog, slower).
        echo: printer of the lines, which carry Markdown bold (``**name**``): the default prints them without it;
            the command line passes one that prints it bold.

    Returns:
        ``{"ranking": [...], "nll_before": float, "nll_after": float, "selected": [...]}``.
    """
    scene, model, log = make_hidden_log(hidden)
    out = None if out is None else Path(out)
    before = compare(log, scene, model, out=None if out is None else out / "before", title="Before: the default model")
    echo(
        f"Hidden in the log: {hidden}. The default model scores {before.headline['nll']:.3f} nats/ray; "
        f"worst group: {group_name(before.worst[0])} "
        f"({before.worst[0]['nll']:.2f} nats/ray)."
    )
    d = diagnose(log, scene, model, out=out, candidates=candidates, rounds=1, steps=100)
    for line in ranking_lines(d.rounds[0]):
        echo(line)
    echo(d.summary)
    after = compare(log, scene, d.model, out=None if out is None else out / "after", title="After: the diagnosed model")
    echo(
        f"NLL per ray: {before.headline['nll']:.3f} -> {after.headline['nll']:.3f} nats; simulated hit rate "
        f"{before.headline['hit_rate_simulated']:.3f} -> {after.headline['hit_rate_simulated']:.3f} "
        f"(measured {before.headline['hit_rate_measured']:.3f}); hit/miss F1 "
        f"{before.headline['f1']:.3f} -> {after.headline['f1']:.3f}."
    )
    q = before.headline["hit_rate_measured"]
    echo("  " + F1_NOTE.format(q=q, always=2 * q / (1 + q)))
    if out is not None:  # the demo ended on the F1 note and never said where its reports were
        echo(f"reports: {out / 'diagnosis.html'}, {out / 'before' / 'report.html'}, {out / 'after' / 'report.html'}")
    return {
        "ranking": d.ranking(),
        "selected": d.selected,
        "nll_before": before.headline["nll"],
        "nll_after": after.headline["nll"],
    }
