"""A JPEG that OpenCV still decodes to a picture while libjpeg warns "Corrupt JPEG data" on
stderr: what a damaged camera stream delivers (tests of issue 34's stream checks)."""

from __future__ import annotations

import os
import tempfile

import cv2
import numpy as np


def opencv_decode_with_stderr(data: bytes) -> tuple[np.ndarray | None, str]:
    """cv2.imdecode and what libjpeg printed on the process's stderr meanwhile."""
    with tempfile.TemporaryFile() as capture:
        saved = os.dup(2)
        os.dup2(capture.fileno(), 2)
        try:
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        capture.seek(0)
        return img, capture.read().decode(errors="replace")


def corrupt_jpeg(data: bytes, seed: int = 1) -> bytes:
    """``data`` with 32 bytes of its entropy-coded data overwritten (no 0xFF, so no marker) at
    the first place where OpenCV still returns a picture and libjpeg warns about it."""
    rng = np.random.default_rng(seed)
    start = data.index(b"\xff\xda") + 200  # past the start of scan
    for offset in range(start, len(data) - 64, 97):
        junk = rng.integers(0, 255, 32, dtype=np.uint8).tobytes()
        bad = data[:offset] + junk + data[offset + 32:]
        img, said = opencv_decode_with_stderr(bad)
        if img is not None and "Corrupt JPEG data" in said:
            return bad
    raise AssertionError("no damage found that libjpeg decodes with a warning")
