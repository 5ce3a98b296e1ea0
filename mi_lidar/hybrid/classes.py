"""Semantic classes of off-road scenes (thesis ch. 4.3.1.3) and their integer ids.

Ids are stored per return in log attribute ``"label"`` and per element in the PLY ``label``
column. Instance ids (log attribute ``"instance"``) are 0 for ground and grass, ``1 ...
PATCH_BASE - 1`` for single objects and ``>= PATCH_BASE`` for shrub patches.
"""

from __future__ import annotations

CLASS_NAMES = (
    "none",
    "ground",
    "grass",
    "rock",
    "low_shrub",
    "small_shrub",
    "medium_shrub",
    "large_shrub",
    "small_tree",
    "medium_tree",
    "large_tree",
)
CLASS_ID = {name: i for i, name in enumerate(CLASS_NAMES)}
GROUND_CLASSES = (CLASS_ID["ground"], CLASS_ID["grass"])
OBJECT_CLASSES = tuple(CLASS_ID[n] for n in CLASS_NAMES[3:])
SHRUB_CLASSES = tuple(CLASS_ID[n] for n in ("low_shrub", "small_shrub", "medium_shrub", "large_shrub"))
PATCH_BASE = 1000


def class_id(name_or_id: str | int) -> int:
    """The integer id of a class given by name or id; raise ValueError naming the choices."""
    if isinstance(name_or_id, str):
        if name_or_id not in CLASS_ID:
            raise ValueError(f"unknown class {name_or_id!r}; choose one of {', '.join(CLASS_NAMES[1:])}")
        return CLASS_ID[name_or_id]
    value = int(name_or_id)
    if not 0 <= value < len(CLASS_NAMES):
        raise ValueError(f"class id {value} out of range 0..{len(CLASS_NAMES) - 1}")
    return value
