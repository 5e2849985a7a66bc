"""Labelled PLY maps: binary little-endian, vertex float x, y, z, [float intensity,] ushort label.

``intensity`` is optional (the lidar's per-point intensity, the mean over a voxel's points in a
map; what the intensity cue of engine/cues.py needs): written when the cloud carries it, between
z and label as in the scans' files; files without it load as before (no intensity).

Open3D's PLY readers drop a ``ushort label`` property, so maps go through ``plyfile``, which keeps
arbitrary vertex properties and reads the binary body with numpy.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.io.files import distinct_points_problem


def read_ply(path: str | Path, require_label: bool = True) -> LabelledCloud:
    """Read a PLY point cloud; other vertex properties end up in ``extra``. A cloud of a few
    distinct points (copies of one) is refused: it is no scan or map."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"map file not found: {path}")
    try:
        data = PlyData.read(str(path))
    except (PlyParseError, ValueError, EOFError) as exc:
        raise ValueError(f"{path}: not a readable PLY file ({exc})") from None
    if "vertex" not in data:
        raise ValueError(f"{path}: PLY file has no vertex element")
    vertex = data["vertex"].data
    names = vertex.dtype.names or ()
    missing = [n for n in ("x", "y", "z") if n not in names]
    if missing:
        raise ValueError(f"{path}: PLY vertex has no {', '.join(missing)} property")
    if require_label and "label" not in names:
        raise ValueError(f"{path}: PLY vertex has no 'label' property (expected ushort label)")
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(np.float64)
    problem = distinct_points_problem(xyz)
    if problem:
        raise ValueError(f"{path}: {problem}")
    label = vertex["label"].astype(np.uint16) if "label" in names else None
    extra = {n: np.asarray(vertex[n]) for n in names if n not in ("x", "y", "z", "label")}
    if "intensity" in extra:  # one type whatever the file stored (uchar, ushort, double)
        extra["intensity"] = extra["intensity"].astype(np.float32)
    return LabelledCloud(xyz, label, extra)


def write_ply(path: str | Path, cloud: LabelledCloud) -> None:
    """Write the engine's map format (plus any extra fields, e.g. intensity as float)."""
    arr = cloud.to_structured()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<").write(str(path))
