"""More evidence per calibration: several frames of one rig, and many label images of one camera.

One frame carries little evidence: on real KITTI frames the forward axis's loss rises only a few
per cent per 25 cm. Two ways to give the search more:

* **Several frames of one rig** (:class:`FrameSet`): a vehicle's camera and lidar, one extrinsic.
  Each frame is its own :class:`~semcal_ros.engine.problem.Problem` (its map in its first scan's
  lidar frame, its labels, camera and parameters: crop_top, merges); every frame is seen from the
  same camera-from-map pose, and the loss is the mean of the frames' losses. A :class:`FrameSet`
  answers everything the search (:func:`~semcal_ros.engine.search.solve`) and the quality report
  (:func:`~semcal_ros.engine.quality.assess`) ask of a problem, so one search, one verdict over
  all frames: its ``render`` and ``target`` are the frames stacked one above the other (each
  frame's cropped rows left out), so agreement, coverage and the label-outlier masks are counted
  over every frame's pixels at once.
* **A static camera's label images** (:func:`fuse_labels`): a camera that did not move sees the
  same street in every image; per pixel, the class most images agree on (a class histogram and
  its argmax). Passing cars and flickering segmentation mistakes are outvoted; the share of
  images that agree with the fused class says how steady each pixel was.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Sequence, TypeVar

import numpy as np

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.labels import INVALID, LabelMapping
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.pose import Pose
from semcal_ros.engine.problem import Evaluation, Problem
from semcal_ros.engine.workers import side_by_side


@dataclass(frozen=True)
class Frame:
    """One frame of a rig as read from a scene folder: its map (in its first scan's lidar
    frame), label image, camera, parameters (the folder's calibrator.yaml) and, optionally, the
    segmenter's class probabilities and the camera image for the overlay."""

    map_cloud: LabelledCloud
    labels: np.ndarray
    camera: CameraModel
    params: CalibrationParams
    probabilities: np.ndarray | None = None
    background: np.ndarray | None = None
    name: str = ""

    def problem(self, center: np.ndarray, mapping: LabelMapping | None = None) -> Problem:
        """The frame's problem, its map cropped around ``center`` (the initial position)."""
        return Problem(self.map_cloud, self.labels, self.camera, center, self.params, mapping,
                       probabilities=self.probabilities, image=self.background)


# --- several frames of one rig ---------------------------------------------------------------
T = TypeVar("T")


class StackedLoss:
    """The loss of a :class:`FrameSet` at one resolution, on the stacked render: each frame's
    own loss on its rows, averaged over the frames (coverage likewise)."""

    def __init__(self, frames: Sequence[Problem], stage: int, rows: Sequence[tuple[int, int, int]]
                 ) -> None:
        self.losses = [f.level(stage).loss for f in frames]
        self.rows = list(rows)  # (first row, height, width) of each frame in the stack

    def evaluate(self, stacked: np.ndarray) -> tuple[float, float]:
        """(mean loss, mean coverage) of a stacked render."""
        losses, coverages = [], []
        for loss, (top, h, w) in zip(self.losses, self.rows):
            value, coverage = loss.evaluate(np.ascontiguousarray(stacked[top:top + h, :w]))
            losses.append(value)
            coverages.append(coverage)
        return float(np.mean(losses)), float(np.mean(coverages))

    def __call__(self, stacked: np.ndarray) -> float:
        return self.evaluate(stacked)[0]

    def floor(self, stacked: np.ndarray) -> float:
        """The mean of the frames' floors (:meth:`LabelLoss.floor`)."""
        return float(np.mean([loss.floor(np.ascontiguousarray(stacked[top:top + h, :w]))
                              for loss, (top, h, w) in zip(self.losses, self.rows)]))


@dataclass(frozen=True)
class StackedLevel:
    """What ``FrameSet.level(stage)`` gives: the scale and the stacked loss."""

    scale: int
    loss: StackedLoss


def _stack(images: Sequence[np.ndarray]) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """The images one above the other, padded to the widest with INVALID, and each one's rows."""
    width = max(im.shape[1] for im in images)
    out = np.full((sum(im.shape[0] for im in images), width), INVALID, np.uint8)
    rows, top = [], 0
    for im in images:
        h, w = im.shape
        out[top:top + h, :w] = im
        rows.append((top, h, w))
        top += h
    return out, rows


def _uncropped(problem: Problem) -> np.ndarray:
    """The frame's aligned target with the rows its loss leaves out (``loss.crop_top``) set to
    INVALID, so that a stack of frames needs no crop of its own."""
    target = problem.target.copy()
    target[:int(round(problem.params.loss.crop_top * target.shape[0]))] = INVALID
    return target


class FrameSet:
    """Several frames of one rig that share one camera-from-map pose (see the module docstring).

    ``frames``: one :class:`Problem` per frame, each with its own map (in that frame's lidar
    frame), labels, camera and parameters. The search, verification and quality settings are the
    first frame's; every frame must share its resolution schedule (the stages are searched
    together). The loss is the mean over frames of each frame's loss; a frame that sees none of
    its map adds its degenerate loss to the mean, so no pose wins by looking away in one frame.
    """

    def __init__(self, frames: Sequence[Problem]) -> None:
        self.frames = list(frames)
        if not self.frames:
            raise ValueError("a frame set needs at least one frame")
        first = self.frames[0]
        scales = [s.scale for s in first.stages]
        for k, f in enumerate(self.frames[1:], start=2):
            if [s.scale for s in f.stages] != scales:
                raise ValueError(f"frame {k} has the resolution schedule "
                                 f"{[s.scale for s in f.stages]}, frame 1 {scales}: frames "
                                 "searched together need one schedule")
        # the stack carries each frame's crop as INVALID rows: no crop of its own
        self.params: CalibrationParams = replace(
            first.params, loss=replace(first.params.loss, crop_top=0.0))
        self.stages = first.stages
        self.mapping = first.mapping
        self.camera = first.camera
        self.target, self.rows = _stack([_uncropped(f) for f in self.frames])
        self._levels: dict[tuple[int, int], StackedLevel] = {}
        # the first stage (finding the basins) on a few frames spread over the set, the later
        # stages on all (schedule.coarse_frames): the first stage costs most evaluations
        k = first.params.schedule.coarse_frames
        if 0 < k < len(self.frames) and len(self.stages) > 1:
            self.coarse = sorted({int(i) for i in np.round(np.linspace(0, len(self.frames) - 1,
                                                                       k))})
        else:
            self.coarse = list(range(len(self.frames)))

    def __len__(self) -> int:
        return len(self.frames)

    def searched(self, stage: int = -1) -> list[Problem]:
        """The frames ``stage`` is searched and judged on: all, or at the first stage of a
        schedule with several the ``schedule.coarse_frames`` ones."""
        if stage % len(self.stages) == 0 and len(self.coarse) < len(self.frames):
            return [self.frames[i] for i in self.coarse]
        return self.frames

    def level(self, stage: int = -1) -> StackedLevel:
        scale = self.stages[stage].scale
        frames = self.searched(stage)
        key = (scale, len(frames))
        if key not in self._levels:
            rows = _stack([f.level(stage).loss.target.reshape(f.level(stage).loss.shape)
                           for f in frames])[1]
            self._levels[key] = StackedLevel(scale, StackedLoss(frames, stage, rows))
        return self._levels[key]

    def _each(self, call: Callable[..., T], pose: Pose, stage: int) -> list[T]:
        """``call(frame, pose, stage)`` for every frame of the stage, in frame order: side by
        side on the workers (engine/workers.py), each frame rendered on its worker's thread,
        instead of one after another, each on the renderer's pool."""
        return side_by_side(lambda f: call(f, pose, stage), self.searched(stage))

    def render(self, pose: Pose, stage: int = -1) -> np.ndarray:
        """Every frame's render from ``pose``, stacked as :attr:`target` is."""
        return _stack(self._each(Problem.render, pose, stage))[0]

    def evaluations(self, pose: Pose, stage: int = -1) -> list[Evaluation]:
        """Each frame's loss and coverage at ``pose``."""
        return self._each(Problem.evaluate, pose, stage)

    def evaluate(self, pose: Pose, stage: int = -1) -> Evaluation:
        each = self.evaluations(pose, stage)
        return Evaluation(float(np.mean([e.loss for e in each])),
                          float(np.mean([e.coverage for e in each])))

    def loss(self, pose: Pose, stage: int = -1) -> float:
        """The mean of the frames' losses at ``pose``."""
        return float(np.mean(self._each(Problem.loss, pose, stage)))

    def floor(self, pose: Pose, stage: int = -1) -> float:
        """The mean of the frames' floors at ``pose`` (:meth:`Problem.floor`)."""
        return float(np.mean(self._each(Problem.floor, pose, stage)))

    def freeze(self, pose: Pose, stage: int | None = None) -> None:
        """Each frame's likelihood confusion held fixed at ``pose`` (``loss.em``, as
        :meth:`Problem.freeze`)."""
        for f in self.frames:
            f.freeze(pose, stage)

    def thaw(self) -> None:
        for f in self.frames:
            f.thaw()

    def masked(self, ignore: np.ndarray) -> "FrameSet":
        """The same frames with the stacked ``ignore`` mask's pixels left out of each one."""
        return FrameSet([f.masked(ignore[top:top + h, :w])
                         for f, (top, h, w) in zip(self.frames, self.rows)])

    def detached(self) -> "FrameSet":
        """The same frames, each with loss objects of its own (:meth:`Problem.detached`)."""
        return FrameSet([f.detached() for f in self.frames])

    def degenerate(self, evaluation: Evaluation) -> bool:
        """True when the frames together show (almost) none of their maps: never a result."""
        lp = self.params.loss
        return evaluation.loss >= lp.degenerate_loss or evaluation.coverage < lp.min_coverage


# --- a static camera's label images ----------------------------------------------------------
@dataclass(frozen=True)
class FusedLabels:
    """Label images of one static camera fused per pixel."""

    labels: np.ndarray  # uint8 (H, W): per pixel the class most images gave (ties: the newest)
    share: np.ndarray  # float32 (H, W): share of the images that gave that class
    images: int

    @property
    def agreement(self) -> float:
        """Mean share over the pixels: 1.0 when every image gave every pixel the same class."""
        return float(self.share.mean())


def fuse_labels(images: Sequence[np.ndarray], min_share: float = 0.0) -> FusedLabels:
    """Per pixel the class most of ``images`` (mono8 trainIds of one camera that did not move,
    oldest first) agree on: a class histogram and its argmax. A tie goes to the class of the
    newest image among the tied ones. ``min_share`` > 0: a pixel whose winning class has a
    smaller share of the images becomes 255 (ignored by the loss). One image is returned as is."""
    if not images:
        raise ValueError("no label image to fuse")
    first = np.asarray(images[0])
    for k, im in enumerate(images):
        im = np.asarray(im)
        if im.dtype != np.uint8 or im.ndim != 2:
            raise ValueError(f"label image {k + 1} must be 8-bit single channel, got {im.dtype} "
                             f"with {im.ndim} dims")
        if im.shape != first.shape:
            raise ValueError(f"label image {k + 1} is {im.shape[1]}x{im.shape[0]}, the first "
                             f"{first.shape[1]}x{first.shape[0]}: fused images come from one "
                             "camera")
    if not 0.0 <= min_share <= 1.0:
        raise ValueError(f"min_share must be in [0, 1], got {min_share}")
    n = len(images)
    if n == 1:
        return FusedLabels(first.copy(), np.ones(first.shape, np.float32), 1)
    stack = np.stack([np.asarray(im) for im in images])
    best = np.zeros(first.shape, np.int32)  # score: count * (n + 1) + newest index + 1
    labels = np.full(first.shape, INVALID, np.uint8)
    order = np.arange(1, n + 1, dtype=np.int32)[:, None, None]
    for c in np.unique(stack):
        hit = stack == c
        count = hit.sum(axis=0, dtype=np.int32)
        newest = (hit * order).max(axis=0)
        score = count * (n + 1) + newest
        win = score > best
        best[win] = score[win]
        labels[win] = c
    share = (best // (n + 1)).astype(np.float32) / n
    if min_share > 0:
        labels[share < min_share] = INVALID
    return FusedLabels(labels, share, n)


__all__ = ["Frame", "FrameSet", "FusedLabels", "StackedLevel", "StackedLoss", "fuse_labels"]
