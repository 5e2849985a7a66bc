"""Label taxonomies and the one place where lidar and image classes meet.

The calibrator compares a rendered map with a label image class by class, so both sides must speak
the same vocabulary. That vocabulary (the *aligned* classes) is the Cityscapes trainId set: the
lidar's SemanticKITTI ids are mapped into it with the alignment of the paper's public code, and image
trainIds are mapped into it with classes that have no lidar counterpart dropped. Segmenters, the map
builder and the calibrator all take their tables from :class:`LabelMapping`, so they cannot disagree.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np
import yaml

#: Value of an aligned label that carries no class: unrendered pixel, ignored or removed class.
INVALID = 255

SEMANTIC_KITTI: dict[int, str] = {
    0: "unlabeled", 1: "outlier", 10: "car", 11: "bicycle", 13: "bus", 15: "motorcycle",
    16: "on-rails", 18: "truck", 20: "other-vehicle", 30: "person", 31: "bicyclist",
    32: "motorcyclist", 40: "road", 44: "parking", 48: "sidewalk", 49: "other-ground",
    50: "building", 51: "fence", 52: "other-structure", 60: "lane-marking", 70: "vegetation",
    71: "trunk", 72: "terrain", 80: "pole", 81: "traffic-sign", 99: "other-object",
    252: "moving-car", 253: "moving-bicyclist", 254: "moving-person", 255: "moving-motorcyclist",
    256: "moving-on-rails", 257: "moving-bus", 258: "moving-truck", 259: "moving-other-vehicle",
}
KITTI_ID: dict[str, int] = {name: idx for idx, name in SEMANTIC_KITTI.items()}

CITYSCAPES: dict[int, str] = {
    0: "road", 1: "sidewalk", 2: "building", 3: "wall", 4: "fence", 5: "pole",
    6: "traffic light", 7: "traffic sign", 8: "vegetation", 9: "terrain", 10: "sky",
    11: "person", 12: "rider", 13: "car", 14: "truck", 15: "bus", 16: "train",
    17: "motorcycle", 18: "bicycle",
}
CITYSCAPES_ID: dict[str, int] = {name: idx for idx, name in CITYSCAPES.items()}
SKY = CITYSCAPES_ID["sky"]

#: Official Cityscapes colours (RGB) by trainId; the paper's L2 loss is taken between these.
CITYSCAPES_PALETTE: dict[int, tuple[int, int, int]] = {
    0: (128, 64, 128), 1: (244, 35, 232), 2: (70, 70, 70), 3: (102, 102, 156),
    4: (190, 153, 153), 5: (153, 153, 153), 6: (250, 170, 30), 7: (220, 220, 0),
    8: (107, 142, 35), 9: (152, 251, 152), 10: (70, 130, 180), 11: (220, 20, 60),
    12: (255, 0, 0), 13: (0, 0, 142), 14: (0, 0, 70), 15: (0, 60, 100), 16: (0, 80, 100),
    17: (0, 0, 230), 18: (119, 11, 32),
}

#: SemanticKITTI -> Cityscapes trainId, as in the authors' public code (method notes).
DEFAULT_ALIGNMENT: dict[str, str] = {
    "road": "road", "lane-marking": "road", "parking": "sidewalk", "sidewalk": "sidewalk",
    "other-ground": "terrain", "terrain": "terrain", "building": "building",
    "other-structure": "building", "fence": "fence", "vegetation": "vegetation",
    "trunk": "vegetation", "pole": "pole", "traffic-sign": "traffic sign", "car": "car",
    "other-vehicle": "car", "truck": "truck", "bus": "bus", "motorcycle": "motorcycle",
    "bicycle": "bicycle", "person": "person", "bicyclist": "rider", "motorcyclist": "rider",
    "on-rails": "train",
    "moving-car": "car", "moving-bicyclist": "rider", "moving-person": "person",
    "moving-motorcyclist": "rider", "moving-on-rails": "train", "moving-bus": "bus",
    "moving-truck": "truck", "moving-other-vehicle": "car",
}

#: Classes that move: removed from the map and masked in the image.
DEFAULT_DYNAMIC: tuple[str, ...] = (
    "person", "rider", "car", "truck", "bus", "train", "motorcycle", "bicycle",
)


#: SemanticKITTI's moving classes (252-259): a moving object never belongs in a map.
MOVING_KITTI: tuple[int, ...] = tuple(i for i, n in SEMANTIC_KITTI.items() if n.startswith("moving-"))
#: Cityscapes vehicle classes: parked ones are part of the scene the camera sees.
VEHICLES: tuple[str, ...] = ("car", "truck", "bus", "train", "motorcycle", "bicycle")
#: SemanticKITTI ids of vehicles that are not marked moving (parked or standing).
VEHICLE_KITTI: tuple[int, ...] = tuple(
    KITTI_ID[k] for k, c in DEFAULT_ALIGNMENT.items() if c in VEHICLES and not k.startswith("moving-"))
#: A vehicle class's moving counterpart (other-vehicle etc. -> moving-other-vehicle).
_MOVING_OF: dict[int, int] = {
    KITTI_ID["car"]: KITTI_ID["moving-car"], KITTI_ID["truck"]: KITTI_ID["moving-truck"],
    KITTI_ID["bus"]: KITTI_ID["moving-bus"], KITTI_ID["on-rails"]: KITTI_ID["moving-on-rails"],
    KITTI_ID["motorcycle"]: KITTI_ID["moving-motorcyclist"],
    KITTI_ID["bicycle"]: KITTI_ID["moving-bicyclist"],
    KITTI_ID["other-vehicle"]: KITTI_ID["moving-other-vehicle"],
}


def moving_id_of(kitti_ids: np.ndarray) -> np.ndarray:
    """The moving class of each vehicle id (moving-other-vehicle for any other id)."""
    lut = np.full(65536, KITTI_ID["moving-other-vehicle"], np.uint16)
    for still, moving in _MOVING_OF.items():
        lut[still] = moving
    return lut[np.asarray(kitti_ids, np.uint16)]


@dataclass(frozen=True)
class LabelMapping:
    """Both domains' tables into the aligned (Cityscapes trainId) classes.

    ``merge`` maps an aligned class onto another in both domains (the paper merged road and
    sidewalk on KITTI). ``dynamic`` classes are dropped from maps and masked in images; image
    classes without a lidar counterpart (wall, traffic light by default) are masked because no
    rendered pixel could ever match them.
    """

    alignment: Mapping[str, str] = field(default_factory=lambda: dict(DEFAULT_ALIGNMENT))
    dynamic: tuple[str, ...] = DEFAULT_DYNAMIC
    merge: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for kitti, city in self.alignment.items():
            if kitti not in KITTI_ID:
                raise ValueError(f"unknown SemanticKITTI class '{kitti}' in label alignment")
            if city not in CITYSCAPES_ID:
                raise ValueError(f"unknown Cityscapes class '{city}' in label alignment")
        for name in (*self.dynamic, *self.merge.keys(), *self.merge.values()):
            if name not in CITYSCAPES_ID:
                raise ValueError(f"unknown Cityscapes class '{name}' in label mapping")

    @classmethod
    def from_yaml(cls, path: str | Path) -> "LabelMapping":
        """Read ``alignment`` (partial overrides), ``dynamic`` and ``merge`` from a YAML file."""
        data = yaml.safe_load(Path(path).read_text()) or {}
        alignment = dict(DEFAULT_ALIGNMENT)
        alignment.update(data.get("alignment", {}) or {})
        return cls(
            alignment=alignment,
            dynamic=tuple(data.get("dynamic", DEFAULT_DYNAMIC)),
            merge=dict(data.get("merge", {}) or {}),
        )

    def with_parked_vehicles(self) -> "LabelMapping":
        """Vehicles count in both domains (parked cars are in the map and in the image, as the
        paper kept them); SemanticKITTI's moving classes leave the alignment, so moving vehicles
        are still dropped from maps. People and riders stay dynamic.

        Not the default: the synthetic scenes' image shows their moving cars, which their maps
        (rightly) do not hold, so counting vehicles there charges every pose for them.
        """
        alignment = {k: c for k, c in self.alignment.items() if KITTI_ID[k] not in MOVING_KITTI}
        dynamic = tuple(c for c in self.dynamic if c not in VEHICLES)
        return LabelMapping(alignment, dynamic, self.merge)

    def _aligned(self, city_name: str) -> int:
        name = self.merge.get(city_name, city_name)
        return CITYSCAPES_ID[name]

    def static_classes(self) -> set[int]:
        """Aligned classes that can appear both in a map and in a label image."""
        out = set()
        for city in self.alignment.values():
            if city not in self.dynamic:
                out.add(self._aligned(city))
        return out

    def lidar_lut(self) -> np.ndarray:
        """uint8[65536]: SemanticKITTI id -> aligned class, INVALID for dynamic/unmapped."""
        lut = np.full(65536, INVALID, dtype=np.uint8)
        for kitti, city in self.alignment.items():
            if city in self.dynamic:
                continue
            lut[KITTI_ID[kitti]] = self._aligned(city)
        return lut

    def image_lut(self) -> np.ndarray:
        """uint8[256]: Cityscapes trainId -> aligned class; sky kept, the rest INVALID."""
        lut = np.full(256, INVALID, dtype=np.uint8)
        static = self.static_classes()
        for train_id, name in CITYSCAPES.items():
            if name in self.dynamic:
                continue
            aligned = self._aligned(name)
            if aligned in static or train_id == SKY:
                lut[train_id] = aligned
        return lut

    def dynamic_kitti_ids(self) -> np.ndarray:
        """SemanticKITTI ids whose aligned class is dynamic (to be removed from maps)."""
        ids = [KITTI_ID[k] for k, c in self.alignment.items() if c in self.dynamic]
        return np.array(sorted(ids), dtype=np.uint16)

    def map_lidar(self, kitti_labels: np.ndarray) -> np.ndarray:
        """Aligned classes of SemanticKITTI labels (upper 16 instance bits are ignored)."""
        return self.lidar_lut()[np.asarray(kitti_labels).astype(np.uint32) & 0xFFFF]

    def map_image(self, train_ids: np.ndarray) -> np.ndarray:
        """Aligned classes of a Cityscapes trainId image."""
        return self.image_lut()[np.asarray(train_ids, dtype=np.uint8)]


def palette_array() -> np.ndarray:
    """uint8[256, 3] colours by aligned class; INVALID and unknown ids are black."""
    pal = np.zeros((256, 3), dtype=np.uint8)
    for idx, rgb in CITYSCAPES_PALETTE.items():
        pal[idx] = rgb
    return pal


def colorize(labels: np.ndarray) -> np.ndarray:
    """RGB picture of a label image (for overlays and debugging)."""
    return palette_array()[labels]
