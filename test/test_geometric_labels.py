"""The geometric point labeller: real KITTI scans against SemanticKITTI (scan 1, held out of the
forest's training), a synthetic scan against its true labels, the CLI's --method geometric, the
cloud_segmenter node with method geometric as a process over DDS, and bad input in one line.

Floors are set below the measured figures (docs/segmentation.md, benchmarks/geometric_labeller.py)
so that a change that breaks a class fails, while the labeller may still be improved.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from semcal_ros.engine.labels import KITTI_ID, LabelMapping
from semcal_ros.segmentation.geometric import GeometricParams, label_scan, point_agreement

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO.parent / "shared" / "data" / "kitti_odometry_00"
needs_kitti = pytest.mark.skipif(not (KITTI / "labels" / "000000.label").is_file(),
                                 reason=f"real KITTI data not found at {KITTI}")

#: Recall floors per class on KITTI 00 scan 1 (aligned classes; scan 0 trained the forest, so
#: scan 1 is held out; measured figures in docs/segmentation.md are higher).
KITTI_FLOORS = {"ground": 0.95, "road": 0.85, "sidewalk": 0.75, "building": 0.85,
                "vegetation": 0.85, "car": 0.85, "pole": 0.55}


def kitti_scan(index: int = 0):
    from semcal_ros.io import kitti

    cloud = kitti.read_scan(KITTI / "velodyne" / f"{index:06d}.bin")
    reference = np.fromfile(KITTI / "labels" / f"{index:06d}.label", np.uint32) & 0xFFFF
    return cloud.xyz, cloud.extra["intensity"], reference


@needs_kitti
def test_kitti_scan_reaches_the_floors_per_class():
    xyz, intensity, reference = kitti_scan(1)
    labels = label_scan(xyz, intensity)
    assert labels.dtype == np.uint16 and labels.shape == (len(xyz),)
    result = point_agreement(labels, reference)
    for name, floor in KITTI_FLOORS.items():
        precision, recall, n_ref, _ = result.per_class[name]
        assert n_ref > 100, name
        assert recall >= floor, f"{name}: recall {recall:.3f} < {floor}\n{result.table()}"
        assert precision >= 0.7, f"{name}: precision {precision:.3f}\n{result.table()}"
    assert result.overall >= 0.85, result.table()
    merged = point_agreement(labels, reference, LabelMapping(dynamic=(), merge={"sidewalk": "road"}))
    assert merged.overall >= 0.9, merged.table()
    # no class the labeller never emits
    emitted = set(np.unique(labels).tolist())
    assert emitted <= {0, KITTI_ID["road"], KITTI_ID["sidewalk"], KITTI_ID["terrain"],
                       KITTI_ID["building"], KITTI_ID["vegetation"], KITTI_ID["trunk"],
                       KITTI_ID["pole"], KITTI_ID["traffic-sign"], KITTI_ID["car"],
                       KITTI_ID["fence"]}, emitted


@needs_kitti
def test_kitti_scan_labels_do_not_depend_on_the_mount_height():
    """The ground is estimated, not assumed: the same scan lifted by 3 m (a roadside mast) gets
    nearly the same labels."""
    xyz, intensity, reference = kitti_scan(1)
    low = label_scan(xyz, intensity)
    high = label_scan(xyz - np.array([0.0, 0.0, 3.0], np.float32), intensity)
    assert (low == high).mean() > 0.9
    assert point_agreement(high, reference).per_class["ground"][1] > 0.95
    # the intensity channel is not used: none gives the same labels
    np.testing.assert_array_equal(label_scan(xyz), low)


@needs_kitti
def test_smoothing_and_min_share_do_what_they_say():
    """Without smoothing the labels are noisier but close; a high min_share leaves the
    uncertain voxels unlabeled and keeps the rest as they were."""
    xyz, intensity, reference = kitti_scan(1)
    smooth = label_scan(xyz, intensity)
    raw = label_scan(xyz, intensity, GeometricParams(smoothing_neighbours=0))
    assert 0.9 < (raw == smooth).mean() < 1.0
    strict = label_scan(xyz, intensity, GeometricParams(min_share=0.6))
    dropped = (strict == 0) & (smooth != 0)
    assert 0.01 < dropped.mean() < 0.5
    np.testing.assert_array_equal(strict[strict != 0], smooth[strict != 0])
    kept = strict != 0
    assert (point_agreement(strict[kept], reference[kept]).overall
            > point_agreement(smooth, reference).overall)


def test_synthetic_scan_against_its_true_labels(scene_factory):
    from semcal_ros.io.ply import read_ply

    scene = scene_factory("junction", 0, "ideal", scans=3, lines=64, write_bag=False)
    cloud = read_ply(sorted((scene / "scans").glob("*.ply"))[1])
    labels = label_scan(cloud.xyz, cloud.extra.get("intensity"))
    result = point_agreement(labels, cloud.label)
    assert result.per_class["ground"][1] > 0.9, result.table()
    assert result.per_class["ground"][0] > 0.9, result.table()
    assert result.overall > 0.5, result.table()


def test_nan_and_far_points_are_unlabeled_and_the_rest_is_labelled():
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-20, 20, (20000, 2)), rng.normal(-1.8, 0.01, 20000)]
    wall = np.c_[np.full(3000, 8.0), rng.uniform(-5, 5, 3000), rng.uniform(-1.8, 2.0, 3000)]
    xyz = np.vstack([ground, wall, [[np.nan, 0, 0], [500.0, 0, 0]]]).astype(np.float32)
    labels = label_scan(xyz)
    assert labels[-2] == 0 and labels[-1] == 0
    ground_ids = {KITTI_ID["road"], KITTI_ID["sidewalk"], KITTI_ID["terrain"]}
    assert np.isin(labels[:20000], list(ground_ids)).mean() > 0.95
    assert (labels[20000:23000] == KITTI_ID["building"]).mean() > 0.8


@pytest.mark.parametrize("xyz,intensity,message", [
    (np.zeros((0, 3)), None, "scan is empty"),
    (np.full((500, 3), np.nan), None, "0 usable points"),
    (np.zeros((10, 2)), None, "(N, 3) array"),
    (np.ones((500, 3)), np.ones(3), "intensity has 3 values for 500 points"),
])
def test_bad_scans_are_refused_in_one_line(xyz, intensity, message):
    with pytest.raises(ValueError, match=None) as err:
        label_scan(xyz, intensity)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_bad_parameters_are_refused_by_name():
    with pytest.raises(ValueError, match="geometric.ground_cell"):
        GeometricParams(ground_cell=0.0)
    with pytest.raises(ValueError, match="geometric.smoothing_neighbours"):
        GeometricParams(smoothing_neighbours=11)
    with pytest.raises(ValueError, match="geometric.min_share"):
        GeometricParams(min_share=1.5)


def test_config_file_holds_the_defaults():
    from semcal_ros.engine.config import apply_flat, load_node_params

    flat = load_node_params(REPO / "config" / "cloud_segmenter.yaml", "cloud_segmenter")
    geometric = {k.removeprefix("geometric."): v for k, v in flat.items()
                 if k.startswith("geometric.")}
    assert set(geometric) == set(vars(GeometricParams()))
    assert apply_flat(GeometricParams(), geometric) == GeometricParams()


# --- the command -------------------------------------------------------------------------------
def semcal(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "semcal_ros.cli", *args], capture_output=True,
                          text=True, timeout=300)


@needs_kitti
def test_cli_method_geometric_writes_a_labelled_ply(tmp_path):
    from semcal_ros.io.ply import read_ply

    out = tmp_path / "labelled.ply"
    run = semcal("segment-cloud", "--method", "geometric",
                 str(KITTI / "velodyne" / "000000.bin"), "--out", str(out))
    assert run.returncode == 0, run.stderr
    assert "points labelled" in run.stdout and "road" in run.stdout
    cloud = read_ply(out)
    xyz, intensity, reference = kitti_scan(0)
    assert len(cloud) == len(xyz)
    np.testing.assert_allclose(cloud.xyz, xyz, atol=1e-6)
    np.testing.assert_allclose(cloud.extra["intensity"], intensity, atol=1e-6)
    assert point_agreement(cloud.label, reference).per_class["ground"][1] > 0.95


def test_cli_bad_input_is_one_line(tmp_path):
    from semcal_ros.engine.cloud import LabelledCloud
    from semcal_ros.io.ply import write_ply

    nan_scan = tmp_path / "nan.ply"
    write_ply(nan_scan, LabelledCloud(np.full((300, 3), np.nan, np.float32),
                                      np.zeros(300, np.uint16), {}))
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    bad_config = tmp_path / "bad.yaml"
    bad_config.write_text(yaml.safe_dump({"cloud_segmenter": {"ros__parameters": {
        "geometric": {"voxle": 0.2}}}}))
    cases = [
        (["--method", "geometric", str(tmp_path / "missing.bin")], "not found"),
        (["--method", "geometric", str(nan_scan)], "0 usable points"),
        (["--method", "geometric", str(empty)], "empty"),
        (["--method", "geometric", "--config", str(bad_config), str(nan_scan)], "voxle"),
        ([str(nan_scan)], "--method onnx needs --model and --model-config"),
    ]
    for args, text in cases:
        run = semcal("segment-cloud", *args, "--out", str(tmp_path / "out.ply"))
        assert run.returncode == 1, (args, run.stdout, run.stderr)
        lines = run.stderr.strip().splitlines()
        assert len(lines) == 1 and text in lines[0], (args, run.stderr)


# --- the node ----------------------------------------------------------------------------------
@needs_kitti
@pytest.mark.ros
def test_cloud_segmenter_node_method_geometric_labels_a_real_scan(tmp_path):
    """cloud_segmenter with method geometric (no model file) as a process over DDS: a real KITTI
    scan in, the same points with SemanticKITTI labels out."""
    rclpy = pytest.importorskip("rclpy")
    from sensor_msgs.msg import PointCloud2

    from semcal_ros.ros import conversions as conv
    from semcal_ros.ros import qos

    sys.path.insert(0, str(Path(__file__).parent))
    from ros_helpers import RosGraph, publish_until

    xyz, intensity, reference = kitti_scan(0)
    points = np.zeros(len(xyz), np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                          ("intensity", "<f4")]))
    points["x"], points["y"], points["z"] = xyz.T
    points["intensity"] = intensity
    graph = RosGraph(tmp_path)
    try:
        node = graph.start_node("cloud_segmenter", params={"method": "geometric"})
        ctx = graph.context()
        listener = rclpy.create_node("geometric_listener", context=ctx)
        executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
        executor.add_node(listener)
        out: list = []
        listener.create_subscription(PointCloud2, "labelled_points", out.append, qos.sensor(5))
        pub = listener.create_publisher(PointCloud2, "points", qos.reliable(2))
        msg = conv.array_to_pointcloud2(points, conv.make_header("velodyne", 3.0))
        try:
            publish_until(executor, pub, msg, lambda: len(out) > 0, 120, "a labelled scan",
                          period=2.0)
        finally:
            executor.shutdown()
            listener.destroy_node()
            ctx.try_shutdown()
        assert node.running(), node.log()
        cloud = conv.pointcloud2_to_cloud(out[0], require_label=True)
        np.testing.assert_allclose(cloud.xyz, xyz, atol=1e-6)
        assert out[0].header.frame_id == "velodyne"
        result = point_agreement(cloud.label, reference)
        assert result.per_class["ground"][1] > 0.95, result.table()
        assert result.per_class["car"][1] > 0.8, result.table()
        np.testing.assert_array_equal(cloud.label, label_scan(xyz, intensity))
        assert "Traceback" not in node.log()
    finally:
        graph.close()
        print(graph.logs())


@needs_kitti
def test_labels_of_a_scan_do_not_depend_on_the_scans_before_it():
    """Patchwork++ adapts its thresholds scan by scan; the labeller must be a pure function."""
    xyz, intensity, _ = kitti_scan(0)
    first = label_scan(xyz, intensity)
    for i in (1, 2):
        other, other_intensity, _ = kitti_scan(i)
        label_scan(other, other_intensity)
    np.testing.assert_array_equal(label_scan(xyz, intensity), first)
