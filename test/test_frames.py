"""Several frames of one rig (FrameSet, semcal calibrate --scene) and a static camera's label
images fused per pixel (fuse_labels, semcal calibrate --labels A B ...)."""

from dataclasses import replace

import numpy as np
import pytest
import yaml

from semcal_ros.cli import main
from semcal_ros.engine.calibration import calibrate_frames_and_draw
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.engine.frames import Frame, FrameSet, fuse_labels
from semcal_ros.engine.labels import INVALID
from semcal_ros.engine.loss import LossParams
from semcal_ros.engine.params import CalibrationParams, VerificationParams
from semcal_ros.engine.pose import Pose, rotation_error_deg, translation_error
from semcal_ros.engine.problem import Problem
from semcal_ros.engine.quality import assess
from semcal_ros.engine.search import solve
from semcal_ros.io import files, ply
from semcal_tools.synthetic import GROUND_TRUTH, PERTURBED_START, camera, target_image

#: where the rig's second frame saw the street from (moved and turned since the first)
SECOND = Pose.from_body_rpy_deg(GROUND_TRUTH.translation + [3.0, -2.0, 0.0],
                                GROUND_TRUTH.body_rpy_deg() + [0.0, 0.0, 15.0])


def in_rig_frame(world: LabelledCloud, seen_from: Pose, camera_in_rig: Pose = GROUND_TRUTH
                 ) -> LabelledCloud:
    """The world as a rig's lidar sees it when its camera, ``camera_in_rig`` in the lidar frame,
    stood at ``seen_from`` in the world: every frame of the rig then shares that one pose."""
    in_camera = seen_from.transform_points(world.xyz)
    return LabelledCloud(in_camera @ camera_in_rig.rotation.T + camera_in_rig.translation,
                         world.label)


@pytest.fixture(scope="module")
def rig(world, target):
    """Two frames of one rig: (map, labels) each, one camera pose (GROUND_TRUTH) for both."""
    second_map = in_rig_frame(world, SECOND)
    return [(world, target), (second_map, target_image(camera(), world=world, pose=SECOND))]


def test_a_second_frame_shares_the_first_frames_pose(rig):
    (_, _), (second_map, second_labels) = rig
    p = Problem(second_map, second_labels, camera(), GROUND_TRUTH.translation)
    # at its floor (every covered pixel drawn right) at the rig's pose, far above it at the world's
    assert p.loss(GROUND_TRUTH) - p.floor(GROUND_TRUTH) < 0.01
    assert p.loss(SECOND) - p.floor(SECOND) > 0.1  # the world pose is not this frame's pose


def test_one_frame_is_the_problem_itself(world, target):
    p = Problem(world, target, camera(), PERTURBED_START.translation)
    fs = FrameSet([p])
    for pose in (GROUND_TRUTH, PERTURBED_START):
        for stage in (0, -1):
            assert fs.loss(pose, stage) == pytest.approx(p.loss(pose, stage), abs=1e-12)
            assert fs.evaluate(pose, stage) == p.evaluate(pose, stage)
    assert np.array_equal(fs.render(GROUND_TRUTH), p.render(GROUND_TRUTH))
    assert np.array_equal(fs.target, p.target)


def test_frame_set_loss_is_the_mean_and_render_stacks(rig):
    problems = [Problem(m, t, camera(), PERTURBED_START.translation) for m, t in rig]
    fs = FrameSet(problems)
    each = [p.loss(PERTURBED_START) for p in problems]
    assert fs.loss(PERTURBED_START) == pytest.approx(np.mean(each), rel=1e-12)
    assert fs.floor(PERTURBED_START) == pytest.approx(
        np.mean([p.floor(PERTURBED_START) for p in problems]), rel=1e-12)
    assert fs.loss(GROUND_TRUTH) - fs.floor(GROUND_TRUTH) < 0.01 < \
        fs.loss(PERTURBED_START) - fs.floor(PERTURBED_START)
    stacked = fs.render(PERTURBED_START, 0)
    assert stacked.shape == (2 * problems[0].render(PERTURBED_START, 0).shape[0],
                             problems[0].render(PERTURBED_START, 0).shape[1])
    # the stacked level's loss on the stacked render is the frames' mean
    assert fs.level(0).loss(stacked) == pytest.approx(fs.loss(PERTURBED_START, 0), rel=1e-12)
    assert fs.degenerate(fs.evaluate(PERTURBED_START)) is False


def test_each_frames_crop_becomes_invalid_rows_of_the_stack(rig):
    cropped = CalibrationParams(loss=LossParams(crop_top=0.5))
    problems = [Problem(rig[0][0], rig[0][1], camera(), GROUND_TRUTH.translation),
                Problem(rig[1][0], rig[1][1], camera(), GROUND_TRUTH.translation, cropped)]
    fs = FrameSet(problems)
    assert fs.params.loss.crop_top == 0.0
    h = camera().height
    assert np.all(fs.target[h:h + h // 2] == INVALID)
    assert np.array_equal(fs.target[h + h // 2:], problems[1].target[h // 2:])
    assert np.array_equal(fs.target[:h], problems[0].target)
    # the stacked loss still uses each frame's own crop
    pose = PERTURBED_START
    assert fs.level(-1).loss(fs.render(pose)) == pytest.approx(
        np.mean([p.loss(pose) for p in problems]), rel=1e-12)


def test_masked_leaves_the_stacked_pixels_out_of_each_frame(rig):
    problems = [Problem(m, t, camera(), GROUND_TRUTH.translation) for m, t in rig]
    fs = FrameSet(problems)
    ignore = np.zeros(fs.target.shape, bool)
    h = camera().height
    ignore[h + 100:h + 200, 50:300] = True  # a block in the second frame only
    masked = fs.masked(ignore)
    assert np.array_equal(masked.frames[0].target, problems[0].target)
    assert np.all(masked.frames[1].target[100:200, 50:300] == INVALID)
    assert np.array_equal(masked.frames[1].target[:100], problems[1].target[:100])


def test_frames_need_one_schedule(world, target):
    other = CalibrationParams.from_file(None)
    other = replace(other, schedule=replace(other.schedule, scales=(2, 1), simplex=(1.0, 0.1),
                                            fatol=(1e-4, 1e-6), max_evaluations=(50, 50),
                                            restarts=(0, 0)))
    with pytest.raises(ValueError, match="one schedule"):
        FrameSet([Problem(world, target, camera(), GROUND_TRUTH.translation),
                  Problem(world, target, camera(), GROUND_TRUTH.translation, other)])


@pytest.mark.slow
def test_search_and_report_take_a_frame_set(rig):
    # one verification start exercises the frame set in the verification as two did
    params = CalibrationParams(verification=VerificationParams(starts=1))
    fs = FrameSet([Problem(m, t, camera(), PERTURBED_START.translation, params) for m, t in rig])
    result = solve(fs, PERTURBED_START, seed=1)
    assert translation_error(result.pose, GROUND_TRUTH) < 0.03
    assert rotation_error_deg(result.pose, GROUND_TRUTH) < 0.1
    report = assess(fs, result.pose)
    assert report.agreement > 0.9 and report.coverage > 0.5
    assert result.quality is not None and result.quality.verdict == "good"


def test_calibrate_frames_draws_one_overlay_per_frame(rig):
    params = CalibrationParams(verification=VerificationParams(starts=1))
    near = Pose.from_body_rpy_deg(GROUND_TRUTH.translation + [0.3, -0.2, 0.1],
                                  GROUND_TRUTH.body_rpy_deg() + [0.0, -0.5, 0.5])
    frames = [Frame(m, t, camera(), params, name=f"f{k}") for k, (m, t) in enumerate(rig)]
    out = calibrate_frames_and_draw(frames, near, seed=0)
    assert translation_error(out.result.pose, GROUND_TRUTH) < 0.03
    assert len(out.overlays) == 2 and out.overlay is out.overlays[0]
    assert all(o.shape == (600, 960, 3) for o in out.overlays)
    assert not np.array_equal(out.overlays[0], out.overlays[1])
    assert [c.name for c in out.frames] == ["f0", "f1"]
    assert all(c.agreement > 0.9 for c in out.frames)
    at_start = [f.problem(near.translation).loss(near) for f in frames]
    assert all(c.loss < 0.5 * s for c, s in zip(out.frames, at_start))


# --- fusion ----------------------------------------------------------------------------------
def test_fusion_outvotes_a_passing_car_and_flicker():
    rng = np.random.default_rng(0)
    street = np.zeros((40, 60), np.uint8)  # road
    street[:15] = 2  # building
    images = []
    for k in range(10):
        im = street.copy()
        im[20:30, 5 * k:5 * k + 10] = 13  # a car driving across
        flicker = rng.random(im.shape) < 0.05
        im[flicker] = 8  # vegetation here and there
        images.append(im)
    fused = fuse_labels(images)
    assert np.array_equal(fused.labels, street)
    assert fused.images == 10
    assert 0.8 < fused.agreement < 0.97
    assert fused.share.min() >= 0.5 and fused.share.max() == 1.0


def test_fusion_ties_go_to_the_newest_and_min_share_ignores():
    a = np.array([[1, 1, 3]], np.uint8)
    b = np.array([[2, 1, 4]], np.uint8)
    c = np.array([[5, 1, 6]], np.uint8)
    fused = fuse_labels([a, b])
    assert fused.labels.tolist() == [[2, 1, 4]]  # 1:1 ties: the newer image
    assert fused.share.tolist() == [[0.5, 1.0, 0.5]]
    strict = fuse_labels([a, b, c], min_share=0.5)
    assert strict.labels.tolist() == [[INVALID, 1, INVALID]]
    assert np.array_equal(fuse_labels([a]).labels, a)


def test_fusion_refuses_images_of_another_camera():
    with pytest.raises(ValueError, match="label image 2 is 4x3, the first 4x2"):
        fuse_labels([np.zeros((2, 4), np.uint8), np.zeros((3, 4), np.uint8)])
    with pytest.raises(ValueError, match="8-bit single channel"):
        fuse_labels([np.zeros((2, 4), np.uint16)])
    with pytest.raises(ValueError, match="no label image"):
        fuse_labels([])


def test_fusing_ten_camera_images_takes_well_under_a_second():
    """The cost of a fused window (the brief's bound: 10 images <= 1 s on 2 cores): measured as
    CPU time of the calling thread, so another job on the machine does not change it."""
    import time

    rng = np.random.default_rng(1)
    images = [rng.integers(0, 19, (600, 960), dtype=np.uint8) for _ in range(10)]
    t0 = time.thread_time()
    fuse_labels(images)
    assert time.thread_time() - t0 < 1.0


# --- the command line ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def scenes(tmp_path_factory, rig):
    root = tmp_path_factory.mktemp("rig")
    fast = {"calibrator": {"ros__parameters": {"engine": {"verification": {"starts": 1}}}}}
    for k, (cloud, labels) in enumerate(rig):
        d = root / f"frame{k}"
        ply.write_ply(d / "map.ply", cloud)
        files.write_label_image(d / "labels.png", labels)
        files.write_camera_info(d / "camera_info.yaml", camera())
        (d / "calibrator.yaml").write_text(yaml.safe_dump(fast))
    files.write_pose(root / "initial.yaml", Pose.from_body_rpy_deg(
        GROUND_TRUTH.translation + [0.4, -0.3, 0.2], GROUND_TRUTH.body_rpy_deg() + [0, -1, 1]))
    return root


def test_cli_calibrates_several_scenes_to_one_pose(scenes, capsys):
    out = scenes / "out"
    argv = ["calibrate", "--scene", str(scenes / "frame0"), str(scenes / "frame1"),
            "--initial", str(scenes / "initial.yaml"), "--output", str(out / "pose.yaml"),
            "--overlay", str(out / "overlay.png"), "--quiet"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "2 frames of one rig: frame0, frame1" in printed
    assert "frame1: loss" in printed
    pose = files.read_pose(out / "pose.yaml")
    assert translation_error(pose, GROUND_TRUTH) < 0.03
    assert rotation_error_deg(pose, GROUND_TRUTH) < 0.1
    for name in ("overlay_frame0.png", "overlay_frame1.png"):
        assert files.read_rgb_image(out / name).shape == (600, 960, 3)


def _error_of(argv, capsys) -> str:
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    return err


def test_cli_scene_errors_are_one_line(scenes, tmp_path, capsys):
    base = ["calibrate", "--initial", str(scenes / "initial.yaml"),
            "--output", str(tmp_path / "p.yaml"), "--quiet"]
    assert "drop --map" in _error_of(base + ["--scene", str(scenes / "frame0"), "--map",
                                             str(scenes / "frame0" / "map.ply")], capsys)
    (tmp_path / "empty").mkdir()
    assert "no map.ply" in _error_of(base + ["--scene", str(tmp_path / "empty")], capsys)
    assert "not a folder" in _error_of(base + ["--scene", str(tmp_path / "nope")], capsys)
    assert "missing --map, --camera-info" in _error_of(
        base + ["--labels", str(scenes / "frame0" / "labels.png")], capsys)


def test_cli_fuses_several_label_images(scenes, tmp_path, capsys):
    labels = files.read_label_image(scenes / "frame0" / "labels.png")
    paths = []
    for k in range(3):
        im = labels.copy()
        im[300:400, 200 * k:200 * k + 150] = 13  # a car in a different place each time
        paths.append(tmp_path / f"l{k}.png")
        files.write_label_image(paths[-1], im)
    d = scenes / "frame0"
    argv = ["calibrate", "--map", str(d / "map.ply"), "--labels", *map(str, paths),
            "--camera-info", str(d / "camera_info.yaml"), "--initial",
            str(scenes / "initial.yaml"), "--output", str(tmp_path / "p.yaml"),
            "--config", str(d / "calibrator.yaml"), "--quiet"]
    assert main(argv) == 0
    assert "3 label images fused per pixel" in capsys.readouterr().out
    assert translation_error(files.read_pose(tmp_path / "p.yaml"), GROUND_TRUTH) < 0.03


def test_drift_watch_window_fuses_the_last_distinct_images():
    from semcal_ros.engine.drift_watch import DriftWatch

    street = np.zeros((20, 30), np.uint8)
    a, b, c = street.copy(), street.copy(), street.copy()
    a[5:10, 0:5] = 13
    b[5:10, 10:15] = 13
    c[5:10, 20:25] = 13
    one = DriftWatch()
    assert one.windowed(a) is a  # window 1: the image itself
    watch = DriftWatch(window=3)
    assert watch.windowed(None) is None
    assert watch.windowed(a) is a  # one image so far
    assert np.array_equal(watch.windowed(a), a)  # the same image again does not count twice
    assert len(watch.recent) == 1
    watch.windowed(b)
    assert np.array_equal(watch.windowed(c), street)  # each car in one image of three
    assert len(watch.recent) == 3
    small = np.zeros((10, 30), np.uint8)
    assert watch.windowed(small) is small and len(watch.recent) == 1  # another size: anew
    with pytest.raises(ValueError, match="label window must be >= 1"):
        DriftWatch(window=0)
