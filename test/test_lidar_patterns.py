"""KITTI scans resampled to other lidars (semcal_tools/lidar_patterns.py), and the shipped
geometric point labeller on them: held-out SemanticKITTI scan 1 seen by fewer beams, by a narrow
top-mounted pattern at 2.5 m and without intensity must keep its coarse classes (issue 41).

Floors are set below the shipped forest's measured figures (docs/segmentation.md,
benchmarks/lidar_patterns.py): a guard against a labeller that loses other lidars, not the
issue's targets, which the shipped forest misses (the retrained one that meets more of them lost
on KITTI object calibrations and is not shipped).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from semcal_ros.engine.labels import KITTI_ID
from semcal_ros.segmentation.geometric import coarse_agreement, label_scan
from semcal_tools.lidar_patterns import (KITTI_HEIGHT, NARROW_BEAMS, Pattern, kitti_rings,
                                         resample, training_patterns)

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO.parent / "shared" / "data" / "kitti_odometry_00"
needs_kitti = pytest.mark.skipif(not (KITTI / "labels" / "000001.label").is_file(),
                                 reason=f"real KITTI data not found at {KITTI}")


def kitti_scan(index: int):
    from semcal_ros.io import kitti

    cloud = kitti.read_scan(KITTI / "velodyne" / f"{index:06d}.bin")
    reference = (np.fromfile(KITTI / "labels" / f"{index:06d}.label", np.uint32) & 0xFFFF
                 ).astype(np.uint16)
    return cloud.xyz, cloud.extra["intensity"], reference


def elevation(xyz: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))


@needs_kitti
def test_rings_of_a_kitti_scan_are_its_64_beams_top_down():
    xyz, _, _ = kitti_scan(1)
    ring = kitti_rings(xyz)
    assert ring.max() == 63
    el = elevation(xyz.astype(np.float64))
    median = np.array([np.median(el[ring == r]) for r in range(64)])
    # top ring about +2.5 deg, bottom about -23.5 deg, falling ring after ring (the last
    # ring's median sits 0.1 deg above its neighbour's: its far returns are missing)
    assert 2.0 < median[0] < 3.0 and -24.5 < median[-1] < -22.5
    assert (np.diff(median[:-1]) < 0).all(), median.round(2)
    counts = np.bincount(ring)
    assert counts[1:-1].min() > 900, counts


@needs_kitti
def test_every_kth_beam_keeps_whole_rings():
    xyz, intensity, labels = kitti_scan(1)
    ring = kitti_rings(xyz)
    pts, lab, inten = resample(xyz, labels, intensity, Pattern("p", every=4, offset=2))
    kept = ring % 4 == 2
    np.testing.assert_allclose(pts, xyz[kept], atol=1e-6)
    np.testing.assert_array_equal(lab, labels[kept])
    np.testing.assert_allclose(inten, intensity[kept])
    assert 0.2 < len(pts) / len(xyz) < 0.3


@needs_kitti
def test_narrow_pattern_at_another_height_sees_its_beams_from_its_own_origin():
    xyz, intensity, labels = kitti_scan(1)
    pattern = Pattern("narrow", beams=NARROW_BEAMS, height=2.5, intensity="none")
    pts, lab, inten = resample(xyz, labels, intensity, pattern)
    assert inten is None
    assert 0.25 < len(pts) / len(xyz) < 0.6
    el = elevation(pts.astype(np.float64))
    beams = np.sort(np.array(NARROW_BEAMS))
    gap = np.abs(el[:, None] - beams[None, :]).min(axis=1)
    assert gap.max() <= 0.25 + 1e-6  # each point within the tolerance of its beam
    assert el.max() < 2.3 and el.min() > -25.5
    # the road lies 2.5 m below the new origin, and nothing above +2 deg was kept
    road = lab == KITTI_ID["road"]
    assert abs(np.median(pts[road, 2]) + 2.5) < 0.15
    # every kept point is a KITTI point moved down by the height difference, label unchanged
    shifted = xyz.astype(np.float64) - [0, 0, 2.5 - KITTI_HEIGHT]
    lookup = {tuple(p): int(lab_) for p, lab_ in zip(np.round(shifted, 4), labels)}
    sample = np.random.default_rng(0).choice(len(pts), 500, replace=False)
    for i in sample:
        assert lookup[tuple(np.round(pts[i].astype(np.float64), 4))] == lab[i]
    # one point per beam and azimuth column: no doubled rings in the dense band (recomputed
    # from the float32 output, a few points fall on the other side of a cell edge)
    col = np.floor((np.degrees(np.arctan2(pts[:, 1], pts[:, 0])) + 180) / 0.2).astype(int)
    beam = np.abs(el[:, None] - beams[None, :]).argmin(axis=1)
    assert len(np.unique(beam * 2000 + col)) >= 0.999 * len(pts)


def test_intensity_rescaled_and_training_patterns():
    xyz = np.random.default_rng(1).normal(size=(1000, 3)).astype(np.float32) * 10
    labels = np.arange(1000, dtype=np.uint16)
    inten = np.linspace(0, 1, 1000).astype(np.float32)
    _, lab, scaled = resample(xyz, labels, inten, Pattern("x", intensity="scale255"))
    np.testing.assert_array_equal(lab, labels)
    np.testing.assert_allclose(scaled, inten * 255, rtol=1e-6)
    patterns = training_patterns(np.random.default_rng(0), 12)
    assert len(patterns) == 12
    assert {p.name.rstrip("0123456789.@")[:6] for p in patterns} >= {"every", "narrow", "unifor"}
    heights = [p.height for p in patterns if p.beams is not None]
    assert min(heights) >= 1.7 and max(heights) <= 2.5 and max(heights) - min(heights) > 0.3


#: Coarse floors on held-out scan 1 per pattern (measured figures in docs/segmentation.md).
PATTERN_FLOORS = {
    "32 beams": (Pattern("32", every=2, offset=1), 0.85, 0.77),
    "narrow at 2.5 m, no intensity": (Pattern("n", beams=NARROW_BEAMS, height=2.5,
                                              intensity="none"), 0.86, 0.85),
}


@needs_kitti
@pytest.mark.parametrize("name", sorted(PATTERN_FLOORS))
def test_labeller_keeps_coarse_classes_on_other_lidars(name):
    pattern, coarse_floor, building_floor = PATTERN_FLOORS[name]
    xyz, intensity, labels = kitti_scan(1)
    pts, lab, inten = resample(xyz, labels, intensity, pattern)
    overall, groups = coarse_agreement(label_scan(pts, inten), lab)
    assert overall >= coarse_floor, (overall, groups)
    assert groups["building"][1] >= building_floor, groups
    assert groups["ground"][1] >= 0.93, groups
