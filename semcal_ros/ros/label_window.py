"""A static camera's last label images, for a calibration against their per-pixel fusion.

A roadside camera sees the same street all day; one label image carries its passing cars and
its segmenter's flickering mistakes. :class:`WindowedCameraInputs` is a camera's
:class:`~semcal_ros.ros.camera_inputs.CameraInputs` that also keeps the last ``window`` usable
label images (the calibrator's ``label_window`` parameter); :func:`window_labels` fuses them
(:func:`~semcal_ros.engine.frames.fuse_labels`) for a goal. A window of 1 keeps only the newest
image: the calibration sees exactly what it saw without a window.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from semcal_ros.engine.frames import fuse_labels
from semcal_ros.ros.camera_inputs import CameraInputs


class WindowedCameraInputs(CameraInputs):
    """:class:`CameraInputs` that also keeps the last ``window`` usable label images."""

    def __init__(self, *args: Any, window: int = 1, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if window < 1:
            raise ValueError(f"parameter 'label_window' must be >= 1 frames, got {window}")
        self._window: deque[np.ndarray] = deque(maxlen=window)

    def on_labels(self, msg: Any) -> bool:
        if not super().on_labels(msg):
            return False
        labels = self.snapshot().labels
        if labels is not None:  # the label callbacks run one at a time (one callback group)
            with self._lock:
                self._window.append(labels)
        return True

    def values(self) -> dict[str, Any]:
        """The camera's diagnostics values and how full its window is."""
        out = super().values()
        with self._lock:
            out["label_window"] = f"{len(self._window)}/{self._window.maxlen}"
        return out

    def label_window(self) -> list[np.ndarray]:
        """The kept label images, oldest first."""
        with self._lock:
            return list(self._window)


def window_labels(camera: CameraInputs, newest: np.ndarray) -> tuple[np.ndarray, str]:
    """The label image a goal calibrates against: the fusion of the camera's window (the images
    of ``newest``'s size, the one the goal was checked with), or ``newest`` itself when the
    window holds one image or none. Also a line saying what was fused ("" for one image)."""
    held = camera.label_window() if isinstance(camera, WindowedCameraInputs) else []
    same = [im for im in held if im.shape == newest.shape]
    if len(same) < 2:
        return newest, ""
    fused = fuse_labels(same)
    return fused.labels, (f"{len(same)} label images fused per pixel ({fused.agreement * 100:.1f}"
                          " % agree with the fused class on average)")


__all__ = ["WindowedCameraInputs", "window_labels"]
