"""``cloud_segmenter``: lidar scans in, the same scans with a ``label`` field out.

Subscribes ``points`` (PointCloud2 with x, y, z and optionally intensity, any layout), labels
them with ``method: onnx``, the user's range-image ONNX model
(:class:`~semcal_ros.segmentation.cloud.CloudSegmenter`, parameters ``model`` and
``model_config``), or with ``method: geometric``, the network-free geometric labeller
(:func:`~semcal_ros.segmentation.geometric.label_scan`, parameters ``geometric.*``, no model
file), and publishes ``labelled_points``: every input field unchanged,
plus ``label`` (uint16 SemanticKITTI ids), same header. Scans that already carry a ``label`` field
(simulation, an upstream segmenter) need no segmenter: feed them to ``map_builder`` directly.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.lib import recfunctions
from sensor_msgs.msg import PointCloud2

from semcal_ros.ros import conversions as conv
from semcal_ros.ros.runtime import run_node
from semcal_ros.ros.segmenter_node import SegmenterNode
from semcal_ros.segmentation.geometric import GeometricParams
from semcal_ros.segmentation.labellers import POINT_LABELLERS, check_labeller, make_labeller
from semcal_ros.segmentation.onnx_runner import RunnerParams

#: The ``method`` values: the registered point labellers.
METHODS = tuple(POINT_LABELLERS)


@dataclass
class CloudSegmenterParams:
    method: str = "onnx"  # onnx (the user's model) or geometric (no model, no network)
    model: str = ""  # ONNX range-image model (required with method onnx)
    model_config: str = ""  # its YAML, e.g. config/models/salsanext_semantickitti.yaml (onnx)
    intensity_field: str = "intensity"  # field fed as remission ("" or missing: none)
    queue_size: int = 5  # scans waiting while the model runs (the oldest is dropped)
    runner: RunnerParams = field(default_factory=RunnerParams)
    diagnostics_period: float = 1.0  # s (0: off)
    geometric: GeometricParams = field(default_factory=GeometricParams)

    def __post_init__(self) -> None:
        check_labeller(self.method, "parameter 'method':")


class _Labeller:
    """A registered labeller behind the ``segment(xyz, intensity)`` call the node makes."""

    def __init__(self, segment: Any) -> None:
        self.segment = segment


def add_label_field(points: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """``points`` (structured, any layout) with a ``label`` uint16 field set (replaced if there)."""
    if "label" in (points.dtype.names or ()):
        points = recfunctions.drop_fields(points, "label", usemask=False)
    points = recfunctions.repack_fields(points)
    out = np.empty(len(points), dtype=points.dtype.descr + [("label", "<u2")])
    for name in points.dtype.names:
        out[name] = points[name]
    out["label"] = labels
    return out


class CloudSegmenterNode(SegmenterNode):
    msg_type, in_topic, out_topic, what = PointCloud2, "points", "labelled_points", "scans"

    def __init__(self) -> None:
        super().__init__("cloud_segmenter", CloudSegmenterParams())

    def require(self, opts: CloudSegmenterParams) -> None:
        if POINT_LABELLERS[opts.method].needs_model:
            super().require(opts)

    def load(self, opts: CloudSegmenterParams) -> Any:
        return _Labeller(make_labeller(opts.method, opts.model, opts.model_config, opts.runner,
                                       opts.geometric))

    def segment_message(self, msg: PointCloud2) -> PointCloud2:
        points = conv.pointcloud2_to_array(msg)
        cloud = conv.pointcloud2_to_cloud(msg)  # names a missing x/y/z field
        name = self.opts.intensity_field
        intensity = np.asarray(points[name], np.float32) if name and name in points.dtype.names \
            else None
        labels = self.segmenter.segment(cloud.xyz, intensity)
        out = conv.array_to_pointcloud2(add_label_field(points, labels), msg.header)
        out.height, out.width = msg.height, msg.width
        out.row_step = out.point_step * msg.width
        out.is_dense = msg.is_dense
        return out


def main(args: list[str] | None = None) -> int:
    return run_node(CloudSegmenterNode, threads=2, args=args)


if __name__ == "__main__":
    sys.exit(main())
