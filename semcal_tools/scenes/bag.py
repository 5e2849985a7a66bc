"""The scene's raw sensor streams as a rosbag2 (mcap), written with ``rosbags`` (no ROS needed).

Topics: ``/lidar/points`` (PointCloud2: x, y, z, intensity float32 + label uint16, packed,
frame ``lidar``), ``/lidar/odom`` (Odometry of the lidar in ``map``), and the static camera's
``/camera/image_raw`` (rgb8), ``/camera/labels`` (mono8 trainIds) and ``/camera/camera_info``,
repeated every ``camera_period`` seconds so a late subscriber still gets them. A multi-camera
scene (``--cameras N``) has no ``/camera/*`` topics but ``/<name>/image_raw``, ``/<name>/labels`` and
``/<name>/camera_info`` per camera, frame ``<name>_optical``. Messages use the
Jazzy definitions of rosbags' type store, so the bag's type hashes match a Jazzy system.
:func:`compress_camera_images` (``semcal scene --compressed``) turns the image topics into
image_transport's ``<topic>/compressed`` streams (camera images JPEG, label images PNG).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from semcal_ros.engine.camera import CameraModel
from semcal_ros.engine.cloud import LabelledCloud

LIDAR_FRAME = "lidar"
MAP_FRAME = "map"

#: PointField datatype of each numpy record type the scans use.
_FIELD_TYPE = {"<f4": "FLOAT32", "<u2": "UINT16"}

TOPICS = {
    "/lidar/points": "sensor_msgs/msg/PointCloud2",
    "/lidar/odom": "nav_msgs/msg/Odometry",
    "/camera/image_raw": "sensor_msgs/msg/Image",
    "/camera/labels": "sensor_msgs/msg/Image",
    "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
}


def typestore():
    store = getattr(Stores, "ROS2_JAZZY", Stores.ROS2_HUMBLE)
    return get_typestore(store)


@dataclass
class CameraFrame:
    """The static camera's messages (one image pair, repeated)."""

    camera: CameraModel
    rgb: np.ndarray  # (H, W, 3) uint8
    labels: np.ndarray  # (H, W) uint8 trainIds
    frame_id: str = "camera_optical"
    prefix: str = "camera"  # topics /<prefix>/image_raw, /<prefix>/labels, /<prefix>/camera_info

    def topics(self) -> dict[str, str]:
        """This camera's topics and types, in the order the bag lists them."""
        return {f"/{self.prefix}/{name}": TOPICS[f"/camera/{name}"]
                for name in ("image_raw", "labels", "camera_info")}


class SceneBagWriter:
    """Writes scans, odometry and periodic camera messages in time order."""

    def __init__(self, path: str | Path, camera: CameraFrame | list[CameraFrame],
                 camera_period: float = 1.0) -> None:
        path = Path(path)
        if path.exists():
            raise FileExistsError(f"bag output already exists: {path}")
        self.ts = typestore()
        self.t = self.ts.types
        self._writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self.cameras = camera if isinstance(camera, list) else [camera]
        self.types = {t: k for t, k in TOPICS.items() if t.startswith("/lidar/")}
        for cam in self.cameras:
            self.types.update(cam.topics())
        self._conn = {topic: self._writer.add_connection(topic, kind, typestore=self.ts)
                      for topic, kind in self.types.items()}
        self.camera_period = camera_period
        self._next_camera: float | None = None
        self._closed = False

    # -- message builders -------------------------------------------------------------------
    def _header(self, stamp: float, frame: str):
        sec = int(np.floor(stamp))
        nsec = int(round((stamp - sec) * 1e9))
        if nsec >= 1_000_000_000:
            sec, nsec = sec + 1, nsec - 1_000_000_000
        time = self.t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        return self.t["std_msgs/msg/Header"](stamp=time, frame_id=frame)

    def _cloud(self, stamp: float, xyz: np.ndarray, intensity: np.ndarray, label: np.ndarray):
        # the project's one record layout (as map.ply and the nodes' PointCloud2): packed LE
        pts = LabelledCloud(xyz, label, {"intensity": intensity.astype(np.float32)}).to_structured()
        field = self.t["sensor_msgs/msg/PointField"]
        fields = [field(name=n, offset=pts.dtype.fields[n][1],
                        datatype=getattr(field, _FIELD_TYPE[pts.dtype.fields[n][0].str]), count=1)
                  for n in pts.dtype.names]
        return self.t["sensor_msgs/msg/PointCloud2"](
            header=self._header(stamp, LIDAR_FRAME), height=1, width=len(pts), fields=fields,
            is_bigendian=False, point_step=pts.dtype.itemsize,
            row_step=pts.dtype.itemsize * len(pts),
            data=np.frombuffer(pts.tobytes(), np.uint8), is_dense=True)

    def _odom(self, stamp: float, translation: np.ndarray, quaternion: np.ndarray):
        g = "geometry_msgs/msg/"
        pose = self.t[g + "Pose"](position=self.t[g + "Point"](*map(float, translation)),
                                  orientation=self.t[g + "Quaternion"](*map(float, quaternion)))
        zero3 = self.t[g + "Vector3"](0.0, 0.0, 0.0)
        return self.t["nav_msgs/msg/Odometry"](
            header=self._header(stamp, MAP_FRAME), child_frame_id=LIDAR_FRAME,
            pose=self.t[g + "PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=self.t[g + "TwistWithCovariance"](
                twist=self.t[g + "Twist"](linear=zero3, angular=zero3), covariance=np.zeros(36)))

    def _image(self, stamp: float, data: np.ndarray, encoding: str, frame_id: str):
        h, w = data.shape[:2]
        channels = 1 if data.ndim == 2 else data.shape[2]
        return self.t["sensor_msgs/msg/Image"](
            header=self._header(stamp, frame_id), height=h, width=w,
            encoding=encoding, is_bigendian=0, step=w * channels,
            data=np.ascontiguousarray(data, np.uint8).reshape(-1))

    def _camera_info(self, stamp: float, frame: CameraFrame):
        cam = frame.camera
        p = np.zeros((3, 4))
        p[:, :3] = cam.k
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.t["sensor_msgs/msg/CameraInfo"](
            header=self._header(stamp, frame.frame_id), height=cam.height, width=cam.width,
            distortion_model=cam.model, d=cam.d.astype(np.float64), k=cam.k.ravel(),
            r=np.eye(3).ravel(), p=p.ravel(), binning_x=0, binning_y=0, roi=roi)

    # -- writing ----------------------------------------------------------------------------
    def _write(self, topic: str, stamp: float, msg) -> None:
        raw = self.ts.serialize_cdr(msg, self.types[topic])
        self._writer.write(self._conn[topic], int(round(stamp * 1e9)), raw)

    def _camera_until(self, stamp: float) -> None:
        if self._next_camera is None:
            self._next_camera = stamp
        while self._next_camera <= stamp + 1e-9:
            t = self._next_camera
            for cam in self.cameras:
                p = f"/{cam.prefix}/"
                self._write(p + "camera_info", t, self._camera_info(t, cam))
                self._write(p + "image_raw", t, self._image(t, cam.rgb, "rgb8", cam.frame_id))
                self._write(p + "labels", t, self._image(t, cam.labels, "mono8", cam.frame_id))
            self._next_camera = t + self.camera_period

    def add_scan(self, stamp: float, translation: np.ndarray, quaternion: np.ndarray,
                 xyz: np.ndarray, intensity: np.ndarray, label: np.ndarray) -> None:
        """A scan in the lidar frame and the lidar's pose (x, y, z; qx, qy, qz, qw) in the map."""
        self._camera_until(stamp)
        self._write("/lidar/odom", stamp, self._odom(stamp, translation, quaternion))
        self._write("/lidar/points", stamp, self._cloud(stamp, xyz, intensity, label))

    def close(self, end_stamp: float | None = None) -> None:
        """Camera messages up to ``end_stamp``, then finish the bag (metadata.yaml)."""
        if self._closed:
            return
        if end_stamp is not None:
            self._camera_until(end_stamp)
        self._closed = True
        self._writer.close()

    def __enter__(self) -> "SceneBagWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# -- compressed camera streams (semcal scene --compressed) ---------------------------------------
def compressed_topic(topic: str) -> str:
    """image_transport's name of a topic's compressed stream."""
    return topic.rstrip("/") + "/compressed"


def compress_camera_images(bag: str | Path, jpeg_quality: int = 95) -> dict[str, str]:
    """Rewrite a bag's ``sensor_msgs/Image`` topics as image_transport's ``<topic>/compressed``
    (``sensor_msgs/CompressedImage``), as a recorder on a unit with little disk stores them:
    colour images JPEG (``rgb8; jpeg compressed bgr8``), mono8 label images PNG (lossless: JPEG
    would change class ids). Every other message is copied byte for byte, in order. Returns
    {old topic: new topic}."""
    from rosbags.rosbag2 import Reader

    from semcal_ros.io.images import encode

    bag = Path(bag)
    tmp = bag.with_name(bag.name + ".compressing")
    if tmp.exists():
        raise FileExistsError(f"{tmp} exists (an interrupted earlier run?): remove it first")
    ts = typestore()
    renamed: dict[str, str] = {}
    with Reader(bag) as reader:
        writer = Writer(tmp, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.open()
        try:
            out = {}
            for conn in reader.connections:
                if conn.msgtype == "sensor_msgs/msg/Image":
                    renamed[conn.topic] = compressed_topic(conn.topic)
                    out[conn.id] = writer.add_connection(renamed[conn.topic],
                                                         "sensor_msgs/msg/CompressedImage",
                                                         typestore=ts)
                else:
                    out[conn.id] = writer.add_connection(conn.topic, conn.msgtype, typestore=ts)
            for conn, stamp_ns, raw in reader.messages():
                if conn.topic in renamed:
                    img = ts.deserialize_cdr(raw, conn.msgtype)
                    channels = 1 if img.encoding in ("mono8", "8UC1") else 3
                    data = np.asarray(img.data, np.uint8).reshape(img.height, img.step)
                    pixels = data[:, :img.width * channels].reshape(
                        (img.height, img.width) if channels == 1 else
                        (img.height, img.width, 3))
                    codec = "png" if channels == 1 else "jpeg"
                    fmt, payload = encode(pixels, codec, "mono8" if channels == 1
                                          else img.encoding, jpeg_quality=jpeg_quality)
                    msg = ts.types["sensor_msgs/msg/CompressedImage"](
                        header=img.header, format=fmt, data=np.frombuffer(payload, np.uint8))
                    raw = ts.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage")
                writer.write(out[conn.id], stamp_ns, raw)
        finally:
            writer.close()
    backup = bag.with_name(bag.name + ".raw")
    bag.rename(backup)
    tmp.rename(bag)
    shutil.rmtree(backup)
    return renamed
