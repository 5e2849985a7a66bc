"""ESPNetv2 semantic segmentation (Mehta et al., CVPR 2019) as an ONNX graph.

Architecture as published in sacmehta/EdgeNets (``model/segmentation/espnetv2.py`` with the
``EESPNet`` encoder and ``nn_layers``), scale s = 2.0, Cityscapes decoder (16 base planes):

* encoder: a strided 3x3 CBR, then down-samplers (avg-pool || strided EESP, plus the input image
  avg-pooled to the same size through a 3x3 CBR and a 1x1 CB: "input reinforcement") with 3 and 7
  EESP blocks at 1/8 and 1/16. An EESP block: grouped 1x1 reduction, four depth-wise 3x3 branches
  with dilations from the receptive-field limit, hierarchical sums, BN+PReLU, grouped 1x1
  expansion, residual, PReLU.
* decoder: efficient pyramid pooling (five depth-wise branches at scales 2, 1.5, 1, 0.5, 0.1,
  channel shuffle, grouped 3x3, 1x1) at 1/16, then three times: bilinear x2 (align_corners),
  plus an encoder skip weighted by a sigmoid of its global average, BN+PReLU, pyramid pooling;
  finally bilinear to the input size. All BatchNorms use eps 1e-5 (PyTorch's default).
"""

from __future__ import annotations

import math
from typing import Callable

import onnx

from semcal_ros.segmentation.export.graph import GraphBuilder, T, Weights, ceil_scale

#: Channels per level for s = 2.0 (EESPNet's ``sc_ch_dict``), blocks at levels 3 and 4.
CHANNELS = (32, 128, 256, 512)
REPEATS = (3, 7)
#: Receptive-field limits per level (``recept_limit``); four branches everywhere.
RECEPT_LIMIT = (13, 11, 9, 7, 5)
BRANCHES = 4
#: Pyramid scales of the decoder's pooling modules, largest first.
PYRAMID_SCALES = (2.0, 1.5, 1.0, 0.5, 0.1)
NUM_CLASSES = 20
BN_EPS = 1e-5
#: Kernel size -> dilation of a 3x3 kernel with that receptive field.
_DILATION = {3: 1, 5: 2, 7: 3, 9: 4, 11: 5, 13: 6, 15: 7, 17: 8}


def build(weights: Weights, width: int, height: int) -> onnx.ModelProto:
    """The ESPNetv2 Cityscapes network for ``width`` x ``height`` input (multiples of 16)."""
    if width % 16 or height % 16:
        raise ValueError(f"ESPNetv2 needs an input size divisible by 16, got {width}x{height}")
    g = GraphBuilder(weights, BN_EPS)
    image = T("input", 3, height, width)
    pyramid = [image]  # the image avg-pooled 0, 1, 2, ... times (input reinforcement)

    def image_at(h: int) -> T:
        while pyramid[-1].h != h:
            pyramid.append(g.avg_pool3s2(pyramid[-1]))
        return pyramid[-1]

    c1, c2, c3, c4 = CHANNELS
    l1 = _cbr(g, image, "base_net.level1", c1, 3, stride=2)
    l2 = _down_sampler(g, l1, "base_net.level2_0", c2, RECEPT_LIMIT[0], image_at)
    l3 = _down_sampler(g, l2, "base_net.level3_0", c3, RECEPT_LIMIT[1], image_at)
    for i in range(REPEATS[0]):
        l3 = _eesp(g, l3, f"base_net.level3.{i}", c3, 1, RECEPT_LIMIT[2])
    l4 = _down_sampler(g, l3, "base_net.level4_0", c4, RECEPT_LIMIT[2], image_at)
    for i in range(REPEATS[1]):
        l4 = _eesp(g, l4, f"base_net.level4.{i}", c4, 1, RECEPT_LIMIT[3])

    base = 16  # Cityscapes decoder planes
    dec = (4 * base, 3 * base, 2 * base, NUM_CLASSES)
    proj = min(NUM_CLASSES // 2, base)
    out = _pyramid_pool(g, l4, "bu_dec_l1", proj, dec[0])
    for level, (skip, planes) in enumerate(((l3, dec[1]), (l2, dec[2]), (l1, dec[3])), 2):
        out = g.resize_bilinear(out, 2 * out.h, 2 * out.w)
        out = g.add(_weighted_skip(g, skip, f"merge_enc_dec_l{level}", out.c), out)
        out = g.prelu(g.batchnorm(out, f"bu_br_l{level}.0"), f"bu_br_l{level}.1.weight")
        out = _pyramid_pool(g, out, f"bu_dec_l{level}", proj, planes, last=level == 4)
    out = g.resize_bilinear(out, height, width)
    weights.check_all_used()
    return g.model(image, out, "espnetv2_cityscapes",
                   "ESPNetv2 (s=2.0) Cityscapes segmentation, rebuilt from sacmehta/EdgeNets")


def _cbr(g: GraphBuilder, x: T, prefix: str, cout: int, k: int, stride: int = 1,
         groups: int = 1) -> T:
    """EdgeNets' espnet_utils CBR: conv (no bias), BatchNorm, PReLU (keys conv/bn/act)."""
    return g.conv(x, f"{prefix}.conv.weight", cout, k, stride, groups=groups,
                  bn=f"{prefix}.bn", prelu=f"{prefix}.act.weight")


def _cbr_seq(g: GraphBuilder, x: T, prefix: str, cout: int, k: int, groups: int = 1) -> T:
    """EdgeNets' cnn_utils CBR: the same layers in an nn.Sequential (keys cbr.0/1/2)."""
    return g.conv(x, f"{prefix}.cbr.0.weight", cout, k, groups=groups, bn=f"{prefix}.cbr.1",
                  prelu=f"{prefix}.cbr.2.weight")


def _eesp(g: GraphBuilder, x: T, prefix: str, cout: int, stride: int, r_lim: int) -> T:
    """EESP block; with stride 2 (inside a down-sampler) it returns before residual and PReLU."""
    n = cout // BRANCHES
    if n * BRANCHES != cout:
        raise AssertionError(f"{prefix}: {cout} channels for {BRANCHES} branches")
    reduced = _cbr(g, x, f"{prefix}.proj_1x1", n, 1, groups=BRANCHES)
    ksizes = sorted(3 + 2 * i if 3 + 2 * i <= r_lim else 3 for i in range(BRANCHES))
    branches: list[T] = []
    for i, ksize in enumerate(ksizes):
        d = _DILATION[ksize]
        y = g.conv(reduced, f"{prefix}.spp_dw.{i}.conv.weight", n, 3, stride, dilation=d,
                   groups=n)
        branches.append(g.add(y, branches[-1]) if branches else y)  # hierarchical fusion
    merged = g.concat(branches)
    merged = g.prelu(g.batchnorm(merged, f"{prefix}.br_after_cat.bn"),
                     f"{prefix}.br_after_cat.act.weight")
    expanded = g.conv(merged, f"{prefix}.conv_1x1_exp.conv.weight", cout, 1, groups=BRANCHES,
                      bn=f"{prefix}.conv_1x1_exp.bn")
    if stride == 2:
        # the module's PReLU exists in the checkpoint but the down-sampler path skips it
        g.weights.take(f"{prefix}.module_act.weight", (cout,))
        return expanded
    if x.c == cout:
        expanded = g.add(expanded, x)
    return g.prelu(expanded, f"{prefix}.module_act.weight")


def _down_sampler(g: GraphBuilder, x: T, prefix: str, cout: int, r_lim: int,
                  image_at: Callable[[int], T]) -> T:
    """avg-pool(x) || EESP(x, stride 2), plus the reinforced input image, then PReLU."""
    pooled = g.avg_pool3s2(x)
    strided = _eesp(g, x, f"{prefix}.eesp", cout - x.c, 2, r_lim)
    out = g.concat([pooled, strided])
    img = image_at(out.h)
    reinf = _cbr(g, img, f"{prefix}.inp_reinf.0", 3, 3)
    reinf = g.conv(reinf, f"{prefix}.inp_reinf.1.conv.weight", cout, 1,
                   bn=f"{prefix}.inp_reinf.1.bn")
    return g.prelu(g.add(out, reinf), f"{prefix}.act.weight")


def _pyramid_pool(g: GraphBuilder, x: T, prefix: str, proj: int, cout: int,
                  last: bool = False) -> T:
    """EfficientPyrPool: projection, five depth-wise branches at pyramid scales, merge."""
    p = _cbr_seq(g, x, f"{prefix}.projection_layer", proj, 1)
    branches = []
    for i, scale in enumerate(PYRAMID_SCALES):
        h = max(ceil_scale(p.h, scale), 5)
        w = max(ceil_scale(p.w, scale), 5)
        key = f"{prefix}.stages.{i}.weight"
        if scale < 1.0:
            y = g.conv(g.adaptive_avg_pool(p, h, w), key, proj, 3, groups=proj)
            y = g.resize_bilinear(y, p.h, p.w)
        elif scale > 1.0:
            y = g.conv(g.resize_bilinear(p, h, w), key, proj, 3, groups=proj)
            y = g.adaptive_avg_pool(y, p.h, p.w)
        else:
            y = g.conv(p, key, proj, 3, groups=proj)
        branches.append(y)
    merged = g.concat(branches)
    merged = g.prelu(g.batchnorm(merged, f"{prefix}.merge_layer.0.br.0"),
                     f"{prefix}.merge_layer.0.br.1.weight")
    merged = g.channel_shuffle(merged, len(PYRAMID_SCALES))
    merged = _cbr_seq(g, merged, f"{prefix}.merge_layer.2", proj, 3, groups=proj)
    if last:  # the classifier: 1x1 conv with bias, no BatchNorm
        return g.conv(merged, f"{prefix}.merge_layer.3.weight", cout, 1,
                      bias=f"{prefix}.merge_layer.3.bias")
    out = g.conv(merged, f"{prefix}.merge_layer.3.weight", cout, 1, bn=f"{prefix}.br.br.0")
    return g.prelu(out, f"{prefix}.br.br.1.weight")


def _weighted_skip(g: GraphBuilder, x: T, prefix: str, cout: int) -> T:
    """EfficientPWConv: grouped 3x3 CBR, scaled by sigmoid(1x1 conv of the global average)."""
    gate = g.sigmoid(g.conv(g.global_avg_pool(x), f"{prefix}.wt_layer.1.weight", cout, 1))
    expanded = _cbr_seq(g, x, f"{prefix}.expansion_layer", cout, 3, groups=math.gcd(x.c, cout))
    return g.mul(expanded, gate)
