"""label_dropout: per-label dropout and its recovery."""

import numpy as np
import pytest

from .loop.helpers import first_kept, hidden_log, recover, room


def test_only_the_dropped_label_loses_hits():
    """Walls (label 1) lose 40 % +- 2 % of their hits; targets (label 2) keep theirs."""
    scene, model, poses = room(20)
    log, _ = hidden_log(scene, model, poses, "label_dropout(drop=[0 0.4 0])")
    clean, _ = hidden_log(scene, model, poses, "label_dropout(drop=[0])")
    label = clean.attributes["label"]
    walls = clean.hit & (label == 1)
    targets = clean.hit & (label == 2)
    first = first_kept(log, clean)
    assert abs(1 - first[walls].mean() - 0.4) < 0.02
    assert first[targets].mean() > 0.99


@pytest.mark.slow
def test_recovers_per_label_dropout():
    """drop = [0, 0.3, 0, 0.5] comes back within 0.05 for the labels with many rays (1 and 3)."""
    scene, model, poses = room(40)
    log, _ = hidden_log(scene, model, poses, "label_dropout(drop=[0 0.3 0 0.5 0])")
    effect, _ = recover(scene, model, log, "label_dropout", steps=150)
    drop = np.asarray(effect["drop"])
    assert abs(drop[1] - 0.3) < 0.05 and abs(drop[3] - 0.5) < 0.05 and drop[2] < 0.05


def test_recovers_a_rare_and_a_near_total_dropout_at_once():
    """drop = [0, 0.95, 0, 0.03]: both come back (within 0.02 and 0.015) from the fitting start 0.02.

    The fitter moves ``drop`` as a logit: in value units its steps took a 3 % dropout to the bound 0 at
    the first step (its lost returns then sit at the likelihood floor, with no gradient to come back).
    """
    scene, model, poses = room(20)
    log, _ = hidden_log(scene, model, poses, "label_dropout(drop=[0 0.95 0 0.03 0])")
    effect, _ = recover(scene, model, log, "label_dropout", steps=150)
    drop = np.asarray(effect["drop"])
    assert abs(drop[1] - 0.95) < 0.02 and abs(drop[3] - 0.03) < 0.015
