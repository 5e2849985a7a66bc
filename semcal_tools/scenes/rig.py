"""Several cameras around one junction (``semcal scene --cameras N``): where each stands, its name.

Roadside installations put several cameras on the masts at a junction's corners. The rig uses the
four corner pavements of the junction layout: cameras 1-4 (``northeast``, ``southeast``,
``southwest``, ``northwest``) stand on a corner mast each and look across the crossing, as the
layout's own camera does (the layout's camera *is* the one of its corner, mast and all); cameras
5-8 (``north``, ``east``, ``south``, ``west``) share the mast of the corner before them in that list
and look out along one arm. Each camera draws its height, aim jitter and pitch from its own random
stream, so a camera is the same whatever N (``--cameras 2`` and ``--cameras 4`` share their first
two cameras).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from semcal_ros.engine.pose import Pose
from semcal_tools.scenes.layouts import MAST_BACK, Layout, aim_camera, mast_xy

#: Camera names in the order ``--cameras N`` takes them.
NAMES = ("northeast", "southeast", "southwest", "northwest", "north", "east", "south", "west")
MAX_CAMERAS = len(NAMES)
_CORNER = {"northeast": (1, 1), "southeast": (1, -1), "southwest": (-1, -1), "northwest": (-1, 1)}
#: outward cameras: the corner whose mast they share and the direction they look (x east, y north)
_OUTWARD = {"north": ("northeast", (0, 1)), "east": ("southeast", (1, 0)),
            "south": ("southwest", (0, -1)), "west": ("northwest", (-1, 0))}


@dataclass(frozen=True)
class RigCamera:
    """One camera of the rig, its pose in the layout frame."""

    name: str
    pose: Pose
    own_mast: bool  # False for the layout's camera: its mast is already in the world
    yaw_deg: float  # body yaw as drawn (the mast stands MAST_BACK behind, along it)

    @property
    def frame_id(self) -> str:
        """The camera's optical frame: camera_info / image headers and its ground truth."""
        return f"{self.name}_optical"

    @property
    def prefix(self) -> str:
        """Topic namespace: ``<name>/labels``, ``<name>/camera_info``, ``<name>/image_raw``."""
        return self.name


def _pose(position: np.ndarray, pitch: float, yaw: float) -> Pose:
    return Pose.from_body_rpy_deg(position, [0.0, pitch, yaw])


def camera_rig(layout: Layout, count: int, rng_for: Callable[[int], np.random.Generator]
               ) -> list[RigCamera]:
    """The first ``count`` cameras of :data:`NAMES` on ``layout`` (a junction); ``rng_for(k)``
    is camera k's own random stream."""
    if layout.corners is None:
        raise ValueError(f"--cameras N places cameras on a junction's corners; the "
                         f"{layout.kind} layout has none (use --kind junction)")
    if not 2 <= count <= MAX_CAMERAS:
        raise ValueError(f"a camera rig has 2 to {MAX_CAMERAS} cameras, got {count}")
    wa, wb, sa, sb = layout.corners
    own = tuple(int(v) for v in np.sign(layout.camera_position[:2]))
    rig: dict[str, RigCamera] = {}
    masts: dict[str, np.ndarray] = {}
    for k, name in enumerate(NAMES[:count]):
        rng = rng_for(k)
        if name in _CORNER:
            sx, sy = _CORNER[name]
            if (sx, sy) == own:
                pose = _pose(layout.camera_position, layout.camera_pitch_deg,
                             layout.camera_yaw_deg)
                rig[name] = RigCamera(name, pose, False, float(layout.camera_yaw_deg))
            else:
                site = np.array([sx * (wb + sb * 0.6), sy * (wa + sa * 0.6)])
                focus = -site * rng.uniform(0.6, 1.4) + rng.uniform(-4.0, 4.0, 2)
                cam, pitch, yaw = aim_camera(site, layout.camera_ground, focus, rng,
                                             pitch_range=(12.0, 22.0))
                rig[name] = RigCamera(name, _pose(cam, pitch, yaw), True, yaw)
            masts[name] = mast_xy(rig[name].pose.translation, rig[name].yaw_deg)
        else:
            corner, (dx, dy) = _OUTWARD[name]
            base = masts[corner]
            along = rng.uniform(25.0, 40.0)
            focus = np.array([dx * along if dx else rng.uniform(-3.0, 3.0),
                              dy * along if dy else rng.uniform(-3.0, 3.0)])
            if dx:
                focus[0] += base[0]
            else:
                focus[1] += base[1]
            cam, pitch, yaw = aim_camera(base, layout.camera_ground, focus, rng,
                                         pitch_range=(12.0, 22.0))
            # on the shared mast: the camera sits MAST_BACK in front of it, as every camera does
            cam[:2] = base + MAST_BACK * np.array([np.cos(np.radians(yaw)),
                                                   np.sin(np.radians(yaw))])
            rig[name] = RigCamera(name, _pose(cam, pitch, yaw), True, yaw)
    return list(rig.values())


__all__ = ["MAX_CAMERAS", "NAMES", "RigCamera", "camera_rig"]
