"""Two hosts on one machine: a vehicle and a roadside unit in network namespaces joined by a veth.

Issue 13 builds the map on a vehicle and calibrates on the roadside unit. This module makes that
setting on one machine for ``test/test_two_hosts.py`` and ``benchmarks/bench_two_hosts.py``:

- :class:`VethPair`: two network namespaces ("vehicle" and "rsu" plus a per-process tag, so two
  runs at once do not collide), each with only ``lo`` and one end of a veth pair (10.77.0.1/24 and
  10.77.0.2/24). Nothing else is reachable from either namespace, so DDS traffic between them has
  exactly one path: the veth, whose byte counters then show what crossed.
- :func:`link_profile` / :func:`link_environment`: the DDS settings a real two-host deployment
  needs (docs/two-hosts.md): Fast DDS with UDPv4 only (no shared memory: nothing may take a
  same-machine shortcut), bound to the link address, discovery range SUBNET with the two hosts
  as static peers, one ROS_DOMAIN_ID.
- :class:`HostGraph` / :class:`Hosts`: node processes started inside a namespace
  (``ip netns exec``) with the log handling of :mod:`semcal_tools.launch`, or on this machine's
  own network for the localhost comparison; :func:`start_pipeline` starts vehicle and roadside.
- ``python test/netns.py client ...``: the roadside unit's action client (a process of its own
  in the rsu namespace): waits until the calibrator holds the vehicle's whole map, sends goals,
  writes each round trip and result as JSON. ``python test/netns.py probe ...``: a node that
  lists which nodes and ``/map`` publishers it can see (the isolation check).

Needs root (``ip netns add``); :func:`unavailable_reason` says why not where it cannot work.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

from semcal_tools.launch import BIN, NodeProcess, ros_args, ros_environment  # noqa: E402
from semcal_tools.live_demo import ODOM_TOPIC, SCAN_TOPIC, scan_count  # noqa: E402

from ros_helpers import reliable_overrides  # noqa: E402

SUBNET = "10.77.0"
PREFIX = 24
#: Socket buffers of the link transport: the map (about 16 MB for the demo scene) is sent as a
#: burst of 64 kB fragments; with the kernel default (208 kB) most of a burst overflows the
#: receiver and waits for repair. Capped by net.core.rmem_max / wmem_max (4 MB here).
SOCKET_BUFFER = 4 * 1024 * 1024
TAG_PREFIX = "semcal"


def run_ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check)


def unavailable_reason() -> str | None:
    """Why namespaces cannot be made here (None: they can)."""
    if shutil.which("ip") is None:
        return "no 'ip' command (iproute2) to make network namespaces"
    if os.geteuid() != 0:
        return "network namespaces need root (ip netns add)"
    probe = f"{TAG_PREFIX}-probe-{os.getpid()}"
    made = run_ip("netns", "add", probe, check=False)
    if made.returncode != 0:
        return f"'ip netns add' failed: {made.stderr.strip() or made.returncode}"
    run_ip("netns", "delete", probe, check=False)
    return None


@dataclass(frozen=True)
class Host:
    """One side of the link: its namespace, its end of the veth and that end's address."""

    role: str  # "vehicle" | "rsu"
    netns: str
    ifname: str
    address: str

    def exec_argv(self, argv: list[str]) -> list[str]:
        """``argv`` run inside this host's namespace (``ip netns exec`` execs it: same pid)."""
        return ["ip", "netns", "exec", self.netns, *argv]

    def counters(self) -> dict[str, int]:
        """rx/tx bytes and packets of this host's veth end."""
        out = run_ip("-j", "-s", "-n", self.netns, "link", "show", "dev", self.ifname)
        stats = json.loads(out.stdout)[0]["stats64"]
        return {f"{way}_{key}": int(stats[way][key]) for way in ("rx", "tx")
                for key in ("bytes", "packets")}


class VethPair:
    """The vehicle and rsu namespaces and the veth between them; :meth:`close` removes both
    namespaces (which removes the veth) and is safe to call more than once."""

    def __init__(self, tag: str | None = None) -> None:
        tag = tag or str(os.getpid())
        # interface names are at most 15 characters: "sv<tag>" / "sr<tag>"
        self.vehicle = Host("vehicle", f"{TAG_PREFIX}-vehicle-{tag}", f"sv{tag}"[:15],
                            f"{SUBNET}.1")
        self.rsu = Host("rsu", f"{TAG_PREFIX}-rsu-{tag}", f"sr{tag}"[:15], f"{SUBNET}.2")
        self._made: list[str] = []
        try:
            self._create()
        except subprocess.CalledProcessError as exc:
            self.close()
            run_ip("link", "delete", self.vehicle.ifname, check=False)  # if not moved yet
            raise RuntimeError(f"could not make the namespaces: {' '.join(exc.cmd)}: "
                               f"{exc.stderr.strip()}") from None

    def _create(self) -> None:
        v, r = self.vehicle, self.rsu
        for host in (v, r):
            run_ip("netns", "delete", host.netns, check=False)  # left over by a killed run
            run_ip("netns", "add", host.netns)
            self._made.append(host.netns)
        run_ip("link", "add", v.ifname, "type", "veth", "peer", "name", r.ifname)
        for host in (v, r):
            run_ip("link", "set", host.ifname, "netns", host.netns)
            run_ip("-n", host.netns, "addr", "add", f"{host.address}/{PREFIX}", "dev",
                   host.ifname)
            run_ip("-n", host.netns, "link", "set", "lo", "up")
            run_ip("-n", host.netns, "link", "set", host.ifname, "up")

    @property
    def hosts(self) -> tuple[Host, Host]:
        return self.vehicle, self.rsu

    def peers(self) -> list[str]:
        return [h.address for h in self.hosts]

    def processes_inside(self) -> list[int]:
        """Pids still running in either namespace (should be none after the graphs closed)."""
        pids: list[int] = []
        for host in self.hosts:
            out = run_ip("netns", "pids", host.netns, check=False)
            pids += [int(p) for p in out.stdout.split()]
        return pids

    def close(self) -> None:
        for name in reversed(self._made):
            run_ip("netns", "delete", name, check=False)
        self._made.clear()

    def __enter__(self) -> "VethPair":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def remove_stale_namespaces() -> list[str]:
    """Delete this module's namespaces whose creating process is gone (a run killed before its
    finalizer ran); returns their names."""
    out = run_ip("netns", "list", check=False).stdout.split("\n")
    removed = []
    for line in out:
        name = line.split(" ")[0]
        parts = name.split("-")
        if len(parts) != 3 or parts[0] != TAG_PREFIX or not parts[2].isdigit():
            continue
        if not Path(f"/proc/{parts[2]}").exists():
            run_ip("netns", "delete", name, check=False)
            removed.append(name)
    return removed


# --- DDS on the link ---------------------------------------------------------------------------
def link_profile(path: Path, address: str, buffer: int = SOCKET_BUFFER,
                 flow_bytes_per_s: int | None = None, flow_topics: tuple[str, ...] = ("/map",)
                 ) -> Path:
    """A Fast DDS profile for one host: UDPv4 only (no shared memory), on ``address`` only.

    ``flow_bytes_per_s``: the writers of ``flow_topics`` (ROS topic names are the profile names
    rmw_fastrtps looks up) send at most that many bytes per second, in 50 ms slices. Without it
    a 16 MB map leaves as one burst; on a link slower than the sender with a shallow queue
    (tc tbf at 100 Mbit/s, 200 ms) most of it was dropped and the repairs stalled (the map did
    not arrive in 18 s); at 10 MB/s it arrived 1.7-3.3 s after the publisher process started,
    with 16.5-16.8 MB on the wire. Needs
    ``RMW_FASTRTPS_PUBLICATION_MODE=ASYNCHRONOUS`` (:func:`link_environment` sets it): a
    synchronous writer with a flow controller is refused ("could not create data writer").
    """
    flow = writers = ""
    if flow_bytes_per_s:
        flow = f"""      <flow_controller_descriptor_list>
        <flow_controller_descriptor>
          <name>link_rate</name>
          <scheduler>FIFO</scheduler>
          <max_bytes_per_period>{max(int(flow_bytes_per_s / 20), 65536)}</max_bytes_per_period>
          <period_ms>50</period_ms>
        </flow_controller_descriptor>
      </flow_controller_descriptor_list>
"""
        writers = "".join(f"""  <data_writer profile_name="{topic}">
    <qos>
      <publishMode>
        <kind>ASYNCHRONOUS</kind>
        <flow_controller_name>link_rate</flow_controller_name>
      </publishMode>
    </qos>
  </data_writer>
""" for topic in flow_topics)
    path.write_text(f"""<?xml version="1.0" encoding="UTF-8" ?>
<!-- semcal_ros two hosts: UDPv4 on the link address only; no shared-memory transport -->
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>link_udp</transport_id>
      <type>UDPv4</type>
      <sendBufferSize>{buffer}</sendBufferSize>
      <receiveBufferSize>{buffer}</receiveBufferSize>
      <interfaceWhiteList><address>{address}</address></interfaceWhiteList>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="semcal_link" is_default_profile="true">
    <rtps>
{flow}      <userTransports><transport_id>link_udp</transport_id></userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
    </rtps>
  </participant>
{writers}</profiles>
""")
    return path


def link_environment(domain: int, profile: Path, peers: list[str]) -> dict[str, str]:
    """The environment of a node on one host: the nodes' usual one (:mod:`launch`), but discovery
    over the subnet with the hosts as static peers and the link profile instead of the
    shared-memory one (asynchronous publication where the profile has a flow controller)."""
    env = ros_environment(domain)
    env.pop("FASTDDS_DEFAULT_PROFILES_FILE", None)
    env.pop("FASTDDS_BUILTIN_TRANSPORTS", None)  # the profile decides the transports
    env.update({"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
                "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
                "ROS_STATIC_PEERS": ";".join(peers),
                "FASTRTPS_DEFAULT_PROFILES_FILE": str(profile)})
    if "<flow_controller_name>" in profile.read_text():
        env["RMW_FASTRTPS_PUBLICATION_MODE"] = "ASYNCHRONOUS"
    return env


class HostGraph:
    """The processes of one host: started in its namespace (``host``; None: this machine's own
    network) with its DDS environment; output in ``log_dir/<role>-<name>.log``. :meth:`close`
    stops them (SIGINT, then SIGKILL)."""

    def __init__(self, role: str, host: Host | None, env: dict[str, str], log_dir: Path) -> None:
        self.role, self.host, self.env, self.log_dir = role, host, env, Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.processes: list[NodeProcess] = []

    def start(self, name: str, argv: list[str]) -> NodeProcess:
        full = self.host.exec_argv(argv) if self.host is not None else argv
        proc = NodeProcess(f"{self.role}-{name}", full, self.env, self.log_dir)
        self.processes.append(proc)
        return proc

    def start_node(self, executable: str, params: dict | None = None, remap: dict | None = None,
                   params_file: str | Path | None = None, name: str | None = None
                   ) -> NodeProcess:
        """A node executable of the venv; ``name`` also renames the ROS node (``__node``)."""
        if name is not None:
            remap = {**(remap or {}), "__node": name}
        return self.start(name or executable,
                          [str(BIN / executable), *ros_args(params, remap, params_file)])

    def start_helper(self, name: str, *args: str) -> NodeProcess:
        """This module as a script (the roadside client, the probe) with the venv's python."""
        return self.start(name, [sys.executable, str(Path(__file__).resolve()), *args])

    def logs(self) -> str:
        return "\n".join(f"----- {p.name} (exit {p.proc.returncode}) -----\n{p.log()}"
                         for p in self.processes)

    def close(self) -> None:
        for proc in reversed(self.processes):
            proc.stop()


class Hosts:
    """Where the vehicle's and the roadside unit's processes run, in one ROS domain: on the two
    sides of ``link``, or (``link`` None) both on this machine with the project's usual local
    settings (:func:`semcal_tools.launch.ros_environment`: localhost discovery, shared memory)
    for comparison. Role "outside" is this machine's own network with discovery over the subnet,
    the link's addresses as static peers and shared memory on: a node that tries to join."""

    def __init__(self, link: VethPair | None, domain: int, log_dir: Path,
                 flow_bytes_per_s: int | None = None) -> None:
        self.link, self.domain, self.log_dir = link, domain, Path(log_dir)
        self.flow_bytes_per_s = flow_bytes_per_s
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.graphs: dict[str, HostGraph] = {}

    def graph(self, role: str) -> HostGraph:
        if role in self.graphs:
            return self.graphs[role]
        if self.link is not None and role in ("vehicle", "rsu"):
            host = getattr(self.link, role)
            profile = link_profile(self.log_dir / f"{role}-fastdds.xml", host.address,
                                   flow_bytes_per_s=self.flow_bytes_per_s)
            graph = HostGraph(role, host, link_environment(self.domain, profile,
                                                           self.link.peers()), self.log_dir)
        else:
            env = ros_environment(self.domain)
            if role == "outside":
                env.update({"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
                            "ROS_STATIC_PEERS": ";".join(self.link.peers() if self.link else [])})
            graph = HostGraph(role, None, env, self.log_dir)
        self.graphs[role] = graph
        return graph

    def logs(self) -> str:
        return "\n".join(g.logs() for g in self.graphs.values())

    def close(self) -> None:
        for graph in self.graphs.values():
            graph.close()


CAMERA_TOPICS = ["/camera/labels", "/camera/camera_info", "/camera/image_raw"]


def start_pipeline(hosts: Hosts, scene: Path, report: Path, goals: int = 1, refused: int = 0,
                   calibrator_params: dict | None = None, timeout: float = 150.0
                   ) -> tuple[NodeProcess, NodeProcess]:
    """Vehicle: ``map_builder`` and a ``bag_player`` for the lidar topics of the scene's bag.
    Roadside: ``calibrator``, a ``bag_player`` for the camera topics and the action client
    (``goals`` calibrations, then ``refused`` goals answered at once; JSON in ``report``).
    Returns (client, lidar player); the players wait for their subscribers before playing."""
    vehicle, rsu = hosts.graph("vehicle"), hosts.graph("rsu")
    bag = scene / "bag"
    # reliable scans and poses (QoS override parameters): the client waits for a map of every
    # scan, and with both cores busy best effort dropped one now and then (the map never
    # completed); the players wait for the acknowledgements before they exit
    vehicle.start_node("map_builder", params={"mapping.icp": False, "publish_period": 1.0,
                                              "queue_size": 100,
                                              **reliable_overrides(SCAN_TOPIC, ODOM_TOPIC)},
                       remap={"scan": SCAN_TOPIC, "odom": ODOM_TOPIC})
    rsu.start_node("calibrator", params_file=REPO / "config" / "calibrator.yaml",
                   params=calibrator_params)
    client = rsu.start_helper("roadside_client", "client", "--initial",
                              str(scene / "initial.yaml"), "--scans", str(scan_count(bag)),
                              "--goals", str(goals), "--refused", str(refused),
                              "--timeout", str(timeout), "--out", str(report))
    rsu.start_node("bag_player", name="camera_player",
                   params={"bag": str(bag), "topics": CAMERA_TOPICS,
                           "wait_for_subscribers": 30.0})
    lidar = vehicle.start_node("bag_player", name="lidar_player",
                               params={"bag": str(bag), "topics": [SCAN_TOPIC, ODOM_TOPIC],
                                       "wait_for_subscribers": 30.0})
    return client, lidar


# --- the roadside client and the probe (run as processes) ----------------------------------------
def roadside_client(args: argparse.Namespace) -> int:
    """Wait for the calibrator and the whole map, send ``--goals`` goals, write the outcomes."""
    import rclpy

    from semcal_ros.io.files import read_pose
    from semcal_ros.ros.client import CalibrateClient, DiagnosticsWatcher, make_goal

    rclpy.init()
    node = rclpy.create_node("roadside_client")
    executor = rclpy.executors.SingleThreadedExecutor()
    executor.add_node(node)
    report: dict[str, Any] = {"goals": []}
    try:
        watcher = DiagnosticsWatcher(node)
        client = CalibrateClient(node)
        t0 = time.monotonic()
        client.wait_for_server(args.timeout)
        print(f"calibrate server found after {time.monotonic() - t0:.1f} s", flush=True)
        watcher.wait(executor, lambda: watcher.map_ready(args.scans), args.timeout,
                     f"the calibrator to hold the map of all {args.scans} scans")
        report["map_points"] = int(watcher.get("calibrator")["map_points"])
        report["map_held_after"] = time.monotonic() - t0
        print(f"calibrator holds the map: {report['map_points']} points", flush=True)
        initial = read_pose(args.initial)
        for i in range(args.goals + args.refused):
            goal = make_goal(initial, verification_starts=0)
            refused = i >= args.goals
            if refused:  # answered at once: the action protocol's own round trip
                goal.bound_translation_m.x = -1.0
            t = time.monotonic()
            out = client.call(executor, goal, timeout=args.timeout)
            seconds = time.monotonic() - t
            result = out.result
            tf = result.transform.transform
            report["goals"].append({
                "kind": "refused" if refused else "calibrate", "status": out.status,
                "message": result.message, "round_trip": seconds,
                "server_seconds": result.seconds, "feedback": len(out.feedback),
                "frame_id": result.transform.header.frame_id,
                "child_frame_id": result.transform.child_frame_id,
                "translation": [tf.translation.x, tf.translation.y, tf.translation.z],
                "rotation": [tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w]})
            print(f"goal {i + 1}: {out.status} in {seconds:.3f} s: {result.message}", flush=True)
        code = 0
    except (TimeoutError, RuntimeError) as exc:
        report["error"] = str(exc)
        print(f"roadside client: {exc}", flush=True)
        code = 1
    finally:
        Path(args.out).write_text(json.dumps(report, indent=1))
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return code


def probe(args: argparse.Namespace) -> int:
    """List, for ``--seconds`` (or until the ``--until`` nodes and a map are seen), the nodes
    and ``/map`` publishers this process can see."""
    import rclpy
    from sensor_msgs.msg import PointCloud2

    from semcal_ros.ros import qos

    rclpy.init()
    node = rclpy.create_node("isolation_probe")
    maps: list[Any] = []
    node.create_subscription(PointCloud2, "/map", maps.append, qos.latched())
    wanted = set(filter(None, args.until.split(",")))

    def seen_enough() -> bool:  # --until: every named node and a map (never, without it)
        return bool(wanted) and bool(maps) and wanted <= set(node.get_node_names())

    deadline = time.monotonic() + args.seconds
    while time.monotonic() < deadline and not seen_enough():
        rclpy.spin_once(node, timeout_sec=0.1)
    seen = {"nodes": sorted(n for n in node.get_node_names() if n != "isolation_probe"),
            "map_publishers": node.count_publishers("/map"), "maps_received": len(maps)}
    Path(args.out).write_text(json.dumps(seen))
    print(json.dumps(seen), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="two-host helpers run as processes")
    sub = ap.add_subparsers(dest="command", required=True)
    c = sub.add_parser("client", help="the roadside unit's action client")
    c.add_argument("--initial", required=True, help="initial pose YAML (the scene's)")
    c.add_argument("--scans", type=int, required=True, help="scans the map must hold")
    c.add_argument("--goals", type=int, default=1, help="calibration goals, one after another")
    c.add_argument("--refused", type=int, default=0,
                   help="then this many goals the calibrator refuses at once")
    c.add_argument("--timeout", type=float, default=120.0)
    c.add_argument("--out", required=True, help="JSON report")
    c.set_defaults(func=roadside_client)
    p = sub.add_parser("probe", help="which nodes and /map publishers are visible")
    p.add_argument("--seconds", type=float, default=3.0,
                   help="how long to listen (with --until: at most)")
    p.add_argument("--until", default="",
                   help="comma-separated node names: stop once all are seen and a map came")
    p.add_argument("--out", required=True)
    p.set_defaults(func=probe)
    args = ap.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
