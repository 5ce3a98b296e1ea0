"""Camera + Lidar dataset generation: a validated spec, frames rendered on Dask, KITTI layout, resumable runs.

- :mod:`.spec`: the dataset spec (YAML or TOML, pydantic) and :func:`load_spec`.
- :mod:`.rig`: Lidars and cameras on the ego vehicle, KITTI calibration, nuScenes rigs.
- :mod:`.scenes`: XML scenes, annotations filled from a primitive library, random annotations, 3D boxes.
- :mod:`.frame`: one frame: ego pose, points with SemanticKITTI labels, images, ``label_2`` rows, files.
- :mod:`.run`: the manifest, resume, and execution on a Dask cluster (:func:`run_dataset`).

See ``docs/datasets.md``.
"""

from mi_lidar.dataset.run import RunReport, run_dataset
from mi_lidar.dataset.spec import DatasetSpec, load_spec

__all__ = ["DatasetSpec", "RunReport", "load_spec", "run_dataset"]
