"""Pictures people look at instead of numbers: the map over the image with the verdict, the loss
curve."""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.labels import INVALID, LabelMapping, colorize
from semcal_ros.engine.render.view import RenderParams
from semcal_ros.engine.pose import Pose
from semcal_ros.engine.render import prepare_map, view_for
from semcal_ros.engine.render.fast import render

if TYPE_CHECKING:  # pragma: no cover
    from semcal_ros.engine.results import QualityReport

#: Banner colour (RGB) per verdict: traffic-light colours, readable at a glance.
VERDICT_COLOURS = {"good": (40, 160, 60), "inconclusive": (230, 160, 20), "failed": (210, 40, 40)}


def render_map_labels(map_cloud: LabelledCloud, camera: CameraModel, pose: Pose,
                      mapping: LabelMapping | None = None,
                      params: RenderParams | None = None) -> np.ndarray:
    """Aligned label image of the map seen from ``pose`` at full resolution, rendered exactly as
    the engine renders it with ``params``."""
    rp = params or RenderParams()
    pmap = prepare_map(map_cloud, mapping, center=pose.translation, radius=rp.crop_radius or None)
    return render(pmap, view_for(camera, pose, pmap, rp))


def blend_labels(rgb: np.ndarray, labels: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """Label colours blended over an RGB image where a label exists, with class borders drawn."""
    out = rgb.astype(np.float32).copy()
    drawn = labels != INVALID
    colours = colorize(labels).astype(np.float32)
    out[drawn] = (1 - alpha) * out[drawn] + alpha * colours[drawn]
    # borders between two rendered classes only: holes in a sparse map are not outlines
    edges = np.zeros(labels.shape, dtype=bool)
    across = (labels[:, 1:] != labels[:, :-1]) & drawn[:, 1:] & drawn[:, :-1]
    down = (labels[1:] != labels[:-1]) & drawn[1:] & drawn[:-1]
    edges[:, 1:] |= across
    edges[1:] |= down
    out[edges] = (255, 255, 255)
    return out.clip(0, 255).astype(np.uint8)


def render_overlay(map_cloud: LabelledCloud, camera: CameraModel, pose: Pose, rgb: np.ndarray,
                   mapping: LabelMapping | None = None,
                   params: RenderParams | None = None) -> np.ndarray:
    """The map rendered at ``pose`` over the camera image (RGB, same size as the image)."""
    if rgb.shape[:2] != (camera.height, camera.width):
        raise ValueError(f"overlay image is {rgb.shape[1]}x{rgb.shape[0]}, camera is "
                         f"{camera.width}x{camera.height}")
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[:, :, None], 3, axis=2)
    return blend_labels(rgb, render_map_labels(map_cloud, camera, pose, mapping, params))


def annotate_quality(rgb: np.ndarray, report: "QualityReport") -> np.ndarray:
    """The overlay with the quality verdict drawn on it: a banner in the verdict's colour with the
    verdict, its reason, agreement, coverage and the per-axis uncertainty, so a picture passed
    around on its own still says whether to trust it."""
    out = np.ascontiguousarray(rgb.copy())
    h, w = out.shape[:2]
    scale = max(0.4, min(1.0, w / 1600.0))
    line = int(26 * scale) + 4
    ut, ur = report.uncertainty_translation_m, report.uncertainty_rpy_deg
    lines = [
        f"{report.verdict.upper()}: {report.reason}",
        f"agreement {report.agreement * 100:.0f} %   coverage {report.coverage * 100:.0f} %",
        "uncertainty x/y/z " + "/".join(f"{v * 100:.1f}" for v in ut) + " cm   "
        + ("roll/pitch/yaw " + "/".join(f"{v:.2f}" for v in ur) if report.roll_free
           else "pitch/yaw " + "/".join(f"{v:.2f}" for v in ur[1:]) + " (roll fixed)") + " deg",
    ]
    band = min(h, line * len(lines) + 8)
    colour = np.array(VERDICT_COLOURS.get(report.verdict, (90, 90, 90)), np.float32)
    out[:band] = (0.35 * out[:band].astype(np.float32) + 0.65 * colour).astype(np.uint8)
    for k, text in enumerate(lines):
        cv2.putText(out, text, (6, 4 + line * (k + 1) - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale,
                    (255, 255, 255), max(1, int(2 * scale)), cv2.LINE_AA)
    return out


def loss_curve(history: list[tuple[int, int, float]], width: int = 800, height: int = 400) -> np.ndarray:
    """RGB plot of the loss per evaluation (log scale), one colour per stage, best-so-far in black.

    Drawn with OpenCV, already a dependency, rather than adding a plotting library for one chart.
    """
    img = np.full((height, width, 3), 255, np.uint8)
    if not history:
        return img
    losses = np.array([h[2] for h in history], dtype=float)
    stages = np.array([h[1] for h in history])
    logl = np.log10(np.maximum(losses, 1e-6))
    lo, hi = float(logl.min()), float(logl.max())
    hi = hi if hi > lo else lo + 1.0
    m = 40
    xs = m + (np.arange(len(losses)) / max(len(losses) - 1, 1)) * (width - 2 * m)
    ys = height - m - (logl - lo) / (hi - lo) * (height - 2 * m)
    palette = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189)]
    for x, y, s in zip(xs, ys, stages):
        cv2.circle(img, (int(x), int(y)), 1, palette[int(s) % len(palette)], -1)
    best = np.minimum.accumulate(logl)
    by = height - m - (best - lo) / (hi - lo) * (height - 2 * m)
    pts = np.stack([xs, by], axis=1).astype(np.int32)
    cv2.polylines(img, [pts], False, (0, 0, 0), 1)
    cv2.rectangle(img, (m, m), (width - m, height - m), (0, 0, 0), 1)
    cv2.putText(img, f"loss 1e{hi:.1f}", (2, m - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    cv2.putText(img, f"1e{lo:.1f}", (2, height - m + 15), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    cv2.putText(img, f"{len(losses)} evaluations (colour = stage)", (width // 2 - 120, height - 10),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    return img
