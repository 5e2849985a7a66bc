"""Label alignment, label-mapping YAML, and the file formats of the engine."""

import numpy as np
import pytest

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.io import files, ply
from semcal_ros.engine.labels import CITYSCAPES_ID, INVALID, KITTI_ID, SKY, LabelMapping


def test_default_alignment_and_dynamic_removal():
    m = LabelMapping()
    lut = m.lidar_lut()
    assert lut[KITTI_ID["lane-marking"]] == CITYSCAPES_ID["road"]
    assert lut[KITTI_ID["trunk"]] == CITYSCAPES_ID["vegetation"]
    assert lut[KITTI_ID["car"]] == INVALID
    assert lut[KITTI_ID["moving-person"]] == INVALID
    img = m.image_lut()
    assert img[CITYSCAPES_ID["wall"]] == INVALID  # no lidar counterpart
    assert img[CITYSCAPES_ID["car"]] == INVALID
    assert img[SKY] == SKY
    assert img[CITYSCAPES_ID["pole"]] == CITYSCAPES_ID["pole"]
    # instance bits are ignored
    assert m.map_lidar(np.array([(7 << 16) | 40], np.uint32))[0] == CITYSCAPES_ID["road"]
    assert KITTI_ID["moving-car"] in m.dynamic_kitti_ids()


def test_merge_yaml(tmp_path):
    p = tmp_path / "m.yaml"
    p.write_text("merge: {sidewalk: road}\n")
    m = LabelMapping.from_yaml(p)
    assert m.lidar_lut()[KITTI_ID["sidewalk"]] == CITYSCAPES_ID["road"]
    assert m.image_lut()[CITYSCAPES_ID["sidewalk"]] == CITYSCAPES_ID["road"]
    p.write_text("merge: {sidewalk: roadz}\n")
    with pytest.raises(ValueError, match="roadz"):
        LabelMapping.from_yaml(p)


def test_ply_roundtrip_and_format(tmp_path):
    rng = np.random.default_rng(0)
    cloud = LabelledCloud(rng.normal(size=(100, 3)), rng.integers(0, 260, 100).astype(np.uint16))
    path = tmp_path / "map.ply"
    ply.write_ply(path, cloud)
    header = path.read_bytes()[:300].decode("ascii", "replace")
    assert "format binary_little_endian 1.0" in header
    assert "property float x" in header and "property ushort label" in header
    back = ply.read_ply(path)
    np.testing.assert_allclose(back.xyz, cloud.xyz.astype(np.float32))
    np.testing.assert_array_equal(back.label, cloud.label)


def test_ply_without_label_is_rejected(tmp_path):
    path = tmp_path / "nolabel.ply"
    ply.write_ply(path, LabelledCloud(np.zeros((3, 3))))
    with pytest.raises(ValueError, match="no 'label' property"):
        ply.read_ply(path)


def test_pose_yaml_forms(tmp_path):
    p = tmp_path / "init.yaml"
    p.write_text("frame_id: map\nchild_frame_id: camera_optical\n"
                 "translation: [1, 2, 6]\nrpy_deg: [0, 15, 30]\n")
    pose = files.read_pose(p)
    np.testing.assert_allclose(pose.body_rpy_deg(), [0, 15, 30], atol=1e-9)
    out = tmp_path / "out.yaml"
    files.write_pose(out, pose, {"loss": 0.5})
    again = files.read_pose(out)
    np.testing.assert_allclose(again.quaternion, pose.quaternion)
    p.write_text("translation: [1, 2, 6]\nrotation: [0, 0, 0, 3]\n")
    with pytest.raises(ValueError, match="unit quaternion"):
        files.read_pose(p)
