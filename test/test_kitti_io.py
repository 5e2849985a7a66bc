"""KITTI odometry files and scene-folder scan lists: format edge cases and the real sequence."""

from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from semcal_ros.io import kitti, scene_scans
from semcal_ros.engine.labels import SEMANTIC_KITTI

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti_odometry_00"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"real KITTI data absent ({DATA})")

TR = np.array([[0.0, -1.0, 0.0, -0.01], [0.0, 0.0, -1.0, -0.05], [1.0, 0.0, 0.0, -0.3],
               [0.0, 0.0, 0.0, 1.0]])  # velodyne (x fwd, z up) -> camera (z fwd, y down)


def _write_sequence(root: Path, n_scans: int, n_poses: int, labels: tuple[int, ...] = ()) -> None:
    (root / "velodyne").mkdir(parents=True)
    (root / "labels").mkdir()
    rng = np.random.default_rng(0)
    for i in range(n_scans):
        rng.normal(size=(50, 4)).astype("<f4").tofile(root / "velodyne" / f"{i:06d}.bin")
    for i in labels:
        (np.full(50, 40, "<u4") | (7 << 16)).astype("<u4").tofile(
            root / "labels" / f"{i:06d}.label")
    rows = []
    for i in range(n_poses):  # camera moving along its z axis (forward)
        pose = np.eye(4)
        pose[2, 3] = float(i)
        rows.append(" ".join(f"{v:.6e}" for v in pose[:3].reshape(-1)))
    (root / "poses.txt").write_text("\n".join(rows) + "\n")
    p = " ".join(["1.0"] * 12)
    tr = " ".join(f"{v:.6e}" for v in TR[:3].reshape(-1))
    (root / "calib.txt").write_text(f"P0: {p}\nP1: {p}\nP2: {p}\nP3: {p}\nTr: {tr}\n")


def test_velodyne_and_labels_roundtrip(tmp_path):
    pts = np.arange(40, dtype="<f4").reshape(10, 4)
    pts.tofile(tmp_path / "a.bin")
    np.testing.assert_array_equal(kitti.read_velodyne(tmp_path / "a.bin"), pts)
    raw = np.array([40 | (3 << 16), 10, 252 | (65535 << 16)], "<u4")
    raw.tofile(tmp_path / "a.label")
    labels = kitti.read_labels(tmp_path / "a.label")
    assert labels.dtype == np.uint16 and labels.tolist() == [40, 10, 252]
    np.arange(10, dtype="<f4").tofile(tmp_path / "bad.bin")
    with pytest.raises(ValueError, match="multiple of 16"):
        kitti.read_velodyne(tmp_path / "bad.bin")
    with pytest.raises(ValueError, match="3 labels for 10 points"):
        kitti.read_scan(tmp_path / "a.bin", tmp_path / "a.label")
    with pytest.raises(FileNotFoundError, match="velodyne scan not found"):
        kitti.read_velodyne(tmp_path / "missing.bin")


def test_poses_and_calib_errors(tmp_path):
    (tmp_path / "poses.txt").write_text("1 2 3\n")
    with pytest.raises(ValueError, match="expected 12 numbers"):
        kitti.read_poses(tmp_path / "poses.txt")
    (tmp_path / "calib.txt").write_text("P0: " + " ".join(["1"] * 12) + "\n")
    with pytest.raises(ValueError, match="no 'Tr'"):
        kitti.read_calib(tmp_path / "calib.txt")
    (tmp_path / "calib.txt").write_text("Tr: 1 2 3\n")
    with pytest.raises(ValueError, match="has 3 numbers"):
        kitti.read_calib(tmp_path / "calib.txt")


def test_lidar_poses_are_z_up_in_lidar0(tmp_path):
    cam = np.tile(np.eye(4), (2, 1, 1))
    cam[1, 2, 3] = 2.0  # camera moved 2 m forward (its z)
    lidar = kitti.lidar_poses(cam, TR)
    np.testing.assert_allclose(lidar[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(lidar[1][:3, 3], [2.0, 0.0, 0.0], atol=1e-12)  # forward = lidar x
    in_cam0 = kitti.lidar_poses(cam, TR, frame="cam0")
    p = np.array([1.0, 2.0, 3.0, 1.0])  # the same lidar point lands on the same world point
    np.testing.assert_allclose(TR @ lidar[1] @ p, in_cam0[1] @ p, atol=1e-12)
    with pytest.raises(ValueError, match="unknown KITTI map frame"):
        kitti.lidar_poses(cam, TR, frame="utm")


def test_open_sequence_pairs_scans_poses_labels(tmp_path):
    _write_sequence(tmp_path / "seq", n_scans=3, n_poses=3, labels=(0, 2))
    seq = kitti.open_sequence(tmp_path / "seq")
    assert len(seq) == 3
    assert [p is not None for p in seq.label_paths] == [True, False, True]
    np.testing.assert_allclose(seq.stamps, [0.0, 0.1, 0.2])
    np.testing.assert_allclose(seq.poses[2][:3, 3], [2.0, 0.0, 0.0], atol=1e-9)
    scan = seq.scan(0)
    assert scan.label.tolist() == [40] * 50 and "intensity" in scan.extra
    assert seq.scan(1).label is None
    _write_sequence(tmp_path / "short", n_scans=3, n_poses=2)
    with pytest.raises(ValueError, match="scan 000002 has no pose"):
        kitti.open_sequence(tmp_path / "short")
    assert kitti.is_kitti_sequence(tmp_path / "seq")
    assert not kitti.is_kitti_sequence(tmp_path)


@needs_data
def test_real_sequence_00():
    seq = kitti.open_sequence(DATA)
    assert len(seq) == 6
    assert [p is not None for p in seq.label_paths] == [True] * 3 + [False] * 3
    scan = seq.scan(0)
    assert 100_000 < len(scan) < 130_000
    assert set(np.unique(scan.label).tolist()) <= set(SEMANTIC_KITTI)
    ground = np.isin(scan.label, [40, 48])  # road, sidewalk: below the sensor (z up, 1.73 m)
    assert -2.0 < np.median(scan.xyz[ground, 2]) < -1.5
    step = np.diff(seq.poses[:, :3, 3], axis=0)  # the car drives forward along lidar x
    assert np.all(step[:, 0] > 0.8) and np.all(np.abs(step[:, 2]) < 0.05)


def _poses_doc(child: str, extrinsic: dict | None = None) -> dict:
    doc = {"frame_id": "map", "child_frame_id": child, "scans": [
        {"file": "000000.ply", "stamp": 10.0, "translation": [1.0, 2.0, 3.0],
         "rotation": [0.0, 0.0, float(np.sin(np.pi / 4)), float(np.cos(np.pi / 4))]}]}
    if extrinsic:
        doc["lidar_extrinsic"] = extrinsic
    return doc


def test_scene_scan_poses_vehicle_frame(tmp_path):
    path = tmp_path / "scans" / "poses.yaml"
    path.parent.mkdir()
    path.write_text(yaml.safe_dump(_poses_doc("base_link")))
    with pytest.raises(ValueError, match="no 'lidar_extrinsic'"):
        scene_scans.read_scan_poses(path)
    ext = {"translation": [1.0, 0.0, 2.0], "rotation": [0.0, 0.0, 0.0, 1.0]}
    path.write_text(yaml.safe_dump(_poses_doc("base_link", ext)))
    poses = scene_scans.read_scan_poses(path)
    # vehicle at (1, 2, 3) turned 90 deg left: the lidar 1 m ahead of it sits at (1, 3, 5)
    np.testing.assert_allclose(poses.poses[0][:3, 3], [1.0, 3.0, 5.0], atol=1e-12)
    assert poses.files[0] == path.parent / "000000.ply" and poses.stamps[0] == 10.0
    assert scene_scans.is_scene_folder(tmp_path)


def test_scene_scan_poses_roundtrip_and_errors(tmp_path):
    rng = np.random.default_rng(1)
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, :3] = Rotation.random(3, random_state=rng).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(3, 3))
    path = tmp_path / "poses.yaml"
    scene_scans.write_scan_poses(path, ["a.ply", "b.ply", "c.ply"], np.arange(3.0), poses)
    back = scene_scans.read_scan_poses(path)
    np.testing.assert_allclose(back.poses, poses, atol=1e-9)
    doc = _poses_doc("lidar")
    doc["scans"][0]["rotation"] = [0.0, 0.0, 0.0, 2.0]
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ValueError, match=r"scans\[0\]: rotation is not a unit quaternion"):
        scene_scans.read_scan_poses(path)
    del doc["scans"][0]["stamp"]
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ValueError, match="no 'stamp'"):
        scene_scans.read_scan_poses(path)
    with pytest.raises(FileNotFoundError, match="scan poses file not found"):
        scene_scans.open_scene_scans(tmp_path / "nowhere")
