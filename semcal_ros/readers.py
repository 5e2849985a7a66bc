"""The two readers every layer uses: a YAML mapping and an image file, with their failures as one
line naming the file. They sit below io/ and segmentation/ alike (a model config and an image
to segment are read with them) so that neither reaches into the other for them; io/files.py
builds the project's formats on them.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml


def load_yaml(path: str | Path, what: str) -> dict:
    """A YAML mapping from ``path``; FileNotFoundError / ValueError in one line (the parser's
    message is several lines: its first says what is wrong)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else "unreadable"
        raise ValueError(f"{path}: invalid YAML ({first})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a YAML mapping")
    return data


def imread(path: str | Path, flags: int = cv2.IMREAD_UNCHANGED, what: str = "image") -> np.ndarray:
    """cv2.imread with the two failures it reports as None turned into clear errors."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    img = cv2.imread(str(path), flags)
    if img is None:
        raise ValueError(f"{path}: not a readable image")
    return img
