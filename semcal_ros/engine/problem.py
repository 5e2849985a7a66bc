"""The registration problem: a labelled map, a camera and its label image, ready for many losses.

A :class:`Problem` is what the search minimises and what everything that judges a pose asks: the
optimiser, the evaluation protocol (one problem for all its starts), quality reports and drift
checks. It prepares the map once (crop around an explicit centre, local origin, Morton chunks) and
one view set-up and target per resolution level of the schedule; ``loss(pose, stage)`` is then one
render and one table lookup per pixel.
"""

from __future__ import annotations

import copy
import threading
from dataclasses import dataclass

import numpy as np

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.cloud import LabelledCloud, finite_rows
from semcal_ros.engine.cues import CuedLoss, EdgeCue, IntensityCue, edge_field, grey_bins
from semcal_ros.engine.labels import INVALID, LabelMapping
from semcal_ros.engine.loss import LabelLoss, aligned_probabilities
from semcal_ros.engine.params import CalibrationParams
from semcal_ros.engine.pose import Pose
from semcal_ros.engine.render import PreparedMap, ViewSetup, prepare_map, view_setup
from semcal_ros.engine.render.fast import render, render_with_keys, render_with_values
from semcal_ros.engine.workers import render_threads


@dataclass(frozen=True)
class Evaluation:
    loss: float
    coverage: float  # share of the target's non-sky pixels that rendered map points cover


@dataclass(frozen=True)
class Level:
    """One resolution: the view set-up and the loss against the downsampled target."""

    scale: int
    setup: ViewSetup
    loss: LabelLoss | CuedLoss  # CuedLoss only with a cue on (engine/cues.py)


def mapping_for(params: CalibrationParams, mapping: LabelMapping | None = None) -> LabelMapping:
    """The label alignment: an explicit one (a YAML given by the user), else the built-in table
    with ``params.labels.merge`` applied (what a parameter file can carry)."""
    if mapping is None:
        mapping = LabelMapping(merge=params.labels.as_dict())
    elif params.labels.merge:
        mapping = LabelMapping(mapping.alignment, mapping.dynamic,
                               {**dict(mapping.merge), **params.labels.as_dict()})
    return mapping.with_parked_vehicles() if params.labels.parked_vehicles else mapping


class Problem:
    """A map, a target label image and a camera made ready for many loss evaluations.

    ``center`` is where the map is cropped (``params.render.crop_radius`` around it) and where
    its local origin lies: the initial camera position for one calibration, any fixed point near
    the camera when many starts share one problem. ``prepared`` is a map already prepared (by
    :func:`~semcal_ros.engine.render.prepare_map` with the same label mapping) to share between problems
    instead of preparing ``map_cloud`` again (which may then be None); ``center`` is then ignored.
    ``probabilities`` (H, W, 19): the segmenter's softmax over Cityscapes trainIds beside the
    labels (``DIR/probabilities.npz``); the loss then takes the expected cost under them.
    ``image``: the camera image (grey or colour, the labels' size), needed only by the cues
    (``params.cues``, engine/cues.py).
    """

    def __init__(self, map_cloud: LabelledCloud | None, target: np.ndarray, camera: CameraModel,
                 center: np.ndarray, params: CalibrationParams | None = None,
                 mapping: LabelMapping | None = None, prepared: PreparedMap | None = None,
                 probabilities: np.ndarray | None = None, image: np.ndarray | None = None
                 ) -> None:
        self.params = params or CalibrationParams()
        self.mapping = mapping_for(self.params, mapping)
        self.camera = camera
        target = np.asarray(target)
        if target.ndim != 2 or target.dtype != np.uint8:
            raise ValueError(f"label image must be a single-channel uint8 image, got {target.dtype} "
                             f"with shape {target.shape}")
        if target.shape != (camera.height, camera.width):
            raise ValueError(f"label image is {target.shape[1]}x{target.shape[0]} but camera_info "
                             f"says {camera.width}x{camera.height}")
        if prepared is None and map_cloud is None:
            raise ValueError("a problem needs a map: a cloud or a prepared map")
        if map_cloud is not None and prepared is None and len(map_cloud):
            bad = len(map_cloud) - int(finite_rows(map_cloud.xyz).sum())
            if bad:
                raise ValueError(f"map contains {bad} NaN or infinite points")
        center = np.asarray(center, dtype=float)
        if center.shape != (3,) or not np.all(np.isfinite(center)):
            raise ValueError(f"crop centre must be 3 finite numbers, got {center}")
        rp = self.params.render
        # a map prepared once serves every camera and goal on it (multi-camera calibrator, drift
        # watch); it must have been prepared with this problem's label mapping
        if prepared is None:
            assert map_cloud is not None  # checked above: one of the two is given
            prepared = prepare_map(map_cloud, self.mapping, center=center,
                                   radius=rp.crop_radius or None)
        self.pmap: PreparedMap = prepared
        self.target = self.mapping.map_image(target)
        if np.all(self.target == INVALID):
            raise ValueError("label image has no pixel of a class the map can match")
        self.probabilities = (None if probabilities is None else aligned_probabilities(
            probabilities, self.mapping.image_lut(), self.target))
        # the cues: the image's edge field and grey bins once per target; None = off (no cost)
        self.edges: np.ndarray | None = None
        self.grey: np.ndarray | None = None
        # last render of this thread: labels, keys, intensity codes (None without the intensity
        # cue), per thread: searches run side by side (engine/workers.py)
        self._local = threading.local()
        cp = self.params.cues
        total = cp.edge_weight + cp.intensity_weight  # each term is in [0, 1]
        if total >= 0.5 * self.params.loss.degenerate_loss:
            raise ValueError(f"engine.cues weights sum to {total:g}: keep them below half of "
                             f"loss.degenerate_loss ({self.params.loss.degenerate_loss:g}), or a "
                             "view that shows the map would count as showing none of it")
        if image is None:
            for name, weight in (("edge_weight", cp.edge_weight),
                                 ("intensity_weight", cp.intensity_weight)):
                if weight > 0:
                    raise ValueError(f"engine.cues.{name} > 0 needs the camera image "
                                     "(image.png beside the labels)")
        elif cp.edge_weight > 0:
            self.edges = edge_field(image, cp, self.target.shape)
        if image is not None and cp.intensity_weight > 0:
            if self.pmap.intensity is None:
                raise ValueError("engine.cues.intensity_weight > 0 needs a map with lidar "
                                 "intensity (map.ply has no 'intensity' property: write it "
                                 "again with semcal real-scene or semcal build-map)")
            self.grey = grey_bins(image, cp.intensity_bins, self.target.shape)
        self.stages = self.params.schedule.stages()
        # the probabilities at each level's resolution: 44 MB at full resolution, shared with
        # the masked and detached copies (the evidence's parts, basins side by side)
        self._sampled: dict[int, np.ndarray] = {}
        self._levels: dict[int, Level] = {}
        for stage in self.stages:
            if stage.scale not in self._levels:
                self._levels[stage.scale] = self._level(stage.scale)

    def _level(self, scale: int, setup: ViewSetup | None = None) -> Level:
        """The loss against ``self.target`` at ``scale``; ``setup`` reuses a view set-up."""
        setup = setup or view_setup(self.camera, self.pmap, self.params.render, scale)
        cam = setup.camera
        off = scale // 2  # the sample nearest the centre of each scale x scale block
        target = self.target[off::scale, off::scale][:cam.height, :cam.width]
        probs = None
        if self.probabilities is not None:  # sampled once per scale, shared by the copies
            probs = self._sampled.get(scale)
            if probs is None or probs.shape[:2] != target.shape:
                probs = self._sampled[scale] = np.ascontiguousarray(
                    self.probabilities[off::scale, off::scale][:cam.height, :cam.width])
        loss = LabelLoss(np.ascontiguousarray(target), self.params.loss, scale, probs)
        if self.edges is None and self.grey is None:
            return Level(scale, setup, loss)
        cp = self.params.cues
        start_row = int(round(self.params.loss.crop_top * cam.height))
        edge = intensity = None
        if self.edges is not None:
            field = self.edges[off::scale, off::scale][:cam.height, :cam.width]
            edge = EdgeCue(field, cp, start_row, setup.splat_lambda, setup.radius_max)
        if self.grey is not None:
            grey = self.grey[off::scale, off::scale][:cam.height, :cam.width]
            intensity = IntensityCue(grey, cp, start_row,
                                     -(-cp.intensity_min_pixels // (scale * scale)))
        return Level(scale, setup, CuedLoss(loss, edge, cp.edge_weight, self._keys_of,
                                            intensity, cp.intensity_weight))

    def _keys_of(self, rendered: np.ndarray) -> tuple[np.ndarray, np.ndarray | None] | None:
        """The z-buffer and intensity image of the render ``rendered`` came from, if it is this
        problem's last one (the same array, or an equal copy of it: a frame set's stack cuts
        copies)."""
        last = self.last_render()
        if last is None:
            return None
        labels, keys, values = last
        if rendered is labels or (rendered.shape == labels.shape
                                  and np.array_equal(rendered, labels)):
            return keys, values
        return None

    def last_render(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
        """This thread's last render with the cues on: labels, z-buffer keys, intensity codes
        (None without the intensity cue); None before one (or with the cues off)."""
        return getattr(self._local, "last", None)

    def level(self, stage: int = -1) -> Level:
        return self._levels[self.stages[stage].scale]

    def render(self, pose: Pose, stage: int = -1) -> np.ndarray:
        """Aligned label image of the map from ``pose`` at the stage's resolution, on the
        renderer's thread pool, or on the calling thread on a worker (engine/workers.py: the
        frames of a rig and independent searches run side by side)."""
        lv = self.level(stage)
        threads = render_threads()
        if self.edges is None and self.grey is None:
            return render(self.pmap, lv.setup.view(pose), threads)
        values = None
        if self.grey is not None:
            assert self.pmap.intensity is not None  # checked when the cue was set up
            labels, keys, values = render_with_values(self.pmap, lv.setup.view(pose),
                                                      self.pmap.intensity, threads)
        else:
            labels, keys = render_with_keys(self.pmap, lv.setup.view(pose), threads)
        self._local.last = (labels, keys, values)  # the cues' inputs, read by its CuedLoss
        return labels

    def evaluate(self, pose: Pose, stage: int = -1) -> Evaluation:
        loss, coverage = self.level(stage).loss.evaluate(self.render(pose, stage))
        return Evaluation(float(loss), float(coverage))

    def loss(self, pose: Pose, stage: int = -1) -> float:
        """The loss (``params.loss.kind``) at ``pose`` (``stage`` -1: full resolution)."""
        return self.level(stage).loss(self.render(pose, stage))

    def floor(self, pose: Pose, stage: int = -1) -> float:
        """The loss at ``pose`` if every pixel the map covers there drew its label's class
        (:meth:`~semcal_ros.engine.loss.LabelLoss.floor`): a loss's rise is judged above it."""
        return self.level(stage).loss.floor(self.render(pose, stage))

    def freeze(self, pose: Pose, stage: int | None = None) -> None:
        """Hold the likelihood's confusion matrix fixed at ``pose`` (EM's E step,
        ``loss.em``) at the level of ``stage``, the only one a stage evaluates (None: every
        level: one render each); other losses are unchanged."""
        levels = self._levels.values() if stage is None else (self.level(stage),)
        for lv in levels:
            lv.loss.freeze(render(self.pmap, lv.setup.view(pose), render_threads()))

    def thaw(self) -> None:
        for lv in self._levels.values():
            lv.loss.thaw()

    def masked(self, ignore: np.ndarray) -> "Problem":
        """The same problem with the target's pixels where ``ignore`` is True left out of the loss
        (set to INVALID): the prepared map and the view set-ups are shared, only the targets and
        their loss tables are rebuilt."""
        other = copy.copy(self)
        other._local = threading.local()
        other.target = np.where(ignore, INVALID, self.target).astype(np.uint8)
        other._levels = {scale: other._level(scale, level.setup)
                         for scale, level in self._levels.items()}
        return other

    def detached(self) -> "Problem":
        """The same problem with loss objects of its own (the prepared map and the view set-ups
        shared): a search run side by side with others holds its E step (:meth:`freeze`) there
        without touching theirs."""
        return self.masked(np.zeros(self.target.shape, dtype=bool))

    def degenerate(self, evaluation: Evaluation) -> bool:
        """True for a view that shows (almost) none of the map: never a result."""
        lp = self.params.loss
        return evaluation.loss >= lp.degenerate_loss or evaluation.coverage < lp.min_coverage
