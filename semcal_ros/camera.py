"""Pinhole camera with plumb_bob distortion, read from ROS camera_info.

Label images are segmentations of the raw (distorted) image, so the map is projected through the
distortion rather than the image being rectified: rectifying a label image would resample labels.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

SUPPORTED_MODELS = ("plumb_bob", "none", "")


def distort(x, y, k1, k2, p1, p2, k3):
    """plumb_bob (OpenCV 5-parameter) distortion of normalised coordinates.

    Written once for both renderers: numpy calls it on arrays, numba compiles it for scalars, and
    the same operation order keeps their images identical.
    """
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


@dataclass(frozen=True)
class CameraModel:
    width: int
    height: int
    k: np.ndarray  # 3x3 intrinsic matrix
    d: np.ndarray  # (5,) k1, k2, p1, p2, k3
    frame_id: str = "camera_optical"

    def __post_init__(self) -> None:
        k = np.asarray(self.k, dtype=float).reshape(3, 3)
        d = np.zeros(5)
        given = np.asarray(self.d, dtype=float).ravel()
        if given.size > 5 and np.any(given[5:] != 0):
            raise ValueError("only plumb_bob distortion (5 coefficients) is supported")
        d[: min(5, given.size)] = given[:5]
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"invalid image size {self.width}x{self.height}")
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            raise ValueError("camera matrix has non-positive focal length")
        object.__setattr__(self, "k", k)
        object.__setattr__(self, "d", d)

    @property
    def fx(self) -> float:
        return float(self.k[0, 0])

    @property
    def fy(self) -> float:
        return float(self.k[1, 1])

    @property
    def cx(self) -> float:
        return float(self.k[0, 2])

    @property
    def cy(self) -> float:
        return float(self.k[1, 2])

    @classmethod
    def from_fov(cls, width: int = 960, height: int = 600, hfov_deg: float = 90.0,
                 d: np.ndarray | tuple[float, ...] = (0.0,) * 5,
                 frame_id: str = "camera_optical") -> "CameraModel":
        """A pinhole camera with square pixels, principal point at the image centre and the
        given horizontal field of view. The defaults are the paper's CARLA camera (960x600,
        90 deg); every synthetic world (scenes, synthetic street) is seen through this one
        model. The focal length is rounded to 1e-9 px so 90 deg gives exactly f = width / 2."""
        if not 0.0 < hfov_deg < 180.0:
            raise ValueError(f"horizontal field of view must be in (0, 180) deg, got {hfov_deg}")
        f = round(width / 2.0 / float(np.tan(np.radians(hfov_deg / 2.0))), 9)
        k = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(width, height, k, np.asarray(d, dtype=float), frame_id)

    @classmethod
    def from_camera_info_dict(cls, data: dict, frame_id: str = "camera_optical") -> "CameraModel":
        """From the camera_calibration_parsers YAML layout."""
        try:
            width, height = int(data["image_width"]), int(data["image_height"])
            k = np.asarray(data["camera_matrix"]["data"], dtype=float)
            model = str(data.get("distortion_model", "plumb_bob"))
            dist = data.get("distortion_coefficients", {"data": [0.0] * 5})["data"]
        except (KeyError, TypeError) as exc:
            raise ValueError(f"camera_info is missing field {exc}") from None
        if model not in SUPPORTED_MODELS:
            raise ValueError(f"unsupported distortion model '{model}' (plumb_bob only)")
        if k.size != 9:
            raise ValueError("camera_matrix must have 9 entries")
        return cls(width, height, k.reshape(3, 3), np.asarray(dist, dtype=float), frame_id)

    def to_camera_info_dict(self, name: str = "camera") -> dict:
        p = np.zeros((3, 4))
        p[:, :3] = self.k
        return {
            "image_width": self.width,
            "image_height": self.height,
            "camera_name": name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": self.k.ravel().tolist()},
            "distortion_model": "plumb_bob",
            "distortion_coefficients": {"rows": 1, "cols": 5, "data": self.d.tolist()},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).ravel().tolist()},
            "projection_matrix": {"rows": 3, "cols": 4, "data": p.ravel().tolist()},
        }

    def scaled(self, factor: int) -> "CameraModel":
        """The same camera seen at 1/factor resolution (pixel centres kept consistent)."""
        if factor == 1:
            return self
        w, h = self.width // factor, self.height // factor
        k = self.k.copy()
        k[0, 0] /= factor
        k[1, 1] /= factor
        k[0, 2] = (k[0, 2] + 0.5) / factor - 0.5
        k[1, 2] = (k[1, 2] + 0.5) / factor - 0.5
        return replace(self, width=w, height=h, k=k)

    def normalized_bounds(self, margin_px: float = 0.0) -> tuple[float, float, float, float]:
        """Box of undistorted normalised coordinates (x/z, y/z) that can land in the image.

        Points outside it are rejected before distortion, where the polynomial can fold far
        points back into the picture.
        """
        n = 64
        u = np.linspace(-margin_px, self.width - 1 + margin_px, n)
        v = np.linspace(-margin_px, self.height - 1 + margin_px, n)
        border = np.concatenate([
            np.stack([u, np.full(n, v[0])], 1), np.stack([u, np.full(n, v[-1])], 1),
            np.stack([np.full(n, u[0]), v], 1), np.stack([np.full(n, u[-1]), v], 1),
        ])
        und = cv2.undistortPoints(
            border.reshape(-1, 1, 2), self.k, self.d, None, None, None,
            (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-9),
        ).reshape(-1, 2)
        pad = 1.05
        return (float(und[:, 0].min() * pad), float(und[:, 0].max() * pad),
                float(und[:, 1].min() * pad), float(und[:, 1].max() * pad))

    def project(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (N, 2) of optical-frame points and a mask of those in front and in view."""
        p = np.asarray(points_cam, dtype=float)
        z = p[:, 2]
        front = z > 1e-6
        zs = np.where(front, z, 1.0)
        x, y = p[:, 0] / zs, p[:, 1] / zs
        xmin, xmax, ymin, ymax = self.normalized_bounds()
        ok = front & (x >= xmin) & (x <= xmax) & (y >= ymin) & (y <= ymax)
        xd, yd = distort(x, y, *self.d)
        uv = np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)
        inside = (uv[:, 0] > -0.5) & (uv[:, 0] < self.width - 0.5) & \
                 (uv[:, 1] > -0.5) & (uv[:, 1] < self.height - 0.5)
        return uv, ok & inside
