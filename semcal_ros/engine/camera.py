"""Camera models read from ROS camera_info: pinhole with ``plumb_bob`` or ``rational_polynomial``
distortion, and the ``equidistant`` fisheye (OpenCV fisheye / Kannala-Brandt).

Label images are segmentations of the raw (distorted) image, so the map is projected through the
distortion rather than the image being rectified: rectifying a label image would resample labels
(and a fisheye beyond 180 deg cannot be rectified onto one plane at all).

Projection is written once per model as scalar functions (``distort``, ``distort_rational``,
``project_equidistant``) that numpy calls on arrays and numba compiles for the fast renderer; the
same operation order keeps both renderers' images identical. The equidistant one uses ``atan2``,
whose numpy and libm versions may differ in the last bit, so numpy reaches it through the same
compiled loop (:func:`equidistant_many`) the fast path inlines.

What is drawn where (docs/lenses.md):

- pinhole models see only points in front of the image plane (z > 0 in the optical frame) and
  within the box of undistorted normalised coordinates the image covers (beyond it the
  polynomial can fold far points back into the picture);
- the equidistant model maps the ray's angle to the optical axis, theta, to an image radius, so
  points behind the image plane (theta > 90 deg) are drawn too, up to :attr:`max_angle` (the
  angle of the farthest image corner, or where the lens polynomial stops growing).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import cv2
import numba
import numpy as np

#: distortion_model values accepted from camera_info and the coefficients each one takes
#: (``""`` and ``none`` mean plumb_bob with no distortion).
COEFFICIENTS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}
ALIASES = {"": "plumb_bob", "none": "plumb_bob"}
SUPPORTED_MODELS = tuple(COEFFICIENTS) + tuple(ALIASES)
#: integer ids the renderer branches on (View.model)
MODEL_ID = {"plumb_bob": 0, "rational_polynomial": 1, "equidistant": 2}
#: the coefficients' names, for messages
COEFFICIENT_NAMES = {"plumb_bob": "k1 k2 p1 p2 k3", "rational_polynomial": "k1 k2 p1 p2 k3 k4 k5 k6",
                     "equidistant": "k1 k2 k3 k4"}

_log = logging.getLogger(__name__)
_said: set[str] = set()


def coefficient_check(model: str, d: np.ndarray) -> tuple[str, str]:
    """(problem, note) of the distortion coefficients ``d`` given for ``model`` (a supported
    one): each model takes exactly its count (plumb_bob 5, rational_polynomial 8, equidistant
    4). Fewer is a problem (padding them with zeros made a 2-coefficient fisheye silently wrong,
    3 m off on a probe scene); more is a problem if one beyond the count is non-zero, else a note
    (CameraInfo writers pad with zeros). None at all means no distortion (the CameraInfo of a
    rectified or simulated camera)."""
    name = ALIASES.get(model, model)
    n, given = COEFFICIENTS[name], np.asarray(d, dtype=float).ravel()
    if given.size == 0 or given.size == n:
        return "", ""
    head = f"{model or name} takes {n} distortion coefficients ({COEFFICIENT_NAMES[name]})"
    if given.size < n:
        return f"{head}, got {given.size}", ""
    if np.any(given[n:] != 0):
        hint = " (8 coefficients: use rational_polynomial)" if name == "plumb_bob" else ""
        return (f"{head}, got {given.size} with non-zero ones beyond the {n}th{hint}"), ""
    extra = given.size - n
    return "", f"{head}: the {extra} zero{'s' * (extra > 1)} beyond them ignored"


def say_once(note: str) -> None:
    """A note about an input that is accepted (logged once per process and text: a CameraInfo
    arrives many times a second)."""
    if note not in _said:
        _said.add(note)
        _log.warning(note)


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


def distort_rational(x, y, k1, k2, p1, p2, k3, k4, k5, k6):
    """rational_polynomial (OpenCV 8-parameter) distortion of normalised coordinates: the
    radial factor is (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)."""
    r2 = x * x + y * y
    radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def equidistant_radius(theta, k1, k2, k3, k4):
    """theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8) (OpenCV fisheye)."""
    t2 = theta * theta
    return theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))


_equidistant_radius = numba.njit(cache=True, inline="always")(equidistant_radius)


@numba.njit(cache=True, inline="always")
def project_equidistant(xc, yc, zc, k1, k2, k3, k4):
    """Optical-frame point -> (xd, yd, theta): normalised fisheye coordinates (pixel = f xd + c)
    and the ray's angle to the optical axis.

    OpenCV computes theta = atan(r / z) from x/z, y/z, which is the same for z > 0 and wrong
    behind the image plane; atan2(r, z) is its continuation to theta in [0, pi], so a 185 deg
    lens draws what lies beside and slightly behind it. On the axis (r = 0) the point lands on
    the principal point.
    """
    r = math.sqrt(xc * xc + yc * yc)
    theta = math.atan2(r, zc)
    theta_d = _equidistant_radius(theta, k1, k2, k3, k4)
    scale = theta_d / r if r > 0.0 else 0.0
    return xc * scale, yc * scale, theta


@numba.njit(cache=True)
def equidistant_many(xc, yc, zc, k):
    """:func:`project_equidistant` over arrays (what the numpy paths call; see module doc)."""
    n = xc.shape[0]
    xd, yd, th = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        xd[i], yd[i], th[i] = project_equidistant(xc[i], yc[i], zc[i], k[0], k[1], k[2], k[3])
    return xd, yd, th


@dataclass(frozen=True)
class CameraModel:
    """A camera as the renderer projects with it. Every door builds one (camera_info YAML,
    CameraInfo messages, calibration files), so its checks here reach them all: a supported
    model, its coefficient count (:func:`coefficient_check`), a size, positive focal lengths."""

    width: int
    height: int
    k: np.ndarray  # 3x3 intrinsic matrix
    d: np.ndarray  # plumb_bob (5,) k1 k2 p1 p2 k3; rational_polynomial (8,) + k4 k5 k6;
    #                equidistant (4,) k1 k2 k3 k4
    frame_id: str = "camera_optical"
    model: str = "plumb_bob"

    def __post_init__(self) -> None:
        model = ALIASES.get(self.model, self.model)
        if model not in COEFFICIENTS:
            raise ValueError(f"unsupported distortion model '{self.model}' "
                             f"(supported: {', '.join(COEFFICIENTS)})")
        n = COEFFICIENTS[model]
        given = np.asarray(self.d, dtype=float).ravel()
        problem, note = coefficient_check(self.model, given)
        if problem:
            raise ValueError(problem)
        if note:
            say_once(note)
        d = np.zeros(n)
        d[: min(n, given.size)] = given[:n]
        k = np.asarray(self.k, dtype=float).reshape(3, 3)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"invalid image size {self.width}x{self.height}")
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            raise ValueError("camera matrix has non-positive focal length")
        object.__setattr__(self, "k", k)
        object.__setattr__(self, "d", d)
        object.__setattr__(self, "model", model)

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

    @property
    def fisheye(self) -> bool:
        return self.model == "equidistant"

    @property
    def coefficients8(self) -> np.ndarray:
        """The coefficients padded to 8 (the renderer's fixed-size argument)."""
        out = np.zeros(8)
        out[: self.d.size] = self.d
        return out

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
    def fisheye_fov(cls, width: int = 960, height: int = 600, hfov_deg: float = 185.0,
                    d: tuple[float, ...] = (0.02, -0.005, 0.0005, 0.0),
                    frame_id: str = "camera_optical") -> "CameraModel":
        """An equidistant fisheye whose horizontal field of view ``hfov_deg`` spans the image
        width (the image is filled; the diagonal sees more). The default coefficients are those
        of a mild real-world Kannala-Brandt fit, monotonic far beyond the corners."""
        theta = np.radians(hfov_deg / 2.0)
        f = round((width / 2.0) / float(equidistant_radius(theta, *d)), 9)
        k = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(width, height, k, np.asarray(d, float), frame_id, "equidistant")

    @classmethod
    def rational_fov(cls, width: int = 960, height: int = 600, hfov_deg: float = 120.0,
                     d: tuple[float, ...] = (0.2, 0.01, 0.0, 0.0, 0.0005, 0.7, 0.05, 0.001),
                     frame_id: str = "camera_optical") -> "CameraModel":
        """A wide-angle pinhole with rational_polynomial barrel distortion whose horizontal
        field of view ``hfov_deg`` (< 180) spans the image width. The default coefficients
        compress the edge to about half the pinhole's radius and grow monotonically for every
        angle (no fold), like a calibrated 120 deg lens."""
        if not 0.0 < hfov_deg < 180.0:
            raise ValueError(f"a pinhole model's field of view must be in (0, 180) deg, got "
                             f"{hfov_deg}")
        x = float(np.tan(np.radians(hfov_deg / 2.0)))
        xd, _ = distort_rational(x, 0.0, *d)
        f = round((width / 2.0) / float(xd), 9)
        k = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(width, height, k, np.asarray(d, float), frame_id, "rational_polynomial")

    @classmethod
    def from_camera_info_dict(cls, data: dict, frame_id: str = "camera_optical") -> "CameraModel":
        """From the camera_calibration_parsers YAML layout."""
        try:
            width, height = int(data["image_width"]), int(data["image_height"])
            k = np.asarray(data["camera_matrix"]["data"], dtype=float)
            model = str(data.get("distortion_model", "plumb_bob"))
            dist = data.get("distortion_coefficients", {"data": []})["data"]
        except (KeyError, TypeError) as exc:
            raise ValueError(f"camera_info is missing field {exc}") from None
        if model not in SUPPORTED_MODELS:
            raise ValueError(f"unsupported distortion model '{model}' "
                             f"(supported: {', '.join(COEFFICIENTS)})")
        if k.size != 9:
            raise ValueError("camera_matrix must have 9 entries")
        return cls(width, height, k.reshape(3, 3), np.asarray(dist, dtype=float), frame_id,
                   model)

    def to_camera_info_dict(self, name: str = "camera") -> dict:
        p = np.zeros((3, 4))
        p[:, :3] = self.k
        return {
            "image_width": self.width,
            "image_height": self.height,
            "camera_name": name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": self.k.ravel().tolist()},
            "distortion_model": self.model,
            "distortion_coefficients": {"rows": 1, "cols": self.d.size, "data": self.d.tolist()},
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

    # -- where the model stops ---------------------------------------------------------------
    def _border(self, margin_px: float, n: int = 64) -> np.ndarray:
        u = np.linspace(-margin_px, self.width - 1 + margin_px, n)
        v = np.linspace(-margin_px, self.height - 1 + margin_px, n)
        return np.concatenate([
            np.stack([u, np.full(n, v[0])], 1), np.stack([u, np.full(n, v[-1])], 1),
            np.stack([np.full(n, u[0]), v], 1), np.stack([np.full(n, u[-1]), v], 1),
        ])

    def _monotonic_limit(self) -> float:
        """Where the radial mapping stops growing: the equidistant theta (rad, at most pi) or
        the rational_polynomial undistorted radius (inf when it grows everywhere searched).
        Beyond it two directions land on one pixel, so nothing beyond is drawn."""
        if self.fisheye:
            t = np.linspace(0.0, np.pi, 20001)
            rd = equidistant_radius(t, *self.d)
        elif self.model == "rational_polynomial":
            t = np.linspace(0.0, 50.0, 50001)
            k1, k2, _p1, _p2, k3, k4, k5, k6 = (float(v) for v in self.d)
            rd, _ = distort_rational(t, 0.0, k1, k2, 0.0, 0.0, k3, k4, k5, k6)
        else:
            return math.inf
        falling = np.flatnonzero(np.diff(rd) <= 0)
        return float(t[falling[0]]) if falling.size else (math.pi if self.fisheye else math.inf)

    def render_limit(self, margin_px: float = 0.0) -> float:
        """The renderer's per-point limit (``View.limit``): equidistant, the largest ray angle
        theta drawn (that of the farthest corner of the image grown by ``margin_px``, or less
        where the lens stops being monotonic); rational_polynomial, the largest r^2 = (x/z)^2 +
        (y/z)^2 before its radial mapping folds; plumb_bob, unused (inf)."""
        mono = self._monotonic_limit()
        if self.fisheye:
            lo, right, bottom = -0.5 - margin_px, self.width - 0.5 + margin_px, \
                self.height - 0.5 + margin_px
            corners = np.array([[lo, lo], [right, lo], [lo, bottom], [right, bottom]])
            rd = np.hypot((corners[:, 0] - self.cx) / self.fx, (corners[:, 1] - self.cy) / self.fy)
            theta = self._theta_from_radius(np.array([rd.max()]), mono)[0]
            return float(min(theta, mono))
        if self.model == "rational_polynomial":
            return mono * mono
        return math.inf

    def _theta_from_radius(self, theta_d: np.ndarray, limit: float) -> np.ndarray:
        """Newton's iteration on theta_d(theta) = theta_d (monotonic below ``limit``); the
        result is clipped to ``limit``."""
        k1, k2, k3, k4 = self.d
        theta = np.minimum(np.asarray(theta_d, float).copy(), limit)
        for _ in range(30):
            t2 = theta * theta
            f = equidistant_radius(theta, k1, k2, k3, k4) - theta_d
            df = 1.0 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            theta = np.clip(theta - f / np.where(np.abs(df) > 1e-12, df, 1e-12), 0.0, limit)
        return theta

    def normalized_bounds(self, margin_px: float = 0.0) -> tuple[float, float, float, float]:
        """Box of undistorted normalised coordinates (x/z, y/z) that can land in the image
        (pinhole models).

        Points outside it are rejected before distortion, where the polynomial can fold far
        points back into the picture. An equidistant lens is bounded by its ray angle instead
        (:meth:`render_limit`); its box is unbounded.
        """
        if self.fisheye:
            return (-math.inf, math.inf, -math.inf, math.inf)
        border = self._border(margin_px)
        if self.model == "plumb_bob":
            und = cv2.undistortPoints(
                border.reshape(-1, 1, 2), self.k, self.d, None, None, None,
                (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-9),
            ).reshape(-1, 2)
        else:
            rays, ok = self.unproject(border)
            und = rays[:, :2] / rays[:, 2:3]
            if not ok.all():  # the image reaches beyond the fold: bound by the fold's radius
                r = math.sqrt(self.render_limit())
                und = np.concatenate([und[ok], [[-r, -r], [r, r]]])
        pad = 1.05
        return (float(und[:, 0].min() * pad), float(und[:, 0].max() * pad),
                float(und[:, 1].min() * pad), float(und[:, 1].max() * pad))

    # -- projection and its inverse ---------------------------------------------------------
    def _lens(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Distorted normalised coordinates of optical-frame points (N, 3), the ray angle theta
        (equidistant) or r^2 = (x/z)^2 + (y/z)^2 (pinhole models), and the mask of points the
        model can see at all (in front of a pinhole; not at the centre of a fisheye)."""
        if self.fisheye:
            xd, yd, theta = equidistant_many(np.ascontiguousarray(p[:, 0]),
                                             np.ascontiguousarray(p[:, 1]),
                                             np.ascontiguousarray(p[:, 2]), self.d)
            return xd, yd, theta, np.einsum("ij,ij->i", p, p) > 1e-12
        z = p[:, 2]
        front = z > 1e-6
        zs = np.where(front, z, 1.0)
        x, y = p[:, 0] / zs, p[:, 1] / zs
        if self.model == "rational_polynomial":
            xd, yd = distort_rational(x, y, *self.d)
        else:
            xd, yd = distort(x, y, *self.d)
        return xd, yd, x * x + y * y, front

    def project(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (N, 2) of optical-frame points and a mask of those the model can
        see (in front and inside the undistorted image box for pinhole models, within
        :meth:`render_limit` for equidistant) and that land in the image."""
        p = np.asarray(points_cam, dtype=float).reshape(-1, 3)
        xd, yd, extent, ok = self._lens(p)
        if self.fisheye:
            ok = ok & (extent <= self.render_limit())
        else:
            zs = np.where(ok, p[:, 2], 1.0)
            x, y = p[:, 0] / zs, p[:, 1] / zs
            xmin, xmax, ymin, ymax = self.normalized_bounds()
            ok = ok & (x >= xmin) & (x <= xmax) & (y >= ymin) & (y <= ymax)
            if self.model == "rational_polynomial":
                ok &= extent <= self.render_limit()
        uv = np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)
        inside = (uv[:, 0] > -0.5) & (uv[:, 0] < self.width - 0.5) & \
                 (uv[:, 1] > -0.5) & (uv[:, 1] < self.height - 0.5)
        return uv, ok & inside

    def unproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unit ray directions (N, 3) in the optical frame through pixels ``uv`` (N, 2), and a
        mask of the pixels the model reaches (converged, within the lens' monotonic range).

        The scene generator casts these rays, so a label image is what the lens sees. The
        inverse is Newton's iteration (on theta for equidistant, on (x, y) with the exact
        Jacobian for the pinhole models); the mask keeps only pixels whose ray projects back
        within 1e-6 px.
        """
        uv = np.asarray(uv, float).reshape(-1, 2)
        xd = (uv[:, 0] - self.cx) / self.fx
        yd = (uv[:, 1] - self.cy) / self.fy
        if self.fisheye:
            rd = np.hypot(xd, yd)
            limit = self._monotonic_limit()
            theta = self._theta_from_radius(rd, limit)
            s = np.where(rd > 0, np.sin(theta) / np.where(rd > 0, rd, 1.0), 0.0)
            rays = np.stack([xd * s, yd * s, np.cos(theta)], axis=1)
        else:
            x, y = self._undistort_newton(xd, yd)
            rays = np.stack([x, y, np.ones_like(x)], axis=1)
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        xb, yb, _, seen = self._lens(rays)
        back = np.stack([self.fx * xb + self.cx, self.fy * yb + self.cy], axis=1)
        ok = seen & np.all(np.isfinite(rays), axis=1) & np.all(np.abs(back - uv) < 1e-6, axis=1)
        if self.fisheye:
            ok &= theta < limit
        return rays, ok

    def _undistort_newton(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised coordinates of distorted ones (pinhole models)."""
        d8 = self.coefficients8
        fn = distort_rational if self.model == "rational_polynomial" else (
            lambda x, y, k1, k2, p1, p2, k3, *_: distort(x, y, k1, k2, p1, p2, k3))
        x, y = xd.copy(), yd.copy()
        h = 1e-7
        for _ in range(40):
            fx_, fy_ = fn(x, y, *d8)
            ex, ey = fx_ - xd, fy_ - yd
            ax, ay = fn(x + h, y, *d8)
            bx, by = fn(x, y + h, *d8)
            j11, j21 = (ax - fx_) / h, (ay - fy_) / h
            j12, j22 = (bx - fx_) / h, (by - fy_) / h
            det = j11 * j22 - j12 * j21
            det = np.where(np.abs(det) > 1e-15, det, 1e-15)
            x = x - (j22 * ex - j12 * ey) / det
            y = y - (-j21 * ex + j11 * ey) / det
        return x, y

    def half_fov_deg(self) -> float:
        """Horizontal half field of view (deg) from the optical axis to the image's left/right
        edge at the principal row (what the scene generator crops the map to)."""
        if self.model == "plumb_bob" and not np.any(self.d):
            return float(np.degrees(np.arctan2(self.width / 2.0, self.fx)))
        rays, _ = self.unproject(np.array([[-0.5, self.cy], [self.width - 0.5, self.cy]]))
        return float(np.degrees(np.max(np.arctan2(np.abs(rays[:, 0]), rays[:, 2]))))
