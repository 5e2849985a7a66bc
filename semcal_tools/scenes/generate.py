"""One synthetic scene folder (docs/CONTRACTS.md) from a kind, a seed and a variant.

The world of a (kind, seed) pair is the same in every variant — variants only change what the
sensors report — so results across variants of one seed compare like with like. Random streams
are split by purpose for the same reason: adding moving actors must not move a building.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import yaml
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.io.files import (
    pose_to_dict, write_camera_info, write_label_image, write_rgb_image,
)
from semcal_ros.io.ply import write_ply
from semcal_ros.mapping.filters import voxel_downsample
from semcal_ros.engine.labels import CITYSCAPES, INVALID, SEMANTIC_KITTI, SKY, LabelMapping
from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.pose import BODY_FROM_OPTICAL, Pose, perturbed_initial
from semcal_tools.scenes import props
from semcal_tools.scenes.actors import Actor, Polyline, actors_at
from semcal_tools.scenes.bag import CameraFrame, SceneBagWriter
from semcal_tools.scenes.labelnoise import add_label_noise
from semcal_tools.scenes.layouts import (
    KINDS, MAST_RADIUS, Layout, build_layout, camera_mast, mast_xy,
)
from semcal_tools.scenes.mesh import LabelledMesh, MeshBuilder
from semcal_tools.scenes.rig import MAX_CAMERAS, RigCamera, camera_rig
from semcal_tools.scenes.sensors import (LENSES, LidarSpec, World, default_camera, lens_camera,
                                      pixel_reach, pixel_rays, rotate, scan)
from semcal_tools.scenes.shading import shade, to_image

VARIANTS = ("ideal", "noisy_labels", "dynamic", "sparse", "pose_noise")
MAP_FRAMES = ("layout", "random")
MASTS = ("pole", "bracket")
#: pose_noise only: the map accumulated with the perturbed poses (map.ply uses the true ones).
NOISY_POSE_MAP = "map_noisy_poses.ply"
GENERATOR_VERSION = 1
LIDAR_HEIGHT = 3.0  # metres above the road


@dataclass(frozen=True)
class SceneOptions:
    """How much to simulate. ``lines`` None means the variant's default (128, or 32 for sparse)."""

    scans: int = 200
    scan_rate_hz: float = 10.0
    lines: int | None = None
    horizontal_step_deg: float = 0.2
    voxel: float = 0.05  # map voxel size, metres
    scan_crop: float = 50.0  # map keeps scan points at most this far from the sensor (d_max)
    map_radius: float = 60.0  # ... at most this far (horizontally) from the camera
    map_view_margin_deg: float = 15.0  # ... within the camera's horizontal view plus this margin
    supersample: int = 2  # RGB image samples per pixel side
    camera_period: float = 1.0  # seconds between repeated camera messages in the bag
    write_bag: bool = True
    write_scans: bool = True  # scans/*.ply (poses.yaml is always written)
    moving_cars: int = 3
    moving_people: int = 4
    pose_noise_m: float = 0.03  # 1-sigma per axis, pose_noise variant
    pose_noise_deg: float = 0.2
    threads: int = 0  # ray-casting threads, 0 = all cores
    start_stamp: float = 1_700_000_000.0
    map_frame: str = "layout"  # "random": the whole scene rotated about z and shifted (MapFrame)
    mast: str = "pole"  # "bracket": the camera's housing, visor and arm on the mast too
    cameras: int = 1  # >= 2: a rig of named cameras round a junction (scenes.rig, cameras/<name>/)
    lens: str = "pinhole"  # fisheye (185 deg equidistant) or wide (120 deg rational_polynomial)

    def validate(self) -> None:
        if self.scans < 2:
            raise ValueError(f"a scene needs at least 2 scans, got {self.scans}")
        if self.scan_rate_hz <= 0:
            raise ValueError("scan rate must be positive")
        if self.lines is not None and not 2 <= self.lines <= 512:
            raise ValueError(f"lidar lines must be in 2..512, got {self.lines}")
        if not 0.01 <= self.horizontal_step_deg <= 5.0:
            raise ValueError("horizontal step must be in 0.01..5 degrees")
        if self.voxel <= 0 or self.supersample < 1:
            raise ValueError("voxel size and supersampling must be positive")
        if self.scan_crop <= 0 or self.map_radius <= 0:
            raise ValueError("scan crop and map radius must be positive")
        if self.map_frame not in MAP_FRAMES:
            raise ValueError(f"unknown map frame '{self.map_frame}' "
                             f"(choose from {', '.join(MAP_FRAMES)})")
        if self.mast not in MASTS:
            raise ValueError(f"unknown mast '{self.mast}' (choose from {', '.join(MASTS)})")
        if not 1 <= self.cameras <= MAX_CAMERAS:
            raise ValueError(f"cameras must be in 1..{MAX_CAMERAS}, got {self.cameras}")
        if self.lens not in LENSES:
            raise ValueError(f"unknown lens '{self.lens}' (choose from {', '.join(LENSES)})")


#: Named sizes of ``semcal scene --size``. ``small`` is the test and demo scene: a shorter drive
#: centred on the camera's view (about 10 s to generate, a 5 s bag). ``large`` makes maps of
#: 3 M points and more: a 0.1 deg horizontal lidar step and the paper's upper d_max (75 m) over
#: a 75 m radius (junction seed 0: 3.8 M points; a 4 cm voxel on top gave 5.3 M).
SIZES = {
    "full": SceneOptions(),
    "small": SceneOptions(scans=50, supersample=1),
    "large": SceneOptions(horizontal_step_deg=0.1, scan_crop=75.0, map_radius=75.0),
}


@dataclass
class SceneResult:
    out: Path
    summary: dict


def _rng(seed: int, kind: str, purpose: str, camera: int = 0) -> np.random.Generator:
    """The stream of one purpose; ``camera`` k >= 1 is the k-th rig camera's own stream (camera
    0 uses the single-camera streams)."""
    # append new purposes at the end: the index is part of every stream's seed
    purposes = ("layout", "actors", "image_actors", "lidar", "noise", "initial", "shading",
                "frame", "rig")
    return np.random.default_rng([int(seed), KINDS.index(kind), purposes.index(purpose)]
                                 + ([int(camera)] if camera else []))


@dataclass(frozen=True)
class MapFrame:
    """Where the layout sits in the scene's map frame: turned about z by ``yaw_deg`` (about the
    layout's origin), then shifted by ``shift``. Users' maps start wherever their mapper started,
    so ``map_frame: random`` draws one (any heading, 20-80 m away horizontally, +-3 m in height);
    everything written (map, poses, ground truth, initial guess, odometry) is in this frame,
    scans stay in the lidar frame and images are unchanged."""

    yaw_deg: float = 0.0
    shift: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def draw(cls, rng: np.random.Generator) -> "MapFrame":
        heading = rng.uniform(0.0, 2 * np.pi)
        distance = rng.uniform(20.0, 80.0)
        return cls(float(rng.uniform(0.0, 360.0)),
                   (float(distance * np.cos(heading)), float(distance * np.sin(heading)),
                    float(rng.uniform(-3.0, 3.0))))

    @property
    def identity(self) -> bool:
        return self.yaw_deg == 0.0 and not any(self.shift)

    @property
    def rotation(self) -> np.ndarray:
        return Rotation.from_euler("z", self.yaw_deg, degrees=True).as_matrix()

    def points(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) layout-frame points in the map frame."""
        if self.identity:
            return xyz
        return rotate(np.asarray(xyz, float), self.rotation) + np.asarray(self.shift)

    def quaternions(self, quats: np.ndarray) -> np.ndarray:
        """(N, 4) x, y, z, w orientations in the map frame."""
        if self.identity:
            return quats
        return (Rotation.from_matrix(self.rotation) * Rotation.from_quat(quats)).as_quat()

    def pose(self, pose: Pose) -> Pose:
        if self.identity:
            return pose
        return Pose.from_matrix(self.rotation @ pose.rotation,
                                self.points(pose.translation[None])[0])


class ViewCrop:
    """The part of the world a map for this camera needs: within ``radius`` (horizontally) of
    the camera and inside its horizontal field of view widened by ``margin_deg`` on each side
    (the evaluation's +-5 deg yaw and +-2.5 m starts stay well inside), plus a 10 m disc around
    the mast. Points are given relative to the camera centre."""

    def __init__(self, camera_pose: Pose, radius: float, margin_deg: float,
                 camera: CameraModel | None = None) -> None:
        camera = camera or default_camera()
        self.radius = radius
        self.yaw = float(np.radians(camera_pose.body_rpy_deg()[2]))
        half_fov = camera.half_fov_deg()
        self.half_angle = float(np.radians(min(180.0, half_fov + margin_deg)))

    def contains(self, rel_xyz: np.ndarray) -> np.ndarray:
        x, y = rel_xyz[:, 0], rel_xyz[:, 1]
        r2 = x * x + y * y
        off = np.abs((np.arctan2(y, x) - self.yaw + np.pi) % (2 * np.pi) - np.pi)
        return (r2 <= self.radius ** 2) & ((off <= self.half_angle) | (r2 <= 100.0))


class ViewsCrop:
    """The union of several cameras' :class:`ViewCrop`: a rig's map holds what any camera sees.
    Points are given relative to ``origin``."""

    def __init__(self, crops: list[tuple[ViewCrop, np.ndarray]], origin: np.ndarray) -> None:
        self.parts = [(crop, (np.asarray(centre, float) - origin).astype(np.float32))
                      for crop, centre in crops]

    def contains(self, rel_xyz: np.ndarray) -> np.ndarray:
        inside = np.zeros(len(rel_xyz), bool)
        for crop, offset in self.parts:
            inside |= crop.contains(rel_xyz - offset)
        return inside


class MapAccumulator:
    """Scans placed with their poses, cropped to the camera's view, voxel-downsampled at the end.

    Works relative to the camera centre in float32 (small numbers) and keeps dynamic points:
    removing them is the map consumer's job.
    """

    def __init__(self, crop: ViewCrop | ViewsCrop, origin: np.ndarray, scan_crop: float,
                 voxel: float,
                 frame: MapFrame = MapFrame()) -> None:
        self.crop, self.origin = crop, np.asarray(origin, float)
        self.scan_crop, self.voxel = scan_crop, voxel
        # crop in the layout frame, voxelise in the map frame (as a mapper would: its voxel grid
        # is aligned with its own axes, not with the streets)
        self.frame = frame
        self._turn = None if frame.identity else frame.rotation.astype(np.float32)
        self._xyz: list[np.ndarray] = []
        self._labels: list[np.ndarray] = []

    def add(self, xyz: np.ndarray, label: np.ndarray, rotation: np.ndarray,
            position: np.ndarray) -> None:
        near = np.einsum("ij,ij->i", xyz, xyz) <= self.scan_crop ** 2
        rel = rotate(xyz[near], rotation) + (position - self.origin).astype(np.float32)
        inside = self.crop.contains(rel)
        self._xyz.append(rel[inside] if self._turn is None else rotate(rel[inside], self._turn))
        self._labels.append(label[near][inside])

    def cloud(self) -> LabelledCloud:
        """The map: one point per voxel (majority class), the grid anchored at the points' lower
        corner. Binned as float32 numbers relative to that corner, centroids in float64."""
        rel = np.concatenate(self._xyz)
        label = np.concatenate(self._labels)
        self._xyz, self._labels = [], []
        if len(rel) == 0:
            return LabelledCloud(np.zeros((0, 3)), np.zeros(0, np.uint16))
        corner = rel.min(axis=0).astype(np.float64)
        thin = voxel_downsample(LabelledCloud((rel - corner).astype(np.float32), label),
                                self.voxel)
        return LabelledCloud(thin.xyz + corner + self.frame.points(self.origin[None])[0],
                             thin.label)


def kitti_to_train_id() -> np.ndarray:
    """uint8[65536]: SemanticKITTI id -> Cityscapes trainId (the label alignment, dynamic kept:
    the camera sees moving cars and people as cars and people)."""
    return LabelMapping(dynamic=()).lidar_lut()


def make_actors(layout: Layout, rng: np.random.Generator, cars: int, people: int,
                moving: bool = True) -> list[Actor]:
    """Cars on the layout's lanes and people on its pavements (moving-* classes)."""
    actors = []
    if layout.lanes:
        for _ in range(cars):
            path, speed = layout.lanes[int(rng.integers(len(layout.lanes)))]
            actors.append(Actor(props.car_mesh(rng, props.MOVING_CAR), path,
                                speed * rng.uniform(0.8, 1.2), rng.uniform(0, path.length)))
    if layout.walkways:
        for _ in range(people):
            walk = layout.walkways[int(rng.integers(len(layout.walkways)))]
            # a short stretch of the walkway near the scene centre, walked back and forth
            s0 = walk.path.closest_arclength(layout.focus) + rng.uniform(-50.0, 50.0)
            s0 = float(np.clip(s0, 0.0, walk.path.length - 20.0))
            xy, _ = walk.path.at(np.array([s0, s0 + rng.uniform(15.0, 40.0)]))
            side = rng.uniform(-1.0, 1.0)
            normal = np.array([-np.sin(_heading(xy)), np.cos(_heading(xy))])
            path = Polyline(xy + side * normal)
            actors.append(Actor(props.person_mesh(rng, props.MOVING_PERSON), path,
                                rng.uniform(1.0, 1.6), rng.uniform(0, 2 * path.length),
                                walk.ground, bounce=True))
    return actors


def _heading(xy: np.ndarray) -> float:
    d = xy[1] - xy[0]
    return float(np.arctan2(d[1], d[0]))


def vehicle_poses(layout: Layout, options: SceneOptions, rng: np.random.Generator
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (N,), lidar positions (N, 3) and quaternions (N, 4) along the drive, the window of
    scans centred on where the path passes the camera's focus."""
    n = options.scans
    dt = 1.0 / options.scan_rate_hz
    times = np.arange(n) * dt
    travel = layout.drive_speed * times[-1]
    if travel > layout.drive.length:
        most = int(layout.drive.length / (layout.drive_speed * dt)) + 1
        raise ValueError(f"{n} scans do not fit the {layout.kind} drive "
                         f"({layout.drive.length:.0f} m at {layout.drive_speed:.1f} m/s); "
                         f"at most {most} at {options.scan_rate_hz:g} Hz")
    centre = layout.drive.closest_arclength(layout.focus)
    s0 = float(np.clip(centre - travel / 2, 0.0, layout.drive.length - travel))
    xy, heading = layout.drive.at(s0 + layout.drive_speed * times)
    # smooth the heading through polyline corners (a vehicle does not turn instantly)
    heading = np.unwrap(heading)
    heading = gaussian_filter1d(heading, sigma=max(0.5, 0.4 / (layout.drive_speed * dt)),
                                mode="nearest")
    phase = rng.uniform(0, 2 * np.pi, 2)
    pitch = np.radians(0.3) * np.sin(2 * np.pi * 0.7 * times + phase[0])
    roll = np.radians(0.2) * np.sin(2 * np.pi * 0.9 * times + phase[1])
    positions = np.c_[xy, np.full(n, LIDAR_HEIGHT)]
    quats = Rotation.from_euler("ZYX", np.c_[heading, pitch, roll]).as_quat()
    return times, positions, quats


def localisation_noise(positions: np.ndarray, quats: np.ndarray, rng: np.random.Generator,
                       sigma_m: float, sigma_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Localisation error: smooth random offsets (correlated over ~0.3 s) of the given 1-sigma.

    White noise through a unit-sum Gaussian filter loses variance by sum(w^2) ~ 1/(2 sqrt(pi) s);
    scaling by the inverse keeps the per-scan 1-sigma at the requested value.
    """
    sigma = 3.0

    def smooth(shape: tuple[int, int]) -> np.ndarray:
        noise = gaussian_filter1d(rng.normal(0, 1, shape), sigma=sigma, axis=0, mode="wrap")
        return noise * np.sqrt(2.0 * np.sqrt(np.pi) * sigma)
    dt = smooth(positions.shape) * sigma_m
    dr = Rotation.from_rotvec(smooth(positions.shape) * np.radians(sigma_deg))
    return positions + dt, (Rotation.from_quat(quats) * dr).as_quat()


def camera_images(world: World, pose: Pose, moving: LabelledMesh, options: SceneOptions,
                  noisy: bool, rng_noise: np.random.Generator, rng_shade: np.random.Generator,
                  rgb: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Label image (trainIds, sky where nothing is hit) and shaded RGB image of the camera
    (None without ``rgb``)."""
    camera = lens_camera(options.lens)
    dirs = pixel_rays(camera, pose)
    hits = world.cast(pose.translation, dirs, moving)
    labels = np.where(hits.hit, kitti_to_train_id()[hits.label], SKY).astype(np.uint8)
    labels = labels.reshape(camera.height, camera.width)
    if options.lens != "pinhole":  # pixels outside the lens' reach are no class at all
        labels[~pixel_reach(camera)] = INVALID
    if noisy:
        labels = add_label_noise(labels, rng_noise)
    if not rgb:
        return labels, None
    s = options.supersample
    dirs = pixel_rays(camera, pose, s) if s > 1 else dirs
    hits = world.cast(pose.translation, dirs, moving) if s > 1 else hits
    azimuth = rng_shade.uniform(0, 2 * np.pi)
    elevation = np.radians(rng_shade.uniform(35.0, 60.0))
    sun = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                    np.sin(elevation)])
    linear = shade(world, pose.translation, dirs, hits, sun, moving)
    return labels, to_image(linear, camera.width, camera.height, s, rng_shade)


def _poses_yaml(path: Path, files: list[str], stamps: np.ndarray, positions: np.ndarray,
                quats: np.ndarray) -> None:
    scans = [{"file": f, "stamp": float(s), "translation": [float(v) for v in p],
              "rotation": [float(v) for v in q]}
             for f, s, p, q in zip(files, stamps, positions, quats)]
    data = {"frame_id": "map", "child_frame_id": "lidar", "scans": scans}
    path.write_text(yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=200))


def _cameras_yaml(path: Path, rig: list[RigCamera]) -> None:
    """The list file of a multi-camera scene: each camera's folder, frame and bag topics."""
    cameras = [{"name": c.name, "folder": f"cameras/{c.name}", "frame_id": c.frame_id,
                "topics": {t: f"/{c.prefix}/{t}" for t in ("labels", "camera_info", "image_raw")}}
               for c in rig]
    path.write_text(yaml.safe_dump({"cameras": cameras}, sort_keys=False))


def _class_counts(labels: np.ndarray) -> dict[str, int]:
    ids, counts = np.unique(labels, return_counts=True)
    return {SEMANTIC_KITTI.get(int(i), str(int(i))): int(c) for i, c in zip(ids, counts)}


def prepare_output(out: Path, force: bool) -> None:
    """An empty output folder; with ``force`` an earlier scene there is replaced."""
    if out.exists() and any(out.iterdir()):
        if not force:
            raise FileExistsError(f"output folder is not empty: {out} (use --force to replace "
                                  "a scene)")
        if not (out / "scene.yaml").is_file():
            raise ValueError(f"refusing to replace {out}: it is not a scene folder (no scene.yaml)")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)


@dataclass
class SceneWorld:
    """Everything a (kind, seed, variant, options) scene is drawn from, before any sensor writes:
    the scene generator and :func:`camera_view` (a camera's labels at another pose) share it."""

    layout: Layout
    truth_layout: Pose
    rig: list
    multi: bool
    static: LabelledMesh
    world: World
    frame: "MapFrame"
    lines: int
    spec: LidarSpec
    scan_actors: list
    image_actors: list
    times: np.ndarray
    positions: np.ndarray
    quats: np.ndarray
    t_camera: float


def scene_world(kind: str, seed: int, variant: str, options: SceneOptions) -> SceneWorld:
    """The world of a scene: layout, camera rig, meshes, map frame, actors and the drive."""
    layout = build_layout(kind, _rng(seed, kind, "layout"))
    truth_layout = Pose.from_body_rpy_deg(layout.camera_position,
                                          [0.0, layout.camera_pitch_deg, layout.camera_yaw_deg])
    static = layout.static
    multi = options.cameras > 1
    rig = (camera_rig(layout, options.cameras, lambda k: _rng(seed, kind, "rig", k)) if multi
           else [RigCamera("camera", truth_layout, False, float(layout.camera_yaw_deg))])
    if options.mast == "bracket" or multi:
        gear = MeshBuilder()
        for cam in rig:
            if cam.own_mast:
                camera_mast(gear, cam.pose.translation, cam.yaw_deg, layout.camera_ground)
            if options.mast == "bracket":
                props.camera_gear(gear, cam.pose.translation,
                                  cam.pose.rotation @ BODY_FROM_OPTICAL.T,
                                  mast_xy(cam.pose.translation, cam.yaw_deg), MAST_RADIUS,
                                  layout.camera_ground)
        static = LabelledMesh.concat([static, gear.build()])
    world = World(static, options.threads)
    frame = MapFrame.draw(_rng(seed, kind, "frame")) if options.map_frame == "random" \
        else MapFrame()
    lines = options.lines or (32 if variant == "sparse" else 128)
    spec = LidarSpec(lines=lines, horizontal_step_deg=options.horizontal_step_deg)
    dynamic = variant == "dynamic"
    n_cars = options.moving_cars * (3 if dynamic else 1)
    n_people = options.moving_people * (3 if dynamic else 1)
    scan_actors = make_actors(layout, _rng(seed, kind, "actors"), n_cars, n_people)
    times, positions, quats = vehicle_poses(layout, options, _rng(seed, kind, "lidar"))
    t_camera = float(times[len(times) // 2])
    image_actors = (make_actors(layout, _rng(seed, kind, "image_actors"), n_cars, n_people)
                    if dynamic else scan_actors)
    return SceneWorld(layout, truth_layout, rig, multi, static, world, frame, lines, spec,
                      scan_actors, image_actors, times, positions, quats, t_camera)


def camera_view(kind: str, seed: int, variant: str, options: SceneOptions, pose: Pose,
                noise_seed: int | str | None = None, world: SceneWorld | None = None,
                camera: int = 0) -> np.ndarray:
    """The label image a scene's camera would see from ``pose`` (map frame): what a camera that
    was knocked or re-aimed delivers (drift benchmarks, the demo). With ``noise_seed`` the
    labels get the noisy_labels variant's segmentation noise drawn from that seed (a new network
    output per frame); ``"scene"``: the noise realisation the scene's rig camera ``camera``
    got (the scene's own label image when ``pose`` is its ground truth); ``world`` reuses a
    :func:`scene_world` already built."""
    sw = world or scene_world(kind, seed, variant, options)
    layout_pose = pose
    if not sw.frame.identity:  # map frame -> layout frame
        rot = sw.frame.rotation
        layout_pose = Pose.from_matrix(rot.T @ pose.rotation,
                                       rot.T @ (pose.translation - np.asarray(sw.frame.shift)))
    labels, _ = camera_images(sw.world, layout_pose, actors_at(sw.image_actors, sw.t_camera),
                              replace(options, supersample=1), noise_seed is not None,
                              _rng(seed, kind, "noise", camera) if noise_seed == "scene"
                              else np.random.default_rng(noise_seed), np.random.default_rng(0),
                              rgb=False)
    return labels


def generate_scene(out: str | Path, kind: str = "junction", seed: int = 0,
                   variant: str = "ideal", options: SceneOptions = SceneOptions(),
                   force: bool = False, progress: bool = True) -> SceneResult:
    """Generate the scene folder ``out``; returns its path and the scene.yaml summary."""
    if kind not in KINDS:
        raise ValueError(f"unknown scene kind '{kind}' (choose from {', '.join(KINDS)})")
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant '{variant}' (choose from {', '.join(VARIANTS)})")
    options.validate()
    out = Path(out)
    prepare_output(out, force)
    t_start = time.perf_counter()
    timing: dict[str, float] = {}

    sw = scene_world(kind, seed, variant, options)
    layout, truth_layout, rig, multi, world, frame = (sw.layout, sw.truth_layout, sw.rig,
                                                      sw.multi, sw.world, sw.frame)
    lines, spec, scan_actors, image_actors = sw.lines, sw.spec, sw.scan_actors, sw.image_actors
    times, positions, quats, t_camera = sw.times, sw.positions, sw.quats, sw.t_camera
    static = sw.static
    timing["layout"] = time.perf_counter() - t_start

    # cameras: the first one's files at the top (the single-camera format), a rig's every
    # camera's under cameras/<name>/ (docs/scenes.md)
    t0 = time.perf_counter()
    camera = lens_camera(options.lens)
    frames = []
    for k, cam in enumerate(rig):
        labels_k, rgb_k = camera_images(world, cam.pose, actors_at(image_actors, t_camera),
                                        options, variant == "noisy_labels",
                                        _rng(seed, kind, "noise", k),
                                        _rng(seed, kind, "shading", k))
        initial = frame.pose(perturbed_initial(cam.pose, _rng(seed, kind, "initial", k)))
        folders = ([out] if k == 0 else []) + ([out / "cameras" / cam.name] if multi else [])
        for folder in folders:
            named = folder != out
            folder.mkdir(parents=True, exist_ok=True)
            write_label_image(folder / "labels.png", labels_k)
            write_rgb_image(folder / "image.png", rgb_k)
            write_camera_info(folder / "camera_info.yaml", camera,
                              cam.name if named else "camera")
            child = cam.frame_id if named else "camera_optical"
            for name, pose in (("ground_truth.yaml", frame.pose(cam.pose)),
                               ("initial.yaml", initial)):
                (folder / name).write_text(yaml.safe_dump(
                    pose_to_dict(pose, child_frame_id=child), sort_keys=False))
        frames.append(CameraFrame(camera, rgb_k, labels_k, cam.frame_id, cam.prefix))
    labels = frames[0].labels
    if multi:
        _cameras_yaml(out / "cameras.yaml", rig)
    timing["camera"] = time.perf_counter() - t0

    # lidar drive
    t0 = time.perf_counter()
    stamps = options.start_stamp + times
    reported_pos, reported_q = positions, quats  # layout frame; written in the map frame
    if variant == "pose_noise":
        reported_pos, reported_q = localisation_noise(
            positions, quats, _rng(seed, kind, "noise"), options.pose_noise_m,
            options.pose_noise_deg)
    written_pos, written_q = frame.points(reported_pos), frame.quaternions(reported_q)
    scan_dir = out / "scans"
    scan_dir.mkdir()
    bag = None
    if options.write_bag:
        bag = SceneBagWriter(out / "bag", frames, options.camera_period)
    rng_lidar = _rng(seed, kind, "lidar")
    origin = rig[0].pose.translation
    view_crop: ViewCrop | ViewsCrop = ViewCrop(truth_layout, options.map_radius,
                                               options.map_view_margin_deg, camera)
    if multi:
        view_crop = ViewsCrop([(ViewCrop(c.pose, options.map_radius, options.map_view_margin_deg,
                                         camera),
                                c.pose.translation) for c in rig], origin)
    accumulators = {"map.ply": MapAccumulator(view_crop, origin, options.scan_crop,
                                              options.voxel, frame)}
    if variant == "pose_noise":  # what accumulating with the perturbed poses would give
        accumulators[NOISY_POSE_MAP] = MapAccumulator(view_crop, origin, options.scan_crop,
                                                      options.voxel, frame)
    directions = spec.directions()
    files = []
    scan_points = 0
    try:
        for i in tqdm(range(options.scans), desc=f"{kind}/{variant} scans", unit="scan",
                      disable=not progress):
            rot = Rotation.from_quat(quats[i]).as_matrix()
            xyz, intensity, label = scan(world, spec, rot, positions[i],
                                         actors_at(scan_actors, float(times[i])), rng_lidar,
                                         directions)
            files.append(f"{i:06d}.ply")
            if options.write_scans:
                write_ply(scan_dir / files[-1], LabelledCloud(xyz, label, {"intensity": intensity}))
            if bag is not None:
                bag.add_scan(float(stamps[i]), written_pos[i], written_q[i], xyz, intensity,
                             label)
            accumulators["map.ply"].add(xyz, label, rot, positions[i])
            if NOISY_POSE_MAP in accumulators:
                accumulators[NOISY_POSE_MAP].add(
                    xyz, label, Rotation.from_quat(reported_q[i]).as_matrix(), reported_pos[i])
            scan_points += len(xyz)
    finally:
        if bag is not None:
            bag.close(float(stamps[-1]))
    _poses_yaml(scan_dir / "poses.yaml", files, stamps, written_pos, written_q)
    if variant == "pose_noise":
        _poses_yaml(scan_dir / "poses_true.yaml", files, stamps, frame.points(positions),
                    frame.quaternions(quats))
    timing["lidar"] = time.perf_counter() - t0

    # map from the true poses (and, for pose_noise, from the perturbed ones)
    t0 = time.perf_counter()
    map_cloud = accumulators["map.ply"].cloud()
    write_ply(out / "map.ply", map_cloud)
    if NOISY_POSE_MAP in accumulators:
        write_ply(out / NOISY_POSE_MAP, accumulators[NOISY_POSE_MAP].cloud())
    timing["map"] = time.perf_counter() - t0
    timing["total"] = time.perf_counter() - t_start

    image_ids, image_counts = np.unique(labels, return_counts=True)
    summary = {
        "kind": kind, "seed": int(seed), "variant": variant,
        "generator_version": GENERATOR_VERSION,
        "options": {k: v for k, v in asdict(replace(options, lines=lines)).items()
                    if (k != "cameras" or multi) and (k != "lens" or options.lens != "pinhole")},
        "lidar": {"lines": lines, "fov_deg": [spec.fov_down_deg, spec.fov_up_deg],
                  "horizontal_step_deg": spec.horizontal_step_deg, "max_range": spec.max_range,
                  "range_noise": spec.range_noise, "height": LIDAR_HEIGHT,
                  "speed": float(layout.drive_speed)},
        "camera": {"height_above_ground": float(layout.camera_position[2] - layout.camera_ground),
                   "pitch_deg": float(layout.camera_pitch_deg),
                   "yaw_deg": float(layout.camera_yaw_deg + frame.yaw_deg),  # map frame
                   "stamp": float(stamps[0] + t_camera),
                   "mast": options.mast},
        **({"cameras": [c.name for c in rig]} if multi else {}),
        "map_frame": {"yaw_deg": frame.yaw_deg, "shift": list(frame.shift),
                      "note": "map = Rz(yaw) * layout + shift"},
        "counts": {"scans": options.scans, "scan_points": int(scan_points),
                   "map_points": len(map_cloud), "mesh_triangles": len(layout.static),
                   "moving_actors_scans": len(scan_actors), "mesh_triangles_world": len(static),
                   "moving_actors_image": len(image_actors)},
        "map_classes": _class_counts(map_cloud.label),
        "image_class_fractions": {
            CITYSCAPES.get(int(i), "ignore"):
                round(float(c) / labels.size, 4) for i, c in zip(image_ids, image_counts)},
        "seconds": {k: round(v, 2) for k, v in timing.items()},
    }
    (out / "scene.yaml").write_text(yaml.safe_dump(summary, sort_keys=False))
    return SceneResult(out, summary)

