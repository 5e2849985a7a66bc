"""Compressed camera images as ``compressed_image_transport`` writes them, encoded and decoded
with OpenCV (no ROS here; :mod:`semcal_ros.ros.compressed` is the adapter).

Camera drivers and recorders on units with little disk publish ``<topic>/compressed``
(``sensor_msgs/CompressedImage``). Its ``format`` field says what the bytes are:
``"rgb8; jpeg compressed bgr8"`` / ``"bgr8; png compressed bgr8"`` (ROS 2: the original encoding,
the codec, and the channel order the codec was given - always bgr8 for colour, because
cv_bridge converts before ``cv::imencode``), ``"mono8; png compressed mono8"``, or a plain
``"jpeg"`` / ``"png"`` from older publishers. Whatever the original encoding, OpenCV decodes a
colour picture as BGR, so :func:`decode_rgb` always swaps to RGB once.

Label images carry class ids: JPEG changes pixel values near every boundary, so a JPEG label
stream is refused (:func:`decode_labels`); PNG is lossless and accepted.
"""

from __future__ import annotations

import cv2
import numpy as np

#: The codecs a CompressedImage may use here, by the name its ``format`` carries.
CODECS = ("jpeg", "png")

_MAGIC = {"jpeg": b"\xff\xd8\xff", "png": b"\x89PNG\r\n\x1a\n"}


class UndecodableImage(ValueError):
    """The bytes do not decode (truncated, corrupt): a transport problem, dropped with a WARN."""


def codec_of(fmt: str, data: bytes) -> str:
    """``jpeg`` or ``png``: named by the format (``"rgb8; jpeg compressed bgr8"``, ``"png"``),
    else sniffed from the data's magic bytes. ValueError for another codec
    (``compressedDepth``, ``tiff`` ...)."""
    text = (fmt or "").strip().lower()
    if "compresseddepth" in text:
        raise ValueError(f"format '{fmt}' is a depth stream (compressedDepth), not a camera image")
    codec_part = text.split(";", 1)[1] if ";" in text else text
    words = ["jpeg" if w == "jpg" else w for w in codec_part.split()]
    named = [c for c in CODECS if c in words]
    if named:
        return named[0]
    if codec_part:
        raise ValueError(f"unsupported compressed image format '{fmt}' (jpeg or png, as "
                         "compressed_image_transport writes them)")
    for codec, magic in _MAGIC.items():
        if bytes(data[:len(magic)]) == magic:
            return codec
    raise UndecodableImage(f"empty format and {len(data)} bytes that are neither JPEG nor PNG")


def _quiet_opencv() -> None:
    """OpenCV logs its own WARN for a truncated PNG: the caller's one line says it better."""
    logging = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging is not None and logging.getLogLevel() > logging.LOG_LEVEL_ERROR:
        logging.setLogLevel(logging.LOG_LEVEL_ERROR)


def _decode(data: bytes, flags: int, codec: str) -> np.ndarray:
    _quiet_opencv()
    buf = np.frombuffer(data, dtype=np.uint8)
    if buf.size == 0:
        raise UndecodableImage(f"no {codec.upper()} data (0 bytes)")
    img = cv2.imdecode(buf, flags)
    if img is None or img.size == 0:
        raise UndecodableImage(f"{buf.size} bytes do not decode as {codec.upper()}")
    return img


def _decode_jpeg_rgb(data: bytes) -> np.ndarray:
    """(H, W, 3) RGB of a JPEG, or :class:`UndecodableImage` also when libjpeg only warned.

    OpenCV decodes a JPEG with damaged entropy-coded data ("Corrupt JPEG data: 39 extraneous
    bytes before marker 0xd9", "premature end of data segment") into a picture with smeared or
    grey blocks and says so only on stderr; simplejpeg runs the same libjpeg-turbo with its
    warnings turned into errors (``strict``), and decodes good data to the same pixels as OpenCV
    (checked in test_safety_streams.py)."""
    import simplejpeg

    raw = bytes(data)
    try:
        return simplejpeg.decode_jpeg(raw, colorspace="RGB", strict=True)
    except ValueError as exc:
        _decode(raw, cv2.IMREAD_COLOR, "jpeg")  # no picture at all: that error, in its words
        why = " ".join(str(exc).split()) or "libjpeg warned"
        raise UndecodableImage(f"{len(raw)} bytes of corrupt JPEG ({why})") from None


def decode_rgb(fmt: str, data: bytes) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a compressed camera image (colour or grey JPEG / PNG); a JPEG that
    libjpeg decodes only with a warning is refused (:func:`_decode_jpeg_rgb`)."""
    codec = codec_of(fmt, data)
    if codec == "jpeg":
        if len(data) == 0:
            raise UndecodableImage("no JPEG data (0 bytes)")
        return _decode_jpeg_rgb(data)
    bgr = _decode(data, cv2.IMREAD_COLOR, codec)  # OpenCV's colour order: BGR
    if bgr.dtype != np.uint8:
        raise ValueError(f"compressed camera image is {bgr.dtype}, expected 8 bit")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def decode_labels(fmt: str, data: bytes) -> np.ndarray:
    """(H, W) uint8 class ids of a PNG-compressed label image; a JPEG one is refused."""
    codec = codec_of(fmt, data)
    if codec == "jpeg" or bytes(data[:3]) == _MAGIC["jpeg"]:
        raise ValueError("a JPEG label stream is refused: JPEG changes class ids near every "
                         "boundary; publish labels raw (mono8) or PNG-compressed")
    img = _decode(data, cv2.IMREAD_UNCHANGED, codec)
    if img.dtype != np.uint8 or img.ndim != 2:
        channels = 1 if img.ndim == 2 else img.shape[2]
        raise ValueError(f"a compressed label image must be 8-bit single channel (mono8), got "
                         f"{img.dtype} with {channels} channel(s)")
    return img


def encode(image: np.ndarray, codec: str, encoding: str, jpeg_quality: int = 95,
           png_level: int = 3) -> tuple[str, bytes]:
    """(format, bytes) as compressed_image_transport writes them, for an ``rgb8`` / ``bgr8`` /
    ``mono8`` image (its defaults: JPEG quality 95, PNG level 3)."""
    if codec not in CODECS:
        raise ValueError(f"unknown codec '{codec}' (choose from {', '.join(CODECS)})")
    img = np.ascontiguousarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {img.dtype}")
    if encoding == "rgb8":
        img, target = cv2.cvtColor(img, cv2.COLOR_RGB2BGR), "bgr8"
    elif encoding == "bgr8":
        target = "bgr8"
    elif encoding == "mono8":
        target = "mono8"
    else:
        raise ValueError(f"cannot compress encoding '{encoding}' (rgb8, bgr8 or mono8)")
    if (target == "mono8") != (img.ndim == 2):
        raise ValueError(f"{encoding} does not fit an image of shape {img.shape}")
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if codec == "jpeg" else \
        [cv2.IMWRITE_PNG_COMPRESSION, png_level]
    ok, buf = cv2.imencode(".jpg" if codec == "jpeg" else ".png", img, params)
    if not ok:
        raise ValueError(f"OpenCV could not encode the image as {codec}")
    return f"{encoding}; {codec} compressed {target}", buf.tobytes()


__all__ = ["CODECS", "UndecodableImage", "codec_of", "decode_labels", "decode_rgb", "encode"]
