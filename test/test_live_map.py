"""The live map's worker without ROS (semcal_ros/workflows/live_map.py): scans wait for their
poses, the map is handed on, a sustained jump back resets it, refusals are counted and said once,
and the status says why it warns. The node around it is tested over DDS in test_ros_e2e.py and
test_bad_inputs_ros.py."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.pose import Pose
from semcal_ros.mapping import MapBuildParams
from semcal_ros.workflows.live_map import LiveMap, LiveMapParams


class Recorder:
    """What the live map hands out: maps published and lines logged, with an event per map."""

    def __init__(self) -> None:
        self.maps: list[LabelledCloud] = []
        self.warnings: list[str] = []
        self.published = threading.Condition()

    def publish(self, cloud: LabelledCloud) -> None:
        with self.published:
            self.maps.append(cloud)
            self.published.notify_all()

    def wait_for(self, live: LiveMap, condition, what: str, timeout: float = 60.0) -> None:
        """Until ``condition(live)`` holds after a publication (event-driven, no fixed sleep)."""
        deadline = time.monotonic() + timeout
        with self.published:
            while not condition(live):
                left = deadline - time.monotonic()
                assert left > 0, f"timed out waiting for {what}: {live.status()}"
                self.published.wait(timeout=min(left, 0.5))


def _scan(rng: np.random.Generator) -> LabelledCloud:
    xyz = np.column_stack([rng.uniform(5, 30, 2000), rng.uniform(-10, 10, 2000),
                           rng.uniform(-2, 5, 2000)])
    return LabelledCloud(xyz, np.where(xyz[:, 2] > 0, 50, 40).astype(np.uint16))


def _pose(x: float) -> Pose:
    return Pose(np.array([x, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]))


@pytest.fixture
def live():
    rec = Recorder()
    params = LiveMapParams(publish_period=0.05, queue_size=5, time_jump=1.0, jump_confirm=3,
                           mapping=MapBuildParams(icp=False, remove_dynamic=False))
    lm = LiveMap(params, lambda cloud: cloud, rec.publish, rec.warnings.append, "'/odom'")
    lm.start()
    yield lm, rec
    lm.close()


def test_scans_wait_for_poses_then_build_and_a_jump_back_resets(live):
    lm, rec = live
    rng = np.random.default_rng(3)
    lm.arrive("scan", 10.0, _scan(rng))  # no pose yet: it waits, and the status says why
    assert lm.status().warn and "no pose received yet on '/odom'" in lm.status().message
    for i in range(4):
        t = 10.0 + 0.1 * i
        lm.arrive("pose", t, _pose(i * 0.1))
        if i:
            lm.arrive("scan", t, _scan(rng))
    rec.wait_for(lm, lambda m: m.published[1] == 4, "a map of 4 scans")
    assert lm.counts.accepted == 4 and len(rec.maps[-1]) == lm.published[0] > 0
    assert not lm.status().warn and lm.status().message == "4 scans in the map"

    # two stray messages (not three in a row): dropped, counted, the map stays
    lm.arrive("scan", 2.0, _scan(rng))
    lm.arrive("pose", 2.1, _pose(0.0))
    lm.arrive("pose", 10.4, _pose(0.4))
    assert lm.matcher.strays == 2 and lm.counts.rejected["stray"] == 2
    assert rec.warnings[-1].startswith("pose at 2.100 s is 8.2 s older than the newest")
    # three in a row: time went back for good; the map starts over with the new pass
    for i in range(3):
        t = 1.0 + 0.1 * i
        lm.arrive("pose", t, _pose(i * 0.1))
        lm.arrive("scan", t, _scan(rng))
    rec.wait_for(lm, lambda m: m.counts.resets == 1 and m.published[1] == 3,
                 "a new map of the 3 scans after the jump")
    assert lm.last_reset.startswith("time jumped back 9.3 s (3 messages in a row")
    assert any(w == lm.last_reset for w in rec.warnings)
    assert lm.status().values["resets"] == 1


def test_refusals_are_counted_and_said_once_and_reset_empties_the_map(live):
    lm, rec = live
    rng = np.random.default_rng(4)
    lm.arrive("pose", 5.0, _pose(0.0))
    lm.arrive("scan", 5.0, LabelledCloud(np.full((30, 3), np.nan)))
    lm.arrive("scan", 5.0, LabelledCloud(np.zeros((0, 3))))
    lm.arrive("pose", 5.1, _pose(0.1))
    lm.arrive("scan", 5.1, _scan(rng))
    rec.wait_for(lm, lambda m: m.published[1] == 1, "a map of the one good scan")
    assert lm.counts.rejected["nan"] == 2
    assert "scan at 5.000 s has only NaN or infinite points (30); ignored" in rec.warnings
    assert "scan at 5.000 s has no points; ignored" in rec.warnings
    for _ in range(3):
        lm.rejected("fields", "scan ignored: PointCloud2 has no x field")
    assert rec.warnings.count("scan ignored: PointCloud2 has no x field") == 1  # said once
    assert lm.counts.rejected["fields"] == 3 and lm.status().values["last_error"] == \
        "scan ignored: PointCloud2 has no x field"

    assert lm.reset() == 0
    assert lm.published == (0, 0) and len(rec.maps[-1]) == 0  # published at once
    assert lm.counts.resets == 1


def test_a_full_queue_drops_the_oldest_scans_with_the_reason(live):
    lm, rec = live
    rng = np.random.default_rng(5)
    lm.arrive("pose", 1.0, _pose(0.0))
    # the pose stream stops; the note comes once poses have been missing for a second
    lm.matcher._pose_arrival = time.monotonic() - 2.0  # noqa: SLF001 - that second, passed
    for i in range(7):
        lm.arrive("scan", 1.1 + 0.1 * i, _scan(rng))
    assert lm.matcher.dropped_queue == 2 and lm.counts.rejected["queue"] == 1
    assert rec.warnings[-1].startswith("scans dropped (queue full): no pose for ")
    status = lm.status()
    assert status.warn and "5 scans wait for their poses; is '/odom' publishing?" in \
        status.message
