"""The point labeller's training scenes with buses and lorries (``train_point_labeller
--large-vehicles``): a bus or lorry mesh has a large vehicle's size and classes, and the scans
of a world with them hold bus / truck points beside the survey drive, which the training
counts as car (docs/segmentation.md, "Why the bus is not car")."""

from __future__ import annotations

import numpy as np

from semcal_ros.engine.labels import KITTI_ID
from semcal_tools.scenes import props
from semcal_tools.train_point_labeller import (CLASSES, SENSORS, class_lut, with_large_vehicles)

LARGE = (KITTI_ID["bus"], KITTI_ID["truck"])


def test_a_large_vehicle_is_bus_or_lorry_sized():
    for seed in range(20):
        mesh = props.large_vehicle_mesh(np.random.default_rng(seed))
        lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        length, width, top = hi - lo
        assert 6.4 < length < 12.6 and 2.3 < width < 2.6 and 2.9 <= top <= 3.9, (length, width, top)
        assert lo[2] == 0.0  # on its wheels
        assert len(set(np.unique(mesh.labels).tolist())) == 1
        assert int(mesh.labels[0]) in LARGE
    # both kinds come up, and the training counts them as car
    kinds = {int(props.large_vehicle_mesh(np.random.default_rng(s)).labels[0]) for s in range(20)}
    assert kinds == set(LARGE)
    assert {CLASSES[class_lut()[k]] for k in LARGE} == {KITTI_ID["car"]}


def test_scans_of_a_world_with_large_vehicles_hit_them_beside_the_drive():
    from scipy.spatial.transform import Rotation

    from semcal_tools.scenes.generate import SceneOptions, scene_world
    from semcal_tools.scenes.sensors import LidarSpec, scan

    sw = scene_world("arterial", 0, "ideal", SceneOptions(write_bag=False, threads=0))
    world = with_large_vehicles(sw, 6, np.random.default_rng(0))
    assert len(world.static) > len(sw.world.static)
    sensor = SENSORS[0]  # an HDL-64E-like lidar at 1.73 m
    spec = LidarSpec(sensor.lines, sensor.fov_up, sensor.fov_down, sensor.step_deg)
    drive = np.asarray(sw.positions, float)[:, :2]
    hits = {}
    for name, w in (("without", sw.world), ("with", world)):
        n_large = 0
        for i in range(0, len(sw.times), max(1, len(sw.times) // 6)):
            position = np.array(sw.positions[i], float)
            position[2] = sensor.height
            heading = Rotation.from_quat(sw.quats[i]).as_matrix()
            xyz, _, label = scan(w, spec, heading, position, [], np.random.default_rng(i),
                                 sensor.directions(np.random.default_rng(i)).astype(np.float32))
            large = np.isin(label, LARGE)
            n_large += int(large.sum())
            if large.any():  # beside the drive: a few metres from the lidar's track
                seen = (xyz[large].astype(float) @ heading.T + position)[:, :2]
                nearest = np.min(np.linalg.norm(seen[:, None] - drive[None], axis=2), axis=1)
                assert np.median(nearest) < 8.0, np.median(nearest)
        hits[name] = n_large
    assert hits["without"] == 0 and hits["with"] > 500, hits
