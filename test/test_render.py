"""The two renderer paths agree pixel for pixel; splats, z-buffer and crop behave as specified."""

import numpy as np
import pytest

from semcal_ros.engine.camera import CameraModel, equidistant_radius
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.labels import CITYSCAPES_ID, INVALID, KITTI_ID
from semcal_ros.engine.pose import Pose
from semcal_ros.engine.render import fast, make_view, prepare_map, reference
from semcal_tools.synthetic import GROUND_TRUTH, camera, street_world


@pytest.fixture(scope="module")
def world():
    return street_world(step=0.15)


@pytest.mark.parametrize("falloff,core,lod", [(0.0, 1.0, 0.0), (0.3, 0.6, 0.0), (0.3, 1.0, 1.5)])
@pytest.mark.parametrize("pose", [
    GROUND_TRUTH,
    Pose.from_body_rpy_deg([3.0, -2.0, 1.5], [2.0, 5.0, 170.0]),  # low, looking the other way
    Pose.from_body_rpy_deg([0.0, 0.0, 30.0], [0.0, 89.0, 0.0]),  # straight down from high up
])
def test_fast_and_reference_are_identical(world, pose, falloff, core, lod):
    cam = CameraModel(960, 600, camera().k, np.array([-0.2, 0.05, 0.002, -0.001, 0.01]))
    pmap = prepare_map(world, center=pose.translation)
    view = make_view(cam, pose, pmap.origin, 32.0, 8.0, depth_falloff=falloff, core_fraction=core,
                     lod_radius=lod)
    a = reference.render(pmap, view)
    b = fast.render(pmap, view)
    assert (a != INVALID).mean() > 0.05  # something was drawn
    np.testing.assert_array_equal(a, b)


def test_identical_with_one_and_two_threads(world):
    pmap = prepare_map(world, center=GROUND_TRUTH.translation)
    view = make_view(camera(), GROUND_TRUTH, pmap.origin, 32.0, 8.0)
    np.testing.assert_array_equal(fast.render_keys(pmap, view, 1), fast.render_keys(pmap, view, 2))


def _two_points_cloud(z_near, z_far, lab_near="pole", lab_far="building"):
    xyz = np.array([[z_near, 0.0, 0.0], [z_far, 0.0, 0.0]])  # on the optical axis of the pose below
    label = np.array([KITTI_ID[lab_near], KITTI_ID[lab_far]], np.uint16)
    return LabelledCloud(xyz, label)


def test_nearest_point_wins_and_disc_radius_follows_distance():
    cam = camera(200, 100)
    pose = Pose.from_body_rpy_deg([0, 0, 0], [0, 0, 0])
    pmap = prepare_map(_two_points_cloud(4.0, 8.0), center=np.zeros(3))
    img = reference.render(pmap, make_view(cam, pose, pmap.origin, 16.0, 8.0))
    centre = (int(round(cam.cy)), int(round(cam.cx)))
    assert img[centre] == CITYSCAPES_ID["pole"]
    # radius 16/4 = 4 px for the near pole, 16/8 = 2 px for the far building
    row = img[centre[0]]
    pole = np.flatnonzero(row == CITYSCAPES_ID["pole"])
    assert pole.max() - pole.min() + 1 == 9
    far_only = prepare_map(_two_points_cloud(8.0, 8.0, "building"), center=np.zeros(3))
    row2 = reference.render(far_only, make_view(cam, pose, far_only.origin, 16.0, 8.0))[centre[0]]
    assert (row2 == CITYSCAPES_ID["building"]).sum() == 5


def test_dynamic_points_are_removed_and_crop_applies():
    xyz = np.array([[1.0, 0, 0], [2.0, 0, 0], [500.0, 0, 0]])
    label = np.array([KITTI_ID["car"], KITTI_ID["road"], KITTI_ID["road"]], np.uint16)
    pmap = prepare_map(LabelledCloud(xyz, label), center=np.zeros(3), radius=100.0)
    assert len(pmap) == 1
    assert pmap.label[0] == CITYSCAPES_ID["road"]
    with pytest.raises(ValueError, match="no static labelled points"):
        prepare_map(LabelledCloud(xyz[:1], label[:1]))


def test_spacing_estimate_matches_a_full_search(world):
    from scipy.spatial import cKDTree

    pmap = prepare_map(world)
    dist, _ = cKDTree(pmap.xyz).query(pmap.xyz, k=2)
    assert pmap.spacing == pytest.approx(float(np.median(dist[:, 1])), rel=0.05)


def test_level_of_detail_thins_far_points_and_keeps_the_picture():
    dense = street_world(step=0.04)
    pmap = prepare_map(dense, center=GROUND_TRUTH.translation)
    lam = 1.5 * camera().fx * pmap.spacing  # the engine's splat size for this density
    full = make_view(camera(), GROUND_TRUTH, pmap.origin, lam, 8.0, depth_falloff=0.3)
    lod = make_view(camera(), GROUND_TRUTH, pmap.origin, lam, 8.0, depth_falloff=0.3,
                    lod_radius=2.0)
    drawn_full = len(reference.project_points(pmap, full)[0])
    drawn_lod = len(reference.project_points(pmap, lod)[0])
    assert drawn_lod < 0.8 * drawn_full  # far chunks are thinned ...
    a, b = fast.render(pmap, full), fast.render(pmap, lod)
    assert abs((a != INVALID).mean() - (b != INVALID).mean()) < 0.03  # ... without opening holes
    assert (a != b).mean() < 0.05
    np.testing.assert_array_equal(b, reference.render(pmap, lod))


def test_disc_rim_occludes_without_label():
    cam = camera(200, 100)
    pose = Pose.from_body_rpy_deg([0, 0, 0], [0, 0, 0])
    pmap = prepare_map(_two_points_cloud(4.0, 8.0), center=np.zeros(3))
    row = reference.render(pmap, make_view(cam, pose, pmap.origin, 16.0, 8.0,
                                           core_fraction=0.5))[int(round(cam.cy))]
    pole = np.flatnonzero(row == CITYSCAPES_ID["pole"])
    assert pole.max() - pole.min() + 1 == 5  # core radius 2 of the 4 px disc
    assert (row == CITYSCAPES_ID["building"]).sum() == 0  # the rim still hides the building
    assert (row == INVALID).sum() == len(row) - 5


@pytest.mark.parametrize("lens", ["rational_polynomial", "equidistant"])
@pytest.mark.parametrize("pose", [
    GROUND_TRUTH,
    Pose.from_body_rpy_deg([3.0, -2.0, 1.5], [2.0, 5.0, 170.0]),  # low, looking the other way
    Pose.from_body_rpy_deg([0.0, 0.0, 30.0], [0.0, 89.0, 0.0]),  # straight down from high up
])
def test_fast_and_reference_are_identical_for_every_lens(world, pose, lens):
    """Each lens model (docs/lenses.md) through both renderers, with the falloff, core and
    level of detail the engine uses; one and two threads."""
    cam = (CameraModel.rational_fov(960, 600, 120.0) if lens == "rational_polynomial"
           else CameraModel.fisheye_fov(960, 600, 185.0))
    pmap = prepare_map(world, center=pose.translation)
    view = make_view(cam, pose, pmap.origin, 32.0, 8.0, depth_falloff=0.3, core_fraction=0.6,
                     lod_radius=1.0)
    a = reference.render(pmap, view)
    assert (a != INVALID).mean() > 0.05
    np.testing.assert_array_equal(a, fast.render(pmap, view))
    np.testing.assert_array_equal(fast.render_keys(pmap, view, 1), fast.render_keys(pmap, view, 2))


def test_fisheye_draws_beside_and_behind_the_image_plane(world):
    """A 185 deg fisheye draws map points more than 90 deg from its axis (z < 0 in the camera),
    outside the circle where the 90 deg rays land; the pinhole of the same pose draws fewer
    points in all."""
    pose = GROUND_TRUTH
    fish = CameraModel.fisheye_fov(960, 600, 185.0)
    pmap = prepare_map(world, center=pose.translation)
    view = make_view(fish, pose, pmap.origin, 32.0, 8.0)
    u, v, _, _, _ = reference.project_points(pmap, view)
    r, t = view.rotation, view.translation
    pc = pmap.xyz.astype(np.float64) @ r.T + t
    behind = pc[:, 2] < 0
    uv, seen = fish.project(pc)
    drawn_behind = seen & behind
    assert drawn_behind.sum() > 100
    # they land outside the circle of the 90 deg rays: radius f theta_d(90 deg) (equidistant)
    radius = np.hypot((uv[drawn_behind, 0] - fish.cx) / fish.fx,
                      (uv[drawn_behind, 1] - fish.cy) / fish.fy)
    assert radius.min() >= equidistant_radius(np.pi / 2, *fish.d) - 1e-9
    pin = make_view(camera(), pose, pmap.origin, 32.0, 8.0)
    assert len(reference.project_points(pmap, pin)[0]) < len(u)


def test_largest_disc_is_an_angle_on_a_sharp_camera():
    """``radius_max_deg``: the cap follows the focal length where it exceeds ``radius_max``, so
    a near point's disc covers the same angle of view on a 1920 px camera as on a 1241 px one;
    cameras at KITTI's focal length (about 720 px) keep the 8 px cap."""
    from semcal_ros.engine.render.view import RenderParams, view_setup

    rp = RenderParams(radius_max=8.0, radius_max_deg=0.6)
    assert rp.radius_max_for(721.5) == 8.0  # 0.6 deg is 7.6 px there
    assert rp.radius_max_for(2117.3) == pytest.approx(2117.3 * np.radians(0.6))
    assert RenderParams(radius_max_deg=0.0).radius_max_for(2117.3) == 8.0  # 0: pixels alone
    default = RenderParams()  # 0.43 deg: 8 px at a 1066 px focal length, 15.9 px on PJLab's
    assert default.radius_max_for(721.5) == default.radius_max_for(480.0) == 8.0
    assert default.radius_max_for(2117.3) == pytest.approx(15.89, abs=0.01)
    cloud = _two_points_cloud(0.6, 8.0)  # a point 0.6 m ahead: its disc hits any cap
    pmap = prepare_map(cloud, center=np.zeros(3))
    pose = Pose.from_body_rpy_deg([0, 0, 0], [0, 0, 0])
    widths = {}
    for fx in (720.0, 2160.0):
        cam = CameraModel(400, 300, np.array([[fx, 0, 199.5], [0, fx, 149.5], [0, 0, 1]]),
                          np.zeros(5))
        for deg in (0.0, 0.6):
            setup = view_setup(cam, pmap, RenderParams(splat_lambda=200.0, radius_max_deg=deg,
                                                       near=0.3))
            row = reference.render(pmap, setup.view(pose))[150]
            widths[fx, deg] = int((row == CITYSCAPES_ID["pole"]).sum())
    assert widths[720.0, 0.0] == widths[720.0, 0.6] == 17  # 2 x 8 + 1
    assert widths[2160.0, 0.0] == 17
    assert widths[2160.0, 0.6] == 2 * int(np.floor(2160.0 * np.radians(0.6))) + 1  # 22 px
    with pytest.raises(ValueError, match="radius_max_deg"):
        RenderParams(radius_max_deg=-1.0)
