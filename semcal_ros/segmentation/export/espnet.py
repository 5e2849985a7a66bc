"""ESPNet (Mehta et al., ECCV 2018), p = 2, q = 8, Cityscapes, as an ONNX graph.

Architecture as published in sacmehta/ESPNet (``test/Model.py``, class ``ESPNet``):

* encoder (ESPNet-C): a strided 3x3 CBR; the input image avg-pooled once and twice and
  concatenated at 1/2 and 1/4; strided ESP down-samplers (3x3 strided reduction, five dilated 3x3
  branches d = 1, 2, 4, 8, 16 with hierarchical sums, BN+PReLU) and p = 2, q = 8 residual ESP
  blocks (1x1 reduction) at 1/4 and 1/8; a 1x1 classifier.
* decoder: BatchNorm on the 1/8 classifier output, transposed 2x2 convolution to 1/4,
  concatenation with a 1x1 projection of the 1/4 features, BN+PReLU, a non-residual ESP block,
  transposed convolution + BN+PReLU to 1/2, concatenation with the first level, 3x3 CBR and a
  transposed convolution to full size. All BatchNorms use eps 1e-3.
"""

from __future__ import annotations

import onnx

from semcal_ros.segmentation.export.graph import GraphBuilder, T, Weights

P, Q = 2, 8
NUM_CLASSES = 20
BN_EPS = 1e-3


def build(weights: Weights, width: int, height: int) -> onnx.ModelProto:
    """The ESPNet Cityscapes network for ``width`` x ``height`` input (multiples of 8)."""
    if width % 8 or height % 8:
        raise ValueError(f"ESPNet needs an input size divisible by 8, got {width}x{height}")
    g = GraphBuilder(weights, BN_EPS)
    image = T("input", 3, height, width)
    classes = NUM_CLASSES

    level1 = g.conv(image, "encoder.level1.conv.weight", 16, 3, 2, bn="encoder.level1.bn",
                    prelu="encoder.level1.act.weight")
    image_2 = g.avg_pool3s2(image)
    image_4 = g.avg_pool3s2(image_2)
    cat1 = _br(g, g.concat([level1, image_2]), "encoder.b1")
    down2 = _esp(g, cat1, "encoder.level2_0", 64, stride=2)
    level2 = down2
    for i in range(P):
        level2 = _esp(g, level2, f"encoder.level2.{i}", 64)
    cat2 = _br(g, g.concat([level2, down2, image_4]), "encoder.b2")
    down3 = _esp(g, cat2, "encoder.level3_0", 128, stride=2)
    level3 = down3
    for i in range(Q):
        level3 = _esp(g, level3, f"encoder.level3.{i}", 128)
    cat3 = _br(g, g.concat([down3, level3]), "encoder.b3")

    # decoder ("RUM"): BatchNorms after a convolution are folded into it
    scores3 = g.conv(cat3, "encoder.classifier.conv.weight", classes, 1, bn="br")
    up3 = g.conv_transpose2(scores3, "up_l3.0.weight", classes)
    proj2 = g.conv(cat2, "level3_C.conv.weight", classes, 1)
    merged = _br(g, g.concat([proj2, up3]), "combine_l2_l3.0")
    merged = _esp(g, merged, "combine_l2_l3.1", classes, residual=False)
    up2 = g.conv_transpose2(merged, "up_l2.0.weight", classes, bn="up_l2.1.bn",
                            prelu="up_l2.1.act.weight")
    fused = g.conv(g.concat([up2, level1]), "conv.conv.weight", classes, 3, bn="conv.bn",
                   prelu="conv.act.weight")
    out = g.conv_transpose2(fused, "classifier.weight", classes)
    weights.check_all_used()
    return g.model(image, out, "espnet_cityscapes",
                   "ESPNet (p=2, q=8) Cityscapes segmentation, rebuilt from sacmehta/ESPNet")


def _br(g: GraphBuilder, x: T, prefix: str) -> T:
    """BR: BatchNorm + PReLU (keys bn, act)."""
    return g.prelu(g.batchnorm(x, f"{prefix}.bn"), f"{prefix}.act.weight")


def _esp(g: GraphBuilder, x: T, prefix: str, cout: int, stride: int = 1,
         residual: bool = True) -> T:
    """ESP block. stride 2: DownSamplerB (3x3 strided reduction, BN and PReLU keys directly
    under the prefix); stride 1: DilatedParllelResidualBlockB (1x1 reduction, BR under
    ``bn``, residual when ``residual`` and the channels match)."""
    n = cout // 5
    n1 = cout - 4 * n
    k = 3 if stride == 2 else 1
    reduced = g.conv(x, f"{prefix}.c1.conv.weight", n, k, stride)
    d1 = g.conv(reduced, f"{prefix}.d1.conv.weight", n1, 3)
    sums: list[T] = []
    for d in (2, 4, 8, 16):
        y = g.conv(reduced, f"{prefix}.d{d}.conv.weight", n, 3, dilation=d)
        sums.append(g.add(sums[-1], y) if sums else y)
    combined = g.concat([d1, *sums])
    if stride == 2:
        return _br(g, combined, prefix)
    if residual and x.c == cout:
        combined = g.add(x, combined)
    return _br(g, combined, f"{prefix}.bn")

