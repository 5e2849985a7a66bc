"""The newest label image, CameraInfo and camera image of one camera, each checked on arrival.

The calibrator (one or many cameras) and the calibration monitor both need, per camera, the
latest usable messages and the reason the last unusable one was refused. Keeping that here means
both refuse the same messages with the same words, and it can be tested without DDS: the
``on_*`` methods take ROS messages and can be called directly.

A message that cannot be used (a label image that is not mono8, a CameraInfo with NaN intrinsics
...) is refused: the reason is logged once (again only when it changes) and kept in
:meth:`CameraInputs.refusals`; what the camera held before is kept. A good message of the same
kind clears the refusal.

Topics: the unnamed camera (``name == ""``) listens on ``camera/labels``, ``camera/camera_info``
and ``camera/image_raw`` (the single-camera calibrator's names); a camera named ``north`` on
``north/labels``, ``north/camera_info`` and ``north/image_raw``. All are relative: remap them or
use a namespace.

``image_transport`` / ``labels_transport`` ``compressed`` subscribe
``sensor_msgs/CompressedImage`` on ``<resolved topic>/compressed`` instead (image_transport's
naming): camera images as JPEG or PNG, label images as PNG only (JPEG changes class ids and is
refused). Compressed data that does not decode, or a JPEG that libjpeg decodes only with its
"Corrupt JPEG data" warning, is dropped with a WARN naming the topic (at most one every
``WARN_PERIOD`` s, counting the frames dropped in between). A label or camera image whose size
differs from the held CameraInfo's is refused on arrival, and the one held is kept.
"""

from __future__ import annotations

import math
import re
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from semcal_ros.engine.camera import CameraModel
from semcal_ros.io.images import UndecodableImage
from semcal_ros.ros import compressed
from semcal_ros.ros import conversions as conv

#: The kinds of input a camera has, as named in refusals and diagnostics.
LABELS, CAMERA_INFO, IMAGE = "label image", "CameraInfo", "camera image"

_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")

#: s between WARNs about undecodable compressed data of one kind (a damaged stream would
#: otherwise log every frame: each damaged frame has its own byte count in its reason).
WARN_PERIOD = 10.0


@dataclass(frozen=True)
class CameraTopics:
    """One camera's name and its three (relative) topic names."""

    name: str  # "" for the unnamed single camera
    labels: str
    camera_info: str
    image: str

    @classmethod
    def for_name(cls, name: str) -> "CameraTopics":
        """``<name>/labels`` etc.; ``camera/...`` for the unnamed camera."""
        prefix = name or "camera"
        return cls(name, f"{prefix}/labels", f"{prefix}/camera_info", f"{prefix}/image_raw")

    @property
    def label(self) -> str:
        """How logs and messages name the camera."""
        return f"camera '{self.name}'" if self.name else "the camera"


def camera_topics(names: Sequence[str]) -> list[CameraTopics]:
    """The topics of each named camera (none named: the one unnamed camera). ValueError naming
    a name that cannot be a topic namespace, or one given twice."""
    names = list(names)
    if not names:
        return [CameraTopics.for_name("")]
    bad = [n for n in names if not _NAME.match(n)]
    if bad:
        raise ValueError(f"parameter 'cameras': {', '.join(repr(n) for n in bad)} cannot name a "
                         "camera (letters, digits and '_', starting with a letter)")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ValueError(f"parameter 'cameras': {', '.join(twice)} given more than once")
    return [CameraTopics.for_name(n) for n in names]


@dataclass(frozen=True)
class CameraSnapshot:
    """What one camera holds at one moment (None: not received yet)."""

    name: str
    labels: np.ndarray | None  # mono8 trainIds
    labels_frame: str
    camera: CameraModel | None
    rgb: np.ndarray | None  # the camera image (for overlays), RGB

    @property
    def frame_id(self) -> str:
        """The camera's frame: its CameraInfo's, else its label image's ("" before either)."""
        if self.camera is not None and self.camera.frame_id:
            return self.camera.frame_id
        return self.labels_frame


class CameraInputs:
    """The newest usable messages of one camera (thread safe).

    ``log_refusal`` is called with one line (``"ignoring CameraInfo: K contains NaN ..."``) when a
    refusal is new or its reason changed; ``resolve`` turns a relative topic name into the full
    one for messages (a node's ``resolve_topic_name``). ``log_warning`` (default:
    ``log_refusal``) says that compressed data did not decode.
    """

    def __init__(self, topics: CameraTopics,
                 log_refusal: Callable[[str], None] | None = None,
                 resolve: Callable[[str], str] | None = None,
                 image_transport: str = "raw", labels_transport: str = "raw",
                 log_warning: Callable[[str], None] | None = None) -> None:
        self.topics = topics
        self._log = log_refusal or (lambda _text: None)
        self._warn = log_warning or self._log
        self._resolve = resolve or (lambda name: name)
        self.transports = {LABELS: compressed.check_transport(labels_transport,
                                                              "labels_transport"),
                           IMAGE: compressed.check_transport(image_transport)}
        self._topic = {LABELS: topics.labels, CAMERA_INFO: topics.camera_info,
                       IMAGE: topics.image}  # as subscribed (resolved for compressed ones)
        self._lock = threading.Lock()
        self._labels: np.ndarray | None = None
        self._labels_frame = ""
        self._camera: CameraModel | None = None
        self._rgb: np.ndarray | None = None
        self._refusals: dict[str, str] = {}
        self._dropped: dict[str, tuple[float, int]] = {}  # kind -> (last WARN, dropped since)
        self._clock = time.monotonic
        self.received = {LABELS: 0, CAMERA_INFO: 0, IMAGE: 0}

    @property
    def name(self) -> str:
        return self.topics.name

    # --- messages ---------------------------------------------------------------------------
    def _sized(self, what: str, convert: Callable[[Any], np.ndarray]
               ) -> Callable[[Any], np.ndarray]:
        """``convert``, then a check that the image has the held CameraInfo's size: a label
        image of another size would replace the good one held (and the next goal abort), a
        camera image of another size would silently not be drawn under the overlay."""
        def checked(msg: Any) -> np.ndarray:
            image = convert(msg)
            with self._lock:
                camera = self._camera
            h, w = image.shape[:2]
            if camera is not None and (w, h) != (camera.width, camera.height):
                raise ValueError(f"the {what} is {w}x{h} but CameraInfo says "
                                 f"{camera.width}x{camera.height}; keeping the one held")
            return image
        return checked

    def on_labels(self, msg: Any) -> bool:
        """Keep a label image (mono8, or PNG CompressedImage) of the CameraInfo's size (any
        size before a CameraInfo); False when refused."""
        labels = self._convert(LABELS, self._sized(LABELS, compressed.to_labels), msg)
        if labels is None:
            return False
        with self._lock:
            self._labels, self._labels_frame = labels, msg.header.frame_id
        return True

    def on_camera_info(self, msg: Any) -> bool:
        """Keep a CameraInfo as a :class:`CameraModel`; False when refused."""
        camera = self._convert(CAMERA_INFO, conv.camera_info_to_model, msg)
        if camera is None:
            return False
        with self._lock:
            self._camera = camera
        return True

    def on_image(self, msg: Any) -> bool:
        """Keep a camera image (rgb8 / bgr8 / JPEG / PNG, kept as RGB) of the CameraInfo's size;
        False when refused."""
        rgb = self._convert(IMAGE, self._sized(IMAGE, compressed.to_rgb), msg)
        if rgb is None:
            return False
        with self._lock:
            self._rgb = rgb
        return True

    def _convert(self, what: str, convert: Callable[[Any], Any], msg: Any) -> Any:
        """``convert(msg)``, or None with the reason logged (once per reason) and kept."""
        try:
            value = convert(msg)
        except ValueError as exc:
            now = self._clock()
            with self._lock:
                self.received[what] += 1
                new = self._refusals.get(what) != str(exc)
                self._refusals[what] = str(exc)
                if isinstance(exc, UndecodableImage):
                    last, dropped = self._dropped.get(what, (-math.inf, 0))
                    due = now - last >= WARN_PERIOD
                    self._dropped[what] = (now, 0) if due else (last, dropped + 1)
            if isinstance(exc, UndecodableImage):
                if due:  # throttled: damaged frames of a stream each have their own reason
                    since = f" ({dropped} more dropped since the last warning)" if dropped else ""
                    self._warn(f"dropping a {what} on {self._resolve(self._topic[what])}: "
                               f"{exc}{since}")
            elif new:
                where = f" ({self.topics.name})" if self.topics.name else ""
                self._log(f"ignoring {what}{where}: {exc}")
            return None
        with self._lock:
            self.received[what] += 1
            self._refusals.pop(what, None)
        return value

    def subscribe(self, node: Any, callback_group: Any = None,
                  qos_overriding_options: Any = None) -> None:
        """Subscribe ``node`` to the camera's three topics (sensor-data QoS, depth 2)."""
        from sensor_msgs.msg import CameraInfo

        from semcal_ros.ros import qos

        labels_type, self._topic[LABELS] = compressed.subscription(
            node, self.topics.labels, self.transports[LABELS])
        image_type, self._topic[IMAGE] = compressed.subscription(
            node, self.topics.image, self.transports[IMAGE])
        for kind, topic, callback in ((labels_type, self._topic[LABELS], self.on_labels),
                                      (CameraInfo, self.topics.camera_info, self.on_camera_info),
                                      (image_type, self._topic[IMAGE], self.on_image)):
            node.create_subscription(kind, topic, callback, qos.sensor(2),
                                     callback_group=callback_group,
                                     qos_overriding_options=qos_overriding_options)

    # --- what is held -----------------------------------------------------------------------
    def snapshot(self) -> CameraSnapshot:
        with self._lock:
            return CameraSnapshot(self.name, self._labels, self._labels_frame, self._camera,
                                  self._rgb)

    def refusals(self) -> dict[str, str]:
        """The reason the last message of each kind was refused (kinds whose last was good are
        absent)."""
        with self._lock:
            return dict(self._refusals)

    def answers_to(self, camera_frame_id: str) -> bool:
        """Whether a goal's ``camera_frame_id`` means this camera: its name, or the frame id of
        its CameraInfo or label image."""
        if not camera_frame_id:
            return False
        snap = self.snapshot()
        ids = {self.name, snap.labels_frame, snap.camera.frame_id if snap.camera else ""} - {""}
        return camera_frame_id in ids

    def problems(self, camera_frame_id: str = "") -> list[str]:
        """What is missing or does not fit together (empty: ready), each naming its topic."""
        from semcal_ros.ros.calibrate_goal import camera_problems

        snap = self.snapshot()
        return camera_problems(camera_frame_id, snap.labels, snap.labels_frame, snap.camera,
                               self._resolve(self._topic[LABELS]),
                               self._resolve(self.topics.camera_info))

    def values(self) -> dict[str, Any]:
        """Key/values for a /diagnostics status."""
        snap = self.snapshot()
        out: dict[str, Any] = {
            "label_image": "x".join(map(str, snap.labels.shape[1::-1]))
            if snap.labels is not None else "none",
            "camera_info": f"{snap.camera.width}x{snap.camera.height} '{snap.camera.frame_id}'"
            if snap.camera is not None else "none",
            "camera_image": "x".join(map(str, snap.rgb.shape[1::-1]))
            if snap.rgb is not None else "none",
        }
        out.update({f"input_error.{k}": v for k, v in self.refusals().items()})
        return out


__all__ = ["CAMERA_INFO", "IMAGE", "LABELS", "CameraInputs", "CameraSnapshot", "CameraTopics",
           "camera_topics"]
