"""Things that move: the survey vehicle's path, cars on lanes and people on pavements.

Every mover follows a 2-D polyline parameterised by arc length, so its pose at any time is a
closed-form lookup; the same world can then be sampled at each lidar scan time and at the camera's
exposure without simulating anything step by step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semcal_tools.scenes.mesh import LabelledMesh


class Polyline:
    """A 2-D path with arc-length lookups of position and heading."""

    def __init__(self, points: np.ndarray) -> None:
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        keep = np.r_[True, np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9]
        pts = pts[keep]
        if len(pts) < 2:
            raise ValueError("a path needs at least two distinct points")
        self.points = pts
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        self.cumulative = np.r_[0.0, np.cumsum(seg)]

    @property
    def length(self) -> float:
        return float(self.cumulative[-1])

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (N, 2) and headings (N,) in radians at arc lengths ``s`` (clamped)."""
        s = np.clip(np.atleast_1d(np.asarray(s, float)), 0.0, self.length)
        i = np.clip(np.searchsorted(self.cumulative, s, side="right") - 1, 0, len(self.points) - 2)
        d = self.points[i + 1] - self.points[i]
        seg = self.cumulative[i + 1] - self.cumulative[i]
        frac = (s - self.cumulative[i]) / seg
        return self.points[i] + frac[:, None] * d, np.arctan2(d[:, 1], d[:, 0])

    def closest_arclength(self, point: np.ndarray) -> float:
        """Arc length of the path point nearest to ``point`` (sampled every 0.5 m)."""
        s = np.linspace(0.0, self.length, max(2, int(self.length / 0.5)))
        xy, _ = self.at(s)
        return float(s[np.argmin(np.linalg.norm(xy - np.asarray(point)[:2], axis=1))])


def arc(centre: np.ndarray, radius: float, a0: float, a1: float, step: float = 1.0) -> np.ndarray:
    """Points on a circular arc from angle a0 to a1 (radians), about ``step`` metres apart."""
    n = max(2, int(abs(a1 - a0) * radius / step) + 1)
    a = np.linspace(a0, a1, n)
    return np.asarray(centre, float) + radius * np.c_[np.cos(a), np.sin(a)]


@dataclass
class Actor:
    """A moving object: a mesh in its own frame driven along a path at constant speed.

    ``bounce`` walks back and forth (people); otherwise the path wraps around (cars leave at one
    end of the scene and enter at the other, far from the sensors).
    """

    mesh: LabelledMesh
    path: Polyline
    speed: float
    start: float
    ground: float = 0.0
    bounce: bool = False

    def pose(self, t: float) -> tuple[np.ndarray, float]:
        travelled = self.start + self.speed * t
        length = self.path.length
        if self.bounce:
            phase = travelled % (2 * length)
            s = phase if phase <= length else 2 * length - phase
            xy, heading = self.path.at(s)
            if phase > length:
                heading = heading + np.pi
        else:
            xy, heading = self.path.at(travelled % length)
        return np.array([xy[0, 0], xy[0, 1], self.ground]), float(heading[0])

    def mesh_at(self, t: float) -> LabelledMesh:
        position, heading = self.pose(t)
        return self.mesh.moved(heading, position)


def actors_at(actors: list[Actor], t: float) -> LabelledMesh:
    """All actors' triangles posed at time ``t``."""
    return LabelledMesh.concat([a.mesh_at(t) for a in actors])
