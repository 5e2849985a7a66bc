"""The two simulated sensors, both ray casts into Open3D's ``RaycastingScene`` (Embree).

The static world is put into one scene once; moving actors, which change per time step, go into a
small second scene, and each ray keeps the nearer of the two hits. This keeps every scan's cost at
the ray count instead of rebuilding the big acceleration structure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.labels import KITTI_ID
from semcal_ros.engine.pose import Pose
from semcal_tools.scenes.mesh import LabelledMesh


@dataclass
class Hits:
    """Per-ray results: distance (inf = no hit), class, albedo and unit normal facing the ray."""

    distance: np.ndarray
    label: np.ndarray
    albedo: np.ndarray
    normal: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.distance)


def rotate(points: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """``points @ rotation.T`` without BLAS: for (N, 3) x (3, 3) a multithreaded BLAS call is
    pure overhead and, on a loaded machine, 100x slower than this loop-free einsum."""
    return np.einsum("ij,kj->ik", points, rotation.astype(points.dtype, copy=False))


def _scene(mesh: LabelledMesh) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
    return scene


class World:
    """The static mesh, ready to be ray-cast together with per-time-step moving actors."""

    def __init__(self, static: LabelledMesh, threads: int = 0) -> None:
        if not len(static):
            raise ValueError("the static scene has no triangles")
        self.static = static
        self.threads = threads
        self._scene = _scene(static)

    def cast(self, origins: np.ndarray, directions: np.ndarray,
             moving: LabelledMesh | None = None, shading: bool = True) -> Hits:
        """Cast rays (unit ``directions``) from ``origins``; the nearer of static/moving wins.

        Without ``shading`` the albedo is left zero and normals are not turned to face the ray
        (the lidar needs only the incidence cosine's magnitude).
        """
        rays = np.empty((len(directions), 6), np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = directions
        tensor = o3d.core.Tensor(rays)
        res = self._scene.cast_rays(tensor, nthreads=self.threads)
        dist = res["t_hit"].numpy()
        prim = res["primitive_ids"].numpy()
        normal = res["primitive_normals"].numpy()
        from_moving = None
        if moving is not None and len(moving):
            dyn = _scene(moving).cast_rays(tensor, nthreads=self.threads)
            dd = dyn["t_hit"].numpy()
            from_moving = dd < dist
            dist = np.where(from_moving, dd, dist)
            prim = np.where(from_moving, dyn["primitive_ids"].numpy(), prim)
            normal = np.where(from_moving[:, None], dyn["primitive_normals"].numpy(), normal)
        hit = np.isfinite(dist)
        label = np.zeros(len(dist), np.uint16)
        albedo = np.zeros((len(dist), 3) if shading else (0, 3), np.float32)
        for mesh, sel in ((self.static, hit if from_moving is None else hit & ~from_moving),
                          (moving, from_moving)):
            if sel is None or not sel.any():
                continue
            label[sel] = mesh.labels[prim[sel]]
            if shading:
                albedo[sel] = mesh.albedo[prim[sel]]
        if shading:  # face the normal towards the ray's origin (winding is not consistent)
            flip = np.einsum("ij,ij->i", normal, directions) > 0
            normal = np.where(flip[:, None], -normal, normal)
            normal[~hit] = 0.0
        return Hits(dist, label, albedo, normal)


# --------------------------------------------------------------------------------------------
# lidar

@dataclass(frozen=True)
class LidarSpec:
    """A spinning lidar: ``lines`` beams evenly over the vertical field of view."""

    lines: int = 128
    fov_up_deg: float = 45.0
    fov_down_deg: float = -45.0
    horizontal_step_deg: float = 0.2
    max_range: float = 100.0
    min_range: float = 1.5
    range_noise: float = 0.01  # 1-sigma, metres

    def directions(self) -> np.ndarray:
        """Unit beam directions (lines * columns, 3) in the lidar frame (x forward, z up),
        ordered ring by ring."""
        if self.lines < 2:
            raise ValueError("a lidar needs at least 2 lines")
        el = np.radians(np.linspace(self.fov_down_deg, self.fov_up_deg, self.lines))
        az = np.radians(np.arange(0.0, 360.0, self.horizontal_step_deg))
        e, a = np.meshgrid(el, az, indexing="ij")
        return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)


#: Diffuse reflectivity by SemanticKITTI class, for the lidar's intensity channel.
REFLECTIVITY = {"road": 0.12, "sidewalk": 0.25, "terrain": 0.35, "lane-marking": 0.75,
                "building": 0.3, "pole": 0.35, "traffic-sign": 0.95, "fence": 0.3, "trunk": 0.3,
                "vegetation": 0.4, "car": 0.45, "moving-car": 0.45, "moving-person": 0.3}


def _reflectivity_lut() -> np.ndarray:
    lut = np.full(65536, 0.3, np.float32)
    for name, v in REFLECTIVITY.items():
        lut[KITTI_ID[name]] = v
    return lut


REFLECTIVITY_LUT = _reflectivity_lut()


def scan(world: World, spec: LidarSpec, rotation: np.ndarray, origin: np.ndarray,
         moving: LabelledMesh | None, rng: np.random.Generator, directions: np.ndarray | None = None
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One sweep: points (N, 3) float32 in the lidar frame, intensity (N,) and label (N,).

    The sweep is taken at one instant (motion-compensated scans); ranges get Gaussian noise,
    intensity is reflectivity times the incidence cosine with a little speckle.
    """
    local = (spec.directions() if directions is None else directions).astype(np.float32)
    world_dirs = rotate(local, rotation)
    hits = world.cast(origin, world_dirs, moving, shading=False)
    ok = np.flatnonzero((hits.distance <= spec.max_range) & (hits.distance >= spec.min_range))
    r = hits.distance[ok] + rng.normal(0.0, spec.range_noise, len(ok)).astype(np.float32)
    points = local[ok] * r[:, None]
    cos = np.abs(np.einsum("ij,ij->i", hits.normal[ok], world_dirs[ok]))
    label = hits.label[ok]
    intensity = REFLECTIVITY_LUT[label] * (0.3 + 0.7 * cos)
    intensity *= rng.uniform(0.9, 1.1, len(ok)).astype(np.float32)
    return points, np.clip(intensity, 0.0, 1.0), label


# --------------------------------------------------------------------------------------------
# camera

def pixel_rays(camera: CameraModel, pose: Pose, supersample: int = 1) -> np.ndarray:
    """Unit ray directions in the map frame through pixel centres (row-major, (H*s)*(W*s), 3).

    Pixel centres are at integer coordinates, as in :meth:`CameraModel.project`; with
    ``supersample`` s, each pixel is covered by s x s evenly spread sub-rays. A distortion-free
    pinhole keeps its closed form (the pinned pinhole scenes); any other lens goes through
    :meth:`CameraModel.unproject`, so a fisheye's label image is what the fisheye sees, rays
    beyond 90 deg included (pixels the lens cannot reach: :func:`pixel_reach`).
    """
    s = supersample
    offs = (np.arange(s) + 0.5) / s - 0.5
    u = (np.arange(camera.width)[:, None] + offs[None]).ravel()
    v = (np.arange(camera.height)[:, None] + offs[None]).ravel()
    uu, vv = np.meshgrid(u, v)
    if _plain_pinhole(camera):
        x = (uu - camera.cx) / camera.fx
        y = (vv - camera.cy) / camera.fy
        d = np.stack([x, y, np.ones_like(x)], -1).reshape(-1, 3)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
    else:
        d, _ = camera.unproject(np.stack([uu.ravel(), vv.ravel()], 1))
    return rotate(d.astype(np.float32), pose.rotation)


def _plain_pinhole(camera: CameraModel) -> bool:
    return camera.model == "plumb_bob" and not np.any(camera.d)


def pixel_reach(camera: CameraModel) -> np.ndarray:
    """(H, W) bool: pixels whose ray the lens model reaches (all of them unless the image is
    larger than a fisheye's image circle or reaches beyond a polynomial's fold)."""
    if _plain_pinhole(camera):
        return np.ones((camera.height, camera.width), bool)
    uu, vv = np.meshgrid(np.arange(camera.width, dtype=float), np.arange(camera.height, dtype=float))
    _, ok = camera.unproject(np.stack([uu.ravel(), vv.ravel()], 1))
    return ok.reshape(camera.height, camera.width)


#: ``semcal scene --lens``: the scene camera's lens (all 960x600, square pixels, centred)
LENSES = ("pinhole", "fisheye", "wide")


def default_camera() -> CameraModel:
    """960x600, 90 deg horizontal field of view, no distortion (as in the paper's CARLA setup)."""
    return CameraModel.from_fov(960, 600, 90.0)


def lens_camera(lens: str = "pinhole") -> CameraModel:
    """The scene camera through ``lens``: ``pinhole`` (the paper's 90 deg, no distortion),
    ``fisheye`` (185 deg across the width, equidistant; about 217 deg on the diagonal) or
    ``wide`` (120 deg across the width, rational_polynomial barrel distortion)."""
    if lens == "pinhole":
        return default_camera()
    if lens == "fisheye":
        return CameraModel.fisheye_fov(960, 600, 185.0)
    if lens == "wide":
        return CameraModel.rational_fov(960, 600, 120.0)
    raise ValueError(f"unknown lens '{lens}' (choose from {', '.join(LENSES)})")
