"""Segmentation with real ONNX models (built by test/onnx_models.py) run by onnxruntime.

The models are 1x1 convolutions with nearest-centre weights, so each label they produce is known
in advance: the tests check the runner's conventions (channel order, normalisation, projection,
output kinds, class tables, resizing, points that lost their pixel) against those labels.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from onnx_models import colour_model, conv1x1_model, range_channel_model
from semcal_ros.cli import main
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.io import files, ply
from semcal_ros.engine.labels import (
    CITYSCAPES_ID, CITYSCAPES_PALETTE, INVALID, KITTI_ID, SEMANTIC_KITTI, LabelMapping,
)
from semcal_ros.segmentation.cloud import CloudSegmenter, project
from semcal_ros.segmentation.image import ImageSegmenter, read_colour_image
from semcal_ros.segmentation.model_config import (
    ImageModelConfig, RangeModelConfig, load_model_config, model_config_from_dict,
)
from semcal_ros.segmentation.onnx_runner import OnnxRunner

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
KITTI_IMAGE = DATA / "kitti_object" / "tr_000000.png"
KITTI_SCAN = DATA / "kitti_odometry_00" / "velodyne" / "000000.bin"
IMAGE_EXAMPLE = ROOT / "config" / "models" / "ocrnet_cityscapes.yaml"
RANGE_EXAMPLE = ROOT / "config" / "models" / "salsanext_semantickitti.yaml"
needs_kitti_image = pytest.mark.skipif(not KITTI_IMAGE.is_file(),
                                       reason=f"real KITTI image not found: {KITTI_IMAGE}")
needs_kitti_scan = pytest.mark.skipif(not KITTI_SCAN.is_file(),
                                      reason=f"real KITTI scan not found: {KITTI_SCAN}")

# ---------------------------------------------------------------- image

# model class -> colour; classes in an order unlike the trainIds, one left unmapped (None)
PALETTE = np.array([[250, 20, 20], [20, 240, 20], [20, 20, 250], [128, 128, 128]])
CLASSES = ("building", "vegetation", CITYSCAPES_ID["sky"], None)
EXPECTED = np.array([[CITYSCAPES_ID["building"], CITYSCAPES_ID["vegetation"]],
                     [CITYSCAPES_ID["sky"], INVALID]], dtype=np.uint8)
NORM = {"mean": (123.675, 116.28, 103.53), "std": (58.395, 57.12, 57.375)}
W, H = 96, 64


def quadrants(height: int = H, width: int = W) -> tuple[np.ndarray, np.ndarray]:
    """An RGB image of the four palette colours in quadrants, and its expected trainIds."""
    rows = (np.arange(height) >= height // 2).astype(int)
    cols = (np.arange(width) >= width // 2).astype(int)
    model_class = rows[:, None] * 2 + cols[None, :]
    return PALETTE[model_class].astype(np.uint8), EXPECTED[rows[:, None], cols[None, :]]


def image_config(**kw) -> ImageModelConfig:
    args = dict(input_width=W, input_height=H, classes=CLASSES, **NORM)
    args.update(kw)
    return ImageModelConfig(**args)


def image_segmenter(tmp_path: Path, config: ImageModelConfig, **model_kw) -> ImageSegmenter:
    model = colour_model(tmp_path / "image.onnx", PALETTE, W, H,
                         channel_order=config.channel_order, mean=config.mean, std=config.std,
                         scale=config.scale, **model_kw)
    return ImageSegmenter(OnnxRunner(model), config)


def test_colour_model_labels_each_quadrant_with_its_cityscapes_class(tmp_path):
    image, expected = quadrants()
    labels = image_segmenter(tmp_path, image_config()).segment(image, "rgb8")
    assert labels.dtype == np.uint8
    np.testing.assert_array_equal(labels, expected)


def test_channel_order_and_encodings(tmp_path):
    # a model trained on BGR input with scale 1/255 and mean/std in 0..1 units
    config = image_config(channel_order="BGR", scale=1 / 255.0, mean=(0.406, 0.456, 0.485),
                          std=(0.225, 0.224, 0.229))
    seg = image_segmenter(tmp_path, config)
    rgb, expected = quadrants()
    bgr = np.ascontiguousarray(rgb[:, :, ::-1])
    alpha = np.full((H, W, 1), 7, np.uint8)
    for image, encoding in ((rgb, "rgb8"), (bgr, "bgr8"),
                            (np.concatenate([rgb, alpha], axis=2), "rgba8"),
                            (np.concatenate([bgr, alpha], axis=2), "bgra8")):
        np.testing.assert_array_equal(seg.segment(image, encoding), expected, err_msg=encoding)


@pytest.mark.parametrize("kind", ["class_map", "class_map_n1hw", "quarter_logits"])
def test_other_output_kinds_and_resizing_back_to_the_image(tmp_path, kind):
    if kind == "quarter_logits":  # SegFormer-like: logits at a quarter of the input size
        config, model_kw = image_config(), {"stride": 4}
    else:
        config = image_config(output="class_map")
        model_kw = {"argmax": True, "class_map_channel": kind == "class_map_n1hw"}
    seg = image_segmenter(tmp_path, config, **model_kw)
    image, expected = quadrants(150, 310)  # other size and aspect than the 96x64 input
    labels = seg.segment(image, "rgb8")
    assert labels.shape == (150, 310)
    inner = np.zeros_like(expected, bool)  # quadrant borders move by up to a model pixel
    inner[12:63, 16:139] = inner[87:138, 171:294] = True
    np.testing.assert_array_equal(labels[inner], expected[inner])
    assert set(np.unique(labels)) == set(np.unique(expected))


def test_ignored_classes_by_index_and_by_name(tmp_path):
    image, expected = quadrants()
    for ignore in ((0,), ("building",)):
        labels = image_segmenter(tmp_path, image_config(ignore=ignore)).segment(image)
        assert np.all(labels[: H // 2, : W // 2] == INVALID)
        np.testing.assert_array_equal(labels[H // 2:], expected[H // 2:])


def test_unsupported_images_are_refused_with_the_reason(tmp_path):
    seg = image_segmenter(tmp_path, image_config())
    rgb, _ = quadrants()
    with pytest.raises(ValueError, match="uint16.*8-bit"):
        seg.segment(rgb.astype(np.uint16) * 256, "rgb8")
    with pytest.raises(ValueError, match=r"\(64, 96, 4\) does not match encoding 'rgb8'"):
        seg.segment(np.dstack([rgb, rgb[:, :, :1]]), "rgb8")
    with pytest.raises(ValueError, match="does not match encoding 'bgr8'"):
        seg.segment(rgb[:, :, 0], "bgr8")
    with pytest.raises(ValueError, match="unsupported image encoding 'mono16'"):
        seg.segment(rgb, "mono16")
    deep = tmp_path / "deep.png"
    cv2.imwrite(str(deep), rgb.astype(np.uint16) * 256)
    with pytest.raises(ValueError, match="16-bit image"):
        read_colour_image(deep)
    grey = tmp_path / "grey.png"
    cv2.imwrite(str(grey), rgb[:, :, 0])
    with pytest.raises(ValueError, match="1-channel image"):
        read_colour_image(grey)


def test_model_that_does_not_fit_its_config_is_refused(tmp_path):
    model = colour_model(tmp_path / "m.onnx", PALETTE, W, H, **NORM)
    runner = OnnxRunner(model)
    with pytest.raises(ValueError, match=r"input 'input' has shape \[1, 3, 64, 96\] but the "
                                         r"model config gives \[1, 3, 512, 1024\]"):
        ImageSegmenter(runner, image_config(input_width=1024, input_height=512))
    with pytest.raises(ValueError, match=r"output 'output' has shape \[1, 4, 64, 96\] but the "
                                         r"model config expects \[1, 5, 'any', 'any'\]"):
        ImageSegmenter(runner, image_config(classes=CLASSES + ("road",)))
    with pytest.raises(ValueError, match=r"output 'output' is tensor\(float\), but output: "
                                         r"class_map needs int values"):
        ImageSegmenter(runner, image_config(output="class_map"))
    class_map = colour_model(tmp_path / "cm.onnx", PALETTE, W, H, argmax=True, **NORM)
    with pytest.raises(ValueError, match=r"output 'output' is tensor\(int64\), but output: "
                                         r"logits needs float values"):
        ImageSegmenter(OnnxRunner(class_map), image_config())
    with pytest.raises(ValueError, match="1 x 5 .range, x, y, z, remission"):
        CloudSegmenter(runner, RangeModelConfig(height=64, width=96, classes=("road",) * 4))
    with pytest.raises(ValueError, match="no output named 'labels' .it has: output"):
        OnnxRunner(model, output_name="labels")
    # symbolic sizes accept any configured input size
    dyn = conv1x1_model(tmp_path / "dyn.onnx", np.eye(4, 3), np.zeros(4), [1, 3, "h", "w"])
    ImageSegmenter(OnnxRunner(dyn), image_config(input_width=1024, input_height=512))


def test_example_configs_load_and_speak_the_engine_taxonomies():
    image = load_model_config(IMAGE_EXAMPLE)
    assert isinstance(image, ImageModelConfig)
    np.testing.assert_array_equal(image.class_lut(), np.arange(19))
    scan = load_model_config(RANGE_EXAMPLE)
    assert isinstance(scan, RangeModelConfig)
    lut = scan.class_lut()
    assert lut.dtype == np.uint16 and len(lut) == 20
    assert lut[0] == KITTI_ID["unlabeled"] and lut[1] == KITTI_ID["car"]
    assert lut[19] == KITTI_ID["traffic-sign"]
    assert scan.means == (12.12, 10.88, 0.23, -1.04, 0.21)
    # every class the range example predicts reaches the calibrator through the one alignment
    assert all(SEMANTIC_KITTI[int(i)] in LabelMapping().alignment for i in lut[1:])


@pytest.mark.parametrize("change, message", [
    ({"classes": ["road", "roadz"]}, "classes\\[1\\]: unknown Cityscapes class 'roadz'"),
    ({"classes": ["road", 77]}, "classes\\[1\\]: 77 is not a Cityscapes id"),
    ({"input_widht": 3}, "unknown key\\(s\\) for a image model config: input_widht"),
    ({"layout": "NHWC"}, "layout 'NHWC' is not supported"),
    ({"ignore": ["sky"]}, "ignore: 'sky' is neither"),
    ({"kind": "lidar"}, "'kind' must be 'image' or 'range'"),
    ({"std": [1, 0, 1]}, "'std' values must be finite and positive"),
])
def test_model_config_errors_name_what_is_wrong(tmp_path, change, message):
    data = {"kind": "image", "input_width": 8, "input_height": 8, "classes": ["road", "pole"]}
    data.update(change)
    with pytest.raises(ValueError, match=message):
        model_config_from_dict(data)


def test_range_config_channel_mapping_and_errors(tmp_path):
    base = {"kind": "range", "height": 4, "width": 8, "classes": ["road"]}
    means = {"range": 1, "x": 2, "y": 3, "z": 4, "remission": 5}
    cfg = model_config_from_dict({**base, "means": means})
    assert cfg.means == (1, 2, 3, 4, 5)
    with pytest.raises(ValueError, match="missing: remission"):
        model_config_from_dict({**base, "stds": {"range": 1, "x": 1, "y": 1, "z": 1}})
    path = tmp_path / "bad.yaml"
    path.write_text("kind: range\nheight: 4\nwidth: 8\nclasses: [road, street]\n")
    with pytest.raises(ValueError, match=f"{path}: classes\\[1\\]: unknown SemanticKITTI class"):
        load_model_config(path)


# ---------------------------------------------------------------- scans

def range_config(**kw) -> RangeModelConfig:
    args = dict(height=64, width=2048, classes=("pole", "building"),
                means=(12.12, 10.88, 0.23, -1.04, 0.21), stds=(12.32, 11.47, 6.91, 0.86, 0.16))
    args.update(kw)
    return RangeModelConfig(**args)


def test_spherical_projection_convention():
    cfg = range_config()
    pts = np.array([
        [10, 0, 0],         # ahead on the horizon: centre column, row (1 - 25/28) * 64 = 6.86
        [0, 10, 0],         # left: a quarter of the width
        [0, -10, 0],        # right: three quarters
        [-10, 1e-4, 0],     # behind, just left: first column
        [-10, -1e-4, 0],    # behind, just right: last column
        [10, 0, -10],       # 45 deg down, below the field of view: bottom row
        [10, 0, 2],         # 11 deg up, above it: top row
        [np.nan, 0, 0],     # unusable
        [0, 0, 0],          # unusable
        [20, 0, 0],         # behind the first point on the same ray: loses its pixel
    ], dtype=np.float32)
    proj = project(pts, cfg)
    row, col = np.divmod(proj.pixel[:7], cfg.width)
    np.testing.assert_array_equal(row, [6, 6, 6, 6, 6, 63, 0])
    np.testing.assert_array_equal(col, [1024, 512, 1536, 0, 2047, 1024, 1024])
    np.testing.assert_array_equal(proj.pixel[7:9], [-1, -1])
    assert proj.pixel[9] == proj.pixel[0] and proj.owner[proj.pixel[0]] == 0
    np.testing.assert_array_equal(proj.lost(), [9])
    assert (proj.owner >= 0).sum() == 7


def pole_and_wall() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A wall 20 m ahead, a thin pole 5 m ahead in front of it, and one NaN point.

    The wall is sampled more densely than the 2048 columns, so many wall points lose their
    pixel to other wall points; the pole hides part of the wall, so others lose it to the pole.
    """
    wy, wz = np.meshgrid(np.linspace(-5, 5, 400), np.linspace(-2, 1, 30))
    wall = np.column_stack([np.full(wy.size, 20.0), wy.ravel(), wz.ravel()])
    py, pz = np.meshgrid([-0.02, 0.0, 0.02], np.linspace(-1.4, 0.2, 40))
    pole = np.column_stack([np.full(py.size, 5.0), py.ravel(), pz.ravel()])
    xyz = np.vstack([wall, pole, [[np.nan, 0, 0]]]).astype(np.float32)
    expected = np.concatenate([np.full(len(wall), KITTI_ID["building"]),
                               np.full(len(pole), KITTI_ID["pole"]), [0]]).astype(np.uint16)
    intensity = np.linspace(0, 1, len(xyz)).astype(np.float32)
    return xyz, intensity, expected


@pytest.mark.parametrize("output", ["logits", "class_map"])
def test_every_point_gets_its_class_including_points_that_lost_their_pixel(tmp_path, output):
    cfg = range_config(output=output)
    model = range_channel_model(tmp_path / "range.onnx", 0, [5.0, 20.0], cfg.means[0],
                                cfg.stds[0], cfg.height, cfg.width, argmax=output == "class_map")
    xyz, intensity, expected = pole_and_wall()
    seg = CloudSegmenter(OnnxRunner(model), cfg)
    labels = seg.segment(xyz, intensity)
    assert labels.dtype == np.uint16
    np.testing.assert_array_equal(labels, expected)

    proj = project(xyz, cfg)
    lost = proj.lost()
    hidden = lost[(expected[lost] == KITTI_ID["building"])
                  & (expected[proj.owner[proj.pixel[lost]]] == KITTI_ID["pole"])]
    assert len(lost) > 2000 and len(hidden) > 20  # the scene exercises both kinds of loss
    # with a 1-pixel window the hidden wall points would take the pole's label
    own_pixel = CloudSegmenter(OnnxRunner(model), range_config(output=output, knn_window=1))
    assert np.all(own_pixel.segment(xyz, intensity)[hidden] == KITTI_ID["pole"])


def test_scan_without_xyz_is_refused(tmp_path):
    cfg = range_config()
    model = range_channel_model(tmp_path / "r.onnx", 0, [5.0, 20.0], 0, 1, 64, 2048)
    seg = CloudSegmenter(OnnxRunner(model), cfg)
    with pytest.raises(ValueError, match=r"\(N, 3\) array of x, y, z, got shape \(10, 2\)"):
        seg.segment(np.zeros((10, 2)))
    with pytest.raises(ValueError, match=r"intensity must have shape \(10,\)"):
        seg.segment(np.ones((10, 3)), np.ones(9))


@needs_kitti_scan
def test_real_kitti_scan_with_a_height_model(tmp_path):
    """The example range config on a real HDL-64E scan: 20 height bands, one per class."""
    cfg = load_model_config(RANGE_EXAMPLE)
    centres = np.linspace(-2.5, 4.0, cfg.num_classes)
    model = range_channel_model(tmp_path / "h.onnx", 3, centres, cfg.means[3], cfg.stds[3],
                                cfg.height, cfg.width)
    scan = np.fromfile(KITTI_SCAN, dtype=np.float32).reshape(-1, 4)
    labels = CloudSegmenter(OnnxRunner(model), cfg).segment(scan[:, :3], scan[:, 3])
    band = cfg.class_lut()[np.abs(scan[:, 2:3] - centres[None, :]).argmin(axis=1)]
    proj = project(scan[:, :3], cfg)
    lost = np.zeros(len(scan), bool)
    lost[proj.lost()] = True
    assert 0.1 < lost.mean() < 0.4
    # pixel owners are labelled from their own height ...
    assert (labels[~lost] == band[~lost]).mean() > 0.999
    # ... lost points like their 3-D nearest owner in the whole scan (a k-d tree reference);
    # the 5x5 window finds it for ~96.5 % of them, their own pixel alone for ~81 %
    owners = proj.owner[proj.owner >= 0]
    _, nearest = cKDTree(scan[owners, :3]).query(scan[lost, :3])
    assert (labels[lost] == labels[owners[nearest]]).mean() > 0.95


# ---------------------------------------------------------------- command line

@pytest.fixture(scope="module")
def example_models(tmp_path_factory):
    """Test models shaped like the two example configs (19 classes 1024x512; 20 classes)."""
    root = tmp_path_factory.mktemp("models")
    image_cfg = load_model_config(IMAGE_EXAMPLE)
    palette = np.array([CITYSCAPES_PALETTE[i] for i in range(19)])
    image = colour_model(root / "image.onnx", palette, 1024, 512, mean=image_cfg.mean,
                         std=image_cfg.std)
    scan_cfg = load_model_config(RANGE_EXAMPLE)
    scan = range_channel_model(root / "range.onnx", 0, [0.1, 5.0, 20.0] + [500.0] * 17,
                               scan_cfg.means[0], scan_cfg.stds[0], 64, 2048)
    return image, scan


@needs_kitti_image
def test_cli_segments_a_real_kitti_image(tmp_path, example_models, capsys):
    out, overlay = tmp_path / "labels.png", tmp_path / "overlay.png"
    code = main(["segment-image", "--model", str(example_models[0]), "--model-config",
                 str(IMAGE_EXAMPLE), str(KITTI_IMAGE), "--out", str(out), "--overlay",
                 str(overlay), "--threads", "1"])
    assert code == 0 and "labelled in" in capsys.readouterr().out
    labels = files.read_label_image(out)
    rgb = files.read_rgb_image(KITTI_IMAGE)
    assert labels.shape == rgb.shape[:2]
    # the same as the library call on the decoded image: the file's BGR order was respected
    direct = ImageSegmenter.from_files(example_models[0], IMAGE_EXAMPLE).segment(rgb, "rgb8")
    np.testing.assert_array_equal(labels, direct)
    assert len(np.unique(labels)) >= 5 and labels.max() <= 18
    assert cv2.imread(str(overlay)).shape == rgb.shape


def test_cli_segments_a_ply_scan_in_a_real_process(tmp_path, example_models):
    xyz, intensity, _ = pole_and_wall()
    ok = np.isfinite(xyz).all(axis=1)
    scan = tmp_path / "scan.ply"
    ply.write_ply(scan, LabelledCloud(xyz[ok], None, {"intensity": intensity[ok]}))
    out = tmp_path / "labelled.ply"
    semcal = Path(sys.executable).with_name("semcal")  # the installed command, as users run it
    command = [str(semcal)] if semcal.is_file() else [
        sys.executable, "-c", "import sys; from semcal_ros.cli import main; sys.exit(main())"]
    proc = subprocess.run(
        [*command, "segment-cloud", "--model",
         str(example_models[1]), "--model-config", str(RANGE_EXAMPLE), str(scan), "--out",
         str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "labelled in" in proc.stdout
    cloud = ply.read_ply(out)
    np.testing.assert_allclose(cloud.xyz, xyz[ok])
    np.testing.assert_allclose(cloud.extra["intensity"], intensity[ok])
    # range 5 m -> model class 1 (car), 20 m -> model class 2 (bicycle) in the example table
    wall = cloud.xyz[:, 0] > 10
    assert np.all(cloud.label[wall] == KITTI_ID["bicycle"])
    assert np.all(cloud.label[~wall] == KITTI_ID["car"])


@needs_kitti_scan
def test_cli_reads_a_kitti_bin(tmp_path, example_models):
    out = tmp_path / "labelled.ply"
    assert main(["segment-cloud", "--model", str(example_models[1]), "--model-config",
                 str(RANGE_EXAMPLE), str(KITTI_SCAN), "--out", str(out)]) == 0
    cloud = ply.read_ply(out)
    assert len(cloud) == KITTI_SCAN.stat().st_size // 16
    assert set(np.unique(cloud.label)) <= {KITTI_ID["car"], KITTI_ID["bicycle"], 0}


def test_cli_errors_are_one_clear_line(tmp_path, example_models, capsys):
    image_model, range_model = map(str, example_models)
    no_z = tmp_path / "flat.ply"
    no_z.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                    "property float y\nend_header\n1 2\n")
    short = tmp_path / "short.bin"
    short.write_bytes(b"\0" * 10)
    deep = tmp_path / "deep.png"
    cv2.imwrite(str(deep), np.zeros((8, 8, 3), np.uint16))
    cases = [
        (["segment-cloud", "--model", range_model, "--model-config", str(RANGE_EXAMPLE),
          str(no_z), "--out", str(tmp_path / "o.ply")], "PLY vertex has no z property"),
        (["segment-cloud", "--model", range_model, "--model-config", str(RANGE_EXAMPLE),
          str(short), "--out", str(tmp_path / "o.ply")], "not a multiple of 16"),
        (["segment-cloud", "--model", range_model, "--model-config", str(IMAGE_EXAMPLE),
          str(short), "--out", str(tmp_path / "o.ply")], "with kind: range"),
        (["segment-cloud", "--model", image_model, "--model-config", str(RANGE_EXAMPLE),
          str(short), "--out", str(tmp_path / "o.ply")], "but the model config gives [1, 5,"),
        (["segment-image", "--model", image_model, "--model-config", str(IMAGE_EXAMPLE),
          str(deep), "--out", str(tmp_path / "o.png")], "16-bit image"),
    ]
    for argv, message in cases:
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err


# ---------------------------------------------------------------- class probabilities

def test_probabilities_are_the_softmax_in_train_ids_aligned_with_the_labels(tmp_path):
    """Model classes in another order, one ignored (None): its share is dropped, the rest
    renormalised; a 2x larger image gets them by nearest neighbour, like the labels."""
    from semcal_ros.segmentation.probabilities import probabilities_from_logits

    segmenter = image_segmenter(tmp_path, image_config())
    rgb, expected = quadrants(2 * H, 2 * W)
    labels, probs = segmenter.segment_with_probabilities(rgb, "rgb8")
    np.testing.assert_array_equal(labels, expected)
    assert probs.shape == (2 * H, 2 * W, 19) and probs.dtype == np.float32
    np.testing.assert_allclose(probs.sum(axis=2), 1.0, atol=1e-5)
    labelled = labels != INVALID
    np.testing.assert_array_equal(probs.argmax(axis=2)[labelled], labels[labelled])
    # against numpy at the model's own resolution: softmax over the 4 model classes, class 3
    # (None) dropped, the three others moved to their trainIds and renormalised
    logits = segmenter.infer(segmenter.preprocess(quadrants()[0], "rgb8"))
    e = np.exp(logits[0] - logits[0].max(axis=0))
    soft = e / e.sum(axis=0)
    kept = soft[:3] / soft[:3].sum(axis=0)
    ref = np.zeros((19, H, W))
    for model_class, name in enumerate(("building", "vegetation", "sky")):
        ref[CITYSCAPES_ID[name]] = kept[model_class]
    mine = probabilities_from_logits(logits, segmenter.lut)
    np.testing.assert_allclose(mine, ref.transpose(1, 2, 0), atol=1e-5)
    # two model classes into one trainId add up
    lut = np.array([CITYSCAPES_ID["road"], CITYSCAPES_ID["road"], 10, INVALID], np.uint8)
    merged = probabilities_from_logits(logits, lut)
    np.testing.assert_allclose(merged[:, :, 0], kept[0] + kept[1], atol=1e-5)


def test_probability_files_and_bytes_round_trip_and_bad_files_are_one_line(tmp_path):
    from semcal_ros.segmentation.probabilities import (
        from_bytes, read_probabilities, to_bytes, write_probabilities)

    rng = np.random.default_rng(3)
    raw = rng.random((5, 7, 19)).astype(np.float32)
    probs = raw / raw.sum(axis=2, keepdims=True)
    path = write_probabilities(tmp_path / "p.npz", probs)
    back = read_probabilities(path, (5, 7))
    assert back.dtype == np.float16 and back.shape == (5, 7, 19)
    np.testing.assert_allclose(back, probs, atol=5e-4)  # float16: 11-bit mantissa
    as_bytes = to_bytes(probs)
    assert as_bytes.dtype == np.uint8
    np.testing.assert_allclose(from_bytes(as_bytes), probs, atol=0.5 / 255 + 1e-6)

    np.savez(tmp_path / "other.npz", labels=np.zeros((5, 7)))
    np.savez(tmp_path / "f32.npz", probabilities=probs)
    (tmp_path / "garbage.npz").write_bytes(b"nope")
    for name, size, message in [("other.npz", None, "no array 'probabilities'"),
                                ("f32.npz", None, "float32, the contract is float16"),
                                ("garbage.npz", None, "not a readable .npz"),
                                ("p.npz", (6, 7), "probabilities are 7x5, the label image 7x6")]:
        with pytest.raises(ValueError, match=message):
            read_probabilities(tmp_path / name, size)
    with pytest.raises(ValueError, match=r"shape \(H, W, 19\)"):
        write_probabilities(tmp_path / "x.npz", probs[:, :, :18])


def test_probabilities_need_logits(tmp_path):
    segmenter = image_segmenter(tmp_path, image_config(output="class_map"), argmax=True)
    with pytest.raises(ValueError, match="class probabilities need a model with output: logits"):
        segmenter.segment_with_probabilities(quadrants()[0], "rgb8")
