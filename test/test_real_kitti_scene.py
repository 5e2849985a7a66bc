"""``semcal kitti-scene`` on the real KITTI odometry 00 frames: scene contract, ground truth,
label transfer to unlabelled scans, the paper's settings file, and bad input.

Needs ``../shared/data`` beside the checkout (skipped without).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from semcal_ros.cli import main
from semcal_ros.io import files, kitti, ply
from semcal_ros.workflows.kitti_scene import parse_scans
from semcal_ros.engine.labels import INVALID, KITTI_ID
from semcal_ros.engine.params import CalibrationParams

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
KITTI = DATA / "kitti_odometry_00"
V2_WEIGHTS = DATA / "models" / "espnetv2_cityscapes" / "espnetv2_s_2.0_city_1024x512.npz"
pytestmark = pytest.mark.skipif(
    not (KITTI / "image_2" / "000000.png").is_file() or not V2_WEIGHTS.is_file(),
    reason=f"shared real data not found at {DATA} (expected ../shared/data beside the checkout)")


@pytest.fixture(scope="module")
def truth_scene(tmp_path_factory) -> tuple[Path, str]:
    """Frame 0, scans 0-3 (3 without labels), labels projected from scan 0's point labels."""
    out = tmp_path_factory.mktemp("kitti") / "scene"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["kitti-scene", "--kitti", str(KITTI), "--frame", "0", "--scans", "0-3",
                     "--out", str(out), "--truth-labels"]) == 0
    return out, buf.getvalue()


def test_scan_ranges():
    assert parse_scans("0-5") == [0, 1, 2, 3, 4, 5]
    assert parse_scans("4,0,2") == [0, 2, 4]
    assert parse_scans("3") == [3]
    for bad in ("5-2", "a", "-1", "1-"):
        with pytest.raises(ValueError, match="expected e.g. 0-5"):
            parse_scans(bad)


def test_scene_follows_the_contract_and_ground_truth_is_p2_tr(truth_scene):
    out, _ = truth_scene
    for name in ("map.ply", "labels.png", "image.png", "camera_info.yaml", "ground_truth.yaml",
                 "initial.yaml", "calibrator.yaml", "scene.yaml", "scans/poses.yaml",
                 "scans/000003.ply"):
        assert (out / name).is_file(), name
    camera = files.read_camera_info(out / "camera_info.yaml")
    assert (camera.width, camera.height) == (1241, 376)
    assert camera.fx == pytest.approx(718.856) and camera.cx == pytest.approx(607.1928)
    assert files.read_label_image(out / "labels.png").shape == (376, 1241)
    np.testing.assert_array_equal(files.read_rgb_image(out / "image.png"),
                                  files.read_rgb_image(KITTI / "image_2" / "000000.png"))
    # the ground-truth camera projects scan 0 exactly as KITTI's P2 x Tr does
    calib = kitti.read_calib(KITTI / "calib.txt")
    xyz = kitti.read_velodyne(KITTI / "velodyne" / "000000.bin")[:, :3].astype(float)
    xyz = xyz[xyz[:, 0] > 5]  # in front of the car
    uvw = np.c_[xyz, np.ones(len(xyz))] @ (calib["P2"] @ calib["Tr"]).T
    truth = files.read_pose(out / "ground_truth.yaml")
    uv, ok = camera.project(truth.transform_points(xyz))
    assert ok.sum() > 10000
    np.testing.assert_allclose(uv[ok], uvw[ok, :2] / uvw[ok, 2:], atol=0.02)
    # a z-up map frame (the lidar's): the camera looks along +x, the road is 1.73 m below
    assert truth.rotation[:, 2] @ [1, 0, 0] > 0.99
    cloud = ply.read_ply(out / "map.ply")
    road = cloud.label == KITTI_ID["road"]
    assert np.median(cloud.xyz[road, 2]) == pytest.approx(-1.73, abs=0.1)
    assert cloud.label.dtype == np.uint16 and KITTI_ID["car"] in set(cloud.label)  # kept
    initial = files.read_pose(out / "initial.yaml")
    assert 0 < np.linalg.norm(initial.translation - truth.translation) < 2.0


def test_scene_map_is_in_the_lidar_frame_of_the_frame_s_own_scan(truth_scene):
    """Issue 26 item 2: the camera at frame 0 is tied to scan 0, so scan 0 stays where its sensor
    measured it (identity pose) and ICP moved the others around it (the builder's group
    anchoring, which keeps the mean pose, had moved scan 0 by 38 cm on scans 0-5)."""
    from semcal_ros.io.scene_scans import open_scene_scans

    out, _ = truth_scene
    scans = open_scene_scans(out)
    np.testing.assert_allclose(scans.poses[0], np.eye(4), atol=1e-9)
    calib = kitti.read_calib(KITTI / "calib.txt")
    given = kitti.lidar_poses(kitti.read_poses(KITTI / "poses.txt"), calib["Tr"])[:4]
    moved = [np.linalg.norm(scans.poses[i][:3, 3] - given[i][:3, 3]) for i in (1, 2, 3)]
    assert 0.02 < min(moved) and max(moved) < 1.0, moved  # ICP ran, within reason


def test_placed_map_keeps_an_inner_scan_fixed_on_real_scans():
    """The same for a frame in the middle of its scans (frame 2 of 0-3; the data has frame 0's
    image only, so at the placement level): poses relative to scan 2, scan 2 is the anchor and
    keeps the identity, its points are as recorded (de-skew moves the points ahead of the car by
    millimetres), and the map holds them."""
    from scipy.spatial import cKDTree

    from semcal_ros.mapping.placement import placed_map

    seq = kitti.open_sequence(KITTI)
    clouds = [seq.scan(i) for i in range(4)]
    poses = np.linalg.inv(seq.poses[2]) @ seq.poses[:4]
    placed = placed_map(clouds, list(poses), [0.1 * i for i in range(4)], 60.0, 0.1)
    np.testing.assert_allclose(placed.poses[2], np.eye(4), atol=1e-9)
    moved = [np.linalg.norm(placed.poses[i][:3, 3] - poses[i][:3, 3]) for i in (0, 1, 3)]
    assert 0.02 < min(moved) and max(moved) < 1.0, moved
    raw = clouds[2].xyz
    ahead = (raw[:, 0] > 5) & (raw[:, 0] < 40) & (np.abs(raw[:, 1]) < 0.3 * raw[:, 0])
    shift = np.linalg.norm(placed.scans[2].xyz[ahead] - raw[ahead], axis=1)
    assert np.median(shift) < 0.02
    dist, _ = cKDTree(placed.map.xyz).query(raw[ahead], workers=1)
    assert np.median(dist) < 0.06  # within the 0.1 m voxel grid of the map


def test_unlabelled_scan_takes_labels_from_its_labelled_neighbours(truth_scene):
    out, printed = truth_scene
    assert "scan 3: no labels; labelled from the nearest labelled point within 0.3 m" in printed
    meta = yaml.safe_load((out / "scene.yaml").read_text())
    assert meta["labelled_scans"] == [0, 1, 2] and meta["scans"] == [0, 1, 2, 3]
    share = meta["transferred_scans"][3]
    assert 0.8 < share < 1.0  # most of scan 3 sees what scans 0-2 saw; the rest is dropped
    scan3 = ply.read_ply(out / "scans" / "000003.ply")
    raw = kitti.read_velodyne(KITTI / "velodyne" / "000003.bin")
    # the share is of the transferred labels (4 digits); moving points (252-259) then left
    assert share * len(raw) - 0.01 * len(raw) < len(scan3) <= share * len(raw) + 1e-4 * len(raw)
    assert np.all(scan3.label > 0) and np.all(scan3.label < 252)
    # road under the car stays road: the lowest points near the sensor are labelled road
    near_ground = (np.hypot(scan3.xyz[:, 0], scan3.xyz[:, 1]) < 10) & (scan3.xyz[:, 2] < -1.5)
    road_like = np.isin(scan3.label[near_ground], [KITTI_ID[n] for n in
                                                    ("road", "sidewalk", "parking",
                                                     "lane-marking")])
    assert road_like.mean() > 0.8


def test_truth_labels_and_the_paper_settings_file(truth_scene):
    out, printed = truth_scene
    labels = files.read_label_image(out / "labels.png")
    valid = labels != INVALID
    assert 0.2 < valid.mean() < 0.7  # the lidar covers the lower part of the image
    assert not valid[:60].any()  # nothing above the lidar's field of view
    params = CalibrationParams.from_file(out / "calibrator.yaml")
    assert params.loss.crop_top == 0.5
    assert params.render.crop_radius == 75.0
    assert params.labels.as_dict() == {"sidewalk": "road"}
    assert "semcal calibrate --config" in printed


def test_scene_with_a_real_segmenter_reports_its_agreement(tmp_path, capsys, exported):
    model, config = exported["espnetv2"]
    out = tmp_path / "scene"
    assert main(["kitti-scene", "--kitti", str(KITTI), "--scans", "0-1", "--out", str(out),
                 "--model", str(model), "--model-config", str(config),
                 "--threads", "2"]) == 0
    printed = capsys.readouterr().out
    assert "labels from model" in printed and "all            18559   72.6%" in printed
    labels = files.read_label_image(out / "labels.png")
    assert labels.shape == (376, 1241) and (labels == 0).mean() > 0.15


def _kitti_copy(tmp_path: Path, drop: str | None = None, calib: str | None = None) -> Path:
    """A KITTI folder of links to the shared files, with one file left out or replaced."""
    root = tmp_path / "kitti"
    for sub in ("velodyne", "labels", "image_2"):
        (root / sub).mkdir(parents=True)
        for f in (KITTI / sub).iterdir():
            if f"{sub}/{f.name}" != drop:
                (root / sub / f.name).symlink_to(f)
    shutil.copy(KITTI / "poses.txt", root / "poses.txt")
    (root / "calib.txt").write_text(calib if calib is not None
                                    else (KITTI / "calib.txt").read_text())
    return root


def test_bad_input_is_one_clear_line(tmp_path, capsys):
    calib_lines = (KITTI / "calib.txt").read_text().splitlines()
    no_p2 = "\n".join(line for line in calib_lines if not line.startswith("P2"))
    no_tr = "\n".join(line for line in calib_lines if not line.startswith("Tr"))
    not_onnx = tmp_path / "m.onnx"
    not_onnx.write_text("no model")
    config = ROOT / "config" / "models" / "espnetv2_cityscapes.yaml"
    cases = [
        (_kitti_copy(tmp_path / "a", drop="image_2/000000.png"), [],
         "no image_2/000000.png for frame 0"),
        (_kitti_copy(tmp_path / "b", drop="velodyne/000004.bin"), [],
         "no velodyne/000004.bin (scan 4)"),
        (_kitti_copy(tmp_path / "c", calib=no_p2), [], "no 'P2'"),
        (_kitti_copy(tmp_path / "d", calib=no_tr), [], "no 'Tr'"),
        (KITTI, ["--scans", "3-5"], "none of the scans 3-5 has a labels/NNNNNN.label file"),
        (KITTI, ["--scans", "0-99"], "no velodyne/000006.bin"),
    ]
    for root, extra, message in cases:
        argv = ["kitti-scene", "--kitti", str(root), "--out", str(tmp_path / "o"),
                "--truth-labels", *extra]
        assert main(argv) == 1, message
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    assert main(["kitti-scene", "--kitti", str(KITTI), "--out", str(tmp_path / "o"), "--model",
                 str(not_onnx), "--model-config", str(config)]) == 1
    err = capsys.readouterr().err
    assert "not a loadable ONNX model" in err and err.count("\n") == 1, err
    assert not (tmp_path / "o").exists()  # nothing written on bad input
