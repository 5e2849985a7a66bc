"""Vehicle and roadside unit as two hosts: two network namespaces joined by a veth pair.

The vehicle namespace runs ``map_builder`` and a ``bag_player`` replaying the demo bag's lidar
topics; the roadside namespace runs the ``calibrator``, a ``bag_player`` for the camera topics
(the camera is on the roadside) and the action client as a process of its own. DDS uses UDPv4
only, bound to the link address, with discovery over the subnet and the two hosts as static peers
(``netns.link_environment``): the map can reach the calibrator only through the veth. The test
checks the calibrated transform against the ground truth and that the traffic took that path:
the veth carried at least the map's bytes, and a node on the machine's own network in the same
ROS domain (shared memory and UDP enabled) sees none of the nodes.

Skipped where network namespaces cannot be made (not root, no ``ip``, ``ip netns add`` fails).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("rclpy")

import netns  # noqa: E402

from semcal_tools.launch import DomainLock  # noqa: E402

pytestmark = pytest.mark.ros

MAP_POINT_BYTES = 14  # x, y, z float32 + label uint16: the least a map point takes on the wire


@pytest.fixture
def two_hosts(tmp_path):
    """The link and one ROS domain; processes, namespaces and the domain are freed whatever
    the test's outcome."""
    reason = netns.unavailable_reason()
    if reason:
        pytest.skip(f"two-host test needs network namespaces: {reason}")
    netns.remove_stale_namespaces()
    try:
        link = netns.VethPair()
    except RuntimeError as exc:
        pytest.skip(str(exc))
    lock = DomainLock()
    hosts = netns.Hosts(link, lock.domain, tmp_path / "logs")
    try:
        yield hosts
    finally:
        hosts.close()
        left = link.processes_inside()
        link.close()
        lock.release()
        print(hosts.logs())  # shown by pytest only when the test failed
        assert not left, f"processes left inside the namespaces: {left}"


def test_namespaces_hold_only_loopback_and_the_link(two_hosts):
    """Each host has loopback and its end of the veth, nothing else: the other host is reached
    through the veth and no other address at all."""
    link = two_hosts.link
    for host, other in ((link.vehicle, link.rsu), (link.rsu, link.vehicle)):
        names = {i["ifname"] for i in json.loads(
            netns.run_ip("-j", "-n", host.netns, "link", "show").stdout)}
        ipv4 = {i["ifname"]: [a["local"] for a in i["addr_info"]] for i in json.loads(
            netns.run_ip("-4", "-j", "-n", host.netns, "addr", "show").stdout)}
        assert names == {"lo", host.ifname}, names
        assert ipv4 == {"lo": ["127.0.0.1"], host.ifname: [host.address]}, ipv4
        route = netns.run_ip("-n", host.netns, "route", "get", other.address)
        assert f"dev {host.ifname}" in route.stdout
        outside = netns.run_ip("-n", host.netns, "route", "get", "8.8.8.8", check=False)
        assert outside.returncode != 0  # no default route: nothing else is reachable


@pytest.mark.slow
def test_vehicle_map_crosses_the_link_and_the_roadside_unit_calibrates(two_hosts, demo_scene):
    from semcal_ros.io.files import read_pose
    from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error

    link, logs = two_hosts.link, two_hosts.log_dir
    before = link.vehicle.counters()
    # the calibrator's default engine schedule, as in test_ros_e2e, and no verification starts
    # (about 20 s of CPU): a cheap one (60/30/30 evaluations, no restarts) ended 50 cm off
    client, lidar_player = netns.start_pipeline(two_hosts, demo_scene, logs / "client.json")

    client.wait_for_log("calibrator holds the map", 150)
    # While the calibrator works: what can a node see from the machine's own network (same
    # domain, static peers named, shared memory on), and, as the control, from the roadside?
    outside = two_hosts.graph("outside").start_helper(
        "probe", "probe", "--seconds", "4", "--out", str(logs / "outside.json"))
    inside = two_hosts.graph("rsu").start_helper(  # the control: until it has seen them
        "probe", "probe", "--seconds", "120", "--until", "map_builder,calibrator",
        "--out", str(logs / "inside.json"))
    assert client.wait(150) == 0, client.log()
    assert outside.wait(30) == 0 and inside.wait(150) == 0
    assert lidar_player.wait(20) == 0
    after = link.vehicle.counters()

    report = json.loads((logs / "client.json").read_text())
    (goal,) = report["goals"]
    truth = read_pose(demo_scene / "ground_truth.yaml")
    result = Pose(np.array(goal["translation"]), np.array(goal["rotation"]))
    sent = after["tx_bytes"] - before["tx_bytes"]
    print(f"two hosts: map of {report['map_points']} points held {report['map_held_after']:.1f} s "
          f"after the client found the server; goal round trip {goal['round_trip']:.2f} s "
          f"(engine {goal['server_seconds']:.2f} s); error "
          f"{translation_error(result, truth) * 100:.2f} cm, "
          f"{rotation_error_deg(result, truth):.3f} deg; vehicle veth sent {sent} B, received "
          f"{after['rx_bytes'] - before['rx_bytes']} B")
    assert goal["status"] == "succeeded", goal["message"]
    assert goal["feedback"] > 0
    assert (goal["frame_id"], goal["child_frame_id"]) == ("map", "camera_optical")
    assert translation_error(result, truth) < 0.05
    assert rotation_error_deg(result, truth) < 0.1

    # the map went over the veth (not through shared memory or loopback)
    assert sent >= report["map_points"] * MAP_POINT_BYTES, (sent, report["map_points"])
    assert after["rx_bytes"] > before["rx_bytes"]  # the acknowledgements and the action came back
    # the roadside sees the vehicle's map builder and its map; the machine's own network does not
    seen_inside = json.loads((logs / "inside.json").read_text())
    seen_outside = json.loads((logs / "outside.json").read_text())
    assert {"map_builder", "calibrator"} <= set(seen_inside["nodes"]), seen_inside
    assert seen_inside["map_publishers"] == 1 and seen_inside["maps_received"] >= 1
    ours = {"map_builder", "calibrator", "lidar_player", "camera_player", "roadside_client",
            "isolation_probe"}
    assert not ours & set(seen_outside["nodes"]), seen_outside
    assert seen_outside["map_publishers"] == 0 and seen_outside["maps_received"] == 0
