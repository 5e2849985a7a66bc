"""Every URDF `semcal export-pose` writes is read by a standard URDF parser (issue 34): no xacro
expressions such as ``-pi/2``, only plain numbers. urdf_parser_py (PyPI, the ROS URDF reader's
Python port) parses it strictly; without it every numeric attribute is read with float()."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from semcal_ros.export import export_pose, framed_pose_from_dict

from test_export_pose import POSES, pose_matrix

NUMERIC = {"origin": ("xyz", "rpy")}


def _framed(name: str):
    pose = POSES[name]
    return framed_pose_from_dict({"frame_id": "map", "child_frame_id": "camera_optical",
                                  "translation": [float(v) for v in pose.translation],
                                  "rotation": [float(v) for v in pose.quaternion]})


def _strict_numbers(text: str) -> None:
    """float() of every xyz / rpy value (what urdfdom does with each attribute)."""
    robot = ET.fromstring(text)
    for element in robot.iter("origin"):
        for attribute in NUMERIC["origin"]:
            values = element.get(attribute).split()
            assert len(values) == 3, (attribute, values)
            for value in values:
                float(value)  # ValueError for '-pi/2'


@pytest.mark.parametrize("body_frame", [None, "camera_link"])
@pytest.mark.parametrize("name", sorted(POSES))
def test_urdf_is_plain_numbers_that_a_urdf_parser_reads(name, body_frame):
    text = export_pose(_framed(name), "urdf", body_frame)
    _strict_numbers(text)
    urdf = pytest.importorskip("urdf_parser_py.urdf")
    robot = urdf.URDF.from_xml_string(text)
    joints = {j.parent: j for j in robot.joints}
    total, frame = np.eye(4), "map"
    while frame != "camera_optical":  # the parsed joints compose to the pose
        joint = joints[frame]
        step = np.eye(4)
        step[:3, :3] = Rotation.from_euler("xyz", joint.origin.rpy).as_matrix()
        step[:3, 3] = joint.origin.xyz
        total, frame = total @ step, joint.child
    np.testing.assert_allclose(total, pose_matrix(POSES[name]), atol=1e-9, rtol=0)
    if body_frame is not None:
        assert joints[body_frame].origin.rpy == [-math.pi / 2, 0.0, -math.pi / 2]
