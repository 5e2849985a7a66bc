"""One calibration as a user gets it: the search, the check that its result may be published, and
the overlay picture.

``semcal calibrate`` and the ``calibrator`` node both call :func:`calibrate_and_draw`, so the two
cannot drift apart: the same problem (a map cloud, or a map prepared once and shared by the
node's cameras and goals), the same refusal of a degenerate result
(:class:`~semcal_ros.errors.CalibrationFailed`, never a result) and the same picture — the map
rendered at the result by the problem itself (the renderer and parameters the search used, no
second preparation of the map), blended over the camera image, with the verdict drawn on it.

:func:`calibrate_frames_and_draw` does the same for several frames of one rig
(:class:`~semcal_ros.engine.frames.FrameSet`): one search, one verdict, one picture per frame.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Sequence, cast

import numpy as np

from semcal_ros.engine import validation
from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.frames import Frame, FrameSet
from semcal_ros.engine.labels import LabelMapping, colorize
from semcal_ros.engine.overlay import annotate_quality, blend_labels
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.pose import Pose
from semcal_ros.engine.problem import Problem
from semcal_ros.engine.quality import label_agreement
from semcal_ros.engine.render import PreparedMap
from semcal_ros.engine.results import CalibrationResult, Progress
from semcal_ros.engine.search import solve
from semcal_ros.errors import CalibrationFailed


@dataclass
class Calibration:
    """A result worth publishing and its picture."""

    result: CalibrationResult
    overlay: np.ndarray | None = None  # RGB uint8, camera size (None: not asked for, or failed)
    overlay_error: str = ""  # why drawing failed (the result stands without its picture)
    # several frames: one picture per frame (``overlay`` is the first) and how each frame agrees
    overlays: list[np.ndarray] = field(default_factory=list)
    frames: list["FrameCheck"] = field(default_factory=list)


@dataclass(frozen=True)
class FrameCheck:
    """One frame of several at the result: its own loss, coverage and label agreement (a frame
    that disagrees while the others agree points at that frame's map or labels)."""

    name: str
    loss: float
    coverage: float
    agreement: float


def draw_overlay(problem: Problem, result: CalibrationResult, labels: np.ndarray,
                 background: np.ndarray | None = None) -> np.ndarray:
    """The map rendered at ``result.pose`` over ``background`` (RGB or grey, the camera's size;
    otherwise the colours of ``labels``, the camera's trainIds), with the verdict drawn on it."""
    camera = problem.camera
    if background is None or background.shape[:2] != (camera.height, camera.width):
        background = colorize(labels)
    if background.ndim == 2:
        background = np.repeat(background[:, :, None], 3, axis=2)
    picture = blend_labels(background, problem.render(result.pose))
    return annotate_quality(picture, result.quality) if result.quality is not None else picture


def calibrate_and_draw(map_cloud: LabelledCloud | None, target: np.ndarray, camera: CameraModel,
                       initial: Pose, params: CalibrationParams | None = None,
                       mapping: LabelMapping | None = None, *,
                       prepared: PreparedMap | None = None,
                       probabilities: np.ndarray | None = None,
                       background: np.ndarray | None = None, draw: bool = True,
                       seed: int | None = None,
                       progress: Callable[[Progress], None] | None = None,
                       should_stop: Callable[[], bool] | None = None) -> Calibration:
    """Calibrate (:func:`~semcal_ros.engine.search.solve` on a :class:`Problem` around
    ``initial``, or on ``prepared``; ``probabilities``: the segmenter's softmax beside the
    labels) and, with ``draw``, draw the overlay over ``background``.

    Raises :class:`~semcal_ros.errors.CalibrationFailed` (with the evaluations and seconds spent)
    for a result that must not be published, ``ValueError`` for unusable input and
    :class:`~semcal_ros.errors.Cancelled` when ``should_stop`` asked. The result's seconds count
    preparing the problem. A failure to draw leaves the result standing (``overlay_error``)."""
    t0 = time.perf_counter()
    problem = Problem(map_cloud, target, camera, initial.translation, params, mapping,
                      prepared=prepared, probabilities=probabilities, image=background)
    result = solve(problem, initial, seed, progress, should_stop)
    result.seconds = time.perf_counter() - t0
    refused = validation.result_problems(float(result.loss), problem.params)
    if refused:
        raise CalibrationFailed("; ".join(refused), result.evaluations, result.seconds)
    out = Calibration(result)
    if draw:
        try:
            out.overlay = draw_overlay(problem, result, target, background)
        except Exception as exc:  # noqa: BLE001 - a by-product; the result stands
            out.overlay_error = f"{type(exc).__name__}: {exc}"
    return out


def calibrate_frames_and_draw(frames: Sequence[Frame], initial: Pose,
                              mapping: LabelMapping | None = None, *, draw: bool = True,
                              seed: int | None = None,
                              progress: Callable[[Progress], None] | None = None,
                              should_stop: Callable[[], bool] | None = None) -> Calibration:
    """:func:`calibrate_and_draw` for several frames of one rig sharing one camera-from-map pose
    (:class:`~semcal_ros.engine.frames.FrameSet`: the loss is the mean over frames, the search,
    verification and quality settings are the first frame's). ``overlays`` holds one picture
    per frame with the verdict over all frames; ``frames`` each frame's own agreement."""
    t0 = time.perf_counter()
    frameset = FrameSet([f.problem(initial.translation, mapping) for f in frames])
    # the search and the report use only what a Problem and a FrameSet both offer
    result = solve(cast(Problem, frameset), initial, seed, progress, should_stop)
    result.seconds = time.perf_counter() - t0
    refused = validation.result_problems(float(result.loss), frameset.params)
    if refused:
        raise CalibrationFailed("; ".join(refused), result.evaluations, result.seconds)
    out = Calibration(result)
    for k, (frame, problem) in enumerate(zip(frames, frameset.frames)):
        rendered = problem.render(result.pose)
        loss, coverage = problem.level(-1).loss.evaluate(rendered)
        agreement = label_agreement(rendered, problem.target, problem.params.loss.crop_top)[0]
        out.frames.append(FrameCheck(frame.name or f"frame {k + 1}", float(loss),
                                     float(coverage), agreement))
    if draw:
        try:
            out.overlays = [draw_overlay(p, result, f.labels, f.background)
                            for f, p in zip(frames, frameset.frames)]
            out.overlay = out.overlays[0]
        except Exception as exc:  # noqa: BLE001 - a by-product; the result stands
            out.overlays, out.overlay_error = [], f"{type(exc).__name__}: {exc}"
    return out


__all__ = ["Calibration", "FrameCheck", "calibrate_and_draw", "calibrate_frames_and_draw",
           "draw_overlay"]
