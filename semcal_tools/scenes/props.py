"""Roadside objects built from mesh primitives, each with its SemanticKITTI classes.

Objects are placed by the layouts (``layouts.py``); every function adds triangles to a
:class:`MeshBuilder` (static scenery) or returns a :class:`LabelledMesh` in object coordinates
(movable things: cars and people, posed per time step by ``actors.py``).
"""

from __future__ import annotations

import numpy as np

from semcal_ros.engine.labels import KITTI_ID
from semcal_tools.scenes.mesh import (
    LabelledMesh, MeshBuilder, blob, box, cylinder, oriented_box, segment_box,
)

ROAD = KITTI_ID["road"]
SIDEWALK = KITTI_ID["sidewalk"]
PARKING = KITTI_ID["parking"]
TERRAIN = KITTI_ID["terrain"]
LANE_MARKING = KITTI_ID["lane-marking"]
BUILDING = KITTI_ID["building"]
FENCE = KITTI_ID["fence"]
VEGETATION = KITTI_ID["vegetation"]
TRUNK = KITTI_ID["trunk"]
POLE = KITTI_ID["pole"]
TRAFFIC_SIGN = KITTI_ID["traffic-sign"]
CAR = KITTI_ID["car"]
BUS = KITTI_ID["bus"]
TRUCK = KITTI_ID["truck"]
MOVING_CAR = KITTI_ID["moving-car"]
MOVING_PERSON = KITTI_ID["moving-person"]

#: Base colours (linear 0..1) of surfaces; objects vary them per instance.
ASPHALT = (0.21, 0.21, 0.22)
MARKING = (0.88, 0.88, 0.84)
PAVEMENT = (0.58, 0.56, 0.53)
GRASS = (0.27, 0.40, 0.15)
BARK = (0.33, 0.24, 0.16)
LEAVES = (0.17, 0.33, 0.11)
METAL = (0.45, 0.46, 0.48)
FACADES = ((0.72, 0.66, 0.55), (0.55, 0.53, 0.50), (0.62, 0.36, 0.27), (0.80, 0.78, 0.72),
           (0.45, 0.42, 0.40), (0.70, 0.60, 0.42))
CAR_PAINT = ((0.75, 0.75, 0.77), (0.08, 0.08, 0.09), (0.55, 0.08, 0.07), (0.12, 0.20, 0.45),
             (0.85, 0.85, 0.85), (0.35, 0.36, 0.38), (0.20, 0.32, 0.22))


def vary(rng: np.random.Generator, colour: tuple[float, float, float], amount: float = 0.08
         ) -> np.ndarray:
    """A colour with a random brightness and tint change (instances should not look cloned)."""
    c = np.asarray(colour) * rng.uniform(1 - amount, 1 + amount) + rng.normal(0, amount / 10, 3)
    return np.clip(c, 0.0, 1.0)


def tree(mb: MeshBuilder, rng: np.random.Generator, xy: tuple[float, float], ground: float,
         scale: float = 1.0) -> None:
    """Trunk (class trunk) and one to three crown blobs (class vegetation)."""
    trunk_h = rng.uniform(2.0, 3.5) * scale
    r = rng.uniform(0.12, 0.25) * scale
    mb.add(*cylinder(xy, r, ground, ground + trunk_h + 0.8 * scale, 8, r * 0.7), TRUNK,
           vary(rng, BARK))
    crown_r = rng.uniform(1.6, 3.2) * scale
    leaves = vary(rng, LEAVES, 0.2)
    for k in range(int(rng.integers(1, 4))):
        off = rng.normal(0, 0.35 * crown_r, 2) if k else np.zeros(2)
        radii = crown_r * rng.uniform(0.75, 1.1, 3)
        radii[2] *= rng.uniform(0.8, 1.3)
        centre = (xy[0] + off[0], xy[1] + off[1], ground + trunk_h + radii[2] * 0.85)
        mb.add(*blob(centre, radii, rng), VEGETATION, vary(rng, leaves, 0.08))


def bush(mb: MeshBuilder, rng: np.random.Generator, xy: tuple[float, float], ground: float) -> None:
    radii = rng.uniform(0.6, 1.4, 3)
    radii[2] *= 0.7
    mb.add(*blob((xy[0], xy[1], ground + radii[2] * 0.6), radii, rng, 0.25, 1), VEGETATION,
           vary(rng, LEAVES, 0.2))


def street_light(mb: MeshBuilder, rng: np.random.Generator, xy: tuple[float, float],
                 ground: float, towards: float) -> None:
    """A lamp post with an arm reaching over the road in direction ``towards`` (radians)."""
    h = rng.uniform(7.0, 9.0)
    mb.add(*cylinder(xy, 0.11, ground, ground + h, 8, 0.07), POLE, METAL)
    reach = rng.uniform(1.5, 2.5)
    tip = np.asarray(xy) + reach * np.array([np.cos(towards), np.sin(towards)])
    mb.add(*segment_box(xy, tip, 0.1, ground + h - 0.12, ground + h), POLE, METAL)
    mb.add(*box(tuple(tip), (0.6, 0.3), ground + h - 0.3, ground + h - 0.05, towards), POLE,
           (0.3, 0.3, 0.3))


def sign(mb: MeshBuilder, rng: np.random.Generator, xy: tuple[float, float], ground: float,
         facing: float, size: float | None = None) -> None:
    """A post (class pole) with one or two sign plates (class traffic-sign) facing ``facing``."""
    size = rng.uniform(0.6, 0.9) if size is None else size
    top = ground + rng.uniform(2.3, 3.0)
    mb.add(*cylinder(xy, 0.04, ground, top + size, 6), POLE, METAL)
    colours = ((0.75, 0.1, 0.1), (0.1, 0.25, 0.7), (0.85, 0.75, 0.1), (0.9, 0.9, 0.9))
    n = int(rng.integers(1, 3))
    centre = np.asarray(xy) + 0.06 * np.array([np.cos(facing), np.sin(facing)])
    for k in range(n):
        z0 = top - k * (size + 0.1)
        mb.add(*box(tuple(centre), (0.03, size), z0, z0 + size, facing), TRAFFIC_SIGN,
               colours[int(rng.integers(len(colours)))])


def gantry(mb: MeshBuilder, rng: np.random.Generator, x: float, y0: float, y1: float,
           ground: float, facing: float) -> None:
    """An overhead sign gantry across a road: two posts and a beam (pole), big plates (sign)."""
    h = rng.uniform(6.0, 7.0)
    for y in (y0, y1):
        mb.add(*cylinder((x, y), 0.25, ground, ground + h + 0.5, 10), POLE, METAL)
    mb.add(*segment_box((x, y0), (x, y1), 0.4, ground + h + 0.1, ground + h + 0.5), POLE, METAL)
    width = abs(y1 - y0)
    for k in range(int(rng.integers(1, 4))):
        yc = min(y0, y1) + width * (k + 1) / 4 + rng.uniform(-1, 1)
        size = rng.uniform(3.0, 4.5)
        mb.add(*box((x - 0.3 * np.cos(facing), yc), (0.1, size), ground + h - 1.8,
                    ground + h + 0.6, 0.0), TRAFFIC_SIGN, (0.05, 0.35, 0.15))


def fence(mb: MeshBuilder, rng: np.random.Generator, points: np.ndarray, ground: float,
          style: str | None = None) -> None:
    """A fence along a 2-D polyline: a solid panel or posts with rails (class fence)."""
    style = style or ("panel" if rng.random() < 0.5 else "rails")
    points = np.asarray(points, float)
    h = rng.uniform(1.0, 1.8)
    colour = vary(rng, (0.55, 0.48, 0.38) if style == "panel" else METAL)
    for p0, p1 in zip(points[:-1], points[1:]):
        if style == "panel":
            mb.add(*segment_box(p0, p1, 0.05, ground, ground + h), FENCE, colour)
            continue
        for z in np.linspace(ground + 0.3, ground + h, 3):
            mb.add(*segment_box(p0, p1, 0.06, z - 0.08, z), FENCE, colour)
        n = max(1, int(np.hypot(*(p1 - p0)) / 2.5))
        for t in np.linspace(0, 1, n + 1):
            mb.add(*cylinder(tuple(p0 + t * (p1 - p0)), 0.05, ground, ground + h, 6), FENCE,
                   colour)


def guard_rail(mb: MeshBuilder, p0: np.ndarray, p1: np.ndarray, ground: float,
               concrete: bool) -> None:
    """A highway barrier (SemanticKITTI labels guard rails as fence)."""
    if concrete:
        mb.add(*segment_box(p0, p1, 0.6, ground, ground + 0.9), FENCE, (0.62, 0.61, 0.58))
        return
    mb.add(*segment_box(p0, p1, 0.08, ground + 0.45, ground + 0.8), FENCE, (0.6, 0.62, 0.64))
    n = max(1, int(np.hypot(*(np.asarray(p1) - p0)) / 4.0))
    for t in np.linspace(0, 1, n + 1):
        p = np.asarray(p0) + t * (np.asarray(p1) - p0)
        mb.add(*box(tuple(p), (0.12, 0.12), ground, ground + 0.75), FENCE, (0.5, 0.5, 0.5))


def building(mb: MeshBuilder, rng: np.random.Generator, origin: tuple[float, float],
             yaw: float, width: float, depth: float, ground: float,
             height: float | None = None) -> None:
    """A building with a varied footprint on a ``width`` x ``depth`` lot, front facing -y.

    Footprints: plain block, L, T or U (courtyard open to the back), stepped heights, sometimes a
    gabled roof. Parts are boxes; their hidden inner faces are never hit by rays from outside.
    """
    height = rng.uniform(7.0, 28.0) if height is None else height
    facade = vary(rng, FACADES[int(rng.integers(len(FACADES)))], 0.05)
    roof = vary(rng, (0.30, 0.28, 0.27), 0.15)
    c, s = np.cos(yaw), np.sin(yaw)

    def part(x0: float, x1: float, y0: float, y1: float, h: float) -> None:
        local = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
        centre = np.asarray(origin) + np.array([c * local[0] - s * local[1],
                                                 s * local[0] + c * local[1]])
        verts, tris = box(tuple(centre), (x1 - x0, y1 - y0), ground, ground + h, yaw)
        mb.add(verts, tris[2:], BUILDING, facade)  # walls
        mb.add(verts, tris[:2], BUILDING, roof)  # roof
        if h < 14.0 and rng.random() < 0.35:  # gabled roof along the longer side
            ridge = rng.uniform(2.0, 4.0)
            along_x = (x1 - x0) >= (y1 - y0)
            if along_x:
                pts = [(x0, y0, h), (x1, y0, h), (x1, y1, h), (x0, y1, h),
                       (x0, (y0 + y1) / 2, h + ridge), (x1, (y0 + y1) / 2, h + ridge)]
            else:
                pts = [(x0, y0, h), (x1, y0, h), (x1, y1, h), (x0, y1, h),
                       ((x0 + x1) / 2, y0, h + ridge), ((x0 + x1) / 2, y1, h + ridge)]
            p = np.array(pts)
            xy = np.asarray(origin) + p[:, :2] @ np.array([[c, s], [-s, c]])
            v = np.c_[xy, p[:, 2] + ground]
            t = ([[0, 1, 5], [0, 5, 4], [3, 2, 5], [3, 5, 4], [0, 3, 4], [1, 2, 5]] if along_x
                 else [[0, 3, 5], [0, 5, 4], [1, 2, 5], [1, 5, 4], [0, 1, 4], [3, 2, 5]])
            mb.add(v, t, BUILDING, roof)

    shape = rng.choice(["block", "block", "L", "T", "U"])
    w, d = width, depth
    if shape == "block":
        part(-w / 2, w / 2, 0, d, height)
        if rng.random() < 0.4:  # a lower annex at one side
            side = rng.choice([-1, 1])
            aw = rng.uniform(0.25, 0.45) * w
            part(side * w / 2 - (aw if side > 0 else 0), side * w / 2 + (0 if side > 0 else aw),
                 d * 0.2, d * rng.uniform(0.9, 1.2), rng.uniform(3.0, 0.6 * height + 3))
    elif shape == "L":
        wing = rng.uniform(0.35, 0.55)
        part(-w / 2, w / 2, 0, d * rng.uniform(0.35, 0.55), height)
        part(-w / 2, -w / 2 + w * wing, 0, d, height * rng.uniform(0.6, 1.0))
    elif shape == "T":
        part(-w / 2, w / 2, 0, d * rng.uniform(0.35, 0.5), height)
        part(-w * 0.2, w * 0.2, 0, d, height * rng.uniform(0.5, 1.2))
    else:  # U, courtyard at the back
        front = d * rng.uniform(0.3, 0.45)
        arm = w * rng.uniform(0.2, 0.3)
        part(-w / 2, w / 2, 0, front, height)
        part(-w / 2, -w / 2 + arm, 0, d, height * rng.uniform(0.7, 1.0))
        part(w / 2 - arm, w / 2, 0, d, height * rng.uniform(0.7, 1.0))


def car_mesh(rng: np.random.Generator, label: int) -> LabelledMesh:
    """A car in its own frame (x forward, centred, on z = 0): body, cabin, wheels."""
    mb = MeshBuilder()
    length = rng.uniform(3.9, 4.9)
    width = rng.uniform(1.7, 1.9)
    paint = vary(rng, CAR_PAINT[int(rng.integers(len(CAR_PAINT)))], 0.05)
    van = rng.random() < 0.15
    mb.add(*box((0, 0), (length, width), 0.3, 1.0 if not van else 1.9), label, paint)
    if not van:
        cab = length * rng.uniform(0.45, 0.6)
        mb.add(*box((-0.1 * length, 0), (cab, width * 0.92), 1.0, rng.uniform(1.4, 1.55)), label,
               np.clip(paint * 0.5 + 0.05, 0, 1))
    for sx in (-1, 1):
        for sy in (-1, 1):
            mb.add(*box((sx * length * 0.32, sy * (width / 2 - 0.15)), (0.6, 0.25), 0.0, 0.35),
                   label, (0.05, 0.05, 0.05))
    return mb.build()


def large_vehicle_mesh(rng: np.random.Generator) -> LabelledMesh:
    """A bus or a lorry in its own frame (x forward, centred, on z = 0), classes bus / truck.

    Not in the scene layouts (their images and maps stay as they are): the point labeller's
    training adds them (``train_point_labeller --large-vehicles``), because a vehicle 2.5-4 m
    tall seen by another lidar was labelled vegetation and building when cars (tops 1.4-1.9 m)
    were the only vehicles it had seen (docs/segmentation.md).
    """
    mb = MeshBuilder()
    width = rng.uniform(2.4, 2.55)
    paint = vary(rng, CAR_PAINT[int(rng.integers(len(CAR_PAINT)))], 0.05)
    if rng.random() < 0.5:  # a bus: one long box with a dark window band
        length, top = rng.uniform(9.0, 12.5), rng.uniform(2.9, 3.4)
        mb.add(*box((0, 0), (length, width), 0.35, top), BUS, paint)
        mb.add(*box((0, 0), (length - 0.2, width + 0.02), 1.2, top - 0.5), BUS, (0.05, 0.06, 0.07))
        axles = (0.35 * length, -0.3 * length)
        label = BUS
    else:  # a lorry: cab and a taller box body behind it
        length, top = rng.uniform(6.5, 10.0), rng.uniform(3.0, 3.9)
        cab = rng.uniform(1.8, 2.3)
        mb.add(*box((length / 2 - cab / 2, 0), (cab, width), 0.45, rng.uniform(2.6, 3.0)), TRUCK,
               paint)
        mb.add(*box((-cab / 2 - 0.1, 0), (length - cab - 0.2, width), 0.9, top), TRUCK,
               vary(rng, (0.8, 0.8, 0.78), 0.1))
        axles = (length / 2 - cab / 2, -0.35 * length)
        label = TRUCK
    for ax in axles:
        for sy in (-1, 1):
            mb.add(*box((ax, sy * (width / 2 - 0.2)), (1.0, 0.35), 0.0, 0.5), label,
                   (0.05, 0.05, 0.05))
    return mb.build()


def person_mesh(rng: np.random.Generator, label: int) -> LabelledMesh:
    """A pedestrian in its own frame: legs, torso, head."""
    mb = MeshBuilder()
    h = rng.uniform(1.55, 1.9)
    clothes = vary(rng, ((0.15, 0.15, 0.2), (0.5, 0.1, 0.1), (0.6, 0.6, 0.55),
                         (0.1, 0.3, 0.5))[int(rng.integers(4))], 0.1)
    mb.add(*box((0, 0), (0.25, 0.4), 0.0, 0.47 * h), label, (0.15, 0.15, 0.25))
    mb.add(*box((0, 0), (0.3, 0.48), 0.47 * h, 0.86 * h), label, clothes)
    mb.add(*cylinder((0, 0), 0.1, 0.86 * h, h, 8), label, (0.8, 0.62, 0.5))
    return mb.build()


def camera_gear(mb: MeshBuilder, position: np.ndarray, body_rotation: np.ndarray,
                mast_xy: np.ndarray, mast_radius: float, ground: float) -> None:
    """The camera's own housing, sun visor and mounting arm (class pole, like any equipment on
    a mast). They sit right behind and above the lens, where no camera ray goes (the housing's
    front face is 2 cm behind the optical centre, the visor more than 55 deg above the axis),
    but the lidar sees them: a map point a few centimetres behind the true camera lands in
    front of any candidate pose a little further back."""
    body = np.asarray(body_rotation, float)  # columns: forward, left, up of the camera body
    position = np.asarray(position, float)
    grey = (0.82, 0.82, 0.80)
    mb.add(*oriented_box(position + body @ [-0.20, 0.0, -0.01], (0.36, 0.16, 0.15), body),
           POLE, grey)
    mb.add(*oriented_box(position + body @ [-0.16, 0.0, 0.10], (0.48, 0.22, 0.01), body),
           POLE, grey)
    under = position + body @ [-0.14, 0.0, -0.09]  # the arm: housing bottom to the mast
    mb.add(*segment_box(under[:2], mast_xy, 0.06, under[2] - 0.12, under[2]), POLE, METAL)
    toward = np.asarray(mast_xy, float) - position[:2]
    if np.hypot(*toward) > mast_radius:  # a cabinet on the mast, 2.5-3.3 m up, facing the road
        d = toward / np.hypot(*toward)
        cab = np.asarray(mast_xy, float) + d * (mast_radius + 0.12)
        mb.add(*box(tuple(cab), (0.25, 0.4), ground + 2.5, ground + 3.3,
                    float(np.arctan2(d[1], d[0]))), POLE, grey)
