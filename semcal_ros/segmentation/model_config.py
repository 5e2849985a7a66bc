"""Model configs: what a user's ONNX model expects and what its classes mean.

semcal_ros ships no network; users bring the ONNX export they trust. A small YAML file next to the
model says how to feed it (input size, channel order, normalisation, range-image geometry) and how
to read its output (logits or a class map, model class -> target class). The target classes are
the engine's own taxonomies from :mod:`semcal_ros.engine.labels` (Cityscapes trainIds for images,
SemanticKITTI ids for scans), resolved here by name or id, so a model config cannot invent classes
the calibrator does not know.

Two kinds, chosen by ``kind:`` in the YAML:

* ``image`` -> :class:`ImageModelConfig` (e.g. OCRNet or SegFormer trained on Cityscapes);
* ``range`` -> :class:`RangeModelConfig` (RangeNet++ / SalsaNext trained on SemanticKITTI).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from semcal_ros.readers import load_yaml
from semcal_ros.engine.labels import CITYSCAPES, CITYSCAPES_ID, INVALID, KITTI_ID, SEMANTIC_KITTI

#: Output kinds a model may have: per-class scores (N x C x H x W) or an argmax already taken
#: inside the model (N x H x W, or N x 1 x H x W as MMDeploy exports it).
OUTPUT_KINDS = ("logits", "class_map")
#: Range-image input channels, in the order of the RangeNet++ / SalsaNext convention.
RANGE_CHANNELS = ("range", "x", "y", "z", "remission")
#: Label a range model's ignored classes become (SemanticKITTI "unlabeled").
KITTI_UNLABELED = KITTI_ID["unlabeled"]


@dataclass(frozen=True)
class ImageModelConfig:
    """How to run an image segmentation model whose classes map to Cityscapes trainIds.

    The network input is ``(pixel * scale - mean) / std`` per channel, in ``channel_order``,
    resized to ``input_width`` x ``input_height`` and laid out NCHW. ``classes[i]`` is the
    Cityscapes class (name or trainId) of model class ``i``; ``None`` or an entry listed in
    ``ignore`` makes those pixels 255 (ignored).
    """

    input_width: int
    input_height: int
    classes: tuple[str | int | None, ...]
    input_name: str | None = None
    output_name: str | None = None
    channel_order: str = "RGB"
    layout: str = "NCHW"
    scale: float = 1.0
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    std: tuple[float, float, float] = (1.0, 1.0, 1.0)
    output: str = "logits"
    ignore: tuple[str | int, ...] = ()

    def __post_init__(self) -> None:
        _check_size("input_width x input_height", self.input_width, self.input_height)
        if self.channel_order not in ("RGB", "BGR"):
            raise ValueError(f"channel_order must be RGB or BGR, got {self.channel_order!r}")
        if self.layout != "NCHW":
            raise ValueError(f"layout {self.layout!r} is not supported: export the model with "
                             "NCHW input (N x 3 x H x W)")
        _check_norm("mean", self.mean, 3)
        _check_norm("std", self.std, 3, positive=True)
        if not self.scale > 0:
            raise ValueError(f"scale must be positive, got {self.scale}")
        _check_output(self.output)
        self.class_lut()  # resolve names now: a typo fails at load time, not on the first frame

    @property
    def num_classes(self) -> int:
        return len(self.classes)

    def class_lut(self) -> np.ndarray:
        """uint8[num_classes]: model class -> Cityscapes trainId (255 = ignored)."""
        return _class_lut(self.classes, self.ignore, CITYSCAPES, CITYSCAPES_ID, INVALID,
                          np.uint8, "Cityscapes")


@dataclass(frozen=True)
class RangeModelConfig:
    """How to run a range-image model (RangeNet++ / SalsaNext convention) on one scan.

    Points are projected spherically to ``height`` x ``width`` between ``fov_down_deg`` and
    ``fov_up_deg``; the five channels (range, x, y, z, remission) are normalised by ``means`` and
    ``stds`` (in :data:`RANGE_CHANNELS` order) and empty pixels are 0. Intensities are multiplied by
    ``intensity_scale`` first (KITTI remission is 0..1; many ROS drivers publish 0..255).
    ``classes[i]`` is the SemanticKITTI class (name or id) of model class ``i``; ignored classes
    become 0 ("unlabeled"). Points that lost their pixel to a nearer point take the label of the
    3-D nearest pixel winner within a ``knn_window`` x ``knn_window`` neighbourhood.
    """

    height: int
    width: int
    classes: tuple[str | int | None, ...]
    fov_up_deg: float = 3.0
    fov_down_deg: float = -25.0
    means: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    stds: tuple[float, float, float, float, float] = (1.0, 1.0, 1.0, 1.0, 1.0)
    intensity_scale: float = 1.0
    input_name: str | None = None
    output_name: str | None = None
    output: str = "logits"
    ignore: tuple[str | int, ...] = ()
    knn_window: int = 5

    def __post_init__(self) -> None:
        _check_size("width x height", self.width, self.height)
        if not self.fov_up_deg > self.fov_down_deg:
            raise ValueError(f"fov_up_deg ({self.fov_up_deg}) must be above fov_down_deg "
                             f"({self.fov_down_deg})")
        _check_norm("means", self.means, 5)
        _check_norm("stds", self.stds, 5, positive=True)
        if self.knn_window < 1 or self.knn_window % 2 == 0:
            raise ValueError(f"knn_window must be an odd number >= 1, got {self.knn_window}")
        _check_output(self.output)
        self.class_lut()

    @property
    def num_classes(self) -> int:
        return len(self.classes)

    def class_lut(self) -> np.ndarray:
        """uint16[num_classes]: model class -> SemanticKITTI id (0 = ignored/unlabeled)."""
        return _class_lut(self.classes, self.ignore, SEMANTIC_KITTI, KITTI_ID, KITTI_UNLABELED,
                          np.uint16, "SemanticKITTI")


ModelConfig = ImageModelConfig | RangeModelConfig


def load_model_config(path: str | Path, kind: type | None = None) -> ModelConfig:
    """Read a model config YAML; ``kind: image`` or ``kind: range`` picks the type.

    ``kind`` (ImageModelConfig or RangeModelConfig) refuses a config of the other kind.
    """
    data = load_yaml(path, "model config")
    try:
        config = model_config_from_dict(data)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path}: {exc}") from None
    if kind is not None and not isinstance(config, kind):
        wanted = "image" if kind is ImageModelConfig else "range"
        raise ValueError(f"{path}: kind is '{data['kind']}', but this needs a model config "
                         f"with kind: {wanted}")
    return config


def model_config_from_dict(data: Mapping[str, Any]) -> ModelConfig:
    data = dict(data)
    kind = data.pop("kind", None)
    types = {"image": ImageModelConfig, "range": RangeModelConfig}
    if kind not in types:
        raise ValueError(f"'kind' must be 'image' or 'range', got {kind!r}")
    cls = types[kind]
    if kind == "range":
        for key in ("means", "stds"):
            if isinstance(data.get(key), Mapping):
                data[key] = _channel_values(key, data[key])
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"unknown key(s) for a {kind} model config: {', '.join(unknown)}")
    required = [f.name for f in dataclasses.fields(cls)
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    missing = [n for n in required if n not in data]
    if missing:
        raise ValueError(f"{kind} model config lacks {', '.join(missing)}")
    for key, value in list(data.items()):
        if isinstance(value, list):
            data[key] = tuple(value)
    if not isinstance(data["classes"], tuple) or not data["classes"]:
        raise ValueError("'classes' must be a non-empty list (model class i -> target class)")
    return cls(**data)


def _channel_values(key: str, values: Mapping[str, Any]) -> tuple[float, ...]:
    """``{range: .., x: .., ...}`` -> a tuple in RANGE_CHANNELS order."""
    extra = sorted(set(values) - set(RANGE_CHANNELS))
    missing = [c for c in RANGE_CHANNELS if c not in values]
    if extra or missing:
        raise ValueError(f"'{key}' needs exactly the channels {', '.join(RANGE_CHANNELS)}"
                         + (f"; unknown: {', '.join(extra)}" if extra else "")
                         + (f"; missing: {', '.join(missing)}" if missing else ""))
    return tuple(float(values[c]) for c in RANGE_CHANNELS)


def _class_lut(classes: Sequence[str | int | None], ignore: Sequence[str | int],
               table: Mapping[int, str], ids: Mapping[str, int], ignored: int,
               dtype: type, taxonomy: str) -> np.ndarray:
    """Resolve the model's class list into target ids; names and ids both accepted."""
    lut = np.empty(len(classes), dtype=dtype)
    for i, entry in enumerate(classes):
        lut[i] = ignored if entry is None else _resolve(entry, table, ids, taxonomy, i)
    for entry in ignore:
        if isinstance(entry, (int, np.integer)) and not isinstance(entry, bool):
            if not 0 <= entry < len(classes):
                raise ValueError(f"ignore: model class {entry} does not exist "
                                 f"({len(classes)} classes)")
            lut[entry] = ignored
            continue
        hits = [i for i, c in enumerate(classes) if c == entry]
        if not hits:
            raise ValueError(f"ignore: {entry!r} is neither a model class index nor a name "
                             "in 'classes'")
        lut[hits] = ignored
    return lut


def _resolve(entry: str | int, table: Mapping[int, str], ids: Mapping[str, int],
             taxonomy: str, index: int) -> int:
    if isinstance(entry, bool):
        raise ValueError(f"classes[{index}]: {entry!r} is not a class")
    if isinstance(entry, (int, np.integer)):
        if int(entry) not in table:
            raise ValueError(f"classes[{index}]: {entry} is not a {taxonomy} id")
        return int(entry)
    if isinstance(entry, str) and entry in ids:
        return ids[entry]
    raise ValueError(f"classes[{index}]: unknown {taxonomy} class {entry!r} "
                     f"(known: {', '.join(ids)})")


def _check_size(what: str, width: Any, height: Any) -> None:
    if not (isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0):
        raise ValueError(f"{what} must be positive integers, got {width!r} x {height!r}")


def _check_norm(name: str, values: Sequence[float], n: int, positive: bool = False) -> None:
    if len(values) != n:
        raise ValueError(f"'{name}' needs {n} values, got {len(values)}")
    arr = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(arr)) or (positive and not np.all(arr > 0)):
        raise ValueError(f"'{name}' values must be finite{' and positive' if positive else ''}, "
                         f"got {list(values)}")


def _check_output(output: str) -> None:
    if output not in OUTPUT_KINDS:
        raise ValueError(f"output must be one of {', '.join(OUTPUT_KINDS)}, got {output!r}")
