"""Build real Cityscapes segmenters as ONNX files from published weights, without PyTorch.

``semcal export-model`` calls :func:`export_model`: it reads a ``.npz`` of a model's PyTorch
``state_dict`` (keys = state_dict names), builds the published architecture as an ONNX graph
(:mod:`.espnetv2`, :mod:`.espnet`), checks every tensor's shape against the architecture, and
writes the ``.onnx`` plus the model config YAML (see docs/segmentation.md) beside it, so the
result runs through :class:`semcal_ros.segmentation.image.ImageSegmenter` unchanged.

The preprocessing facts come from the authors' code: ESPNetv2 (EdgeNets) takes RGB in [0, 1]
normalised with the ImageNet mean and std; ESPNet takes BGR 0-255 minus its Cityscapes mean,
divided by its std *and then by 255* (``ToTensor`` divides after ``Normalize`` in training, and
its test script does the same), hence ``std`` x 255 in its config. Both output 20 channels:
Cityscapes trainIds 0-18 and 19 = background/void, ignored.

The EdgeTPU DeepLab (:mod:`.edgetpu_deeplab`) comes as an int8 TFLite file whose weights were
dequantised into a ``.npz`` with its operator list in a ``.graph.json`` beside it; the exporter
writes that operator list as ONNX. RGB, ``(x - 128) / 128``, 19 outputs = trainIds 0-18.
"""

#: Exportable architectures (light names for the command line; the builders are in exporter).
ARCH_NAMES = ("espnetv2", "espnet", "edgetpu_deeplab")
#: Default input size per architecture: the authors' Cityscapes size (half resolution) for the
#: ESPNets; KITTI's native 1241 x 376 for the fully convolutional DeepLab (80.7 % agreement on
#: KITTI 00 frame 0 there, 79.9-81.8 % at 1249x385 .. 1857x561 for up to 3x the time).
DEFAULT_SIZES = {"espnetv2": (1024, 512), "espnet": (1024, 512), "edgetpu_deeplab": (1241, 376)}
DEFAULT_SIZE = DEFAULT_SIZES["espnetv2"]
