"""Synthetic scenes: contract formats, internal consistency, bag round trip, variants."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from plyfile import PlyData
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from semcal_ros.engine.camera import CameraModel
from semcal_ros.io.files import read_camera_info, read_label_image, read_pose, read_rgb_image
from semcal_ros.io.ply import read_ply
from semcal_ros.engine.labels import CITYSCAPES, CITYSCAPES_ID, INVALID, KITTI_ID, LabelMapping
from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error
from semcal_tools.scenes import SIZES, SceneOptions, catalogue
from semcal_tools.scenes.generate import vehicle_poses
from semcal_tools.scenes.layouts import KINDS, build_layout
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.mapping.filters import voxel_downsample
from scene_fingerprints import PINNED_FILE, PINNED_FILES, compare, fingerprint, key_name

#: Options that make a scene cheap where only its variant's effect is tested.
TINY = dict(scans=6, horizontal_step_deg=1.0, write_bag=False)


def zbuffer_labels(points: np.ndarray, labels: np.ndarray, camera: CameraModel, pose: Pose,
                   voxel: float = 0.05, max_half: int = 4) -> np.ndarray:
    """Nearest-point label per pixel; each point a square about one voxel wide on screen."""
    pc = pose.transform_points(points)
    uv, ok = camera.project(pc)
    pc, uv, labels = pc[ok], uv[ok], labels[ok]
    half = np.clip(np.floor(0.5 * camera.fx * voxel / pc[:, 2]), 0, max_half).astype(int)
    empty = np.iinfo(np.uint64).max
    key = (np.minimum(pc[:, 2] * 1000, 2 ** 24 - 1).astype(np.uint64) << np.uint64(8)) \
        | labels.astype(np.uint64)
    buf = np.full(camera.width * camera.height, empty, np.uint64)
    iu, iv = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    for h in np.unique(half):
        sel = half == h
        for du in range(-h, h + 1):
            for dv in range(-h, h + 1):
                u, v = iu[sel] + du, iv[sel] + dv
                inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
                np.minimum.at(buf, v[inside] * camera.width + u[inside], key[sel][inside])
    out = np.where(buf == empty, INVALID, buf & np.uint64(255)).astype(np.uint8)
    return out.reshape(camera.height, camera.width)


def agreement(scene: Path, pose: Pose) -> float:
    """Fraction of pixels where the rendered map's class equals the label image's class."""
    mapping = LabelMapping()
    cloud = read_ply(scene / "map.ply")
    aligned = mapping.map_lidar(cloud.label)
    keep = aligned != INVALID
    rendered = zbuffer_labels(cloud.xyz[keep], aligned[keep],
                              read_camera_info(scene / "camera_info.yaml"), pose)
    target = mapping.map_image(read_label_image(scene / "labels.png"))
    valid = (rendered != INVALID) & (target != INVALID)
    assert valid.mean() > 0.3, "the map covers too little of the image to compare"
    return float((rendered[valid] == target[valid]).mean())


def read_poses(path: Path) -> dict:
    return yaml.safe_load(path.read_text())


# ------------------------------------------------------------------------------------------
def test_scene_folder_has_the_contract_files_and_formats(demo_scene: Path):
    ply = PlyData.read(str(demo_scene / "map.ply"))
    assert not ply.text and ply.byte_order == "<"
    props = {p.name: p.val_dtype for p in ply["vertex"].properties}
    assert props == {"x": "f4", "y": "f4", "z": "f4", "label": "u2"}
    meta = yaml.safe_load((demo_scene / "scene.yaml").read_text())
    assert 500_000 <= meta["counts"]["map_points"] <= 3_000_000
    assert meta["kind"] == "junction" and meta["variant"] == "ideal"

    labels = read_label_image(demo_scene / "labels.png")
    rgb = read_rgb_image(demo_scene / "image.png")
    assert labels.shape == (600, 960) and rgb.shape == (600, 960, 3)
    assert set(np.unique(labels)) <= set(CITYSCAPES)
    for name in ("road", "sidewalk", "building", "vegetation", "pole", "traffic sign"):
        assert (labels == CITYSCAPES_ID[name]).mean() > 0.0005, name
    camera = read_camera_info(demo_scene / "camera_info.yaml")
    assert (camera.width, camera.height) == (960, 600)
    assert np.degrees(2 * np.arctan(camera.width / 2 / camera.fx)) == pytest.approx(90.0)

    truth = read_pose(demo_scene / "ground_truth.yaml")
    roll, pitch, _ = truth.body_rpy_deg()
    assert roll == pytest.approx(0.0, abs=1e-9) and 5.0 < pitch < 35.0
    assert 5.0 <= truth.translation[2] - 0.15 <= 8.0
    initial = read_pose(demo_scene / "initial.yaml")
    assert 0.05 < translation_error(initial, truth) <= np.sqrt(3.0)
    assert 0.01 < rotation_error_deg(initial, truth) <= 3.0

    poses = read_poses(demo_scene / "scans" / "poses.yaml")
    assert (poses["frame_id"], poses["child_frame_id"]) == ("map", "lidar")
    assert len(poses["scans"]) == meta["counts"]["scans"] == 50
    stamps = [s["stamp"] for s in poses["scans"]]
    assert np.all(np.diff(stamps) > 0)
    first = poses["scans"][0]
    scan = PlyData.read(str(demo_scene / "scans" / first["file"]))
    assert {p.name: p.val_dtype for p in scan["vertex"].properties} == {
        "x": "f4", "y": "f4", "z": "f4", "intensity": "f4", "label": "u2"}
    assert len(first["translation"]) == 3 and len(first["rotation"]) == 4
    assert not (demo_scene / "scans" / "poses_true.yaml").exists()


def test_map_agrees_with_label_image_at_ground_truth_and_not_off_it(demo_scene: Path):
    truth = read_pose(demo_scene / "ground_truth.yaml")
    at_truth = agreement(demo_scene, truth)
    assert at_truth > 0.95
    rpy = truth.body_rpy_deg()
    off = Pose.from_body_rpy_deg(truth.translation + [0.35, -0.35, 0.0], rpy + [0.0, 0.7, 0.7])
    at_off = agreement(demo_scene, off)  # 0.5 m and 1 deg away
    assert 1.0 - at_off > 3.0 * (1.0 - at_truth)


def test_scans_placed_with_their_poses_lie_on_the_map(demo_scene: Path):
    cloud = read_ply(demo_scene / "map.ply")
    tree = cKDTree(cloud.xyz)
    poses = read_poses(demo_scene / "scans" / "poses.yaml")["scans"]
    entry = poses[len(poses) // 2]
    scan = read_ply(demo_scene / "scans" / entry["file"])
    assert scan.extra["intensity"].min() >= 0.0 and scan.extra["intensity"].max() <= 1.0
    world = Rotation.from_quat(entry["rotation"]).apply(scan.xyz) + entry["translation"]
    dist, idx = tree.query(world, distance_upper_bound=1.0)
    covered = np.isfinite(dist)
    assert covered.mean() > 0.3  # the map is cropped to the camera's view
    assert np.median(dist[covered]) < 0.04
    static = covered & (scan.label < 252)
    assert (cloud.label[idx[static]] == scan.label[static]).mean() > 0.9


def test_bag_reads_back_with_rosbags_and_decodes_with_rclpy(demo_scene: Path):
    from rclpy.serialization import deserialize_message
    from rosbags.rosbag2 import Reader
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2

    types = {"sensor_msgs/msg/PointCloud2": PointCloud2, "nav_msgs/msg/Odometry": Odometry,
             "sensor_msgs/msg/Image": Image, "sensor_msgs/msg/CameraInfo": CameraInfo}
    poses = read_poses(demo_scene / "scans" / "poses.yaml")["scans"]
    messages: dict[str, list] = {}
    info = yaml.safe_load((demo_scene / "bag" / "metadata.yaml").read_text())
    assert info["rosbag2_bagfile_information"]["storage_identifier"] == "mcap"
    with Reader(demo_scene / "bag") as reader:
        for conn, stamp, raw in reader.messages():
            msg = deserialize_message(raw, types[conn.msgtype])
            header_ns = msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec
            assert abs(header_ns - stamp) < 1000
            messages.setdefault(conn.topic, []).append(msg)
    assert len(messages["/lidar/points"]) == len(messages["/lidar/odom"]) == len(poses)
    assert len(messages["/camera/image_raw"]) == len(messages["/camera/labels"]) >= 4
    assert len(messages["/camera/camera_info"]) >= 4

    cloud = messages["/lidar/points"][7]
    assert cloud.header.frame_id == "lidar"
    assert [(f.name, f.datatype) for f in cloud.fields] == [
        ("x", 7), ("y", 7), ("z", 7), ("intensity", 7), ("label", 4)]
    fmt = np.dtype({"names": [f.name for f in cloud.fields],
                    "formats": ["<f4"] * 4 + ["<u2"],
                    "offsets": [f.offset for f in cloud.fields], "itemsize": cloud.point_step})
    points = np.frombuffer(bytes(cloud.data), fmt)
    scan = read_ply(demo_scene / "scans" / poses[7]["file"])
    assert len(points) == cloud.width == len(scan)
    np.testing.assert_array_equal(points["x"], scan.xyz[:, 0].astype(np.float32))
    np.testing.assert_array_equal(points["label"], scan.label)

    odom = messages["/lidar/odom"][7]
    assert (odom.header.frame_id, odom.child_frame_id) == ("map", "lidar")
    p = odom.pose.pose
    np.testing.assert_allclose([p.position.x, p.position.y, p.position.z],
                               poses[7]["translation"], atol=1e-9)
    np.testing.assert_allclose([p.orientation.x, p.orientation.y, p.orientation.z,
                                p.orientation.w], poses[7]["rotation"], atol=1e-9)

    image, labels = messages["/camera/image_raw"][-1], messages["/camera/labels"][-1]
    assert (image.encoding, labels.encoding) == ("rgb8", "mono8")
    np.testing.assert_array_equal(np.frombuffer(bytes(image.data), np.uint8).reshape(600, 960, 3),
                                  read_rgb_image(demo_scene / "image.png"))
    np.testing.assert_array_equal(np.frombuffer(bytes(labels.data), np.uint8).reshape(600, 960),
                                  read_label_image(demo_scene / "labels.png"))
    info = messages["/camera/camera_info"][0]
    np.testing.assert_allclose(np.reshape(info.k, (3, 3)),
                               read_camera_info(demo_scene / "camera_info.yaml").k)
    cam_stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9
                  for m in messages["/camera/image_raw"]]
    assert np.all(np.diff(cam_stamps) > 0.5)


@pytest.mark.parametrize("key", list(PINNED_FILES), ids=key_name)
def test_existing_seeds_still_make_the_same_scenes(scene_factory, key):
    """Existing (kind, seed, variant) triples keep making the same scenes, whatever options are
    added: labels exactly, geometry and shading within rounding (test/scene_fingerprints.py)."""
    pinned = json.loads(PINNED_FILE.read_text())[key_name(key)]
    scene = scene_factory(*key, **TINY)
    problems = [line for name, want in pinned.items()
                for line in compare(name, fingerprint(scene / name), want)]
    assert not problems, "\n".join(problems)


def test_the_fingerprint_sees_a_real_change(scene_factory, tmp_path):
    """The tolerances are tight enough: a scan with a few points moved by a centimetre, a label
    image with one changed pixel and a shaded image two grey levels brighter over 25 blocks (2.5 %
    of them; another CPU moved 0.2 %) fail."""
    from semcal_ros.io.files import write_label_image, write_rgb_image
    from semcal_ros.io.ply import write_ply

    scene = scene_factory("junction", 3, "ideal", **TINY)
    cloud = read_ply(scene / "scans" / "000003.ply")
    want = fingerprint(scene / "scans" / "000003.ply")
    assert compare("scans/000003.ply", want, want) == []
    moved = cloud.label == np.bincount(cloud.label).argmax()
    cloud.xyz[np.flatnonzero(moved)[::2]] += 0.01
    write_ply(tmp_path / "moved.ply", cloud)
    assert compare("scans/000003.ply", fingerprint(tmp_path / "moved.ply"), want)

    labels = read_label_image(scene / "labels.png")
    labels[0, 0] = (labels[0, 0] + 1) % 19
    write_label_image(tmp_path / "labels.png", labels)
    assert compare("labels.png", fingerprint(tmp_path / "labels.png"),
                   fingerprint(scene / "labels.png"))

    rgb = read_rgb_image(scene / "image.png")
    brighter = rgb.copy()
    brighter[:120, :120] = np.minimum(brighter[:120, :120].astype(int) + 2, 255)  # 25 blocks
    write_rgb_image(tmp_path / "image.png", brighter)
    assert compare("image.png", fingerprint(tmp_path / "image.png"),
                   fingerprint(scene / "image.png"))


# ------------------------------------------------------------------------------------------
def test_variants_change_only_what_they_should(scene_factory):
    ideal = scene_factory("junction", 3, "ideal", **TINY)
    noisy = scene_factory("junction", 3, "noisy_labels", **TINY)
    moved = scene_factory("junction", 3, "pose_noise", **TINY)
    sparse = scene_factory("junction", 3, "sparse", **TINY)

    a, b = read_label_image(ideal / "labels.png"), read_label_image(noisy / "labels.png")
    changed = (a != b).mean()
    assert 0.005 < changed < 0.15
    np.testing.assert_array_equal(read_rgb_image(ideal / "image.png"),
                                  read_rgb_image(noisy / "image.png"))

    # pose noise: poses.yaml perturbed by cm / tenths of a degree, the map from the true poses
    np.testing.assert_array_equal(read_ply(moved / "map.ply").xyz, read_ply(ideal / "map.ply").xyz)
    true = read_poses(moved / "scans" / "poses_true.yaml")["scans"]
    given = read_poses(moved / "scans" / "poses.yaml")["scans"]
    assert true == read_poses(ideal / "scans" / "poses.yaml")["scans"]
    dt = np.array([np.linalg.norm(np.subtract(g["translation"], t["translation"]))
                   for g, t in zip(given, true)])
    dr = np.array([np.degrees((Rotation.from_quat(g["rotation"]).inv()
                               * Rotation.from_quat(t["rotation"])).magnitude())
                   for g, t in zip(given, true)])
    assert 0.005 < dt.mean() < 0.15 and 0.02 < dr.mean() < 1.0
    # ... and the map accumulated with the perturbed poses is blurred relative to the true one
    blurred = read_ply(moved / "map_noisy_poses.ply")
    shift, _ = cKDTree(read_ply(moved / "map.ply").xyz).query(blurred.xyz)
    assert 0.01 < np.median(shift) < 0.1
    assert not (ideal / "map_noisy_poses.ply").exists()

    n_ideal = len(read_ply(ideal / "scans" / "000003.ply"))
    n_sparse = len(read_ply(sparse / "scans" / "000003.ply"))
    assert yaml.safe_load((sparse / "scene.yaml").read_text())["lidar"]["lines"] == 32
    assert 0.15 * n_ideal < n_sparse < 0.4 * n_ideal  # 32 of 128 lines


def test_dynamic_variant_has_movers_in_scans_and_other_ones_in_the_image(scene_factory):
    ideal = scene_factory("arterial", 1, "ideal", **TINY)
    dynamic = scene_factory("arterial", 1, "dynamic", **TINY)
    moving = (KITTI_ID["moving-car"], KITTI_ID["moving-person"])

    def movers(scene: Path) -> int:
        return sum(int(np.isin(read_ply(p).label, moving).sum())
                   for p in sorted((scene / "scans").glob("*.ply")))

    assert movers(dynamic) > movers(ideal) > 0
    car, person = CITYSCAPES_ID["car"], CITYSCAPES_ID["person"]
    a, b = read_label_image(ideal / "labels.png"), read_label_image(dynamic / "labels.png")
    dyn_a, dyn_b = np.isin(a, [car, person]), np.isin(b, [car, person])
    differ = a != b
    # other movers in the image, the same world around them (parked cars are in both)
    assert differ.sum() > 500
    assert np.all(dyn_a[differ] | dyn_b[differ])
    assert yaml.safe_load((dynamic / "scene.yaml").read_text())["counts"][
        "moving_actors_image"] > 0


@pytest.mark.parametrize("kind", KINDS)
def test_layouts_carry_every_roadside_class(kind):
    layout = build_layout(kind, np.random.default_rng(5))
    present = set(np.unique(layout.static.labels).tolist())
    wanted = {"road", "terrain", "lane-marking", "pole", "traffic-sign", "fence", "trunk",
              "vegetation"}
    if kind != "highway":
        wanted |= {"sidewalk", "building", "car"}
    assert {KITTI_ID[n] for n in wanted} <= present
    assert np.all(np.isfinite(layout.static.vertices))
    # the full-size drive (200 scans at 10 Hz) fits the path even at the fastest speed drawn
    fastest = {"junction": 9.0, "arterial": 13.0, "highway": 27.0, "roundabout": 8.0}[kind]
    assert layout.drive.length >= fastest * (SceneOptions().scans - 1) / SceneOptions().scan_rate_hz


def voxel_majority(xyz: np.ndarray, labels: np.ndarray, voxel: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    out = voxel_downsample(LabelledCloud(xyz, labels), voxel)
    return out.xyz, out.label


def test_voxel_filter_keeps_the_most_frequent_class_and_its_centroid():
    """The scenes' maps use the map builder's voxel filter: majority class, its centroid."""
    xyz = np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [0.03, 0.01, 0.04],
                    [0.04, 0.04, 0.04], [0.31, 0.0, 0.0], [0.32, 0.0, 0.0]])
    labels = np.array([50, 40, 50, 40, 70, 80], np.uint16)
    # voxel 0.1: voxel A has 50, 40, 50, 40 (tie 2:2 -> smaller id 40), voxel B 70 vs 80 (tie)
    out, lab = voxel_majority(xyz, labels, 0.1)
    order = np.argsort(out[:, 0])
    np.testing.assert_array_equal(lab[order], [40, 70])
    np.testing.assert_allclose(out[order][0], [0.03, 0.03, 0.03])
    out, lab = voxel_majority(xyz, np.array([50, 50, 50, 40, 80, 80], np.uint16), 0.1)
    order = np.argsort(out[:, 0])
    np.testing.assert_array_equal(lab[order], [50, 80])
    np.testing.assert_allclose(out[order][0], [0.02, 0.04 / 3, 0.07 / 3])
    # float32 points (the scenes' maps) are averaged in float64: no float32 sum error
    many = np.full((100_000, 3), 0.3 + 1e-7, np.float32)
    out, _ = voxel_majority(many, np.full(100_000, 40, np.uint16), 1.0)
    assert out.dtype == np.float64 and out[0, 0] == np.float64(many[0, 0])


@pytest.mark.slow
def test_cli_generates_a_scene_and_rejects_bad_input(tmp_path: Path):
    semcal = Path(sys.executable).with_name("semcal")
    out = tmp_path / "hw"
    done = subprocess.run([str(semcal), "scene", "--kind", "highway", "--seed", "2", "--size",
                           "small", "--scans", "3", "--lines", "8", "--no-bag", "--quiet",
                           "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert len(list((out / "scans").glob("*.ply"))) == 3 and (out / "map.ply").is_file()
    again = subprocess.run([str(semcal), "scene", "--kind", "highway", "--out", str(out)],
                           capture_output=True, text=True, timeout=60)
    assert again.returncode == 1 and "not empty" in again.stderr
    bad = subprocess.run([str(semcal), "scene", "--kind", "racetrack", "--out",
                          str(tmp_path / "x")], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1 and "unknown scene kind 'racetrack'" in bad.stderr
    listed = subprocess.run([str(semcal), "scene", "--list", "--out", "S"], capture_output=True,
                            text=True, timeout=60)
    assert listed.returncode == 0, listed.stderr
    lines = listed.stdout.splitlines()
    assert len(lines) == len(catalogue()) and "--out S/roundabout-sparse" in listed.stdout
    unknown = subprocess.run([str(semcal), "scene", "--catalogue", "roundabout-foggy", "--out",
                              str(tmp_path / "y")], capture_output=True, text=True, timeout=60)
    assert unknown.returncode == 1 and "no catalogue scene 'roundabout-foggy'" in unknown.stderr


# ------------------------------------------------------------------------------------------
# what users have: random map frames, the camera's own gear, curved drives, other lidars

def test_random_map_frame_moves_everything_written_and_nothing_seen(scene_factory):
    plain = scene_factory("junction", 3, "ideal", **TINY)
    moved = scene_factory("junction", 3, "ideal", map_frame="random", **TINY)
    meta = yaml.safe_load((moved / "scene.yaml").read_text())["map_frame"]
    turn = Rotation.from_euler("z", meta["yaw_deg"], degrees=True)
    shift = np.asarray(meta["shift"])
    assert 20.0 <= np.hypot(*shift[:2]) <= 80.0 and abs(shift[2]) <= 3.0

    for name in ("ground_truth.yaml", "initial.yaml"):
        a, b = read_pose(plain / name), read_pose(moved / name)
        np.testing.assert_allclose(b.translation, turn.apply(a.translation) + shift, atol=1e-9)
        np.testing.assert_allclose(b.rotation, turn.as_matrix() @ a.rotation, atol=1e-9)
    for a, b in zip(read_poses(plain / "scans" / "poses.yaml")["scans"],
                    read_poses(moved / "scans" / "poses.yaml")["scans"]):
        np.testing.assert_allclose(b["translation"], turn.apply(a["translation"]) + shift,
                                   atol=1e-9)
        assert rotation_error_deg(Pose(np.zeros(3), b["rotation"]), Pose(
            np.zeros(3), (turn * Rotation.from_quat(a["rotation"])).as_quat())) < 1e-6
    # the sensors saw the same world: images and scans identical
    for name in ("labels.png", "image.png", "scans/000003.ply"):
        assert (plain / name).read_bytes() == (moved / name).read_bytes(), name
    # the map is the same surface, voxelised on the map frame's own grid
    a, b = read_ply(plain / "map.ply"), read_ply(moved / "map.ply")
    dist, idx = cKDTree(b.xyz).query(turn.apply(a.xyz) + shift)
    assert np.median(dist) < 0.03 and np.percentile(dist, 95) < 0.05
    assert (b.label[idx] == a.label).mean() > 0.97
    assert 0.9 < len(b) / len(a) < 1.1


def test_bracket_mast_puts_the_camera_housing_in_the_map_but_not_in_the_image(scene_factory):
    plain = scene_factory("junction", 3, "ideal", **TINY)
    gear = scene_factory("junction", 3, "ideal", mast="bracket", **TINY)
    assert (plain / "labels.png").read_bytes() == (gear / "labels.png").read_bytes()
    truth = read_pose(gear / "ground_truth.yaml")

    def behind_lens(scene: Path) -> int:
        cloud = read_ply(scene / "map.ply")
        pc = truth.transform_points(cloud.xyz)
        # the housing, straight behind the optical centre and in front of the mast
        near = (pc[:, 2] < 0.0) & (pc[:, 2] > -0.2) & (np.hypot(pc[:, 0], pc[:, 1]) < 0.12)
        assert np.all(cloud.label[near] == KITTI_ID["pole"])
        return int(near.sum())

    assert behind_lens(plain) == 0 and behind_lens(gear) >= 3


def test_roundabout_drive_turns_round_the_ring():
    layout = build_layout("roundabout", np.random.default_rng(0))
    _, positions, quats = vehicle_poses(layout, SceneOptions(), np.random.default_rng(1))
    heading = np.unwrap(Rotation.from_quat(quats).as_euler("ZYX")[:, 0])
    assert np.degrees(heading.max() - heading.min()) > 90.0  # a curved lidar path
    radius = np.hypot(positions[:, 0], positions[:, 1])
    assert radius.min() < 20.0  # it passes the island (centred on the map origin)
    cam = np.hypot(*layout.camera_position[:2])
    assert cam < 35.0 and 6.0 <= layout.camera_position[2] - layout.camera_ground <= 9.0


def test_line_count_is_an_option(scene_factory):
    ideal = scene_factory("junction", 3, "ideal", **TINY)
    lines64 = scene_factory("junction", 3, "ideal", lines=64, **TINY)
    assert yaml.safe_load((lines64 / "scene.yaml").read_text())["lidar"]["lines"] == 64
    n128 = len(read_ply(ideal / "scans" / "000003.ply"))
    assert 0.4 * n128 < len(read_ply(lines64 / "scans" / "000003.ply")) < 0.6 * n128


def test_catalogue_covers_every_layout_and_condition():
    entries = catalogue()
    names = [e.name for e in entries]
    assert len(set(names)) == len(names)
    for kind in ("junction", "arterial", "roundabout", "highway"):
        for row in ("ideal", "noisy_labels", "dynamic", "sparse", "lines64", "large"):
            assert f"{kind}-{row}" in names
    by_name = {e.name: e for e in entries}
    assert by_name["roundabout-lines64"].options().lines == 64
    assert by_name["highway-sparse"].variant == "sparse"
    assert by_name["junction-pose_noise"].map_file == "map_noisy_poses.ply"
    assert by_name["junction-large"].options().horizontal_step_deg < SIZES["full"].horizontal_step_deg
    assert by_name["highway-large"].options().voxel < by_name["junction-large"].options().voxel
    assert "--voxel 0.03" in by_name["highway-large"].command()
    for e in entries:
        e.options().validate()
        opts = e.options()
        assert (opts.map_frame, opts.mast, opts.write_bag) == ("random", "bracket", False)
    legacy = catalogue(user_like=False)
    assert {(e.options().map_frame, e.options().mast) for e in legacy} == {("layout", "pole")}
    with pytest.raises(ValueError, match="unknown catalogue row"):
        catalogue(rows=("foggy",))
    with pytest.raises(ValueError, match="unknown map frame"):
        SceneOptions(map_frame="utm").validate()


# ------------------------------------------------------------------------------------------
def test_camera_rig_scene_has_each_camera_its_files_topics_and_a_map_that_fits_it(scene_factory):
    """``--cameras 2``: two named cameras on one map, each with its own files and bag topics; the
    top-level files are the first camera's (single-camera readers still work)."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    scene = scene_factory("junction", 0, "ideal", cameras=2, scans=20, write_scans=False)
    listed = yaml.safe_load((scene / "cameras.yaml").read_text())["cameras"]
    assert [c["name"] for c in listed] == ["northeast", "southeast"]
    truths = {}
    for cam in listed:
        folder = scene / cam["folder"]
        truth = yaml.safe_load((folder / "ground_truth.yaml").read_text())
        assert truth["child_frame_id"] == cam["frame_id"] == f"{cam['name']}_optical"
        truths[cam["name"]] = read_pose(folder / "ground_truth.yaml")
        # the shared map agrees with this camera's own labels at its truth, not 1 m off
        here = scene / "check"
        here.mkdir(exist_ok=True)
        for f in ("labels.png", "camera_info.yaml"):
            (here / f).write_bytes((folder / f).read_bytes())
        (here / "map.ply").unlink(missing_ok=True)
        (here / "map.ply").symlink_to(scene / "map.ply")
        good = agreement(here, truths[cam["name"]])
        off = Pose(truths[cam["name"]].translation + [1.0, 0.0, 0.0],
                   truths[cam["name"]].quaternion)
        assert good > 0.85 and good > agreement(here, off) + 0.05, cam["name"]
    a, b = truths.values()
    assert translation_error(a, b) > 5.0 and rotation_error_deg(a, b) > 30.0
    first = scene / listed[0]["folder"]
    for f in ("labels.png", "image.png"):
        assert (scene / f).read_bytes() == (first / f).read_bytes()
    assert not np.array_equal(read_label_image(first / "labels.png"),
                              read_label_image(scene / listed[1]["folder"] / "labels.png"))

    store = get_typestore(Stores.ROS2_JAZZY)
    seen: dict[str, set] = {}
    with Reader(scene / "bag") as reader:
        assert not any(c.topic.startswith("/camera/") for c in reader.connections)
        for conn, _, raw in reader.messages():
            if not conn.topic.startswith("/lidar/"):
                msg = store.deserialize_cdr(raw, conn.msgtype)
                seen.setdefault(conn.topic, set()).add(msg.header.frame_id)
                if conn.topic == "/southeast/labels":
                    np.testing.assert_array_equal(
                        np.asarray(msg.data).reshape(600, 960),
                        read_label_image(scene / "cameras/southeast/labels.png"))
    assert seen == {t: {c["frame_id"]} for c in listed for t in c["topics"].values()}


def test_camera_rig_is_for_junctions_and_at_most_eight():
    from semcal_tools.scenes.rig import camera_rig

    rng = lambda k: np.random.default_rng(k)  # noqa: E731
    with pytest.raises(ValueError, match="junction"):
        camera_rig(build_layout("arterial", np.random.default_rng(0)), 2, rng)
    layout = build_layout("junction", np.random.default_rng(0))
    with pytest.raises(ValueError, match="2 to 8"):
        camera_rig(layout, 9, rng)
    rig = camera_rig(layout, 8, rng)
    assert len({c.name for c in rig}) == 8
    # the layout's own camera is the rig camera of its corner; outward ones share a corner mast
    assert sum(np.allclose(c.pose.translation, layout.camera_position) for c in rig) == 1
    assert sum(not c.own_mast for c in rig) == 1
