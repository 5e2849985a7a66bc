"""The map a node holds, prepared once for every camera and goal that uses it.

A calibrator serving several cameras used to crop and prepare the map again for every goal, and
held the received cloud besides. Here a received map is checked (finite points only, labels
required), prepared once with the node's label mapping (:func:`semcal_ros.engine.render.prepare_map`:
dynamic and unmapped classes dropped, float32 local coordinates, Morton chunks) and the cloud is
then dropped: what stays is the prepared map, its point count and bounding box. Every
:class:`~semcal_ros.engine.problem.Problem` of every camera shares it (``Problem(..., prepared=...)``).

The whole map is prepared (no crop): cameras stand anywhere on it. The renderer still draws only
what lies within ``render.far`` of the camera (chunks outside the view are culled).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.labels import LabelMapping
from semcal_ros.engine.render import PreparedMap, prepare_map

#: What a :class:`~semcal_ros.engine.problem.Problem` gets as its cloud when given a prepared map (it
#: only checks the cloud's points; the prepared map is what it renders).
EMPTY_CLOUD = LabelledCloud(np.zeros((0, 3)), np.zeros(0, np.uint16))


@dataclass(frozen=True)
class HeldMap:
    prepared: PreparedMap
    points: int  # finite points of the map as received
    lo: np.ndarray  # bounding box of those points
    hi: np.ndarray
    frame: str
    source: str  # "topic" or the file it was read from
    seconds: float = 0.0  # preparing it took

    def __len__(self) -> int:
        return self.points

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.lo, self.hi

    @classmethod
    def from_cloud(cls, cloud: LabelledCloud, mapping: LabelMapping, frame: str,
                   source: str) -> "HeldMap":
        """Prepare ``cloud`` (finite points with labels); ValueError when nothing usable is in
        it."""
        import time

        t0 = time.perf_counter()
        if len(cloud) == 0:
            raise ValueError("the map has no point")
        prepared = prepare_map(cloud, mapping)
        xyz = cloud.xyz
        return cls(prepared, len(cloud), xyz.min(axis=0).astype(float),
                   xyz.max(axis=0).astype(float), frame, source, time.perf_counter() - t0)


__all__ = ["EMPTY_CLOUD", "HeldMap"]
