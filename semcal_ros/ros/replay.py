"""Play a rosbag2 (mcap or sqlite3) into the live ROS graph: the engine of ``bag_player`` and
``semcal replay``.

There is no ``ros2 bag`` on PyPI, so bags are read with ``rosbags`` and their CDR bytes are
published unchanged (an rclpy publisher accepts serialized bytes): no message is deserialised.
Messages keep their recorded spacing, scaled by ``rate``; ``/clock`` carries the bag's time so
nodes with ``use_sim_time`` follow it. Before exiting, every reliable publisher waits until its
subscribers acknowledged everything (a reliable burst followed by an exit otherwise loses the
tail until the next heartbeat, which never comes).
"""

from __future__ import annotations

import importlib
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from semcal_ros.ros import qos as semcal_qos
from semcal_ros.ros.conversions import seconds_to_stamp


@dataclass
class ReplayParams:
    bag: str = ""  # folder of a rosbag2 (metadata.yaml + .mcap/.db3) or a single .mcap/.db3
    rate: float = 1.0  # playback speed factor
    clock: bool = False  # publish /clock with the bag's time
    clock_frequency: float = 50.0  # Hz of /clock while waiting between messages
    loop: bool = False  # start over at the end until stopped
    topics: tuple[str, ...] = ()  # only these topics (empty: all)
    wait_for_subscribers: float = 2.0  # s to wait for every topic to have a subscriber
    # s to wait before the first message, after the wait above: a publisher sees a subscriber
    # before that subscriber has matched the publisher, and best-effort samples sent in between
    # are lost (measured: up to 0.7 s on a loaded machine)
    start_delay: float = 1.0
    ack_timeout: float = 10.0  # s to wait for reliable subscribers to acknowledge at the end
    depth: int = 10  # publisher history depth (transient-local topics keep their recorded one)
    # read every message once before playing: chunk CRCs checked, every message decoded (a
    # damaged bag is refused instead of publishing garbage); ~0.35 s per 160 MB
    verify: bool = True

    def __post_init__(self) -> None:
        if not (self.rate > 0 and math.isfinite(self.rate)):
            raise ValueError(f"rate must be a positive number, got {self.rate}")
        if self.clock_frequency <= 0:
            raise ValueError(f"clock_frequency must be positive, got {self.clock_frequency}")
        if self.depth < 1:
            raise ValueError(f"depth must be at least 1, got {self.depth}")


@dataclass
class ReplayStats:
    messages: int = 0
    loops: int = 0
    bag_seconds: float = 0.0  # duration of the bag (first to last message)
    wall_seconds: float = 0.0
    per_topic: dict[str, int] = field(default_factory=dict)
    skipped_topics: dict[str, str] = field(default_factory=dict)  # topic -> reason
    unacknowledged: list[str] = field(default_factory=list)


def open_bag(path: str | Path):
    """A ``rosbags`` reader (opened) of a bag folder or a single .mcap/.db3 file."""
    from rosbags.rosbag2 import Reader

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"bag not found: {path}")
    if path.is_file():  # rosbags opens folders; a lone storage file is read via its folder
        if not (path.parent / "metadata.yaml").is_file():
            raise ValueError(f"{path}: a bag file needs its metadata.yaml next to it "
                             f"(pass the bag folder)")
        path = path.parent
    elif not (path / "metadata.yaml").is_file():
        raise ValueError(f"{path}: not a rosbag2 folder (no metadata.yaml)")
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # rosbags raises its own error types for corrupt bags
        raise ValueError(f"{path}: cannot read bag ({exc})") from None
    return reader


@dataclass
class BagCheck:
    errors: list[str] = field(default_factory=list)  # the bag is damaged
    notes: list[str] = field(default_factory=list)  # what could not be checked


def _mcap_chunk_crcs(path: Path) -> list[int]:
    """The CRC field of every chunk record of an mcap file (0: the writer stored none)."""
    import struct

    crcs = []
    with open(path, "rb") as f:
        f.seek(8)  # magic
        while True:
            head = f.read(9)
            if len(head) < 9 or head[0] in (0x02, 0x0F):  # footer / data end: no more chunks
                break
            op, length = head[0], struct.unpack_from("<Q", head, 1)[0]
            if op == 0x06:  # chunk: start time, end time, uncompressed size, crc, ...
                crcs.append(struct.unpack_from("<I", f.read(28), 24)[0])
                f.seek(length - 28, 1)
            else:
                f.seek(length, 1)
    return crcs


def verify_bag(path: str | Path) -> BagCheck:
    """Read every message of the bag once: a chunk whose CRC does not match (rosbags checks the
    CRCs the writer stored) or a message that no longer decodes is an error; what the storage
    cannot tell (an mcap without CRCs, sqlite3 has none) is a note."""
    from rosbags.typesys import Stores, get_typestore

    check = BagCheck()
    typestore = get_typestore(Stores.ROS2_JAZZY)
    reader = open_bag(path)
    count, where = 0, "at the start"
    try:
        for conn, stamp_ns, raw in reader.messages():
            where = f"after message {count} ({conn.topic} at {stamp_ns * 1e-9:.3f} s)"
            if conn.msgtype in typestore.types:
                try:
                    typestore.deserialize_cdr(raw, conn.msgtype)
                except Exception as exc:  # noqa: BLE001 - any decoding failure is damage
                    check.errors.append(f"message {count} on {conn.topic} at "
                                        f"{stamp_ns * 1e-9:.3f} s does not decode as "
                                        f"{conn.msgtype} ({type(exc).__name__}: {exc})")
                    break
            count += 1
    except Exception as exc:  # noqa: BLE001 - rosbags' ReaderError and struct errors alike
        check.errors.append(f"damaged {where}: {exc}".rstrip("."))
    finally:
        reader.close()
    folder = Path(path) if Path(path).is_dir() else Path(path).parent
    mcaps = sorted(folder.glob("*.mcap"))
    if not check.errors and mcaps and any(c == 0 for m in mcaps for c in _mcap_chunk_crcs(m)):
        check.notes.append("its chunks carry no CRC (written by rosbags?): damage inside "
                           "message data cannot be detected")
    return check


def message_class(msgtype: str) -> Any:
    """The rclpy message class of ``pkg/msg/Name`` (ImportError if the package is missing)."""
    parts = msgtype.split("/")
    if len(parts) != 3:
        raise ImportError(f"not a message type name: {msgtype}")
    module = importlib.import_module(f"{parts[0]}.{parts[1]}")
    return getattr(module, parts[2])


def publisher_qos(connection: Any, depth: int) -> QoSProfile:
    """The recorded offered QoS where it says something, else reliable / volatile / ``depth``."""
    profiles = getattr(getattr(connection, "ext", None), "offered_qos_profiles", None) or []
    reliability, durability, keep = ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE, depth
    for profile in profiles:
        if int(profile.reliability) == int(ReliabilityPolicy.BEST_EFFORT):
            reliability = ReliabilityPolicy.BEST_EFFORT
        if int(profile.durability) == int(DurabilityPolicy.TRANSIENT_LOCAL):
            durability = DurabilityPolicy.TRANSIENT_LOCAL
            keep = max(int(profile.depth), 1)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=keep, reliability=reliability,
                      durability=durability)


class BagReplay:
    """Publishes one bag through ``node``; :meth:`run` blocks until the end (or a stop)."""

    def __init__(self, node: Node, params: ReplayParams,
                 log: Callable[[str], None] | None = None) -> None:
        if not params.bag:
            raise ValueError("no bag given (parameter 'bag')")
        self.node, self.params = node, params
        self.log = log or (lambda text: node.get_logger().info(text))
        if params.verify:
            check = verify_bag(params.bag)
            if check.errors:
                raise ValueError(f"{params.bag}: {check.errors[0]}")
            for note in check.notes:
                node.get_logger().warning(f"{params.bag}: {note}")
        self.reader = open_bag(params.bag)
        self.stats = ReplayStats()
        self.publishers: dict[str, Any] = {}
        self.connections = []
        wanted = set(params.topics)
        for conn in self.reader.connections:
            if wanted and conn.topic not in wanted:
                continue
            try:
                cls = message_class(conn.msgtype)
            except (ImportError, AttributeError) as exc:
                self.stats.skipped_topics[conn.topic] = f"type {conn.msgtype} unavailable ({exc})"
                continue
            if conn.topic not in self.publishers:
                self.publishers[conn.topic] = node.create_publisher(
                    cls, conn.topic, publisher_qos(conn, params.depth))
            self.connections.append(conn)
        missing = wanted - {c.topic for c in self.reader.connections}
        if missing:
            raise ValueError(f"topic(s) not in the bag: {', '.join(sorted(missing))}")
        for topic, reason in self.stats.skipped_topics.items():
            self.log(f"skipping {topic}: {reason}")
        if not self.connections:
            raise ValueError(f"{params.bag}: nothing to play")
        self.clock_pub = node.create_publisher(Clock, "/clock", semcal_qos.reliable(1)) \
            if params.clock else None
        self.start_ns = min(self.reader.start_time, self.reader.end_time)
        self.stats.bag_seconds = max(self.reader.end_time - self.start_ns, 0) * 1e-9
        self.message_count = sum(c.msgcount for c in self.connections)

    def close(self) -> None:
        self.reader.close()

    # --- playing ---------------------------------------------------------------------------
    def _publish_clock(self, bag_ns: int) -> None:
        if self.clock_pub is not None:
            self.clock_pub.publish(Clock(clock=seconds_to_stamp(bag_ns * 1e-9)))

    def _wait_until(self, wall_target: float, bag_at: Callable[[float], int],
                    should_stop: Callable[[], bool]) -> bool:
        """Sleep until ``wall_target`` (monotonic), publishing /clock on the way; False if
        stopped."""
        period = 1.0 / self.params.clock_frequency
        while True:
            if should_stop():
                return False
            now = time.monotonic()
            if now >= wall_target:
                return True
            if self.clock_pub is not None:
                self._publish_clock(bag_at(now))
                time.sleep(min(period, wall_target - now))
            else:
                time.sleep(min(0.05, wall_target - now))

    def _wait_for_subscribers(self, should_stop: Callable[[], bool]) -> None:
        deadline = time.monotonic() + self.params.wait_for_subscribers
        while time.monotonic() < deadline and not should_stop():
            if all(p.get_subscription_count() > 0 for p in self.publishers.values()):
                return
            time.sleep(0.02)
        lonely = [t for t, p in self.publishers.items() if p.get_subscription_count() == 0]
        if lonely and self.params.wait_for_subscribers > 0:
            self.log(f"no subscriber yet on {', '.join(lonely)}; playing anyway")

    def run(self, should_stop: Callable[[], bool] = lambda: False,
            on_message: Callable[[str, int], None] | None = None) -> ReplayStats:
        """Play (looping if asked) until the end or ``should_stop()``; then wait for acks."""
        p = self.params
        t_start = time.monotonic()
        self._wait_for_subscribers(should_stop)
        if p.start_delay > 0:
            time.sleep(p.start_delay)
        while not should_stop():
            wall0 = time.monotonic()

            def bag_at(wall: float) -> int:
                return self.start_ns + int((wall - wall0) * p.rate * 1e9)

            self._publish_clock(self.start_ns)
            for conn, stamp_ns, raw in self.reader.messages(connections=self.connections):
                target = wall0 + (stamp_ns - self.start_ns) * 1e-9 / p.rate
                if not self._wait_until(target, bag_at, should_stop):
                    break
                self._publish_clock(stamp_ns)
                self.publishers[conn.topic].publish(raw)
                self.stats.messages += 1
                self.stats.per_topic[conn.topic] = self.stats.per_topic.get(conn.topic, 0) + 1
                if on_message is not None:
                    on_message(conn.topic, stamp_ns)
            else:
                self.stats.loops += 1
                if p.loop:
                    continue
            break
        if not should_stop():
            self.stats.unacknowledged = self.wait_for_acks()
        self.stats.wall_seconds = time.monotonic() - t_start
        return self.stats

    def wait_for_acks(self) -> list[str]:
        """Topics whose reliable subscribers did not acknowledge everything in time."""
        late = []
        deadline = time.monotonic() + self.params.ack_timeout
        for topic, pub in self.publishers.items():
            if pub.qos_profile.reliability != ReliabilityPolicy.RELIABLE:
                continue
            left = max(deadline - time.monotonic(), 0.0)
            if not pub.wait_for_all_acked(Duration(seconds=left)):
                late.append(topic)
        return late
