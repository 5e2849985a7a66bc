"""Cues beside the labels: terms of the loss that use what the label images throw away.

One real frame's labels pin the pose only loosely (on KITTI the forward axis's loss rises a few
per cent per 25 cm). Its camera image and the map's geometry carry more:

* **Depth-discontinuity edges against image edges** (Levinson & Thrun 2013, "Automatic online
  calibration of cameras and lasers"): where the rendered depth jumps from a near surface to a
  far one, the near side is an object's outline, and the camera image should have an edge there.
  Each rendered pixel's edge strength is its relative range jump to its farthest 4-neighbour,
  ``x = sqrt(min(jump, 1))`` when the jump exceeds ``edge_min_jump`` (the renderer's own depth
  falloff inside a disc stays below it); it is scored ``edge_inset`` x its disc radius further
  from the far side (a disc reaches past the outermost point). The image's edges (Sobel
  magnitude of the blurred grey image, scaled by its 99th percentile) are spread by Levinson's
  inverse distance transform ``D = alpha E + (1 - alpha) max_q E_q decay^d(p, q)`` (d the
  chessboard distance in full-resolution pixels), computed once per target as the label loss's
  distance transform is.
  The term is ``1 - sum(x D) / sum(x)``: 0 when every depth edge lies on a full-strength image
  edge, 1 when none is near one (or the view has no depth edge). A weighted mean, so a weight
  means the same on every image size and resolution level.
* **Lidar intensity against grey level** (Pandey et al. 2015, mutual information of lidar
  reflectivity and image grey level; Koide et al. 2023 score it by the normalised information
  distance, NID, with 10 bins): the renderer draws, in the same pass as the labels, the
  intensity of the point that wins each pixel (``render.fast.render_with_values``; the map's
  intensity as rank codes, ``render.prepare.intensity_codes``). Over the pixels where both exist
  (from the loss's first row on) the joint histogram of intensity bin and grey bin (``bins``
  each, equally filled: the map's codes by rank, the grey image by its own quantiles) gives
  ``NID = (H(X, Y) - I(X; Y)) / H(X, Y)`` in [0, 1]: 0 when one side fixes the other, 1 when
  they are independent (or fewer than ``intensity_min_pixels`` pixels carry both). A map
  without intensity (map.ply without the property) cannot have the cue.

The combined loss is ``label loss + edge_weight x edge term + intensity_weight x NID``
(:class:`CuedLoss`); with both weights 0 nothing here runs. ``edge_terms`` and
``intensity_histogram`` (numba) are what the search calls; ``edge_terms_reference``,
``inverse_distance_transform_reference`` and ``nid_reference`` (numpy) define them for the
tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import cv2
import numba
import numpy as np

from semcal_ros.engine.config import check_finite, check_rule
from semcal_ros.engine.render.view import MAX_DEPTH_MM


@dataclass(frozen=True)
class CueParams:
    """The ``engine.cues`` group: weights of the cues beside the labels (0 = off)."""

    edge_weight: float = 0.0  # weight of the depth-edge term against the label loss
    edge_min_jump: float = 0.5  # relative range jump (far / near - 1) that makes a depth edge
    edge_decay: float = 0.98  # inverse distance transform: factor per full-resolution pixel
    edge_alpha: float = 0.333  # share of a pixel's own edge strength in it (Levinson & Thrun)
    edge_blur_px: float = 1.0  # Gaussian sigma of the grey image before the gradient (0: none)
    # share of a disc's radius by which a depth edge is moved inwards before it is scored: a disc
    # reaches past the outermost point (radius = splat_scale x point gap), so found edges lie
    # outside the outline; measured: without it every outline sits 2-5 px up and left
    edge_inset: float = 0.67
    intensity_weight: float = 0.0  # weight of the intensity-grey NID term against the label loss
    intensity_bins: int = 10  # bins per side of the joint histogram (Koide et al. 2023: 10)
    intensity_min_pixels: int = 200  # fewer pixels with both (full resolution): the term is 1

    def __post_init__(self) -> None:
        check_finite(self)
        check_rule("cues.edge_weight", self.edge_weight, self.edge_weight >= 0, ">= 0")
        check_rule("cues.edge_min_jump", self.edge_min_jump, self.edge_min_jump > 0, "> 0")
        check_rule("cues.edge_decay", self.edge_decay, 0 < self.edge_decay < 1, "in (0, 1)")
        check_rule("cues.edge_alpha", self.edge_alpha, 0 <= self.edge_alpha <= 1, "in [0, 1]")
        check_rule("cues.edge_blur_px", self.edge_blur_px, self.edge_blur_px >= 0, ">= 0")
        check_rule("cues.edge_inset", self.edge_inset, 0 <= self.edge_inset <= 2, "in [0, 2]")
        check_rule("cues.intensity_weight", self.intensity_weight, self.intensity_weight >= 0,
                   ">= 0")
        check_rule("cues.intensity_bins", self.intensity_bins, 2 <= self.intensity_bins <= 64,
                   "in [2, 64]")
        check_rule("cues.intensity_min_pixels", self.intensity_min_pixels,
                   self.intensity_min_pixels >= 1, ">= 1")

    @property
    def active(self) -> bool:
        return self.edge_weight > 0 or self.intensity_weight > 0


# --- the image side: edges and their inverse distance transform, once per target ------------
def grey_image(image: np.ndarray) -> np.ndarray:
    """float32 grey levels of a camera image (H, W), (H, W, 3) or (H, W, 4), any integer or
    float type."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] in (3, 4):
        image = image[..., :3].astype(np.float32).mean(axis=2)
    if image.ndim != 2:
        raise ValueError(f"camera image must be grey or colour (H, W[, 3]), got shape "
                         f"{image.shape}")
    return np.ascontiguousarray(image, dtype=np.float32)


def image_edges(image: np.ndarray, blur_px: float = 1.0) -> np.ndarray:
    """Edge strength in [0, 1] per pixel: the Sobel gradient magnitude of the (blurred) grey
    image over its 99th percentile, clipped. The percentile, not the maximum, so a few saturated
    highlights do not flatten every other edge."""
    grey = grey_image(image)
    if blur_px > 0:
        grey = cv2.GaussianBlur(grey, (0, 0), blur_px)
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3)
    mag = np.sqrt(gx * gx + gy * gy)
    top = float(np.percentile(mag, 99.0))
    if top <= 0:
        return np.zeros_like(mag)
    return np.clip(mag / top, 0.0, 1.0).astype(np.float32)


@numba.njit(cache=True, nogil=True)
def _spread(edges, decay):
    """max_q E_q decay^d(p, q), d the chessboard distance: two raster passes over the
    8-neighbourhood (exact for the chessboard metric, as a chamfer distance transform is)."""
    h, w = edges.shape
    out = edges.copy()
    for v in range(h):
        for u in range(w):
            best = out[v, u]
            for dv, du in ((-1, -1), (-1, 0), (-1, 1), (0, -1)):
                vv, uu = v + dv, u + du
                if 0 <= vv < h and 0 <= uu < w:
                    c = out[vv, uu] * decay
                    if c > best:
                        best = c
            out[v, u] = best
    for v in range(h - 1, -1, -1):
        for u in range(w - 1, -1, -1):
            best = out[v, u]
            for dv, du in ((1, 1), (1, 0), (1, -1), (0, 1)):
                vv, uu = v + dv, u + du
                if 0 <= vv < h and 0 <= uu < w:
                    c = out[vv, uu] * decay
                    if c > best:
                        best = c
            out[v, u] = best
    return out


def inverse_distance_transform(edges: np.ndarray, decay: float, alpha: float) -> np.ndarray:
    """Levinson & Thrun's D = alpha E + (1 - alpha) max_q E_q decay^d(p, q) (float32)."""
    e = np.ascontiguousarray(edges, dtype=np.float32)
    return (alpha * e + (1.0 - alpha) * _spread(e, np.float32(decay))).astype(np.float32)


def inverse_distance_transform_reference(edges: np.ndarray, decay: float, alpha: float
                                         ) -> np.ndarray:
    """The definition: a 3x3 maximum filter times ``decay``, repeated until nothing changes
    (each round reaches one chessboard ring further)."""
    e = np.asarray(edges, dtype=np.float32)
    out = e.copy()
    while True:
        grown = np.maximum(out, cv2.dilate(out, np.ones((3, 3), np.uint8)) * np.float32(decay))
        if np.array_equal(grown, out):
            break
        out = grown
    return (alpha * e + (1.0 - alpha) * out).astype(np.float32)


def edge_field(image: np.ndarray, params: CueParams, shape: tuple[int, int]) -> np.ndarray:
    """The full-resolution inverse distance transform of ``image``'s edges; the image must be
    the label image's size (``shape``)."""
    grey = grey_image(image)
    if grey.shape != shape:
        raise ValueError(f"camera image is {grey.shape[1]}x{grey.shape[0]} but the labels are "
                         f"{shape[1]}x{shape[0]}")
    return inverse_distance_transform(image_edges(grey, params.edge_blur_px), params.edge_decay,
                                      params.edge_alpha)


# --- the map side: depth edges of the render, scored on the field --------------------------
@numba.njit(cache=True, inline="always")
def _inset_index(u, v, du, dv, d_mm, width, height, inset, kmax):
    """Where an edge found at (u, v), its far neighbour at (u + du, v + dv), is scored: moved
    ``inset`` (px x m: the share of the disc radius times lambda) away from the far side, so a
    disc's overshoot beyond the outermost point does not push every outline outwards."""
    k = min(int(math.floor(inset / (d_mm * 0.001) + 0.5)), kmax)  # discs stop at radius_max
    uu = min(max(u - k * du, 0), width - 1)
    vv = min(max(v - k * dv, 0), height - 1)
    return vv * width + uu


@numba.njit(cache=True, nogil=True)
def edge_terms(keys, width, field, start, min_jump, inset, kmax):
    """(sum x D, sum x) over the z-buffer ``keys`` (flat uint32, depth mm in the upper 24 bits;
    empty pixels never make an edge) from flat index ``start`` on; ``field`` flat float32;
    ``inset``, ``kmax`` see :func:`_inset_index` (0: scored where found)."""
    n = keys.shape[0]
    h = n // width
    num = 0.0
    den = 0.0
    for p in range(start, n):
        d = keys[p] >> 8
        if d >= MAX_DEPTH_MM or d == 0:
            continue
        v = p // width
        u = p - v * width
        far = d
        du = 0
        dv = 0
        if u > 0:
            q = keys[p - 1] >> 8
            if q < MAX_DEPTH_MM and q > far:
                far, du, dv = q, -1, 0
        if u < width - 1:
            q = keys[p + 1] >> 8
            if q < MAX_DEPTH_MM and q > far:
                far, du, dv = q, 1, 0
        if v > 0:
            q = keys[p - width] >> 8
            if q < MAX_DEPTH_MM and q > far:
                far, du, dv = q, 0, -1
        if v < h - 1:
            q = keys[p + width] >> 8
            if q < MAX_DEPTH_MM and q > far:
                far, du, dv = q, 0, 1
        jump = (far - d) / d
        if jump > min_jump:
            x = math.sqrt(min(jump, 1.0))
            num += x * field[_inset_index(u, v, du, dv, d, width, h, inset, kmax)]
            den += x
    return num, den


def edge_terms_reference(keys: np.ndarray, field: np.ndarray, start_row: int, min_jump: float,
                         inset: float = 0.0, kmax: int = 0) -> tuple[float, float]:
    """The definition of :func:`edge_terms` on (H, W) arrays, rows from ``start_row`` on."""
    h, w = keys.shape
    depth = (keys.astype(np.int64) >> 8).astype(np.float64)
    valid = (depth < MAX_DEPTH_MM) & (depth > 0)
    d = np.where(valid, depth, -np.inf)
    pad = np.pad(d, 1, constant_values=-np.inf)
    # own depth first, then left, right, up, down: the first strict maximum wins, as the kernel
    stack = np.stack([d, pad[1:-1, :-2], pad[1:-1, 2:], pad[:-2, 1:-1], pad[2:, 1:-1]])
    which = np.argmax(stack, axis=0)
    far = np.take_along_axis(stack, which[None], 0)[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        jump = np.where(valid, (far - d) / np.where(valid, d, 1.0), 0.0)
    x = np.where(jump > min_jump, np.sqrt(np.minimum(jump, 1.0)), 0.0)
    x[:start_row] = 0.0
    vs, us = np.nonzero(x > 0)
    du = np.array([0, -1, 1, 0, 0])[which[vs, us]]
    dv = np.array([0, 0, 0, -1, 1])[which[vs, us]]
    k = np.minimum(np.floor(inset / (depth[vs, us] * 0.001) + 0.5).astype(int), kmax)
    uu = np.clip(us - k * du, 0, w - 1)
    vv = np.clip(vs - k * dv, 0, h - 1)
    return float(np.sum(x[vs, us] * field[vv, uu])), float(np.sum(x))


class EdgeCue:
    """The depth-edge term at one resolution: the field sampled as the level's target is."""

    def __init__(self, field: np.ndarray, params: CueParams, start_row: int,
                 splat_lambda: float = 0.0, radius_max: float = 0.0) -> None:
        self.field = np.ascontiguousarray(field, dtype=np.float32)
        self.shape = self.field.shape
        self.flat = self.field.ravel()
        self.start = start_row * self.shape[1]
        self.min_jump = float(params.edge_min_jump)
        self.inset = float(params.edge_inset * splat_lambda)  # px x m
        self.kmax = int(math.floor(params.edge_inset * radius_max + 0.5))

    def term(self, keys: np.ndarray) -> float:
        """1 - the edge-weighted mean of the field at the render's depth edges (1: no edge)."""
        flat = np.ascontiguousarray(keys).ravel()
        if flat.shape[0] != self.flat.shape[0]:
            raise ValueError(f"z-buffer {keys.shape} != cue field {self.shape}")
        num, den = edge_terms(flat, self.shape[1], self.flat, self.start, self.min_jump,
                              self.inset, self.kmax)
        return 1.0 - num / den if den > 0 else 1.0


# --- lidar intensity against grey level: NID of their joint histogram --------------------
def grey_bins(image: np.ndarray, bins: int, shape: tuple[int, int]) -> np.ndarray:
    """The camera image's grey level per pixel as a bin 0..bins-1 (uint8, full resolution),
    equally filled: edges at the grey image's own quantiles (so a dark or a bright image uses
    every bin, as the map's rank codes do). The image must be the label image's size."""
    grey = grey_image(image)
    if grey.shape != shape:
        raise ValueError(f"camera image is {grey.shape[1]}x{grey.shape[0]} but the labels are "
                         f"{shape[1]}x{shape[0]}")
    edges = np.quantile(grey, np.arange(1, bins) / bins)
    return np.searchsorted(edges, grey, side="right").astype(np.uint8)


def code_bins(bins: int) -> np.ndarray:
    """Bin of each intensity code 0..254 (rank codes, ``render.prepare.intensity_codes``);
    255 (no intensity) stays 255."""
    lut = (np.arange(256) * bins // 255).astype(np.uint8)  # 0..254 -> 0..bins-1
    lut[255] = 255
    return lut


@numba.njit(cache=True, nogil=True)
def intensity_histogram(values, grey, start, lut, bins):
    """Joint histogram (bins x bins, int64) of the intensity bin ``lut[values[p]]`` and the grey
    bin ``grey[p]`` over flat pixels from ``start`` on whose value is not 255."""
    hist = np.zeros((bins, bins), np.int64)
    for p in range(start, values.shape[0]):
        v = values[p]
        if v == 255:
            continue
        hist[lut[v], grey[p]] += 1
    return hist


@numba.njit(cache=True, nogil=True)
def nid_of_histogram(hist):
    """(H(X,Y) - I(X;Y)) / H(X,Y) = (2 H(X,Y) - H(X) - H(Y)) / H(X,Y) of a joint histogram;
    1 when it is empty or holds a single cell (no information either way)."""
    n = hist.sum()
    if n == 0:
        return 1.0
    bx, by = hist.shape
    hxy = 0.0
    hx = 0.0
    hy = 0.0
    for i in range(bx):
        row = 0
        for j in range(by):
            c = hist[i, j]
            row += c
            if c > 0:
                q = c / n
                hxy -= q * math.log(q)
        if row > 0:
            q = row / n
            hx -= q * math.log(q)
    for j in range(by):
        col = 0
        for i in range(bx):
            col += hist[i, j]
        if col > 0:
            q = col / n
            hy -= q * math.log(q)
    if hxy <= 0.0:
        return 1.0
    return min(max((2.0 * hxy - hx - hy) / hxy, 0.0), 1.0)


def nid_reference(x: np.ndarray, y: np.ndarray, bins: int) -> float:
    """The definition: NID of two equally long arrays of bin indices 0..bins-1."""
    x = np.asarray(x).ravel()
    y = np.asarray(y).ravel()
    if x.size == 0:
        return 1.0
    joint = np.histogram2d(x, y, bins=bins, range=[[0, bins], [0, bins]])[0] / x.size

    def entropy(p: np.ndarray) -> float:
        p = p[p > 0]
        return float(-(p * np.log(p)).sum())

    hxy = entropy(joint.ravel())
    if hxy <= 0:
        return 1.0
    mi = entropy(joint.sum(axis=1)) + entropy(joint.sum(axis=0)) - hxy
    return float(np.clip((hxy - mi) / hxy, 0.0, 1.0))


class IntensityCue:
    """The intensity-grey NID term at one resolution: the grey bins sampled as the level's
    target is; ``min_pixels`` already scaled to the level."""

    def __init__(self, grey: np.ndarray, params: CueParams, start_row: int,
                 min_pixels: int) -> None:
        self.grey = np.ascontiguousarray(grey, dtype=np.uint8)
        self.shape = self.grey.shape
        self.flat = self.grey.ravel()
        self.start = start_row * self.shape[1]
        self.bins = int(params.intensity_bins)
        self.lut = code_bins(self.bins)
        self.min_pixels = max(1, int(min_pixels))

    def histogram(self, values: np.ndarray) -> np.ndarray:
        flat = np.ascontiguousarray(values).ravel()
        if flat.shape[0] != self.flat.shape[0]:
            raise ValueError(f"intensity image {values.shape} != grey bins {self.shape}")
        return intensity_histogram(flat, self.flat, self.start, self.lut, self.bins)

    def term(self, values: np.ndarray) -> float:
        """NID of the rendered intensity and the grey level (1: too few pixels with both)."""
        hist = self.histogram(values)
        if hist.sum() < self.min_pixels:
            return 1.0
        return float(nid_of_histogram(hist))


class CuedLoss:
    """A level's label loss with the cues added: what ``Problem.level(stage).loss`` is when a
    cue is on. Called with a label image the problem rendered last (``Problem.render``), it adds
    each cue's term from that render's z-buffer and intensity image (``keys_of`` finds them);
    given any other label image (none of the problem's renders) it is the label loss alone.
    Everything else (target, shape, freeze, thaw) is the label loss's."""

    def __init__(self, labels, edge: EdgeCue | None, weight: float,
                 keys_of: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None] | None],
                 intensity: IntensityCue | None = None, intensity_weight: float = 0.0) -> None:
        self.labels = labels
        self.edge = edge
        self.weight = float(weight)
        self.keys_of = keys_of
        self.intensity = intensity
        self.intensity_weight = float(intensity_weight)

    def __getattr__(self, name: str):
        return getattr(self.labels, name)

    def evaluate(self, rendered: np.ndarray) -> tuple[float, float]:
        loss, coverage = self.labels.evaluate(rendered)
        if loss >= self.labels.params.degenerate_loss:
            return loss, coverage
        found = self.keys_of(rendered)
        if found is None:
            return loss, coverage
        keys, values = found
        total = float(loss)
        if self.edge is not None:
            total += self.weight * self.edge.term(keys)
        if self.intensity is not None and values is not None:
            total += self.intensity_weight * self.intensity.term(values)
        return total, coverage

    def __call__(self, rendered: np.ndarray) -> float:
        return self.evaluate(rendered)[0]


__all__ = ["CueParams", "CuedLoss", "EdgeCue", "IntensityCue", "code_bins", "edge_field",
           "edge_terms", "edge_terms_reference", "grey_bins", "grey_image", "image_edges",
           "intensity_histogram", "inverse_distance_transform",
           "inverse_distance_transform_reference", "nid_of_histogram", "nid_reference"]
