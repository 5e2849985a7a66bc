"""Everything one render needs besides the map: camera, pose, splat size, as plain numbers."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semcal_ros.engine.camera import MODEL_ID, CameraModel
from semcal_ros.engine.config import check_finite, check_rule
from semcal_ros.engine.labels import INVALID
from semcal_ros.engine.pose import Pose
from semcal_ros.engine.render.prepare import PreparedMap

#: Splat radii are quantised to 1/RADIUS_STEPS pixel; one precomputed disc per step.
RADIUS_STEPS = 4
DEPTH_BITS = 24
MAX_DEPTH_MM = (1 << DEPTH_BITS) - 1
EMPTY_KEY = np.uint32(0xFFFFFFFF)


@dataclass(frozen=True)
class RenderParams:
    splat_lambda: float = 0.0  # disc radius px = splat_lambda / distance m; 0 = from the map
    splat_scale: float = 1.5  # with splat_lambda 0: disc radius = splat_scale x point spacing
    radius_max: float = 8.0  # px, full resolution
    # deg: the largest disc as an angle of view; a camera with more pixels per degree than
    # radius_max / radius_max_deg (1066 px focal length) gets proportionally larger discs
    # (0 = radius_max alone); KITTI's and the catalogue's cameras keep radius_max
    radius_max_deg: float = 0.43
    depth_falloff: float = 0.3  # depth factor at a disc's rim: nearest centre wins within a surface
    depth_falloff_coarse: float = 0.05  # the same for reduced-resolution stages (smoother basin)
    core_fraction: float = 1.0  # share of the disc radius that carries the label (rim: depth only)
    lod_radius: float = 0.75  # px: chunks whose discs are smaller are thinned (0: draw all points)
    near: float = 0.5  # m
    far: float = 150.0  # m
    crop_radius: float = 120.0  # m around the crop centre (initial position); 0 keeps the whole map

    def __post_init__(self) -> None:
        check_finite(self)
        for name in ("splat_lambda", "lod_radius", "crop_radius", "depth_falloff",
                     "depth_falloff_coarse"):
            check_rule(f"render.{name}", getattr(self, name), getattr(self, name) >= 0, ">= 0")
        check_rule("render.splat_scale", self.splat_scale, self.splat_scale > 0, "> 0")
        check_rule("render.radius_max", self.radius_max, self.radius_max >= 1, ">= 1 px")
        check_rule("render.radius_max_deg", self.radius_max_deg,
                   0 <= self.radius_max_deg <= 5, "in [0, 5] deg")
        check_rule("render.core_fraction", self.core_fraction, 0 < self.core_fraction <= 1,
               "in (0, 1]")
        check_rule("render.near", self.near, 0 < self.near < self.far, f"in (0, far = {self.far})")

    def splat_lambda_for(self, point_spacing_m: float, focal_px: float) -> float:
        """The disc size: given, or one that closes the gaps between neighbouring points.

        The paper tuned lambda by eye until a rendered view looked as dense as the target; a
        disc of ``splat_scale`` times the map's median nearest-neighbour gap does that for any
        map and camera (lidar maps are anisotropic, so the gap between scan lines is larger than
        that median); much larger discs overshoot outlines and bias the pose.
        """
        if self.splat_lambda > 0:
            return self.splat_lambda
        return self.splat_scale * focal_px * max(point_spacing_m, 1e-3)

    def radius_max_for(self, focal_px: float) -> float:
        """The largest disc (px, full resolution) on a camera of this focal length: at least
        ``radius_max``, and ``radius_max_deg`` of view. A pixel cap alone is a smaller angle on
        a sharper camera: a sparse lidar's ground rings, whose discs hit the cap, then leave
        holes on a 1920 px image that they close on a 1241 px one, and the holes reward a
        view from too high (docs/engine.md "The largest disc")."""
        return max(self.radius_max, focal_px * np.radians(self.radius_max_deg))


@dataclass(frozen=True)
class View:
    width: int
    height: int
    rotation: np.ndarray  # (3, 3) local map -> camera
    translation: np.ndarray  # (3,) local map -> camera
    intrinsics: np.ndarray  # fx, fy, cx, cy
    distortion: np.ndarray  # (8,) plumb_bob/rational k1 k2 p1 p2 k3 k4 k5 k6; equidistant k1..k4
    bounds: np.ndarray  # xmin, xmax, ymin, ymax of normalised coordinates in view
    splat_lambda: float  # radius (px) = splat_lambda / distance (m)
    radius_max: float  # px
    near: float
    far: float
    disc_offsets: np.ndarray  # (K, 2) int32 du, dv of all discs, concatenated
    disc_start: np.ndarray  # (S + 2,) int32: disc s = offsets[start[s]:start[s+1]]
    disc_falloff: np.ndarray  # (K,) float64: 1 + depth_falloff * (offset / radius)^2
    disc_rim: np.ndarray  # (K,) uint32: 0 where the offset carries the label, 0xFF (INVALID) on
    #                       the rim (depth only): a key's label byte is ``label | rim``
    disc_linear: np.ndarray  # (K,) int64: dv * width + du, the offset in the flat z-buffer
    lod_radius: float = 0.0  # px: chunks whose discs are smaller are thinned (0: all points)
    distorted: bool = True  # False when all distortion coefficients are zero (skips the polynomial)
    model: int = 0  # camera.MODEL_ID: 0 plumb_bob, 1 rational_polynomial, 2 equidistant
    limit: float = np.inf  # camera.render_limit: equidistant max theta, rational max r^2


def disc_table(radius_max: float, depth_falloff: float,
               core_fraction: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixel offsets of filled discs of radius s / RADIUS_STEPS, s = 0..S (s=0 is one pixel).

    Each offset carries a depth factor that grows towards the disc's rim. Among points of one
    surface (nearly equal depth) a pixel then goes to the point whose centre is nearest, not to the
    nearest point: plain nearest-wins discs let every region grow by most of a radius into the
    farther region beside it, which biases the pose (the camera drifts up and back). Across real
    occlusions (depth gaps larger than the falloff) the nearer surface still wins.

    Only the disc's core (radius ``core_fraction * r``) carries the label; the rim occludes what
    lies behind but renders as "no label". At a silhouette (a pole before a wall, a roof against
    the sky) the rim is where a disc overshoots the true outline, so it is masked instead of
    counted as the wrong class. Returned as offsets, start, falloff and rim (0 in the core,
    INVALID on the rim: OR-ed into the label, so the hot loop has no branch for it).
    """
    steps = int(np.floor(radius_max * RADIUS_STEPS))
    offsets, falloff, core, start = [], [], [], [0]
    for s in range(steps + 1):
        r = s / RADIUS_STEPS
        span = int(np.floor(r))
        du, dv = np.meshgrid(np.arange(-span, span + 1), np.arange(-span, span + 1))
        rho2 = du * du + dv * dv
        inside = rho2 <= r * r
        offsets.append(np.stack([du[inside], dv[inside]], axis=1))
        falloff.append(1.0 + depth_falloff * rho2[inside] / max(r * r, 1.0))
        core.append(rho2[inside] <= max((core_fraction * r) ** 2, 0.0))
        start.append(start[-1] + int(inside.sum()))
    return (np.ascontiguousarray(np.concatenate(offsets), dtype=np.int32),
            np.asarray(start, dtype=np.int32),
            np.ascontiguousarray(np.concatenate(falloff), dtype=np.float64),
            np.where(np.concatenate(core), 0, INVALID).astype(np.uint32))


_DISC_CACHE: dict[tuple[float, float, float], tuple[np.ndarray, ...]] = {}
_LINEAR_CACHE: dict[tuple[float, float, float, int], np.ndarray] = {}


def _disc(radius_max: float, depth_falloff: float, core_fraction: float, width: int
          ) -> tuple[np.ndarray, ...]:
    """The disc table and its offsets in a z-buffer ``width`` wide, made once per setting."""
    key = (float(radius_max), float(depth_falloff), float(core_fraction))
    if key not in _DISC_CACHE:
        _DISC_CACHE[key] = disc_table(*key)
    offsets, start, falloff, rim = _DISC_CACHE[key]
    if (*key, width) not in _LINEAR_CACHE:
        _LINEAR_CACHE[(*key, width)] = np.ascontiguousarray(
            offsets[:, 1].astype(np.int64) * width + offsets[:, 0])
    return offsets, start, falloff, rim, _LINEAR_CACHE[(*key, width)]


def make_view(camera: CameraModel, pose: Pose, origin: np.ndarray, splat_lambda: float,
              radius_max: float, near: float = 0.3, far: float = 200.0,
              bounds: np.ndarray | None = None, depth_falloff: float = 0.0,
              core_fraction: float = 1.0, lod_radius: float = 0.0,
              limit: float | None = None) -> View:
    """A view of the map (whose local origin is ``origin``) from ``pose``. ``bounds`` and
    ``limit`` (the camera's, computed when None) are passed by :class:`ViewSetup`, which computes
    them once per stage."""
    r, t = pose.world_to_camera()
    t_local = t + r @ np.asarray(origin, float)
    offsets, start, falloff, rim, linear = _disc(radius_max, depth_falloff, core_fraction,
                                                 camera.width)
    if bounds is None:
        bounds = np.asarray(camera.normalized_bounds(margin_px=radius_max))
    return View(
        width=camera.width, height=camera.height,
        rotation=np.ascontiguousarray(r), translation=np.ascontiguousarray(t_local),
        intrinsics=np.array([camera.fx, camera.fy, camera.cx, camera.cy]),
        distortion=np.ascontiguousarray(camera.coefficients8, dtype=np.float64),
        bounds=np.asarray(bounds, dtype=np.float64),
        splat_lambda=float(splat_lambda), radius_max=float(radius_max),
        near=float(near), far=float(far), disc_offsets=offsets, disc_start=start,
        disc_falloff=falloff, disc_rim=rim, disc_linear=linear, lod_radius=float(lod_radius),
        distorted=bool(np.any(camera.d != 0.0)), model=MODEL_ID[camera.model],
        limit=float(camera.render_limit(radius_max) if limit is None else limit),
    )


@dataclass(frozen=True)
class ViewSetup:
    """Everything a view of one prepared map needs except the pose, at one resolution.

    Made once per calibration stage (the distortion bounds alone take a few ms of OpenCV); then
    :meth:`view` is cheap enough to call per loss evaluation.
    """

    camera: CameraModel  # already scaled to the stage's resolution
    origin: np.ndarray
    splat_lambda: float
    radius_max: float
    depth_falloff: float
    bounds: np.ndarray
    params: RenderParams
    limit: float = np.inf

    def view(self, pose: Pose) -> View:
        rp = self.params
        return make_view(self.camera, pose, self.origin, self.splat_lambda, self.radius_max,
                         rp.near, rp.far, self.bounds, self.depth_falloff, rp.core_fraction,
                         rp.lod_radius, self.limit)


def view_setup(camera: CameraModel, pmap: PreparedMap, params: RenderParams | None = None,
               scale: int = 1) -> ViewSetup:
    """The one way to set up a render: the optimiser, the overlay, the bench and the scenes all
    come through here, so a parameter changed in ``params`` changes every picture alike.

    The splat size follows the map's point spacing and the (scaled) focal length; reduced
    resolutions use the coarse depth falloff and a proportionally smaller largest disc.
    """
    rp = params or RenderParams()
    cam = camera.scaled(scale)
    radius_max = max(1.0, rp.radius_max_for(camera.fx) / scale)
    return ViewSetup(
        camera=cam, origin=pmap.origin,
        splat_lambda=rp.splat_lambda_for(pmap.spacing, camera.fx) / scale,
        radius_max=radius_max,
        depth_falloff=rp.depth_falloff if scale == 1 else rp.depth_falloff_coarse,
        bounds=np.asarray(cam.normalized_bounds(margin_px=radius_max)), params=rp,
        limit=cam.render_limit(radius_max))


def view_for(camera: CameraModel, pose: Pose, pmap: PreparedMap,
             params: RenderParams | None = None, scale: int = 1) -> View:
    """A single view (see :func:`view_setup`)."""
    return view_setup(camera, pmap, params, scale).view(pose)
