"""A result's uncertainty from independent evidence: the result refined again on disjoint parts.

How far the pose can move before the loss rises (the loss-rise probes, :func:`~semcal_ros.engine.
quality.axis_uncertainty`) says how sharp the loss is, not how right its minimum is: on real
labels the basin is shallow whether its bottom is right or biased, and five-frame KITTI results
within 6-9 cm reported +-89 to +-125 cm. Evidence that does not share its errors says more. The
result is refined again, from itself, at full resolution, on parts of its evidence that share no
pixel:

* several frames, three or more: each frame left out in turn (the jackknife, Quenouille 1956 /
  Tukey 1958): sigma^2 = (N - 1) / N x sum (theta_i - mean)^2. Odd against even frames pitted
  one frame against two in a group of three (27-104 cm of +- on KITTI results within 6 cm);
* two frames: each alone; sigma = |A - B| / 2 (each half carries half the evidence, so its
  error is sqrt(2) x the whole's, and |A - B| is sqrt(2) x a half's);
* one frame: the block jackknife (Kunsch 1989): the image cut into four vertical strips, each
  left out in turn, sigma as for frames. Label errors come in regions (a facade called
  vegetation, a hedge called terrain), so the parts must be larger than those regions: leaving a
  quarter of the scene out moves the result when that quarter's labels pulled it, while three
  quarters keep the geometry of the whole (left and right halves alone lost it: 25-317 cm on
  KITTI frames within 10 cm). Interleaved 32 px tile halves were tried first: each half sees
  every region, so they agreed within centimetres on results 0.4-1.3 m off (KITTI 00 001112,
  001668), and called them good.

The per-axis figures are map x, y, z (m) and body roll, pitch, yaw (deg), as the quality report
gives them. No search here: the caller passes ``refine(part, start_vector) -> vector``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from semcal_ros.engine.pose import Pose

#: vertical strips of a single frame's block jackknife
STRIPS = 4


@dataclass(frozen=True)
class Evidence:
    """The uncertainty from independent evidence and how it was measured."""

    sigma: np.ndarray  # (6,) x, y, z (m), roll, pitch, yaw (deg)
    moves: np.ndarray  # (6,) the largest move of a part's refinement from the result, per axis
    method: str  # "leave-one-out of 8 frames", "each of 2 frames alone", "... of 4 image strips"
    parts: int  # refinements run
    frames: int = 1  # label images behind the result


def axis_offsets(pose: Pose, reference: Pose) -> np.ndarray:
    """(6,) ``pose`` - ``reference``: map x, y, z (m), body roll, pitch, yaw (deg, wrapped)."""
    d = np.concatenate([pose.translation - reference.translation,
                        pose.body_rpy_deg() - reference.body_rpy_deg()])
    d[3:] = (d[3:] + 180.0) % 360.0 - 180.0
    return d


def strips(width: int, count: int = STRIPS) -> list[np.ndarray]:
    """The image's columns cut into ``count`` vertical strips: a bool column mask per strip."""
    edges = np.linspace(0, width, count + 1).round().astype(int)
    cols = np.arange(width)
    return [(cols >= a) & (cols < b) for a, b in zip(edges[:-1], edges[1:])]


def independent_parts(problem: Any) -> tuple[str, list[list[Any]]]:
    """(method, groups): each group a list of sub-problems refined alone, whose spread gives the
    uncertainty (:func:`evidence_uncertainty`). A frame set gives its leave-one-out sets (three
    frames or more) or each of two frames alone; a single problem leaves each image strip out in
    turn (:meth:`masked`: the strip's pixels ignored)."""
    frames = getattr(problem, "frames", None)
    if frames is not None and len(frames) >= 2:
        from semcal_ros.engine.frames import FrameSet

        def sub(keep: Sequence[int]) -> Any:
            chosen = [frames[k] for k in keep]
            return chosen[0] if len(chosen) == 1 else FrameSet(chosen)

        n = len(frames)
        if n >= 3:
            return (f"leave-one-out of {n} frames",
                    [[sub([k for k in range(n) if k != i]) for i in range(n)]])
        return "each of 2 frames alone", [[sub([0]), sub([1])]]
    h, w = problem.target.shape
    parts = [problem.masked(np.broadcast_to(strip[None, :], (h, w))) for strip in strips(w)]
    return f"leave-one-out of {STRIPS} image strips", [parts]


def evidence_uncertainty(problem: Any, pose: Pose,
                         refine: Callable[[list[Any], np.ndarray, bool], list[np.ndarray]]
                         ) -> Evidence:
    """Refine ``pose`` on each independent part of ``problem``'s evidence
    (:func:`independent_parts`) and measure their spread (see the module docstring).
    ``refine(parts, start, shared)`` refines each part from ``start`` and gives their vectors
    in the parts' order; ``shared``: the parts are made of ``problem``'s own frames (a frame
    set's), so whatever a part holds in a frame (the E step) it holds for every part; else each
    part is a copy with loss objects of its own (a single frame's masked strips)."""
    method, groups = independent_parts(problem)
    shared = getattr(problem, "frames", None) is not None
    variances, moves, parts = [], np.zeros(6), 0
    for group in groups:
        thetas = np.array([axis_offsets(Pose.from_vector(v), pose)
                           for v in refine(group, pose.vector(), shared)])
        parts += len(group)
        moves = np.maximum(moves, np.max(np.abs(thetas), axis=0))
        n = len(thetas)
        if n == 2:
            variances.append(((thetas[0] - thetas[1]) / 2.0) ** 2)
        else:  # the jackknife
            variances.append((n - 1) / n * np.sum((thetas - thetas.mean(axis=0)) ** 2, axis=0))
    sigma = np.sqrt(np.mean(variances, axis=0))
    frames = getattr(problem, "frames", None)
    return Evidence(sigma, moves, method, parts, len(frames) if frames is not None else 1)


__all__ = ["STRIPS", "Evidence", "axis_offsets", "evidence_uncertainty", "independent_parts",
           "strips"]
