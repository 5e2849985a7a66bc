"""How well a label image agrees with labelled lidar points projected into it.

A real image segmenter has no ground truth on KITTI odometry frames, but the SemanticKITTI point
labels of the scan taken with the image do: projected through the camera's projection matrix
and the lidar extrinsic, each point says which class its pixel should have. Agreement is the
share of projected points whose pixel carries the point's class, compared in the aligned classes
of :class:`semcal_ros.engine.labels.LabelMapping` (so a map and a label image are compared the way the
calibrator compares them), overall and per class.

Points are not tested for occlusion: the lidar sits 0.3 m from the camera, so a few points behind
an edge land on the occluder's pixel. This costs a little agreement at object boundaries.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semcal_ros.engine.labels import CITYSCAPES_ID, INVALID, LabelMapping

#: The classes the agreement is reported for (the paper's KITTI case: road and sidewalk merged).
REPORTED_CLASSES = ("road", "building", "vegetation", "terrain", "pole", "car")


def kitti_agreement_mapping() -> LabelMapping:
    """Aligned classes with road and sidewalk merged and cars kept (they are real pixels here)."""
    return LabelMapping(dynamic=(), merge={"sidewalk": "road"})


def project_points(xyz: np.ndarray, projection: np.ndarray, width: int, height: int,
                   min_depth: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Pixel (row, col) of points through a 3x4 ``projection`` (e.g. P2 @ Tr), nearest pixel.

    Returns the pixel indices and the indices of the points that land in the image in front of
    the camera (depth > ``min_depth``). Pixel centres are at integer coordinates (OpenCV's and
    KITTI's convention).
    """
    xyz = np.asarray(xyz, float)
    uvw = np.c_[xyz, np.ones(len(xyz))] @ np.asarray(projection, float).T
    depth = uvw[:, 2]
    front = depth > min_depth
    u = np.full(len(xyz), -1.0)
    v = np.full(len(xyz), -1.0)
    u[front] = uvw[front, 0] / depth[front]
    v[front] = uvw[front, 1] / depth[front]
    col = np.round(u).astype(np.int64)
    row = np.round(v).astype(np.int64)
    inside = front & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    idx = np.flatnonzero(inside)
    return np.stack([row[idx], col[idx]], axis=1), idx


@dataclass(frozen=True)
class Agreement:
    """Share of projected points whose pixel has their class: overall and per class."""

    overall: float
    points: int
    per_class: dict[str, tuple[float, int]]  # name -> (share, points)

    def table(self) -> str:
        lines = [f"{'class':<12}{'points':>8}{'agree':>8}"]
        for name, (share, n) in self.per_class.items():
            lines.append(f"{name:<12}{n:>8}" + (f"{100 * share:>7.1f}%" if n else f"{'-':>8}"))
        lines.append(f"{'all':<12}{self.points:>8}{100 * self.overall:>7.1f}%")
        return "\n".join(lines)


def label_agreement(train_ids: np.ndarray, xyz: np.ndarray, kitti_labels: np.ndarray,
                    projection: np.ndarray, classes: tuple[str, ...] = REPORTED_CLASSES,
                    mapping: LabelMapping | None = None) -> Agreement:
    """Agreement of a trainId image with SemanticKITTI-labelled points (see the module doc).

    Only points whose aligned class is one of ``classes`` count; the image's label at their
    pixel is aligned with the same mapping, so "sidewalk" in the image matches "road" points
    when the mapping merges them.
    """
    mapping = mapping or kitti_agreement_mapping()
    height, width = train_ids.shape
    pixels, idx = project_points(xyz, projection, width, height)
    truth = mapping.map_lidar(np.asarray(kitti_labels)[idx])
    seen = mapping.map_image(train_ids)[pixels[:, 0], pixels[:, 1]]
    wanted = np.array([CITYSCAPES_ID[mapping.merge.get(c, c)] for c in classes])
    keep = np.isin(truth, wanted) & (truth != INVALID)
    truth, seen = truth[keep], seen[keep]
    per_class = {}
    for name, aligned in zip(classes, wanted):
        sel = truth == aligned
        n = int(sel.sum())
        per_class[name] = (float((seen[sel] == aligned).mean()) if n else float("nan"), n)
    overall = float((seen == truth).mean()) if len(truth) else float("nan")
    return Agreement(overall, int(len(truth)), per_class)

