"""PCD point clouds (ascii, binary and binary_compressed) with every field kept.

Open3D's tensor reader (``open3d.t.io``) decodes all three encodings (binary_compressed is LZF,
as the PJLab rig writes it) and keeps fields the legacy reader drops (intensity, ring, per-point
timestamp), so no parser is written here: this module only turns its result into the project's
:class:`~semcal_ros.engine.cloud.LabelledCloud` and names a bad file in one line.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.io.files import distinct_points_problem

#: PCD fields read as the intensity channel, first match wins (vendors name it differently).
INTENSITY_FIELDS = ("intensity", "reflectance", "remission", "i")


def read_pcd(path: str | Path) -> LabelledCloud:
    """x, y, z as float64; intensity (float32) as ``extra['intensity']``; other scalar fields
    (ring, timestamp, ...) under their own names; a ``label`` field becomes the labels."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"scan not found: {path}")
    head = path.read_bytes()[:11]
    if not (head.startswith(b"# .PCD") or head.startswith(b"VERSION")
            or head.startswith(b"FIELDS")):
        raise ValueError(f"{path}: not a PCD file (no PCD header)")
    cloud = o3d.t.io.read_point_cloud(str(path))
    if "positions" not in cloud.point or len(cloud.point.positions) == 0:
        raise ValueError(f"{path}: PCD file has no x, y, z points")
    xyz = cloud.point.positions.numpy().astype(np.float64)
    problem = distinct_points_problem(xyz)
    if problem:
        raise ValueError(f"{path}: {problem}")
    extra: dict[str, np.ndarray] = {}
    label = None
    for name in cloud.point:
        if name == "positions":
            continue
        values = cloud.point[name].numpy()
        if values.ndim == 2 and values.shape[1] != 1:
            continue  # colours, normals: not scan fields the map uses
        values = values.reshape(-1)
        if name == "label":
            label = values.astype(np.uint16)
        elif name.lower() in INTENSITY_FIELDS and "intensity" not in extra:
            extra["intensity"] = values.astype(np.float32)
        else:
            extra[name] = values
    return LabelledCloud(xyz, label, extra)
