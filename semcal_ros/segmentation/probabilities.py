"""Class probabilities of an image segmenter, in Cityscapes trainIds 0-18 (docs/CONTRACTS.md).

A label image keeps only the winning class; a loss for real labels can instead charge a mismatch
by how sure the network was (issue 18). The probabilities are the softmax of the model's logits,
summed into the trainIds of its class table; classes the config ignores (ESPNetv2's channel 19 =
background) are dropped and the rest renormalised, so every pixel's 19 values sum to 1. They are
taken at the model's output resolution and resized to the image with nearest neighbour, exactly
as the labels are, so they are pixel-aligned with the label image: argmax == label wherever the
label is not 255 (for one-to-one class tables; ties after rounding aside, see
:func:`argmax_agrees`).

Stored forms:

* file ``probabilities.npz``: key ``probabilities``, float16, shape (H, W, 19)
  (:func:`write_probabilities`, :func:`read_probabilities`);
* ROS ``sensor_msgs/Image``, encoding ``8UC19``: probability x 255, rounded
  (:func:`to_bytes`, :func:`from_bytes`).
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import cv2
import numba as nb
import numpy as np

from semcal_ros.engine.labels import INVALID

#: Cityscapes trainIds 0-18: the probabilities' last axis.
NUM_TRAIN_IDS = 19
#: The npz key and the ROS image encoding of the two stored forms.
NPZ_KEY = "probabilities"
ROS_ENCODING = f"8UC{NUM_TRAIN_IDS}"


_CHUNK = 4096  # pixels per block (as in decode.py): running maxima and sums stay in cache


@nb.njit(cache=True, nogil=True, fastmath=True)
def _softmax_into_train_ids(scores: np.ndarray, lut: np.ndarray,
                            out: np.ndarray) -> None:  # pragma: no cover
    """out[p, lut[c]] += softmax_c(scores[:, p]); classes with lut >= 19 dropped; rows renormalised.

    One compiled pass, block by block over the channel planes: 50 ms for 19 x 376 x 1241 where
    numpy (max, exp, a class-table matmul, a transpose) took 200 ms at the same load.
    """
    n_classes, n = scores.shape
    n_out = out.shape[1]
    best = np.empty(_CHUNK, np.float32)
    total = np.empty(_CHUNK, np.float32)
    for start in range(0, n, _CHUNK):
        stop = min(n, start + _CHUNK)
        size = stop - start
        best[:size] = scores[0, start:stop]
        for c in range(1, n_classes):
            row = scores[c, start:stop]
            for i in range(size):
                if row[i] > best[i]:
                    best[i] = row[i]
        out[start:stop, :] = 0.0
        total[:size] = 0.0
        for c in range(n_classes):
            k = lut[c]
            if k >= n_out:
                continue
            row = scores[c, start:stop]
            for i in range(size):
                e = np.exp(row[i] - best[i])
                out[start + i, k] += e
                total[i] += e
        for i in range(size):
            if total[i] > 0:
                inv = 1.0 / total[i]
                for k in range(n_out):
                    out[start + i, k] *= inv


def probabilities_from_logits(logits: np.ndarray, lut: np.ndarray,
                              size: tuple[int, int] | None = None) -> np.ndarray:
    """(1, C, h, w) logits -> (H, W, 19) float32 trainId probabilities (see the module doc).

    ``lut`` is the model config's class table (model class -> trainId, 255 = ignored).
    ``size`` = (H, W) of the label image (default: the logits' own); nearest-neighbour resize,
    the same as the labels get. A pixel whose every class is ignored gets zeros.
    """
    _, n_classes, h, w = logits.shape
    scores = np.ascontiguousarray(logits[0], dtype=np.float32).reshape(n_classes, h * w)
    probs = np.empty((h * w, NUM_TRAIN_IDS), np.float32)
    _softmax_into_train_ids(scores, np.ascontiguousarray(lut, dtype=np.int64), probs)
    probs = probs.reshape(h, w, NUM_TRAIN_IDS)
    if size is not None and tuple(size) != (h, w):
        probs = cv2.resize(probs, (size[1], size[0]), interpolation=cv2.INTER_NEAREST)
    return probs


def argmax_agrees(probabilities: np.ndarray, labels: np.ndarray) -> tuple[float, float]:
    """(share of labelled pixels whose argmax is their label, share of them with a tied top).

    Rounding (float16, or x 255 to bytes) can make the two best classes equal; argmax then
    takes the lower trainId. Where the top value is unique the argmax must be the label.
    """
    probs = np.asarray(probabilities)
    labelled = labels != INVALID
    top = probs.max(axis=2)
    tied = (probs == top[:, :, None]).sum(axis=2) > 1
    agree = probs.argmax(axis=2) == labels
    n = max(int(labelled.sum()), 1)
    return float((agree & labelled).sum() / n), float((tied & labelled).sum() / n)


def write_probabilities(path: str | Path, probabilities: np.ndarray) -> Path:
    """``path`` (.npz, compressed): key ``probabilities``, float16 (H, W, 19)."""
    probs = np.asarray(probabilities)
    _check(probs, str(path))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as f:  # savez would append .npz to any other suffix
        np.savez_compressed(f, **{NPZ_KEY: probs.astype(np.float16)})
    return path


def read_probabilities(path: str | Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """The (H, W, 19) float16 array of a probabilities file; one clear line when it is not one.

    ``size`` = (H, W) it must have (the label image's / camera's), if given.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"probabilities file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files if key == NPZ_KEY}
            names = list(data.files)
    except (OSError, ValueError, AttributeError, TypeError, zipfile.BadZipFile,
            EOFError) as exc:
        raise ValueError(f"{path}: not a readable .npz file ({exc})") from None
    if NPZ_KEY not in arrays:
        raise ValueError(f"{path}: no array '{NPZ_KEY}' (has: {', '.join(names)})")
    probs = arrays[NPZ_KEY]
    _check(probs, str(path))
    if probs.dtype != np.float16:
        raise ValueError(f"{path}: probabilities are {probs.dtype}, the contract is float16")
    if size is not None and probs.shape[:2] != tuple(size):
        raise ValueError(f"{path}: probabilities are {probs.shape[1]}x{probs.shape[0]}, the "
                         f"label image {size[1]}x{size[0]}")
    return probs


def to_bytes(probabilities: np.ndarray) -> np.ndarray:
    """(H, W, 19) uint8: probability x 255, rounded (the ``8UC19`` image's pixels)."""
    probs = np.asarray(probabilities, np.float32)
    _check(probs, "probabilities")
    return np.rint(np.clip(probs, 0.0, 1.0) * 255.0).astype(np.uint8)


def from_bytes(data: np.ndarray) -> np.ndarray:
    """(H, W, 19) float32 probabilities of ``8UC19`` pixels (byte / 255; sums within ~0.04)."""
    return np.asarray(data, np.float32) * np.float32(1.0 / 255.0)


def _check(probs: np.ndarray, where: str) -> None:
    if probs.ndim != 3 or probs.shape[2] != NUM_TRAIN_IDS:
        raise ValueError(f"{where}: probabilities must have shape (H, W, {NUM_TRAIN_IDS}), "
                         f"got {probs.shape}")
