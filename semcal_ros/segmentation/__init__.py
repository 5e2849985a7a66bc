"""Semantic segmentation with the user's ONNX models: images to Cityscapes trainIds, lidar scans
to SemanticKITTI ids. Both outputs are the raw taxonomies of :mod:`semcal_ros.engine.labels`; the
calibrator aligns them with :class:`semcal_ros.engine.labels.LabelMapping`.

Heavy imports (onnxruntime, numba) stay in the submodules; import from them directly:
``from semcal_ros.segmentation.image import ImageSegmenter``,
``from semcal_ros.segmentation.cloud import CloudSegmenter``.
"""
