"""A moving rig's label image + labelled scan pairs (semcal_ros/ros/rig_pairs.py), without DDS:
pairing by the nearest stamp once it is settled, the tolerance, unpaired images counted (once),
the last N pairs kept, images and scans sent again replacing the held ones, unusable scans
refused in one line with everything held kept, and the calibrator's rig parameters."""

from __future__ import annotations

import re

import numpy as np
import pytest

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.errors import InputError
from semcal_ros.ros.rig_pairs import (Pair, RigPairs, Scan, ScanBuffer, rig_frame_problems,
                                      rig_problems, usable_scan)


def scan(stamp: float, frame: str = "velodyne", n: int = 50) -> Scan:
    rng = np.random.default_rng(int(stamp * 1000))
    return Scan(stamp, LabelledCloud(rng.uniform(-20, 20, (n, 3)),
                                     np.full(n, 40, np.uint16)), frame)


def labels(value: int = 0) -> np.ndarray:
    return np.full((4, 6), value, np.uint8)


def make(frames: int = 2, tolerance: float = 0.05, held: int = 10) -> tuple[ScanBuffer, RigPairs]:
    scans = ScanBuffer(held)
    return scans, RigPairs(frames, tolerance, scans)


def feed_scan(scans: ScanBuffer, rig: RigPairs, s: Scan) -> None:
    scans.add(s)
    rig.resolve()


def test_a_label_image_waits_for_the_scan_after_it_and_takes_the_nearest():
    scans, rig = make()
    feed_scan(scans, rig, scan(10.00))
    rig.add_labels(10.06, labels(1))  # 10.00 is 0.06 away, but the next scan may be nearer
    assert rig.pairs() == [] and rig.values()["rig_waiting"] == 1
    feed_scan(scans, rig, scan(10.10))
    (pair,) = rig.pairs()
    assert pair.scan.stamp == pytest.approx(10.10) and pair.labels_stamp == pytest.approx(10.06)
    assert rig.unpaired == 0 and rig.values()["rig_pairs"] == "1/2"
    assert pair.name == "labels 10.060 s + scan 10.100 s"


def test_a_label_image_with_no_scan_within_the_tolerance_is_counted_once():
    scans, rig = make(tolerance=0.05)
    feed_scan(scans, rig, scan(10.0))
    feed_scan(scans, rig, scan(10.1))
    rig.add_labels(10.3, labels())  # waits: no scan at or after 10.3 yet
    assert rig.unpaired == 0
    feed_scan(scans, rig, scan(10.5))
    assert rig.pairs() == [] and rig.unpaired == 1
    assert "label image 10.300 s: the nearest held scan is 0.200 s away " \
           "(rig_stamp_tolerance 0.05 s)" == rig.last_unpaired
    rig.add_labels(10.3, labels())  # sent again: settled at once, counted once
    assert rig.unpaired == 1
    rig.add_labels(9.0, labels())  # older than every held scan
    assert rig.unpaired == 2 and "1.000 s away" in rig.last_unpaired


def test_the_last_n_pairs_are_kept_and_a_resent_image_replaces_its_pair():
    scans, rig = make(frames=2)
    for t in (1.0, 2.0, 3.0):
        feed_scan(scans, rig, scan(t))
        rig.add_labels(t + 0.01, labels(int(t)))
    # the scan after each image arrives with the next round; the last image waits for one
    assert [p.scan.stamp for p in rig.pairs()] == [1.0, 2.0]
    feed_scan(scans, rig, scan(4.0))
    assert [p.labels_stamp for p in rig.pairs()] == pytest.approx([2.01, 3.01])
    rig.add_labels(3.01, labels(9))  # the same image again, new content: replaces, not added
    pairs = rig.pairs()
    assert [p.labels_stamp for p in pairs] == pytest.approx([2.01, 3.01])
    assert int(pairs[-1].labels[0, 0]) == 9


def test_scans_sent_again_replace_the_held_one_and_the_buffer_is_bounded():
    scans = ScanBuffer(3)
    for t in (1.0, 2.0, 2.0, 3.0, 4.0):
        scans.add(scan(t))
    assert [s.stamp for s in scans.held()] == [2.0, 3.0, 4.0]
    assert scans.values()["rig_scans_held"] == "3/3"


def test_too_many_images_waiting_for_a_scan_are_counted_unpaired():
    scans = ScanBuffer(2)
    rig = RigPairs(2, 0.05, scans, waiting=3)
    for k in range(5):
        rig.add_labels(float(k), labels())
    assert rig.unpaired == 2 and "3 newer images waited for a scan" in rig.last_unpaired
    assert rig.values()["rig_waiting"] == 3


def test_unusable_scans_are_refused_with_the_reason():
    xyz = np.ones((5, 3))
    cases = [
        (LabelledCloud(xyz, np.zeros(5, np.uint16)), "", "the scan has no frame_id"),
        (LabelledCloud(xyz), "velodyne", "the scan has no 'label' field"),
        (LabelledCloud(np.zeros((0, 3)), np.zeros(0, np.uint16)), "velodyne",
         "the scan is empty"),
        (LabelledCloud(np.full((5, 3), np.nan), np.zeros(5, np.uint16)), "velodyne",
         "the scan has no finite point (5 points)"),
    ]
    for cloud, frame, message in cases:
        with pytest.raises(InputError, match=re.escape(message)):
            usable_scan(cloud, 1.0, frame)
    nan_one = xyz.copy()
    nan_one[0] = np.nan
    held = usable_scan(LabelledCloud(nan_one, np.arange(5, dtype=np.uint16)), 1.0, "velodyne")
    assert len(held.cloud) == 4 and list(held.cloud.label) == [1, 2, 3, 4]


def test_a_bad_scan_message_is_one_line_and_keeps_what_is_held():
    pytest.importorskip("rclpy")
    from semcal_ros.ros import conversions as conv
    from semcal_ros.ros.rig_pairs import on_scan_message

    class Camera:
        def __init__(self, rig: RigPairs) -> None:
            self.rig = rig

    scans, rig = make(frames=1)
    logged: list[str] = []
    good = np.zeros(100, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<u2")])
    good["x"] = np.linspace(1, 30, 100)
    rig.add_labels(5.0, labels())
    assert on_scan_message(conv.array_to_pointcloud2(good, conv.make_header("velodyne", 5.0)),
                           scans, [Camera(rig)], logged.append, "/labelled_points")
    assert len(rig.pairs()) == 1 and logged == []
    bad = np.zeros(100, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    for _ in range(2):  # the same reason is logged once
        assert not on_scan_message(conv.array_to_pointcloud2(bad, conv.make_header("velodyne",
                                                                                   6.0)),
                                   scans, [Camera(rig)], logged.append, "/labelled_points")
    assert logged == ["ignoring labelled scan on '/labelled_points': the scan has no 'label' "
                      "field (send it through cloud_segmenter); keeping the 1 scans and the "
                      "pairs held"]
    assert len(scans.held()) == 1 and len(rig.pairs()) == 1
    assert "no 'label' field" in scans.values()["input_error.labelled_scan"]


def test_goal_problems_name_the_missing_pairs_and_the_frame():
    class Camera:
        width, height = 6, 4

    pairs = [Pair(1.0, labels(), scan(1.0))]
    (text,) = rig_problems(pairs, 3, Camera(), 2, "/cam/labels", "/labelled_points")
    assert text == ("1 of rig_frames 3 label image + labelled scan pairs held (labels on "
                    "'/cam/labels', scans on '/labelled_points'; 2 label images unpaired so far)")
    assert rig_problems(pairs, 1, Camera(), 0, "", "") == []
    mixed = pairs + [Pair(2.0, np.zeros((5, 6), np.uint8), scan(2.0, "lidar_top"))]
    problems = rig_problems(mixed, 2, Camera(), 0, "", "")
    assert "the held scans are in frames lidar_top, velodyne: one rig, one lidar frame" in problems
    assert "held label images of 6x5 but CameraInfo says 6x4" in problems
    assert rig_frame_problems(pairs, "map") == [
        "initial_pose is in frame 'map' but the rig's scans are in 'velodyne' (give the camera's "
        "pose in the lidar frame)"]
    assert rig_frame_problems(pairs, "velodyne") == rig_frame_problems(pairs, "") == []


def test_the_calibrator_refuses_bad_rig_parameters_in_one_line():
    pytest.importorskip("rclpy")
    from semcal_ros.ros.nodes.calibrator import CalibratorNodeParams

    assert CalibratorNodeParams().rig_frames == 1  # the map and the newest image, as before
    for kwargs, message in (
            ({"rig_frames": 0}, "rig_frames must be >= 1 frames, got 0"),
            ({"rig_stamp_tolerance": 0.0}, "rig_stamp_tolerance must be > 0 s, got 0.0"),
            ({"rig_scans_held": 0}, "rig_scans_held must be >= 1 scans, got 0"),
            ({"rig_frames": 3, "label_window": 4},
             "label_window 4 (a static camera) and rig_frames 3 (a moving rig) exclude each "
             "other: set one to 1")):
        with pytest.raises(ValueError, match=re.escape(message)):
            CalibratorNodeParams(**kwargs)


def test_a_frame_map_is_the_scan_as_real_scene_makes_a_one_scan_map():
    from semcal_ros.engine.labels import KITTI_ID
    from semcal_ros.ros.rig_pairs import MAP_PARAMS, frame_map

    road, car_moving = KITTI_ID["road"], 252
    xyz = np.array([[5.0, 0.0, 0.0], [5.01, 0.01, 0.0], [5.02, 0.0, 0.01],  # one voxel
                    [10.0, 0.0, 0.0],  # a moving car's point
                    [MAP_PARAMS.d_max + 5.0, 0.0, 0.0]])  # beyond the map builder's reach
    label = np.array([road, road, 50, car_moving, road], np.uint16)
    held = frame_map(LabelledCloud(xyz, label))
    assert len(held) == 1 and int(held.label[0]) == road  # the voxel's majority
    assert np.linalg.norm(held.xyz[0] - [5.0, 0.0, 0.0]) < MAP_PARAMS.voxel
    with pytest.raises(InputError, match="none of the scan's 2 points is a static labelled "
                                         "point within 60 m of the lidar"):
        frame_map(LabelledCloud(xyz[3:5], label[3:5]))
