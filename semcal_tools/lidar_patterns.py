"""Labelled KITTI scans as other lidars would have seen them: the point labeller's augmentation
and the per-pattern test of ``benchmarks/lidar_patterns.py``.

A SemanticKITTI scan (HDL-64E, 1.73 m up) is resampled, labels kept, to:

* **every k-th beam** (32 or 16 of the 64): the HDL-64E's rings, recovered from the scan order
  (:func:`kitti_rings`), kept or dropped whole;
* **another beam table at another mounting height**: the points seen from a virtual sensor
  ``height - 1.73`` m above KITTI's (the scan shifted down, the origin kept), each point given
  to the nearest beam of the table if within ``tolerance_deg`` of it (0.25 deg: half KITTI's
  widest ring spacing, so that every beam finds a ring; a table finer than KITTI's 0.35-0.5 deg
  cannot be filled more densely than the source), and in each (beam, azimuth column) cell only the nearest
  point kept (what a beam would hit first). :data:`NARROW_BEAMS` is a top-mounted 64-beam
  pattern of +2 to -19 deg (the PJLab frames' lidar: 0.17 deg apart from -6 to +2 deg, 1 deg
  from -6 to -14, then -18.9), without its beams above +2 deg, which KITTI never saw;
* **intensity** rescaled (0-255 as many ROS drivers publish it) or absent.

What this cannot make: points KITTI's sensor did not see (over the roofs of cars from 2.5 m, the
upper floors of a facade beyond +2 deg), and a finer ring spacing than KITTI's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: KITTI's HDL-64E mounting height above the road (m).
KITTI_HEIGHT = 1.73

#: Elevations (deg) of a narrow, top-mounted 64-beam lidar's beams at or below +2.1 deg
#: (measured on PJLab's frames: the median elevation of each ring of ``calib.pcd``).
NARROW_BEAMS: tuple[float, ...] = tuple(
    [-24.9, -18.89, -13.93, -12.97, -12.01, -11.03, -9.88, -9.06, -8.06, -7.06]
    + [round(-6.06 + 0.1686 * i, 2) for i in range(49)])


@dataclass(frozen=True)
class Pattern:
    """How to resample a KITTI scan. ``every``/``offset``: keep rings ``offset``, ``offset +
    every``, ...; ``beams``: a beam table (deg) seen from ``height`` m above the road
    (``None``: KITTI's own rings and height), a beam taking the points within ``tolerance_deg``
    that lie nearer to it than to another beam; ``intensity``: ``"keep"``, ``"scale255"`` (x255) or
    ``"none"``; ``column_deg``: azimuth step of the resampled beams."""

    name: str
    every: int = 1
    offset: int = 0
    beams: tuple[float, ...] | None = None
    height: float = KITTI_HEIGHT
    intensity: str = "keep"
    column_deg: float = 0.2
    tolerance_deg: float = 0.25


#: The held-out test's patterns (``benchmarks/lidar_patterns.py``), one per sensor kind.
TEST_PATTERNS: tuple[Pattern, ...] = (
    Pattern("hdl64 (as recorded)"),
    Pattern("32 beams (every 2nd)", every=2, offset=1),
    Pattern("16 beams (every 4th)", every=4, offset=2),
    Pattern("narrow +2/-19 deg at 1.7 m", beams=NARROW_BEAMS, height=1.7),
    Pattern("narrow +2/-19 deg at 2.1 m", beams=NARROW_BEAMS, height=2.1),
    Pattern("narrow +2/-19 deg at 2.5 m", beams=NARROW_BEAMS, height=2.5),
    Pattern("16 beams at 2.5 m", beams=tuple(np.linspace(-15.0, 15.0, 16).round(2)), height=2.5),
    Pattern("intensity x255", intensity="scale255"),
    Pattern("no intensity", intensity="none"),
    Pattern("narrow at 2.5 m, no intensity", beams=NARROW_BEAMS, height=2.5, intensity="none"),
)


def kitti_rings(xyz: np.ndarray) -> np.ndarray:
    """(N,) ring (laser) index (0 = top) of each point of a KITTI velodyne scan in its stored
    order.

    KITTI stores the HDL-64E's points laser by laser, each sweeping the azimuth upwards from
    0 deg (straight ahead) through +-180 deg back to 0: a laser ends where, after its wrap from
    +180 to -180 deg, the azimuth comes back to 0. A wrap within 200 points of the previous one
    is a jitter around +-180 deg, not a new sweep."""
    az = np.arctan2(np.asarray(xyz)[:, 1], np.asarray(xyz)[:, 0])
    wraps = np.flatnonzero(np.diff(az) < -np.pi) + 1
    ahead = np.flatnonzero((az[1:] >= 0) & (az[:-1] < 0)) + 1  # from -0 to +0
    ring = np.zeros(len(az), np.int64)
    last = -(10 ** 9)
    for w in wraps:
        if w - last <= 200:
            continue
        last = w
        k = np.searchsorted(ahead, w)
        if k < len(ahead):
            ring[ahead[k]] = 1
    return np.cumsum(ring)


def _beam_of(elevation: np.ndarray, beams: np.ndarray, tolerance: float) -> np.ndarray:
    """Nearest beam of a sorted table for each elevation (deg), -1 when farther than
    ``tolerance``."""
    pos = np.clip(np.searchsorted(beams, elevation), 1, len(beams) - 1)
    lower, upper = beams[pos - 1], beams[pos]
    nearest = np.where(elevation - lower < upper - elevation, pos - 1, pos)
    return np.where(np.abs(elevation - beams[nearest]) <= tolerance, nearest, -1)


def resample(xyz: np.ndarray, labels: np.ndarray, intensity: np.ndarray | None,
             pattern: Pattern) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(xyz, labels, intensity) of a KITTI scan (points in stored order) as ``pattern``'s
    sensor sees it, in that sensor's frame (z up, origin at the sensor)."""
    xyz = np.asarray(xyz, np.float64)
    keep = np.ones(len(xyz), bool)
    if pattern.every > 1:
        keep &= kitti_rings(xyz) % pattern.every == pattern.offset % pattern.every
    pts = xyz - np.array([0.0, 0.0, pattern.height - KITTI_HEIGHT])
    if pattern.beams is not None:
        beams = np.sort(np.asarray(pattern.beams, np.float64))
        horizontal = np.hypot(pts[:, 0], pts[:, 1])
        elevation = np.degrees(np.arctan2(pts[:, 2], horizontal))
        beam = _beam_of(elevation, beams, pattern.tolerance_deg)
        keep &= beam >= 0
        n_col = int(round(360.0 / pattern.column_deg))
        col = (np.floor((np.degrees(np.arctan2(pts[:, 1], pts[:, 0])) + 180.0)
                        / pattern.column_deg).astype(np.int64)) % n_col
        cand = np.flatnonzero(keep)
        cell = beam[cand] * n_col + col[cand]
        rng = np.linalg.norm(pts[cand], axis=1)
        order = np.lexsort((rng, cell))
        first = np.r_[True, cell[order][1:] != cell[order][:-1]]
        keep = np.zeros(len(xyz), bool)
        keep[cand[order[first]]] = True
    out_i = None
    if intensity is not None and pattern.intensity != "none":
        out_i = np.asarray(intensity, np.float32)[keep]
        if pattern.intensity == "scale255":
            out_i = out_i * np.float32(255.0)
    return pts[keep].astype(np.float32), np.asarray(labels)[keep], out_i


def training_patterns(rng: np.random.Generator, count: int) -> list[Pattern]:
    """``count`` random sensors for the labeller's augmentation: every 2nd or 4th beam at
    KITTI's height, the narrow pattern or a uniform 16-40-beam table at 1.7-2.5 m, with a tilt
    of up to +-1 deg of the whole table."""
    out = []
    for i in range(count):
        kind = i % 4
        height = float(rng.uniform(1.7, 2.5))
        tilt = float(rng.uniform(-1.0, 1.0))
        if kind == 0:
            every = int(rng.choice([2, 4]))
            out.append(Pattern(f"every{every}", every=every, offset=int(rng.integers(every))))
        elif kind in (1, 2):
            out.append(Pattern(f"narrow@{height:.2f}", beams=tuple(b + tilt for b in NARROW_BEAMS),
                               height=height))
        else:
            lines = int(rng.choice([16, 32, 40]))
            top = float(rng.uniform(2.0, 15.0))
            bottom = float(rng.uniform(-25.0, -15.0))
            out.append(Pattern(f"uniform{lines}@{height:.2f}",
                               beams=tuple(np.linspace(bottom, top, lines)), height=height))
    return out
