"""The point labellers, in one registry: every place that offers a choice of labeller (the
``cloud_segmenter`` node's ``method``, ``semcal segment-cloud --method``, ``semcal real-scene
--cloud-labels``) lists :data:`POINT_LABELLERS` instead of a list of its own, as the losses are
listed once in :data:`semcal_ros.engine.loss.LOSS_KINDS`.

A labeller is ``segment(xyz, intensity) -> SemanticKITTI ids (uint16)``; :func:`make_labeller`
builds one by name. The ONNX one needs a model and its config; the geometric one needs nothing
(its thresholds are :class:`~semcal_ros.segmentation.geometric.GeometricParams`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

if TYPE_CHECKING:  # the labellers' modules load onnxruntime / numba: imported when built
    from semcal_ros.segmentation.geometric import GeometricParams
    from semcal_ros.segmentation.onnx_runner import RunnerParams

#: ``segment(xyz (N, 3), intensity (N,) or None) -> (N,) uint16 SemanticKITTI ids``
Labeller = Callable[[np.ndarray, "np.ndarray | None"], np.ndarray]


@dataclass(frozen=True)
class PointLabeller:
    """One kind of point labeller: its name (the value users write) and what it needs."""

    name: str
    needs_model: bool  # an ONNX model and its config (else it runs on the points alone)
    summary: str


#: Every point labeller by name, the default first.
POINT_LABELLERS: dict[str, PointLabeller] = {
    "onnx": PointLabeller("onnx", True, "an ONNX range-image model (RangeNet++/SalsaNext "
                                        "convention, configured by a model config YAML)"),
    "geometric": PointLabeller("geometric", False, "the network-free geometric labeller "
                                                   "(ground segmentation, shape features, a shipped forest)"),
}
#: The labellers that need no model file (they can run inside a workflow on any scan).
MODEL_FREE = tuple(name for name, kind in POINT_LABELLERS.items() if not kind.needs_model)


def check_labeller(name: str, what: str = "method") -> PointLabeller:
    """The registered labeller ``name``; ValueError naming the choices otherwise."""
    if name not in POINT_LABELLERS:
        raise ValueError(f"{what} '{name}' is not one of {', '.join(POINT_LABELLERS)}")
    return POINT_LABELLERS[name]


def make_labeller(name: str, model: str | Path | None = None,
                  model_config: str | Path | None = None, runner: RunnerParams | None = None,
                  geometric: GeometricParams | None = None) -> Labeller:
    """The labeller ``name``, built (a model is loaded and checked here)."""
    kind = check_labeller(name)
    if kind.needs_model:
        if not model or not model_config:
            raise ValueError(f"the {name} labeller needs a model and its model config")
        from semcal_ros.segmentation.cloud import CloudSegmenter
        from semcal_ros.segmentation.onnx_runner import RunnerParams

        return CloudSegmenter.from_files(model, model_config, runner or RunnerParams()).segment
    from semcal_ros.segmentation.geometric import GeometricParams, label_scan

    params = geometric or GeometricParams()

    def geometric_labels(xyz: np.ndarray, intensity: np.ndarray | None) -> np.ndarray:
        return np.asarray(label_scan(xyz, intensity, params), np.uint16)

    return geometric_labels


__all__ = ["Labeller", "MODEL_FREE", "POINT_LABELLERS", "PointLabeller", "check_labeller",
           "make_labeller"]
