"""``semcal real-scene`` on each source format of ``../shared/data``: KITTI odometry (.bin +
calib.txt, SemanticKITTI labels, poses.txt), KITTI object (.bin + P2/R0_rect/Tr_velo_to_cam),
PJLab (binary_compressed PCD + the two JSON files; ascii PCD; K/D/T calib.txt), a .ply scan
through the generic form (camera_info YAML + T_cam_lidar YAML); the written scene folder, the
ground truth against the files' extrinsic, the derived calibrator.yaml, the parked/moving vehicle
policy, and bad input (one line, exit 1, nothing written).

Needs ``../shared/data`` beside the checkout (skipped without).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from semcal_ros.cli import main
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.io import files, kitti, ply
from semcal_ros.io.calibration_files import write_extrinsic_yaml
from semcal_ros.io.lidar_scans import read_lidar_scan
from semcal_ros.workflows.scene_labels import mark_moved_vehicles
from semcal_ros.engine.labels import (CITYSCAPES_ID, INVALID, KITTI_ID, MOVING_KITTI, VEHICLE_KITTI,
                               LabelMapping)
from semcal_ros.engine.params import CalibrationParams

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
KITTI = DATA / "kitti_odometry_00"
OBJECT = DATA / "kitti_object"
PJLAB = DATA / "pjlab_lidar_camera"
needs_data = pytest.mark.skipif(
    not (KITTI / "image_2" / "000000.png").is_file() or not (PJLAB / "ours1").is_dir(),
    reason=f"shared real data not found at {DATA} (expected ../shared/data beside the checkout)")


def orthonormal(r: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(r)
    return u @ vt


def as_matrix(pose) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = pose.rotation, pose.translation
    return m


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    code = main(["real-scene", *map(str, argv)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def height_labels(xyz: np.ndarray) -> np.ndarray:
    """A crude labelling for format tests: lowest band road, above 2.5 m vegetation, else
    building (the labels' content is not what these tests check)."""
    ground = np.percentile(xyz[:, 2], 5)
    return np.where(xyz[:, 2] < ground + 0.3, KITTI_ID["road"],
                    np.where(xyz[:, 2] > ground + 2.5, KITTI_ID["vegetation"],
                             KITTI_ID["building"])).astype(np.uint16)


def ground_band_labels(xyz: np.ndarray) -> np.ndarray:
    """Road within 0.3 m of the ground under the lidar (the median height of the returns more
    than 15 deg down, all ground on PJLab's frames), building above: a lidar's near ground
    rings labelled as a ground segmenter would."""
    steep = np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])) < -np.radians(15.0)
    ground = np.median(xyz[steep, 2])
    return np.where(xyz[:, 2] < ground + 0.3, KITTI_ID["road"],
                    KITTI_ID["building"]).astype(np.uint16)


def check_scene(out: Path, width: int, height: int, t_cam_lidar: np.ndarray) -> dict:
    """The contract's files, labels.png size, ground truth = inverse of the extrinsic (1e-6)."""
    for name in ("map.ply", "labels.png", "image.png", "camera_info.yaml", "ground_truth.yaml",
                 "initial.yaml", "calibrator.yaml", "scene.yaml", "scans/poses.yaml"):
        assert (out / name).is_file(), name
    assert files.read_label_image(out / "labels.png").shape == (height, width)
    camera = files.read_camera_info(out / "camera_info.yaml")
    assert (camera.width, camera.height) == (width, height)
    truth = as_matrix(files.read_pose(out / "ground_truth.yaml"))
    np.testing.assert_allclose(truth @ t_cam_lidar, np.eye(4), atol=1e-6)
    initial = files.read_pose(out / "initial.yaml")
    assert 0 < np.linalg.norm(initial.translation - truth[:3, 3]) < 2.0
    cloud = ply.read_ply(out / "map.ply")
    assert len(cloud) > 10000 and cloud.label.dtype == np.uint16
    assert not np.isin(cloud.label, MOVING_KITTI).any()
    return yaml.safe_load((out / "scene.yaml").read_text())


@needs_data
def test_kitti_odometry_two_scans_semantickitti_parked_cars_stay(tmp_path, capsys):
    out = tmp_path / "scene"
    scans = [KITTI / "velodyne" / f"00000{i}.bin" for i in (0, 1)]
    code, printed, err = run(["--image", KITTI / "image_2" / "000000.png", "--scans", *scans,
                              "--calib", KITTI / "calib.txt", "--poses", KITTI / "poses.txt",
                              "--cloud-labels", "semantickitti", "--truth-labels",
                              "--out", out], capsys)
    assert code == 0, err
    calib = kitti.read_calib(KITTI / "calib.txt")
    k = calib["P2"][:, :3]
    offset = np.eye(4)
    offset[:3, 3] = np.linalg.solve(k, calib["P2"][:, 3])
    tr = calib["Tr"].copy()
    tr[:3, :3] = orthonormal(tr[:3, :3])
    meta = check_scene(out, 1241, 376, offset @ tr)
    assert meta["kind"] == "real" and meta["cloud_labels"] == "SemanticKITTI label files"
    cloud = ply.read_ply(out / "map.ply")
    assert np.isin(cloud.label, VEHICLE_KITTI).mean() > 0.02  # parked cars stay
    raw = kitti.read_labels(KITTI / "labels" / "000000.label")
    assert np.isin(raw, MOVING_KITTI).any()  # frame 0 has moving points: they were removed
    params = CalibrationParams.from_file(out / "calibrator.yaml")
    assert params.labels.parked_vehicles and params.labels.as_dict() == {"sidewalk": "road"}
    # HDL-64E: nothing above ~+2 deg (near poles and signs reach higher), seen from the
    # initial pose, less a 5 deg pitch margin
    assert 0.02 < params.loss.crop_top < 0.3
    # the HDL-64E's rings lie a fraction of a degree apart on the ground: no blind zone
    assert params.loss.blind_rows == 0.0 and "loss.blind_rows" not in printed
    gap = float(printed.split("near ground rings ahead: at most ")[1].split(" deg")[0])
    assert 0.1 < gap < 1.0, printed
    labels = files.read_label_image(out / "labels.png")
    rows = np.flatnonzero((labels != INVALID).any(axis=1))
    assert rows.min() > params.loss.crop_top * 376  # the crop leaves every labelled row in
    assert (labels == CITYSCAPES_ID["car"]).mean() > 0.03  # the truth-label image shows cars
    # the second scan sits ahead in the first scan's frame: poses.txt says 0.86 m, the scans
    # registered to each other (de-skew + ICP, the poses scans/ holds) 0.68 m (docs/mapping.md)
    poses = yaml.safe_load((out / "scans" / "poses.yaml").read_text())["scans"]
    np.testing.assert_allclose(poses[0]["translation"], 0, atol=1e-9)
    assert 0.6 < poses[1]["translation"][0] < 0.8, poses[1]["translation"]
    assert "map label shares: vegetation" in printed and "image label shares" in printed

    removed = tmp_path / "no_vehicles"
    code, _, err = run(["--image", KITTI / "image_2" / "000000.png", "--scans", scans[0],
                        "--calib", KITTI / "calib.txt", "--cloud-labels", "semantickitti",
                        "--truth-labels", "--remove-vehicles", "--out", removed], capsys)
    assert code == 0, err
    assert not np.isin(ply.read_ply(removed / "map.ply").label, VEHICLE_KITTI).any()
    assert not CalibrationParams.from_file(removed / "calibrator.yaml").labels.parked_vehicles


@needs_data
def test_kitti_scans_without_poses_are_registered_to_each_other(tmp_path, capsys):
    """Issue 41 item 3: three KITTI scans and no poses file: each is registered to the one
    before it, then placed as given poses are (de-skew + multiway ICP, scan 0 fixed). The car
    moves ~0.7 m per sweep straight ahead (ICP's figure with poses.txt: the test above)."""
    out = tmp_path / "scene"
    scans = [KITTI / "velodyne" / f"00000{i}.bin" for i in (0, 1, 2)]
    code, printed, err = run(["--image", KITTI / "image_2" / "000000.png", "--scans", *scans,
                              "--calib", KITTI / "calib.txt", "--cloud-labels", "semantickitti",
                              "--truth-labels", "--out", out], capsys)
    assert code == 0, err
    poses = yaml.safe_load((out / "scans" / "poses.yaml").read_text())["scans"]
    np.testing.assert_allclose(poses[0]["translation"], 0, atol=1e-9)
    for k, (lo, hi) in ((1, (0.6, 0.8)), (2, (1.25, 1.6))):
        x, y, z = poses[k]["translation"]
        assert lo < x < hi and abs(y) < 0.1 and abs(z) < 0.1, poses[k]["translation"]
    meta = yaml.safe_load((out / "scene.yaml").read_text())
    assert any("registered scan to scan" in n for n in meta["cloud_label_notes"]), meta
    assert len(ply.read_ply(out / "map.ply")) > len(kitti.read_velodyne(scans[0])) // 4


@needs_data
def test_kitti_object_calib_with_r0_rect_and_a_label_file(tmp_path, capsys):
    frame = OBJECT / "tr_000000"
    scan = kitti.read_velodyne(frame.with_suffix(".bin"))
    label_file = tmp_path / "tr_000000.label"
    height_labels(scan[:, :3].astype(float)).astype("<u4").tofile(label_file)
    out = tmp_path / "scene"
    code, printed, err = run(["--image", frame.with_suffix(".png"), "--scans",
                              frame.with_suffix(".bin"), "--calib", frame.with_suffix(".txt"),
                              "--cloud-labels", label_file, "--truth-labels", "--out", out],
                             capsys)
    assert code == 0, err
    entries = {line.split(":")[0]: np.array(line.split(":")[1].split(), float)
               for line in frame.with_suffix(".txt").read_text().splitlines() if ":" in line}
    p2 = entries["P2"].reshape(3, 4)
    r0, tr = np.eye(4), np.eye(4)
    r0[:3, :3] = orthonormal(entries["R0_rect"].reshape(3, 3))
    tr[:3, :] = entries["Tr_velo_to_cam"].reshape(3, 4)
    tr[:3, :3] = orthonormal(tr[:3, :3])
    offset = np.eye(4)
    offset[:3, 3] = np.linalg.solve(p2[:, :3], p2[:, 3])
    h, w = files.read_rgb_image(frame.with_suffix(".png")).shape[:2]
    check_scene(out, w, h, offset @ r0 @ tr)
    # the ground truth projects as KITTI's own P2 R0_rect Tr_velo_to_cam chain does
    xyz = scan[scan[:, 0] > 5, :3].astype(float)
    r0_raw, tr_raw = np.eye(4), np.eye(4)
    r0_raw[:3, :3] = entries["R0_rect"].reshape(3, 3)
    tr_raw[:3, :] = entries["Tr_velo_to_cam"].reshape(3, 4)
    uvw = np.c_[xyz, np.ones(len(xyz))] @ (p2 @ r0_raw @ tr_raw).T
    camera = files.read_camera_info(out / "camera_info.yaml")
    uv, ok = camera.project(files.read_pose(out / "ground_truth.yaml").transform_points(xyz))
    assert ok.sum() > 5000
    np.testing.assert_allclose(uv[ok], uvw[ok, :2] / uvw[ok, 2:], atol=0.05)
    assert "label files tr_000000.label" in printed


@needs_data
def test_pjlab_binary_compressed_pcd_and_json_pair(tmp_path, capsys):
    folder = PJLAB / "auto_calib"
    cloud = read_lidar_scan(folder / "calib.pcd")
    assert len(cloud) == 85546 and {"intensity", "ring", "timestamp"} <= set(cloud.extra)
    assert 0 < cloud.extra["intensity"].max() <= 255
    labelled = tmp_path / "calib_labelled.ply"
    ply.write_ply(labelled, LabelledCloud(cloud.xyz, height_labels(cloud.xyz)))
    out = tmp_path / "scene"
    code, _, err = run(["--image", folder / "calib.png", "--scans", folder / "calib.pcd",
                        "--calib", folder / "center_camera-intrinsic.json",
                        folder / "top_center_lidar-to-center_camera-extrinsic.json",
                        "--cloud-labels", labelled, "--truth-labels", "--out", out], capsys)
    assert code == 0, err
    import json

    ext = json.loads((folder / "top_center_lidar-to-center_camera-extrinsic.json").read_text())
    t = np.array(next(iter(ext.values()))["param"]["sensor_calib"]["data"], float)
    t[:3, :3] = orthonormal(t[:3, :3])
    check_scene(out, 1920, 1200, t)
    camera = files.read_camera_info(out / "camera_info.yaml")
    np.testing.assert_allclose(camera.d, [-0.102933, -0.040925, 0.00057951, -0.00419933,
                                          0.429959])
    assert camera.fx == pytest.approx(2117.31) and camera.cy == pytest.approx(656.457)
    scan = ply.read_ply(out / "scans" / "000000.ply")
    assert len(scan) == 85546 and "intensity" in scan.extra  # the scan keeps its fields


@needs_data
def test_pjlab_ascii_pcd_json_size_mismatch_and_override(tmp_path, capsys):
    folder = PJLAB / "manual_calib"
    cloud = read_lidar_scan(folder / "0.pcd")
    label_file = tmp_path / "0.label"
    height_labels(cloud.xyz).astype("<u4").tofile(label_file)
    argv = ["--image", folder / "0.png", "--scans", folder / "0.pcd", "--calib",
            folder / "center_camera-intrinsic.json",
            folder / "top_center_lidar-to-center_camera-extrinsic.json",
            "--cloud-labels", label_file, "--truth-labels", "--out", tmp_path / "scene"]
    code, _, err = run(argv, capsys)  # the JSON says 1920x1080, the image is 1920x1200
    assert code == 1 and "calibration is for 1920x1080 images, the image is 1920x1200" in err
    assert err.count("\n") == 1 and not (tmp_path / "scene").exists()
    code, _, err = run(argv + ["--ignore-calib-size"], capsys)
    assert code == 0, err
    assert files.read_label_image(tmp_path / "scene" / "labels.png").shape == (1200, 1920)


@needs_data
def test_pjlab_kdt_calib_txt(tmp_path, capsys):
    folder = PJLAB / "ours1"
    cloud = read_lidar_scan(folder / "calib.pcd")
    label_file = tmp_path / "calib.label"
    ground_band_labels(cloud.xyz).astype("<u4").tofile(label_file)
    out = tmp_path / "scene"
    code, _, err = run(["--image", folder / "calib.jpg", "--scans", folder / "calib.pcd",
                        "--calib", folder / "calib.txt", "--cloud-labels", label_file,
                        "--labels", tmp_path / "missing.png", "--out", out], capsys)
    assert code == 1 and "label image not found" in err and err.count("\n") == 1
    code, _, err = run(["--image", folder / "calib.jpg", "--scans", folder / "calib.pcd",
                        "--calib", folder / "calib.txt", "--cloud-labels", label_file,
                        "--truth-labels", "--blind-rows", "0.7", "--out", out], capsys)
    assert code == 1 and "--blind-rows must be in [0, 0.5], got 0.7" in err
    assert err.count("\n") == 1 and not out.exists()
    code, printed, err = run(["--image", folder / "calib.jpg", "--scans", folder / "calib.pcd",
                              "--calib", folder / "calib.txt", "--cloud-labels", label_file,
                              "--truth-labels", "--out", out], capsys)
    assert code == 0, err
    # a top-mounted lidar whose lowest rings lie 6 and 5 deg apart (-24.9, -18.9, -14 deg): its
    # blind zone is found in the data and left out of the loss by the scene's calibrator.yaml
    assert "near ground rings ahead: at most 6.0 deg apart -> loss.blind_rows 0.2" in printed
    assert CalibrationParams.from_file(out / "calibrator.yaml").loss.blind_rows == 0.2
    values = {line.split(":")[0]: np.array(line.split(":")[1].split(), float)
              for line in (folder / "calib.txt").read_text().splitlines() if ":" in line}
    t = np.eye(4)
    t[:3, :] = values["T"].reshape(3, 4)
    t[:3, :3] = orthonormal(t[:3, :3])
    check_scene(out, 1920, 1200, t)
    camera = files.read_camera_info(out / "camera_info.yaml")
    np.testing.assert_allclose(camera.d, [*values["D"], 0.0])
    np.testing.assert_allclose(camera.k.ravel(), values["K"])


@needs_data
def test_generic_form_with_a_ply_scan_camera_info_and_extrinsic_yaml(tmp_path, capsys):
    """The contract form other tools call: .ply scan, camera_info YAML, T_cam_lidar YAML."""
    scan = kitti.read_scan(KITTI / "velodyne" / "000000.bin",
                           KITTI / "labels" / "000000.label")
    keep = (scan.xyz[:, 0] > 0) & (np.hypot(scan.xyz[:, 0], scan.xyz[:, 1]) < 40)
    ply_path = tmp_path / "scan.ply"
    ply.write_ply(ply_path, scan.select(keep))
    calib = kitti.read_calib(KITTI / "calib.txt")
    camera, t_cam_lidar = kitti.camera_from_calib(calib, 1241, 376)
    files.write_camera_info(tmp_path / "camera_info.yaml", camera)
    write_extrinsic_yaml(tmp_path / "T.yaml", t_cam_lidar)
    labels = np.full((376, 1241), CITYSCAPES_ID["road"], np.uint8)
    files.write_label_image(tmp_path / "labels.png", labels)
    out = tmp_path / "scene"
    code, _, err = run(["--image", KITTI / "image_2" / "000000.png", "--scans", ply_path,
                        "--camera-info", tmp_path / "camera_info.yaml",
                        "--extrinsic", tmp_path / "T.yaml", "--cloud-labels", ply_path,
                        "--labels", tmp_path / "labels.png", "--out", out], capsys)
    assert code == 0, err
    check_scene(out, 1241, 376, t_cam_lidar)
    np.testing.assert_array_equal(files.read_label_image(out / "labels.png"), labels)
    moving = np.isin(scan.label, MOVING_KITTI)  # moving points leave the scans too
    assert len(ply.read_ply(out / "scans" / "000000.ply")) == (keep & ~moving).sum()


@needs_data
def test_geometric_labels_on_a_real_scan(tmp_path, capsys):
    pytest.importorskip("semcal_ros.segmentation.geometric",
                        reason="the geometric labeller is not on this checkout")
    out = tmp_path / "scene"
    frame = OBJECT / "tr_000001"
    code, printed, err = run(["--image", frame.with_suffix(".png"), "--scans",
                              frame.with_suffix(".bin"), "--calib", frame.with_suffix(".txt"),
                              "--cloud-labels", "geometric", "--truth-labels", "--out", out],
                             capsys)
    assert code == 0, err
    cloud = ply.read_ply(out / "map.ply")
    ground = np.isin(cloud.label, [KITTI_ID[n] for n in ("road", "sidewalk", "terrain",
                                                         "parking")])
    assert ground.mean() > 0.2 and "point labels: geometric labeller" in printed


def test_bad_inputs_are_one_line(tmp_path, capsys):
    image = tmp_path / "image.png"
    files.write_rgb_image(image, np.zeros((100, 200, 3), np.uint8))
    scan = tmp_path / "scan.ply"
    xyz = np.random.default_rng(0).uniform(-20, 20, (500, 3))
    ply.write_ply(scan, LabelledCloud(xyz, np.full(500, KITTI_ID["building"], np.uint16)))
    from semcal_ros.engine.camera import CameraModel

    files.write_camera_info(tmp_path / "cam.yaml", CameraModel.from_fov(200, 100, 90.0))
    files.write_camera_info(tmp_path / "big.yaml", CameraModel.from_fov(400, 200, 90.0))
    t = np.eye(4)
    t[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]
    write_extrinsic_yaml(tmp_path / "T.yaml", t)
    (tmp_path / "bad_T.yaml").write_text("T_cam_lidar: [[1, 2], [3, 4]]\n")
    (tmp_path / "scan.xyz").write_text("1 2 3\n")
    (tmp_path / "calib.cfg").write_text("P2: 1 2 3\n")
    (tmp_path / "calib.txt").write_text("foo: 1 2 3\n")
    files.write_label_image(tmp_path / "small.png", np.zeros((50, 100), np.uint8))
    base = ["--image", image, "--scans", scan, "--camera-info", tmp_path / "cam.yaml",
            "--extrinsic", tmp_path / "T.yaml", "--cloud-labels", scan, "--out",
            tmp_path / "out"]

    def argv(**change) -> list:
        out = list(base)
        for key, value in change.items():
            flag = "--" + key.replace("_", "-")
            if flag in out:
                i = out.index(flag)
                if value is None:
                    del out[i:i + 2]
                else:
                    out[i + 1] = value
            else:
                out += [flag, value]
        return out + (["--truth-labels"] if "labels" not in change else [])

    cases = [
        (argv(scans=tmp_path / "missing.ply"), "scan not found"),
        (argv(scans=tmp_path / "scan.xyz"), "unknown scan format '.xyz'"),
        (argv(image=tmp_path / "missing.png"), "image not found"),
        (argv(camera_info=tmp_path / "big.yaml"), "camera_info is 400x200, the image"),
        (argv(labels=tmp_path / "small.png"), "label image is 100x50, the camera image 200x100"),
        (argv(extrinsic=tmp_path / "bad_T.yaml"), "expected 12 (3x4) or 16 (4x4)"),
        (argv(camera_info=None, extrinsic=None, calib=tmp_path / "calib.cfg"),
         "unknown calibration format '.cfg'"),
        (argv(camera_info=None, extrinsic=None, calib=tmp_path / "calib.txt"),
         "unknown calibration format (expected KITTI"),
        (argv(cloud_labels=tmp_path / "missing.label"), "point label file not found"),
        (argv(scans=[scan, scan][0]) + ["--poses", tmp_path / "missing.yaml"],
         "poses file not found"),
        (argv(extrinsic=None), "--truth-labels needs the true extrinsic"),
    ]
    for args, message in cases:
        code, _, err = run(args, capsys)
        assert code == 1, message
        assert message in err and err.count("\n") == 1, (message, err)
        assert not (tmp_path / "out").exists(), message


def test_two_scans_that_cannot_be_registered_need_poses(tmp_path, capsys):
    image = tmp_path / "image.png"
    files.write_rgb_image(image, np.zeros((100, 200, 3), np.uint8))
    rng = np.random.default_rng(0)
    scan, other = tmp_path / "a.ply", tmp_path / "b.ply"  # two scans of places 500 m apart
    ply.write_ply(scan, LabelledCloud(rng.uniform(-20, 20, (500, 3)), np.ones(500, np.uint16)))
    ply.write_ply(other, LabelledCloud(rng.uniform(480, 520, (500, 3)), np.ones(500, np.uint16)))
    from semcal_ros.engine.camera import CameraModel

    files.write_camera_info(tmp_path / "cam.yaml", CameraModel.from_fov(200, 100, 90.0))
    write_extrinsic_yaml(tmp_path / "T.yaml", np.eye(4))
    files.write_label_image(tmp_path / "l.png", np.zeros((100, 200), np.uint8))
    code, _, err = run(["--image", image, "--scans", scan, other, "--camera-info",
                        tmp_path / "cam.yaml", "--extrinsic", tmp_path / "T.yaml",
                        "--cloud-labels", scan, other, "--labels", tmp_path / "l.png",
                        "--out", tmp_path / "out"], capsys)
    assert code == 1 and "scan 2 could not be registered to scan 1" in err and "--poses" in err
    assert err.count("\n") == 1


def test_moved_vehicles_are_relabelled_parked_ones_kept():
    rng = np.random.default_rng(1)
    ground = np.c_[rng.uniform(-20, 20, (4000, 2)), np.full(4000, -1.7)]

    def car(x: float, y: float) -> np.ndarray:
        return np.c_[rng.uniform(x - 2, x + 2, 300), rng.uniform(y - 0.9, y + 0.9, 300),
                     rng.uniform(-1.7, -0.3, 300)]

    def scan(moving_x: float) -> LabelledCloud:
        xyz = np.vstack([ground, car(8, 4), car(moving_x, -3)])
        label = np.r_[np.full(4000, KITTI_ID["road"]), np.full(600, KITTI_ID["car"])]
        return LabelledCloud(xyz, label.astype(np.uint16))

    clouds = [scan(0.0), scan(4.0), scan(8.0)]
    counts = mark_moved_vehicles(clouds, [np.eye(4)] * 3)
    assert counts == [1, 1, 1]  # each scan's moving car is elsewhere in its farthest scan
    first = clouds[0].label
    assert np.all(first[4000:4300] == KITTI_ID["car"])  # the parked car stays
    assert np.all(first[4300:] == KITTI_ID["moving-car"])  # the moving one is marked


def test_parked_vehicle_mapping_counts_cars_and_drops_moving_ones():
    default, parked = LabelMapping(), LabelMapping().with_parked_vehicles()
    car, moving = KITTI_ID["car"], KITTI_ID["moving-car"]
    assert default.lidar_lut()[car] == INVALID and default.image_lut()[13] == INVALID
    assert parked.lidar_lut()[car] == CITYSCAPES_ID["car"]
    assert parked.image_lut()[CITYSCAPES_ID["car"]] == CITYSCAPES_ID["car"]
    assert parked.lidar_lut()[moving] == INVALID  # moving vehicles never enter a map
    assert parked.image_lut()[CITYSCAPES_ID["person"]] == INVALID  # people stay dynamic


def ground_rings(elevations_deg, height: float = 2.0, azimuth_deg=(-60.0, 60.0)) -> LabelledCloud:
    """Flat road sampled by lidar rings at the given elevations, seen from ``height`` m."""
    az = np.radians(np.arange(*azimuth_deg, 0.2))
    xyz = []
    for e in elevations_deg:
        r = height / np.tan(np.radians(-e))
        xyz.append(np.c_[r * np.cos(az), r * np.sin(az), np.full(len(az), -height)])
    xyz = np.vstack(xyz)
    return LabelledCloud(xyz, np.full(len(xyz), KITTI_ID["road"], np.uint16))


def test_the_blind_zone_is_found_where_the_near_ground_rings_lie_far_apart():
    from semcal_ros.engine.camera import CameraModel
    from semcal_ros.engine.pose import Pose
    from semcal_ros.workflows.real_scene import (RealSceneOptions, derived_engine_settings,
                                                 near_ground_gap_deg)

    k = np.array([[2100.0, 0, 960], [0, 2100.0, 600], [0, 0, 1]])
    camera = CameraModel(1920, 1200, k, np.zeros(5))
    ahead = Pose.from_body_rpy_deg([0.1, 0.0, -0.1], [0.0, 8.0, 0.0])  # looking along +x, down
    behind = Pose.from_body_rpy_deg([0.1, 0.0, -0.1], [0.0, 8.0, 180.0])
    dense = ground_rings(np.arange(-24.9, -2.0, 0.4))  # an HDL-64E's lower block
    # PJLab's lidar: -24.9, -18.9, then 1 deg apart from -14 to -6 (docs/segmentation.md)
    sparse = ground_rings([-24.9, -18.9, *np.arange(-14.0, -5.5, 1.0)])
    assert near_ground_gap_deg(dense, camera, ahead) == pytest.approx(0.4, abs=0.01)
    assert near_ground_gap_deg(sparse, camera, ahead) == pytest.approx(6.0, abs=0.01)
    # sparse rings behind the camera, dense ones ahead: what the camera looks at decides
    mixed = LabelledCloud(np.vstack([dense.xyz, -sparse.xyz * [1, 1, -1]]),
                          np.concatenate([dense.label, sparse.label]))
    assert near_ground_gap_deg(mixed, camera, ahead) == pytest.approx(0.4, abs=0.01)
    assert near_ground_gap_deg(mixed, camera, behind) == pytest.approx(6.0, abs=0.01)
    # no ground in view (too few points to judge): no blind zone
    few = LabelledCloud(sparse.xyz[:20], sparse.label[:20])
    assert near_ground_gap_deg(few, camera, ahead) == 0.0

    def blind(cloud, **options):
        engine = derived_engine_settings(cloud, camera, ahead, RealSceneOptions(**options))
        return engine["loss"].get("blind_rows", 0.0)

    assert blind(dense) == 0.0 and blind(sparse) == 0.2
    assert blind(sparse, blind_rows=0.0) == 0.0 and blind(dense, blind_rows=0.3) == 0.3
