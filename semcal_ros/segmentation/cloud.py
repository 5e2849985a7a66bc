"""Lidar scan -> SemanticKITTI label per point, through a range-image ONNX model.

The RangeNet++ / SalsaNext convention: every point is projected spherically to a ``height`` x
``width`` image (column from the azimuth, row from the elevation between ``fov_down`` and
``fov_up``; rows outside the field of view are clipped to the border rows), the nearest point wins
a pixel, and the five channels range, x, y, z, remission are normalised by the model's per-channel
mean and std, with 0 in empty pixels. The model labels pixels; a point takes its pixel's label if it
owns the pixel. A point that lost its pixel to a nearer point (a wall behind a pole, two points
within one azimuth step) takes the label of the 3-D nearest pixel owner in a small window around
its pixel - the image neighbourhood makes the search a fixed-size gather instead of a k-d tree
over the scan. Points with no usable coordinates (NaN, range 0) get 0 ("unlabeled").
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numba as nb
import numpy as np

from semcal_ros.segmentation.decode import labels_from_class_map, labels_from_logits
from semcal_ros.segmentation.model_config import (
    KITTI_UNLABELED, RANGE_CHANNELS, RangeModelConfig, load_model_config,
)
from semcal_ros.segmentation.onnx_runner import OnnxRunner, RunnerParams


@dataclass(frozen=True)
class RangeProjection:
    """Where each point of a scan landed in the range image.

    ``pixel[i]`` is the flat pixel index (row * width + col) of point ``i``, -1 for points
    without usable coordinates; ``owner[p]`` is the point that won pixel ``p`` (the nearest), -1
    for an empty pixel; ``depth`` is each point's range in metres.
    """

    pixel: np.ndarray
    owner: np.ndarray
    depth: np.ndarray
    height: int
    width: int

    def lost(self) -> np.ndarray:
        """Indices of projected points that do not own their pixel."""
        valid = np.flatnonzero(self.pixel >= 0)
        return valid[self.owner[self.pixel[valid]] != valid]


def project(xyz: np.ndarray, config: RangeModelConfig) -> RangeProjection:
    """Spherical projection of (N, 3) float32 points to the config's range image."""
    pts = np.asarray(xyz, dtype=np.float32)
    n = len(pts)
    depth = np.sqrt(np.einsum("ij,ij->i", pts, pts))
    usable = np.isfinite(depth) & (depth > 0)
    index = (np.arange(n, dtype=np.int32) if usable.all()
             else np.flatnonzero(usable).astype(np.int32))
    p, d = (pts, depth) if len(index) == n else (pts[index], depth[index])

    h, w = config.height, config.width
    fov_down = np.float32(np.radians(config.fov_down_deg))  # float32 constants keep the
    fov = np.float32(np.radians(config.fov_up_deg)) - fov_down  # arrays float32 (half the time)
    azimuth = np.arctan2(p[:, 1], p[:, 0])  # column 0 looks backwards, the image centre forwards
    col = np.floor((0.5 - azimuth * np.float32(0.5 / np.pi)) * w).astype(np.int32)
    np.clip(col, 0, w - 1, out=col)
    elevation = np.arcsin(np.clip(p[:, 2] / d, -1.0, 1.0))
    row = np.floor((1.0 - (elevation - fov_down) / fov) * h).astype(np.int32)
    np.clip(row, 0, h - 1, out=row)
    flat = row * w + col

    owner = np.full(h * w, -1, dtype=np.int32)
    _nearest_wins(flat, d, index, owner)
    pixel = np.full(n, -1, dtype=np.int32)
    pixel[index] = flat
    return RangeProjection(pixel, owner, depth, h, w)


def range_tensor(xyz: np.ndarray, intensity: np.ndarray | None, proj: RangeProjection,
                 config: RangeModelConfig) -> np.ndarray:
    """(1, 5, H, W) float32 network input: normalised range, x, y, z, remission; 0 where empty.

    Without intensities the remission channel is 0 everywhere, i.e. the training mean.
    """
    has_intensity = intensity is not None
    remission = (np.asarray(intensity, dtype=np.float32) if has_intensity
                 else np.zeros(1, np.float32))
    means = np.asarray(config.means, dtype=np.float32)
    factors = (1.0 / np.asarray(config.stds, dtype=np.float64)).astype(np.float32)
    tensor = np.zeros((len(RANGE_CHANNELS), proj.height * proj.width), dtype=np.float32)
    _fill_tensor(proj.owner, np.asarray(xyz, dtype=np.float32), proj.depth, remission,
                 has_intensity, np.float32(config.intensity_scale), means, factors, tensor)
    return tensor.reshape(1, len(RANGE_CHANNELS), proj.height, proj.width)


def label_points(pixel_labels: np.ndarray, xyz: np.ndarray, proj: RangeProjection,
                 window: int) -> np.ndarray:
    """Per-point labels from per-pixel labels (flat, H*W); lost points via their neighbourhood."""
    n = len(proj.pixel)
    labels = np.full(n, KITTI_UNLABELED, dtype=pixel_labels.dtype)
    valid = proj.pixel >= 0
    labels[valid] = pixel_labels[proj.pixel[valid]]
    lost = proj.lost()
    if len(lost) and window > 1:
        _label_lost(lost, proj.pixel, proj.owner, np.asarray(xyz, dtype=np.float32),
                    pixel_labels, proj.height, proj.width, window // 2, labels)
    return labels


# Compiled loops: each is a single pass that numpy would need several temporaries (and, for the
# neighbourhood search, an M x window^2 x 3 gather: ~20 ms instead of ~2 ms) to express.

@nb.njit(cache=True, nogil=True)
def _nearest_wins(flat, depth, index, owner):  # pragma: no cover - compiled
    """owner[pixel] = the nearest point landing there (the first one on equal range)."""
    nearest = np.full(len(owner), np.inf, np.float32)
    for k in range(len(flat)):
        p = flat[k]
        if depth[k] < nearest[p]:
            nearest[p] = depth[k]
            owner[p] = index[k]


@nb.njit(cache=True, nogil=True)
def _fill_tensor(owner, xyz, depth, remission, has_remission, remission_scale, means,
                 factors, tensor):  # pragma: no cover - compiled
    for p in range(len(owner)):
        o = owner[p]
        if o < 0:
            continue
        tensor[0, p] = (depth[o] - means[0]) * factors[0]
        for axis in range(3):
            tensor[1 + axis, p] = (xyz[o, axis] - means[1 + axis]) * factors[1 + axis]
        if has_remission:
            tensor[4, p] = (remission[o] * remission_scale - means[4]) * factors[4]


@nb.njit(cache=True, nogil=True)
def _label_lost(lost, pixel, owner, xyz, pixel_labels, height, width, half,
                labels):  # pragma: no cover - compiled
    """For each lost point: the label of the 3-D nearest pixel owner in the window around its
    pixel (rows stop at the border, columns wrap around: the azimuth is circular). The owners'
    coordinates are first laid out in pixel order, so a window reads neighbouring memory."""
    image = np.full((len(owner), 3), np.inf, np.float32)  # inf: empty pixels never win
    for p in range(len(owner)):
        o = owner[p]
        if o >= 0:
            image[p, 0] = xyz[o, 0]
            image[p, 1] = xyz[o, 1]
            image[p, 2] = xyz[o, 2]
    for j in range(len(lost)):
        i = lost[j]
        p = pixel[i]
        row = p // width
        col = p - row * width
        best = p  # the own pixel is always owned
        best_d = np.inf
        for dr in range(-half, half + 1):
            r = row + dr
            if r < 0 or r >= height:
                continue
            base = r * width
            for dc in range(-half, half + 1):
                c = col + dc  # wrap by comparison: an integer modulo here doubled the run time
                if c < 0:
                    c += width
                elif c >= width:
                    c -= width
                q = base + c
                dx = image[q, 0] - xyz[i, 0]
                dy = image[q, 1] - xyz[i, 1]
                dz = image[q, 2] - xyz[i, 2]
                d = dx * dx + dy * dy + dz * dz
                if d < best_d:
                    best_d = d
                    best = q
        labels[i] = pixel_labels[best]


class CloudSegmenter:
    """Runs a range-image model; :meth:`segment` is the call the nodes and the CLI make.

    :meth:`preprocess`, :meth:`infer` and :meth:`postprocess` are its steps, public so a benchmark
    can time the runner's own work apart from the model's.
    """

    def __init__(self, runner: OnnxRunner, config: RangeModelConfig) -> None:
        self.runner = runner
        self.config = config
        self.lut = config.class_lut()
        runner.check_input([1, len(RANGE_CHANNELS), config.height, config.width],
                           "1 x 5 (range, x, y, z, remission) x height x width")
        self._size = (config.height, config.width)
        runner.check_segmentation_output(config.output, config.num_classes, self._size)

    @classmethod
    def from_files(cls, model: str | Path, config: str | Path,
                   params: RunnerParams = RunnerParams()) -> "CloudSegmenter":
        cfg = load_model_config(config, RangeModelConfig)
        return cls(OnnxRunner(model, params, cfg.input_name, cfg.output_name), cfg)

    def segment(self, xyz: np.ndarray, intensity: np.ndarray | None = None) -> np.ndarray:
        """(N,) uint16 SemanticKITTI ids of (N, 3) points; ``intensity`` (N,) or None."""
        xyz, intensity = check_scan(xyz, intensity)
        tensor, proj = self.preprocess(xyz, intensity)
        return self.postprocess(self.infer(tensor), xyz, proj)

    def preprocess(self, xyz: np.ndarray, intensity: np.ndarray | None
                   ) -> tuple[np.ndarray, RangeProjection]:
        proj = project(xyz, self.config)
        return range_tensor(xyz, intensity, proj, self.config), proj

    def infer(self, tensor: np.ndarray) -> np.ndarray:
        output = self.runner.run(tensor)
        self.runner.check_segmentation_output(self.config.output, self.config.num_classes,
                                              self._size, output.shape)
        return output

    def postprocess(self, output: np.ndarray, xyz: np.ndarray,
                    proj: RangeProjection) -> np.ndarray:
        if self.config.output == "logits":
            pixel_labels = labels_from_logits(output, self.lut)
        else:
            pixel_labels = labels_from_class_map(output, self.lut, KITTI_UNLABELED)
        return label_points(pixel_labels.ravel(), xyz, proj, self.config.knn_window)


def check_scan(xyz: np.ndarray, intensity: np.ndarray | None
               ) -> tuple[np.ndarray, np.ndarray | None]:
    """Raise a clear ValueError unless ``xyz`` is (N, 3) numbers and ``intensity`` (N,)."""
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.issubdtype(xyz.dtype, np.number):
        raise ValueError(f"scan points must be an (N, 3) array of x, y, z, got shape {xyz.shape} "
                         f"({xyz.dtype})")
    xyz = np.ascontiguousarray(xyz, dtype=np.float32)
    if intensity is not None:
        intensity = np.asarray(intensity)
        if intensity.shape != (len(xyz),):
            raise ValueError(f"intensity must have shape ({len(xyz)},) like the points, "
                             f"got {intensity.shape}")
    return xyz, intensity
