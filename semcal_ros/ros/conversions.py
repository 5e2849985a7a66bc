"""ROS messages <-> numpy arrays and the library's types (LabelledCloud, CameraModel, Pose).

The one place where message layouts are known: nodes call these and hand library types on, so no
ROS message goes past ``semcal_ros/ros``. Point clouds and images are converted with numpy views
of the message buffer (no per-point Python), because a 100k-point scan arrives ten times a second.
The replacements for ``sensor_msgs_py`` and ``cv_bridge``, which are not on PyPI.
"""

from __future__ import annotations

import math

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose as PoseMsg
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, Transform, TransformStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import Header

from semcal_ros.engine import validation
from semcal_ros.engine.camera import (COEFFICIENTS, SUPPORTED_MODELS, CameraModel,
                                      coefficient_check)
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.pose import Pose

#: PointField datatype -> numpy type (without byte order).
POINTFIELD_TO_NUMPY: dict[int, str] = {
    PointField.INT8: "i1", PointField.UINT8: "u1", PointField.INT16: "i2",
    PointField.UINT16: "u2", PointField.INT32: "i4", PointField.UINT32: "u4",
    PointField.FLOAT32: "f4", PointField.FLOAT64: "f8",
}
NUMPY_TO_POINTFIELD: dict[str, int] = {v: k for k, v in POINTFIELD_TO_NUMPY.items()}

#: Image encodings understood here: channels per pixel.
IMAGE_CHANNELS: dict[str, int] = {"rgb8": 3, "bgr8": 3, "mono8": 1, "8UC1": 1}


# --- time and headers ------------------------------------------------------------------------
def stamp_to_seconds(stamp: Time) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def seconds_to_stamp(seconds: float) -> Time:
    sec = math.floor(seconds)
    nanosec = int(round((seconds - sec) * 1e9))
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return Time(sec=int(sec), nanosec=nanosec)


def make_header(frame_id: str, stamp: Time | float | None = None) -> Header:
    if isinstance(stamp, (int, float)):
        stamp = seconds_to_stamp(float(stamp))
    return Header(frame_id=frame_id, stamp=stamp if stamp is not None else Time())


# --- PointCloud2 -----------------------------------------------------------------------------
def pointcloud2_dtype(msg: PointCloud2) -> np.dtype:
    """The structured numpy dtype of one point, honouring every field's offset and count."""
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in POINTFIELD_TO_NUMPY:
            raise ValueError(f"PointCloud2 field '{f.name}' has unknown datatype {f.datatype}")
        if f.name in names:
            raise ValueError(f"PointCloud2 has field '{f.name}' twice")
        base = np.dtype(order + POINTFIELD_TO_NUMPY[f.datatype])
        count = max(int(f.count), 1)
        if f.offset + base.itemsize * count > msg.point_step:
            raise ValueError(f"PointCloud2 field '{f.name}' (offset {f.offset}) does not fit in "
                             f"point_step {msg.point_step}")
        names.append(f.name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(int(f.offset))
    return np.dtype({"names": names, "formats": formats, "offsets": offsets,
                     "itemsize": int(msg.point_step)})


def pointcloud2_to_array(msg: PointCloud2) -> np.ndarray:
    """All points as a flat structured array (a view of the message buffer where possible)."""
    dtype = pointcloud2_dtype(msg)
    height, width = int(msg.height), int(msg.width)
    n = height * width
    if n == 0:
        return np.zeros(0, dtype)
    row_bytes = width * msg.point_step
    if msg.row_step < row_bytes:
        raise ValueError(f"PointCloud2 row_step {msg.row_step} is smaller than width x "
                         f"point_step ({row_bytes})")
    raw = np.frombuffer(msg.data, dtype=np.uint8)
    if raw.size < (height - 1) * msg.row_step + row_bytes:
        raise ValueError(f"PointCloud2 data has {raw.size} bytes, too few for {height} x {width} "
                         f"points (row_step {msg.row_step}, point_step {msg.point_step})")
    if msg.row_step == row_bytes:
        return raw[: n * msg.point_step].view(dtype)
    rows = np.lib.stride_tricks.as_strided(raw, (height, row_bytes), (msg.row_step, 1))
    return np.ascontiguousarray(rows).reshape(-1).view(dtype)


def _label_values(values: np.ndarray) -> np.ndarray:
    """SemanticKITTI ids as uint16: the low 16 bits of 32-bit ids (the high half is the
    instance), rounded floats for drivers that publish labels as float."""
    if values.dtype.kind == "f":
        finite = np.isfinite(values)
        out = np.zeros(values.shape, np.uint16)
        out[finite] = np.clip(np.rint(values[finite]), 0, 65535).astype(np.uint16)
        return out
    if values.dtype.itemsize > 2:
        return (values.astype(np.int64) & 0xFFFF).astype(np.uint16)
    return values.astype(np.uint16)


def pointcloud2_to_cloud(msg: PointCloud2, require_label: bool = False) -> LabelledCloud:
    """A LabelledCloud (xyz float64, label uint16 when a 'label' field exists, other scalar
    fields in ``extra``). Points are kept as they are, NaN included (``.finite()`` drops them)."""
    arr = pointcloud2_to_array(msg)
    names = arr.dtype.names or ()
    missing = [n for n in ("x", "y", "z") if n not in names]
    if missing:
        raise ValueError(f"PointCloud2 has no {', '.join(missing)} field "
                         f"(fields: {', '.join(names) or 'none'})")
    if require_label and "label" not in names:
        raise ValueError(f"PointCloud2 has no 'label' field (fields: {', '.join(names)})")
    xyz = np.empty((len(arr), 3), dtype=np.float64)
    for i, axis in enumerate("xyz"):
        xyz[:, i] = arr[axis]
    label = _label_values(arr["label"]) if "label" in names else None
    extra = {n: np.array(arr[n]) for n in names
             if n not in ("x", "y", "z", "label") and arr.dtype[n].shape == ()}
    return LabelledCloud(xyz, label, extra)


def array_to_pointcloud2(arr: np.ndarray, header: Header) -> PointCloud2:
    """A dense (height 1) PointCloud2 of a structured array; fields keep the array's layout."""
    if arr.dtype.names is None:
        raise ValueError("expected a structured array with named fields")
    arr = np.ascontiguousarray(arr)
    fields = []
    for name in arr.dtype.names:
        ftype, offset = arr.dtype.fields[name][:2]
        base, count = (ftype.base, int(np.prod(ftype.shape))) if ftype.shape else (ftype, 1)
        key = base.newbyteorder("<").str[1:] if base.byteorder != ">" else base.str[1:]
        if key not in NUMPY_TO_POINTFIELD:
            raise ValueError(f"field '{name}': dtype {base} has no PointField datatype")
        fields.append(PointField(name=name, offset=int(offset),
                                 datatype=NUMPY_TO_POINTFIELD[key], count=count))
    msg = PointCloud2(header=header, height=1, width=len(arr), fields=fields,
                      is_bigendian=arr.dtype.fields[arr.dtype.names[0]][0].byteorder == ">",
                      point_step=arr.dtype.itemsize, row_step=arr.dtype.itemsize * len(arr),
                      is_dense=False)
    msg.data = arr.tobytes()
    return msg


def cloud_to_pointcloud2(cloud: LabelledCloud, header: Header,
                         extra_fields: bool = True) -> PointCloud2:
    """x, y, z as float32, extra fields as they are, label as uint16 (last)."""
    msg = array_to_pointcloud2(cloud.to_structured(extra_fields), header)
    msg.is_dense = bool(np.all(np.isfinite(cloud.xyz)))
    return msg


# --- Image -----------------------------------------------------------------------------------
def image_to_numpy(msg: Image) -> np.ndarray:
    """(H, W) for mono8/8UC1, (H, W, 3) in the encoding's channel order for rgb8/bgr8."""
    channels = IMAGE_CHANNELS.get(msg.encoding)
    if channels is None:
        raise ValueError(f"unsupported image encoding '{msg.encoding}' "
                         f"(supported: {', '.join(IMAGE_CHANNELS)})")
    h, w = int(msg.height), int(msg.width)
    row = w * channels
    if msg.step < row:
        raise ValueError(f"image step {msg.step} is smaller than width x channels ({row})")
    raw = np.frombuffer(msg.data, dtype=np.uint8)
    if h and raw.size < (h - 1) * msg.step + row:
        raise ValueError(f"image data has {raw.size} bytes, too few for {w}x{h} "
                         f"{msg.encoding} (step {msg.step})")
    rows = np.lib.stride_tricks.as_strided(raw, (h, row), (msg.step, 1))
    shape = (h, w) if channels == 1 else (h, w, channels)
    return np.ascontiguousarray(rows).reshape(shape)


def image_to_rgb(msg: Image) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an rgb8 or bgr8 image."""
    if msg.encoding not in ("rgb8", "bgr8"):
        raise ValueError(f"expected an rgb8 or bgr8 image, got encoding '{msg.encoding}'")
    img = image_to_numpy(msg)
    return np.ascontiguousarray(img[:, :, ::-1]) if msg.encoding == "bgr8" else img


def image_to_labels(msg: Image) -> np.ndarray:
    """(H, W) uint8 label image (Cityscapes trainIds) of a mono8 / 8UC1 image."""
    if msg.encoding not in ("mono8", "8UC1"):
        raise ValueError(f"expected a mono8 label image, got encoding '{msg.encoding}'")
    return image_to_numpy(msg)


def numpy_to_image(img: np.ndarray, encoding: str, header: Header) -> Image:
    """An Image of a uint8 (H, W) mono8 or (H, W, 3) rgb8/bgr8 array (no conversion of order)."""
    channels = IMAGE_CHANNELS.get(encoding)
    if channels is None:
        raise ValueError(f"unsupported image encoding '{encoding}' "
                         f"(supported: {', '.join(IMAGE_CHANNELS)})")
    img = np.asarray(img)
    expected = 2 if channels == 1 else 3
    if img.dtype != np.uint8 or img.ndim != expected or (channels == 3 and img.shape[2] != 3):
        raise ValueError(f"{encoding} needs a uint8 array of {expected} dims"
                         + (" with 3 channels" if channels == 3 else "")
                         + f", got {img.dtype} {img.shape}")
    msg = Image(header=header, height=img.shape[0], width=img.shape[1], encoding=encoding,
                is_bigendian=0, step=img.shape[1] * channels)
    msg.data = np.ascontiguousarray(img).tobytes()
    return msg


# --- CameraInfo ------------------------------------------------------------------------------
def camera_info_to_model(msg: CameraInfo) -> CameraModel:
    """CameraModel of the raw image; frame id from the header. ValueError naming every problem
    (the caller says it is a CameraInfo; the messages do not repeat it)."""
    model = msg.distortion_model
    d = np.asarray(msg.d, dtype=float)
    problems = []
    if model not in SUPPORTED_MODELS:
        problems.append(f"unsupported distortion model '{model}' (supported: "
                        f"{', '.join(COEFFICIENTS)})")
    else:
        problem, _note = coefficient_check(model, d)  # the note is said by CameraModel
        if problem:
            problems.append(problem)
    if msg.binning_x > 1 or msg.binning_y > 1:
        problems.append(f"binning {msg.binning_x}x{msg.binning_y} is not supported")
    roi = msg.roi
    if roi.width and (roi.width, roi.height) != (msg.width, msg.height):
        problems.append("a region of interest smaller than the image is not supported")
    k = np.asarray(msg.k, dtype=float).reshape(3, 3)
    problems += validation.camera_problems(msg.width, msg.height, k, d)
    validation.check(problems)
    return CameraModel(int(msg.width), int(msg.height), k, d,
                       msg.header.frame_id or "camera_optical", model or "plumb_bob")


def model_to_camera_info(camera: CameraModel, header: Header | None = None) -> CameraInfo:
    p = np.zeros((3, 4))
    p[:, :3] = camera.k
    return CameraInfo(header=header or make_header(camera.frame_id), width=camera.width,
                      height=camera.height, distortion_model=camera.model,
                      d=[float(v) for v in camera.d], k=camera.k.ravel(), r=np.eye(3).ravel(),
                      p=p.ravel())


# --- poses -----------------------------------------------------------------------------------
def pose_to_msg(pose: Pose) -> PoseMsg:
    msg = PoseMsg()
    msg.position.x, msg.position.y, msg.position.z = (float(v) for v in pose.translation)
    q = pose.quaternion
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = (
        float(v) for v in q)
    return msg


def pose_from_msg(msg: PoseMsg) -> Pose:
    """Raises ValueError naming the problem for non-finite values or a non-unit quaternion."""
    t = [msg.position.x, msg.position.y, msg.position.z]
    q = [msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w]
    return Pose(np.array(t), np.array(q))


def pose_from_transform(msg: Transform | TransformStamped) -> Pose:
    tf = msg.transform if isinstance(msg, TransformStamped) else msg
    t = [tf.translation.x, tf.translation.y, tf.translation.z]
    q = [tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w]
    return Pose(np.array(t), np.array(q))


def transform_from_pose(pose: Pose, frame_id: str, child_frame_id: str,
                        stamp: Time | float | None = None) -> TransformStamped:
    """The pose of ``child_frame_id`` in ``frame_id`` (tf's parent -> child transform)."""
    msg = TransformStamped(header=make_header(frame_id, stamp), child_frame_id=child_frame_id)
    tr, rot = msg.transform.translation, msg.transform.rotation
    tr.x, tr.y, tr.z = (float(v) for v in pose.translation)
    rot.x, rot.y, rot.z, rot.w = (float(v) for v in pose.quaternion)
    return msg


def stamped_pose(msg: Odometry | PoseStamped | PoseWithCovarianceStamped | TransformStamped
                 ) -> tuple[float, Pose, str]:
    """(stamp in seconds, pose, parent frame id) of a pose-carrying message."""
    if isinstance(msg, Odometry):
        pose = pose_from_msg(msg.pose.pose)
    elif isinstance(msg, PoseWithCovarianceStamped):
        pose = pose_from_msg(msg.pose.pose)
    elif isinstance(msg, PoseStamped):
        pose = pose_from_msg(msg.pose)
    elif isinstance(msg, TransformStamped):
        pose = pose_from_transform(msg)
    else:
        raise ValueError(f"no pose in a {type(msg).__name__} message")
    return stamp_to_seconds(msg.header.stamp), pose, msg.header.frame_id
