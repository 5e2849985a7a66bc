"""Train the geometric point labeller's forest (``semcal_ros/segmentation/data/point_labeller.npz``).

Where exact point labels exist: synthetic scans of the scene generator's worlds (every layout,
several seeds) seen by eight simulated lidars (spinning 16-128 beams at 1.7-5 m, a solid-state
pattern with a narrow field of view; ``--narrow-lidar`` adds a narrow top-mounted 64-beam pattern
denser near the horizon), plus at most one SemanticKITTI scan (``--kitti-scans``; the
benchmarks hold the others out) as recorded and resampled to ``--kitti-patterns`` other lidars
(every 2nd / 4th beam, the narrow pattern and 16-40 even beams at 1.7-2.5 m:
:mod:`semcal_tools.lidar_patterns`).
Each scan goes through the labeller's own feature code
(:func:`semcal_ros.segmentation.geometric.scan_features`), each voxel takes the majority class of
its points, and a scikit-learn random forest is fitted on a class-capped sample and written as
plain arrays (:mod:`semcal_ros.segmentation.forest`). scikit-learn is needed here only, never at
run time (requirements.txt lists it under development).

    python -m semcal_tools.train_point_labeller --out semcal_ros/segmentation/data/point_labeller.npz

Two steps, so each stays short on 2 cores: ``--samples-out S.npz`` writes the feature samples
(scans -> features); ``--samples S.npz [S2.npz ...]`` fits on saved samples.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from semcal_ros.engine.labels import KITTI_ID
from semcal_tools.lidar_patterns import NARROW_BEAMS, resample, training_patterns

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO.parent / "shared" / "data" / "kitti_odometry_00"

#: The forest's classes (SemanticKITTI ids; 0 = other: people, bicycles, clutter -> unlabeled).
CLASSES = (0, KITTI_ID["road"], KITTI_ID["sidewalk"], KITTI_ID["terrain"], KITTI_ID["building"],
           KITTI_ID["fence"], KITTI_ID["vegetation"], KITTI_ID["trunk"], KITTI_ID["pole"],
           KITTI_ID["traffic-sign"], KITTI_ID["car"])
#: SemanticKITTI id -> training class id (anything not listed: 0, other).
TRAIN_CLASS = {
    "road": "road", "lane-marking": "road", "parking": "sidewalk", "sidewalk": "sidewalk",
    "other-ground": "terrain", "terrain": "terrain", "building": "building",
    "other-structure": "building", "fence": "fence", "vegetation": "vegetation",
    "trunk": "trunk", "pole": "pole", "traffic-sign": "traffic-sign", "car": "car",
    "truck": "car", "bus": "car", "other-vehicle": "car", "moving-car": "car",
    "moving-truck": "car", "moving-bus": "car", "moving-other-vehicle": "car",
}


def class_lut() -> np.ndarray:
    """uint8[65536]: SemanticKITTI id -> column of :data:`CLASSES`."""
    lut = np.zeros(65536, np.uint8)
    for name, target in TRAIN_CLASS.items():
        lut[KITTI_ID[name]] = CLASSES.index(KITTI_ID[target])
    return lut


@dataclass(frozen=True)
class Sensor:
    """A simulated lidar: spinning (``lines`` beams evenly over fov_down..fov_up, a column every
    ``step_deg``) or solid-state (``random_points`` directions drawn over +-``half_width_deg``
    and fov_down..fov_up, forward), mounted ``height`` m above the road."""

    name: str
    lines: int
    fov_up: float
    fov_down: float
    step_deg: float
    height: float
    random_points: int = 0
    half_width_deg: float = 180.0
    range_noise: float = 0.02
    elevations: tuple[float, ...] | None = None  # a beam table (deg) instead of even lines

    def directions(self, rng: np.random.Generator) -> np.ndarray:
        if self.elevations is not None:
            el = np.radians(np.asarray(self.elevations, np.float64))
            az = np.radians(np.arange(0.0, 360.0, self.step_deg))
            e, a = np.meshgrid(el, az, indexing="ij")
            return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)],
                            -1).reshape(-1, 3)
        if self.random_points:
            az = np.radians(rng.uniform(-self.half_width_deg, self.half_width_deg,
                                        self.random_points))
            el = np.radians(rng.uniform(self.fov_down, self.fov_up, self.random_points))
            return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
        from semcal_tools.scenes.sensors import LidarSpec

        return LidarSpec(self.lines, self.fov_up, self.fov_down, self.step_deg).directions()


SENSORS = (
    Sensor("hdl64", 64, 2.0, -24.9, 0.18, 1.73),
    Sensor("hdl32", 32, 10.7, -30.7, 0.2, 1.9),
    Sensor("vlp16", 16, 15.0, -15.0, 0.2, 1.8),
    Sensor("os128", 128, 22.5, -22.5, 0.35, 2.0),
    Sensor("pandar40", 40, 7.0, -16.0, 0.2, 2.1),
    Sensor("scene128", 128, 45.0, -45.0, 0.25, 3.0),
    Sensor("livox", 0, 12.5, -12.5, 0.0, 1.8, random_points=100_000, half_width_deg=40.0),
    Sensor("mast64", 64, 2.0, -24.9, 0.2, 5.0),
)
#: the PJLab frames' top-mounted 64-beam lidar: dense near the horizon, +15 to -25 deg
#: (``--narrow-lidar``: issue 41's retrained forest, not the shipped one)
NARROW_SENSOR = Sensor("narrow64", 64, 14.88, -24.9, 0.2, 2.4,
                       elevations=NARROW_BEAMS + (3.04, 5.06, 8.06, 11.03, 14.88))


def voxel_targets(labels: np.ndarray, inverse: np.ndarray, n_voxels: int) -> np.ndarray:
    """Majority training class of each voxel's points."""
    cls = class_lut()[labels]
    votes = np.bincount(inverse * len(CLASSES) + cls, minlength=n_voxels * len(CLASSES))
    return votes.reshape(n_voxels, len(CLASSES)).argmax(axis=1).astype(np.uint8)


def scan_samples(xyz: np.ndarray, labels: np.ndarray, intensity: np.ndarray | None = None,
                 min_x: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(features (V, F), target class (V,)) of one labelled scan; with ``min_x`` only the
    voxels whose centroid lies ahead of that x (a spatial train/test split)."""
    from semcal_ros.segmentation.geometric import scan_features

    index, feats = scan_features(xyz, intensity)
    target = voxel_targets(np.asarray(labels)[index], feats.inverse, len(feats.values))
    if min_x is None:
        return feats.values, target
    x = np.bincount(feats.inverse, np.asarray(xyz, float)[index, 0]) / np.bincount(feats.inverse)
    return feats.values[x > min_x], target[x > min_x]


def with_large_vehicles(sw, count: int, rng: np.random.Generator):
    """The scene world's static mesh with ``count`` buses and lorries parked beside its survey
    drive (3-4.5 m to either side of a random drive pose, along it), as a ray-castable World."""
    from scipy.spatial.transform import Rotation

    from semcal_tools.scenes import props
    from semcal_tools.scenes.mesh import LabelledMesh
    from semcal_tools.scenes.sensors import World

    parts = [sw.world.static]
    for _ in range(count):
        i = int(rng.integers(len(sw.times)))
        yaw = float(Rotation.from_quat(sw.quats[i]).as_euler("zyx")[0])
        side = rng.choice((-1.0, 1.0)) * rng.uniform(3.0, 4.5)
        xy = np.asarray(sw.positions[i][:2], float) + side * np.array([-np.sin(yaw), np.cos(yaw)])
        heading = yaw + (np.pi if rng.random() < 0.5 else 0.0)
        parts.append(props.large_vehicle_mesh(rng).moved(heading, (xy[0], xy[1], 0.0)))
    return World(LabelledMesh.concat(parts), sw.world.threads)


def synthetic_samples(kinds: tuple[str, ...], seeds: range, scans_per_sensor: int,
                      rng: np.random.Generator, log=print,
                      sensors: tuple[Sensor, ...] = SENSORS,
                      large_vehicles: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Features and targets of simulated scans: every kind x seed world, every sensor at
    ``scans_per_sensor`` random places of the survey drive (the mast lidar at the camera mast);
    ``large_vehicles`` buses and lorries added beside the drive of each world."""
    from scipy.spatial.transform import Rotation

    from semcal_tools.scenes.generate import SceneOptions, scene_world
    from semcal_tools.scenes.sensors import LidarSpec, scan

    xs, ys = [], []
    for kind in kinds:
        for seed in seeds:
            t0 = time.perf_counter()
            sw = scene_world(kind, seed, "ideal", SceneOptions(write_bag=False, threads=0))
            # their own random stream: the scans' places are those drawn without them
            world = (with_large_vehicles(sw, large_vehicles, np.random.default_rng(
                [seed, kinds.index(kind), 41])) if large_vehicles else sw.world)
            n_pts = 0
            for sensor in sensors:
                spec = LidarSpec(max(sensor.lines, 2), sensor.fov_up, sensor.fov_down,
                                 max(sensor.step_deg, 0.01), range_noise=sensor.range_noise)
                for _ in range(scans_per_sensor):
                    i = int(rng.integers(len(sw.times)))
                    heading = Rotation.from_quat(sw.quats[i])
                    position = np.array(sw.positions[i], float)
                    if sensor.name.startswith("mast"):
                        position[:2] = sw.layout.camera_position[:2] + rng.normal(0, 2.0, 2)
                        position[2] = sw.layout.camera_ground + sensor.height
                        heading = Rotation.from_euler("z", rng.uniform(0, 360), degrees=True)
                    else:
                        position[2] = sensor.height
                    from semcal_tools.scenes.actors import actors_at

                    xyz, intensity, label = scan(world, spec, heading.as_matrix(), position,
                                                 actors_at(sw.scan_actors, float(sw.times[i])),
                                                 rng, sensor.directions(rng).astype(np.float32))
                    if len(xyz) < 500:
                        continue
                    x, y = scan_samples(xyz, label, intensity)
                    xs.append(x)
                    ys.append(y)
                    n_pts += len(xyz)
            log(f"{kind} seed {seed}: {len(sensors) * scans_per_sensor} scans, {n_pts} points, "
                f"{time.perf_counter() - t0:.0f} s")
    return np.concatenate(xs), np.concatenate(ys)


def kitti_samples(scans: list[int], min_x: float | None = None, patterns: int = 0,
                  seed: int = 0, log=print) -> tuple[np.ndarray, np.ndarray]:
    """Features and targets of SemanticKITTI scans as recorded and, with ``patterns``, as that
    many other lidars would have seen them (:func:`semcal_tools.lidar_patterns.resample`: fewer
    beams, a narrow top-mounted pattern, other mounting heights)."""
    from semcal_ros.io import kitti

    xs, ys = [], []
    rng = np.random.default_rng(seed)
    for i in scans:
        cloud = kitti.read_scan(KITTI / "velodyne" / f"{i:06d}.bin")
        labels = (np.fromfile(KITTI / "labels" / f"{i:06d}.label", np.uint32) & 0xFFFF
                  ).astype(np.uint16)
        intensity = cloud.extra.get("intensity")
        views = [(cloud.xyz, labels, intensity)]
        for pattern in training_patterns(rng, patterns):
            views.append(resample(cloud.xyz, labels, intensity, pattern))
        for xyz, lab, inten in views:
            x, y = scan_samples(xyz, lab, inten, min_x)
            xs.append(x)
            ys.append(y)
        log(f"SemanticKITTI scan {i}: {len(views)} views, {sum(len(v[0]) for v in views)} points")
    return np.concatenate(xs), np.concatenate(ys)


def capped(x: np.ndarray, y: np.ndarray, cap: int, rng: np.random.Generator
           ) -> tuple[np.ndarray, np.ndarray]:
    """At most ``cap`` random samples of each class (rare classes keep all theirs)."""
    keep = []
    for c in np.unique(y):
        members = np.flatnonzero(y == c)
        keep.append(members if len(members) <= cap else rng.choice(members, cap, replace=False))
    sel = np.sort(np.concatenate(keep))
    return x[sel], y[sel]


def fit(x: np.ndarray, y: np.ndarray, weight: np.ndarray, trees: int, depth: int,
        min_leaf: int, seed: int):
    from sklearn.ensemble import RandomForestClassifier

    model = RandomForestClassifier(n_estimators=trees, max_depth=depth, min_samples_leaf=min_leaf,
                                   max_features="sqrt", n_jobs=2, random_state=seed)
    # every class column present, also the ones a sample lacks: add one dummy row per class
    missing = sorted(set(range(len(CLASSES))) - set(np.unique(y).tolist()))
    if missing:
        x = np.vstack([x, np.zeros((len(missing), x.shape[1]), x.dtype)])
        y = np.concatenate([y, np.array(missing, y.dtype)])
        weight = np.concatenate([weight, np.full(len(missing), 1e-6)])
    model.fit(x, y, sample_weight=weight)
    return model


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="forest file to write (.npz)")
    ap.add_argument("--samples-out", type=Path, help="write the feature samples here and stop")
    ap.add_argument("--samples", type=Path, nargs="*", default=[],
                    help="fit on these saved samples instead of simulating")
    ap.add_argument("--kinds", default="junction,arterial,highway,roundabout")
    ap.add_argument("--seeds", default="0-1", help="seed range of each kind, e.g. 0-1")
    ap.add_argument("--scans-per-sensor", type=int, default=1)
    ap.add_argument("--kitti-scans", default="0",
                    help="SemanticKITTI scans used for training ('' for none; at most one)")
    ap.add_argument("--kitti-min-x", type=float,
                    help="only the SemanticKITTI voxels ahead of this x (m): with the benchmark's "
                         "--max-x, a test on ground the training never saw")
    ap.add_argument("--kitti-weight", type=float, default=1.0,
                    help="weight of the SemanticKITTI samples relative to all synthetic ones")
    ap.add_argument("--kitti-patterns", type=int, default=0,
                    help="also the SemanticKITTI scan resampled to this many other lidars "
                         "(semcal_tools/lidar_patterns.py)")
    ap.add_argument("--kitti-cap", type=int, default=20_000,
                    help="samples per class of the SemanticKITTI source (all its views)")
    ap.add_argument("--narrow-lidar", action="store_true",
                    help="also scan the synthetic worlds with the narrow top-mounted lidar")
    ap.add_argument("--large-vehicles", type=int, default=0, metavar="N",
                    help="N buses and lorries parked beside each synthetic world's drive")
    ap.add_argument("--cap", type=int, default=20_000, help="samples per class and source")
    ap.add_argument("--trees", type=int, default=20)
    ap.add_argument("--depth", type=int, default=18)
    ap.add_argument("--min-leaf", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)

    kitti_scans = [int(s) for s in args.kitti_scans.split(",") if s.strip()]
    if len(kitti_scans) > 1:
        print("at most one SemanticKITTI scan may be used for training (the others are held "
              "out)", file=sys.stderr)
        return 1
    sources: list[tuple[str, np.ndarray, np.ndarray]] = []
    if args.samples:
        for path in args.samples:
            with np.load(path) as data:
                sources.append((path.stem, data["x"], data["y"]))
    else:
        lo, hi = (int(v) for v in args.seeds.split("-"))
        x, y = synthetic_samples(tuple(args.kinds.split(",")), range(lo, hi + 1),
                                 args.scans_per_sensor, rng,
                                 sensors=SENSORS + ((NARROW_SENSOR,) if args.narrow_lidar else ()),
                                 large_vehicles=args.large_vehicles)
        sources.append(("synthetic", x, y))
        if args.samples_out:
            np.savez_compressed(args.samples_out, x=x, y=y)
            print(f"wrote {len(y)} samples to {args.samples_out}")
            return 0
    if kitti_scans:
        x, y = kitti_samples(kitti_scans, args.kitti_min_x, args.kitti_patterns, args.seed)
        sources.append(("kitti", x, y))
    xs, ys, ws = [], [], []
    for name, x, y in sources:
        x, y = capped(x, y, args.kitti_cap if name == "kitti" else args.cap, rng)
        # each source weighs 1 in all (the SemanticKITTI one --kitti-weight), whatever its size
        w = np.full(len(y), (args.kitti_weight if name == "kitti" else 1.0) / len(y))
        counts = np.bincount(y, minlength=len(CLASSES))
        print(f"{name}: {len(y)} samples, per class {dict(zip(CLASSES, counts.tolist()))}")
        xs.append(x)
        ys.append(y)
        ws.append(w)
    x, y, w = np.concatenate(xs), np.concatenate(ys), np.concatenate(ws) * len(np.concatenate(ys))
    t0 = time.perf_counter()
    model = fit(x, y, w, args.trees, args.depth, args.min_leaf, args.seed)
    print(f"fitted {args.trees} trees on {len(y)} samples in {time.perf_counter() - t0:.0f} s")

    from semcal_ros.segmentation.forest import from_sklearn
    from semcal_ros.segmentation.point_features import FEATURE_NAMES

    forest = from_sklearn(model, np.array(CLASSES), FEATURE_NAMES)
    check = forest.predict_proba(x[:2000]).argmax(axis=1)
    agree = float((check == model.predict_proba(x[:2000]).argmax(axis=1)).mean())
    print(f"exported forest: {len(forest.feature)} nodes, {len(forest.leaf_values)} leaves; "
          f"agrees with scikit-learn on {100 * agree:.1f} % of 2000 samples")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        forest.save(args.out)
        print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
