"""Procedural roadside layouts: an urban junction, a straight arterial road, a highway (and the
roundabout of roundabout.py, built from the shared pieces here).

A layout is the static world (one labelled mesh), the survey vehicle's path, the infrastructure
camera's pose, and the lanes and pavements that moving actors use. The three kinds differ in what
a calibration can lock onto: the junction has buildings, poles and kerbs in every direction; the
arterial has long parallel structures (translation along the road is weakly observed); the
highway is mostly flat asphalt and terrain with a few barriers, poles and signs.

Conventions: map frame x east, y north, z up; asphalt at z = 0, pavements 0.15 m higher;
right-hand traffic.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from semcal_tools.scenes import props
from semcal_tools.scenes.actors import Polyline, arc
from semcal_tools.scenes.mesh import (
    LabelledMesh, MeshBuilder, SmoothNoise, box, cylinder, height_grid, quad, quads,
)

#: Layout kinds; the order is part of the seeding (append new kinds at the end).
KINDS = ("junction", "arterial", "highway", "roundabout")

KERB = 0.15  # pavement height above the road
FAR = 320.0  # roads and the ground plane extend this far, so the camera sees a horizon
LANE = 3.25
MARK_Z = 0.01  # lane markings sit this much above the asphalt


@dataclass
class Walkway:
    path: Polyline
    ground: float


@dataclass
class Layout:
    kind: str
    static: LabelledMesh
    drive: Polyline
    drive_speed: float  # m/s of the survey vehicle
    focus: np.ndarray  # (2,) what the camera looks at; the drive is centred on passing it
    camera_position: np.ndarray  # (3,) camera centre in the map frame
    camera_pitch_deg: float  # positive looks down
    camera_yaw_deg: float
    camera_ground: float  # ground height under the camera mast
    lanes: list[tuple[Polyline, float]] = field(default_factory=list)  # path, typical speed
    walkways: list[Walkway] = field(default_factory=list)
    # junction only: half widths of road A (along x) and B (along y) and the pavement widths
    # (wa, wb, sa, sb), so more cameras can stand on the corners (scenes.rig)
    corners: tuple[float, float, float, float] | None = None


def build_layout(kind: str, rng: np.random.Generator) -> Layout:
    from semcal_tools.scenes.roundabout import roundabout  # it builds on this module's pieces

    builders = {"junction": junction, "arterial": arterial, "highway": highway,
                "roundabout": roundabout}
    if kind not in builders:
        raise ValueError(f"unknown scene kind '{kind}' (choose from {', '.join(KINDS)})")
    return builders[kind](rng)


# --------------------------------------------------------------------------------------------
# shared pieces

def aim_camera(position_xy: np.ndarray, ground: float, focus: np.ndarray,
               rng: np.random.Generator, height_range: tuple[float, float] = (5.0, 8.0),
               pitch_range: tuple[float, float] = (12.0, 30.0)
               ) -> tuple[np.ndarray, float, float]:
    """A mast-mounted camera at ``position_xy`` looking roughly at ``focus`` (pitched down)."""
    height = rng.uniform(*height_range)
    d = np.asarray(focus, float) - position_xy
    yaw = np.degrees(np.arctan2(d[1], d[0])) + rng.uniform(-6.0, 6.0)
    pitch = np.degrees(np.arctan2(height, np.hypot(*d))) + rng.uniform(-3.0, 3.0)
    pitch = float(np.clip(pitch, *pitch_range))
    return np.array([position_xy[0], position_xy[1], ground + height]), pitch, float(yaw)


#: The camera mast's distance behind the camera centre and its radius, metres.
MAST_BACK, MAST_RADIUS = 0.35, 0.12


def mast_xy(position: np.ndarray, yaw_deg: float) -> np.ndarray:
    """Where the camera's mast stands: ``MAST_BACK`` behind the camera, horizontally."""
    return np.asarray(position[:2], float) - MAST_BACK * np.array(
        [np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))])


def camera_mast(mb: MeshBuilder, position: np.ndarray, yaw_deg: float, ground: float) -> None:
    """The camera's own mast, a little behind the camera (the lidar sees it as a pole)."""
    back = mast_xy(position, yaw_deg)
    mb.add(*cylinder(tuple(back), MAST_RADIUS, ground, position[2] + 0.3, 8), props.POLE,
           props.METAL)


def dashes(x0: float, x1: float, y: float, width: float, dash: float, gap: float,
           skip: tuple[float, float] | None = None) -> np.ndarray:
    """Rectangles (x0, x1, y0, y1) of a dashed (or, with gap 0, solid) line along x."""
    if gap <= 0:
        starts, ends = np.array([x0]), np.array([x1])
    else:
        starts = np.arange(x0, x1, dash + gap)
        ends = np.minimum(starts + dash, x1)
    rects = np.c_[starts, ends, np.full(len(starts), y - width / 2), np.full(len(starts), y + width / 2)]
    if skip is not None:
        rects = split_rects(rects, skip)
    return rects


def split_rects(rects: np.ndarray, skip: tuple[float, float]) -> np.ndarray:
    """Cut the x-range ``skip`` out of x-aligned rectangles (markings stop at junctions)."""
    out = []
    for x0, x1, y0, y1 in rects:
        if x1 <= skip[0] or x0 >= skip[1]:
            out.append((x0, x1, y0, y1))
            continue
        if x0 < skip[0]:
            out.append((x0, skip[0], y0, y1))
        if x1 > skip[1]:
            out.append((skip[1], x1, y0, y1))
    return np.array(out, float).reshape(-1, 4)


def swap_xy(rects: np.ndarray) -> np.ndarray:
    """x-aligned rectangles mirrored onto the y axis (for the crossing road)."""
    return np.asarray(rects)[:, [2, 3, 0, 1]]


def road_markings(half_lanes: int, length: tuple[float, float], skip: tuple[float, float] | None,
                  lane: float = LANE, double_centre: bool | None = None) -> np.ndarray:
    """Centre line, lane separators and edge lines of a two-way road along x (rectangles)."""
    x0, x1 = length
    parts = []
    double = half_lanes >= 2 if double_centre is None else double_centre
    if double:
        parts += [dashes(x0, x1, y, 0.12, 0, 0, skip) for y in (-0.12, 0.12)]
    else:
        parts.append(dashes(x0, x1, 0.0, 0.12, 3.0, 6.0, skip))
    for k in range(1, half_lanes):
        for sgn in (-1, 1):
            parts.append(dashes(x0, x1, sgn * k * lane, 0.12, 3.0, 6.0, skip))
    for sgn in (-1, 1):
        parts.append(dashes(x0, x1, sgn * (half_lanes * lane - 0.1), 0.15, 0, 0, skip))
    return np.concatenate(parts)


def zebra(x_centre: float, half_width: float, depth: float = 4.0) -> np.ndarray:
    """Zebra-crossing stripes across a road along x at ``x_centre`` (stripes run along x)."""
    ys = np.arange(-half_width + 0.5, half_width - 0.5, 1.0)
    return np.c_[np.full(len(ys), x_centre - depth / 2), np.full(len(ys), x_centre + depth / 2),
                 ys, ys + 0.5]


def lane_paths(half_lanes: int, y_offset: float = 0.0, lane: float = LANE,
               along_y: bool = False) -> list[tuple[Polyline, int]]:
    """Lane centre lines of a two-way road along x (or y), each with its lane index from the
    centre and directed with right-hand traffic."""
    out = []
    for k in range(half_lanes):
        offset = (k + 0.5) * lane
        fwd = np.array([[-FAR, -offset + y_offset], [FAR, -offset + y_offset]])
        back = np.array([[FAR, offset + y_offset], [-FAR, offset + y_offset]])
        if along_y:  # heading +y has its right side at +x
            fwd = np.array([[offset + y_offset, -FAR], [offset + y_offset, FAR]])
            back = np.array([[-offset + y_offset, FAR], [-offset + y_offset, -FAR]])
        out += [(Polyline(fwd), k), (Polyline(back), k)]
    return out


def lot_ground(mb: MeshBuilder, rng: np.random.Generator, x: tuple[float, float],
               y: tuple[float, float], base: float, cell: float = 1.5) -> None:
    """A grass lot slightly above the pavement with gentle bumps (class terrain)."""
    noise = SmoothNoise(rng, rng.uniform(8.0, 20.0), 0.12)
    x0, x1 = sorted(x)
    y0, y1 = sorted(y)
    mb.add(*height_grid(x0, x1, y0, y1, cell, lambda gx, gy: base + 0.05 + np.abs(noise(gx, gy))),
           props.TERRAIN, props.vary(rng, props.GRASS, 0.1))


def row_positions(rng: np.random.Generator, start: float, end: float, spacing: tuple[float, float]
                  ) -> np.ndarray:
    """Positions from ``start`` towards ``end`` with random spacing (either direction)."""
    sgn = 1.0 if end >= start else -1.0
    out, p = [], start
    while (end - p) * sgn > 0:
        out.append(p)
        p += sgn * rng.uniform(*spacing)
    return np.array(out)


def far_ground(mb: MeshBuilder, rng: np.random.Generator) -> None:
    """A flat terrain plane under everything, out to the horizon."""
    mb.add(*quad(-FAR * 1.5, FAR * 1.5, -FAR * 1.5, FAR * 1.5, -0.03), props.TERRAIN,
           props.vary(rng, props.GRASS, 0.05))


def buildings_row(mb: MeshBuilder, rng: np.random.Generator, along: tuple[float, float],
                  frontage: float, side: float, axis: str, ground: float,
                  height_range: tuple[float, float], keep_clear: list[tuple[float, float]] = ()
                  ) -> float:
    """Buildings along a road edge, garden fences in some gaps; returns the largest depth used.

    ``along`` is the span along the road, ``frontage`` the coordinate of the building fronts
    across it, ``side`` (+1/-1) the direction away from the road, ``axis`` the road direction.
    Spans in ``keep_clear`` (along-road intervals, e.g. side streets) stay free.
    """
    depth_max = 0.0
    pos = along[0]
    sgn = 1.0 if along[1] >= along[0] else -1.0

    def at(u: float, v: float) -> tuple[float, float]:
        return (u, v) if axis == "x" else (v, u)

    while (along[1] - pos) * sgn > 10.0:
        width = rng.uniform(12.0, 32.0)
        gap = rng.uniform(3.0, 12.0) if rng.random() < 0.5 else 0.0
        centre = pos + sgn * width / 2
        lo, hi = sorted((pos, pos + sgn * width))
        if any(lo < b and hi > a for a, b in keep_clear) or (along[1] - centre) * sgn < width / 2:
            pos += sgn * 4.0
            continue
        depth = rng.uniform(12.0, 24.0)
        setback = rng.uniform(0.0, 4.0)
        front = frontage + side * setback
        if axis == "x":
            origin, yaw = (centre, front), (0.0 if side > 0 else np.pi)
        else:
            origin, yaw = (front, centre), (-np.pi / 2 if side > 0 else np.pi / 2)
        props.building(mb, rng, origin, yaw, width, depth, ground, rng.uniform(*height_range))
        depth_max = max(depth_max, depth + setback)
        pos += sgn * width
        if gap > 0 and rng.random() < 0.6:  # a garden fence across the gap, at the frontage
            line = frontage + side * 0.3
            props.fence(mb, rng, np.array([at(pos + sgn * 0.3, line),
                                           at(pos + sgn * (gap - 0.3), line)]), ground)
        pos += sgn * gap
    return depth_max


def scatter(rng: np.random.Generator, x: tuple[float, float], y: tuple[float, float], n: int,
            min_dist: float, avoid: list[np.ndarray] = ()) -> np.ndarray:
    """Up to ``n`` random points in a box, at least ``min_dist`` apart (dart throwing)."""
    pts: list[np.ndarray] = list(avoid)
    out = []
    for _ in range(n * 20):
        if len(out) >= n:
            break
        p = np.array([rng.uniform(*sorted(x)), rng.uniform(*sorted(y))])
        if all(np.hypot(*(p - q)) >= min_dist for q in pts):
            pts.append(p)
            out.append(p)
    return np.array(out).reshape(-1, 2)


def far_from(point: np.ndarray, others: list[np.ndarray], radius: float) -> bool:
    return all(np.hypot(*(np.asarray(point)[:2] - np.asarray(o)[:2])) > radius for o in others)


# --------------------------------------------------------------------------------------------
# junction

def junction(rng: np.random.Generator) -> Layout:
    """Two two-way roads crossing; buildings, parks, trees, lights and signs at the corners."""
    mb = MeshBuilder()
    far_ground(mb, rng)
    extent = 110.0
    na, nb = int(rng.integers(1, 3)), int(rng.integers(1, 3))
    park_a = rng.random() < 0.7
    park_b = rng.random() < 0.4 or not park_a  # parked cars on at least one road
    wa = na * LANE + (2.3 if park_a else 0.0)  # half widths of road A (along x) and B (along y)
    wb = nb * LANE + (2.3 if park_b else 0.0)
    sa, sb = rng.uniform(3.0, 5.0), rng.uniform(3.0, 5.0)  # pavement widths
    asphalt = props.vary(rng, props.ASPHALT, 0.1)
    mb.add(*quad(-FAR, FAR, -wa, wa, 0.0), props.ROAD, asphalt)
    mb.add(*quad(-wb, wb, -FAR, FAR, 0.0), props.ROAD, asphalt)

    box_a = (-wb - sb, wb + sb)  # markings stop inside the crossing
    box_b = (-wa - sa, wa + sa)
    marks = [road_markings(na, (-FAR, FAR), box_a),
             swap_xy(road_markings(nb, (-FAR, FAR), box_b))]
    for sgn in (-1, 1):
        marks.append(zebra(sgn * (wb + sb + 2.5), wa))
        marks.append(swap_xy(zebra(sgn * (wa + sa + 2.5), wb)))
        marks.append(np.array([[sgn * (wb + sb + 5.0), sgn * (wb + sb + 5.4),
                                *sorted((0.0, -sgn * na * LANE))]]))  # stop lines
        marks.append(swap_xy(np.array([[sgn * (wa + sa + 5.0), sgn * (wa + sa + 5.4),
                                        *sorted((0.0, sgn * nb * LANE))]])))
    mb.add(*quads(np.concatenate(marks), MARK_Z), props.LANE_MARKING, props.MARKING)

    pavement = props.vary(rng, props.PAVEMENT, 0.08)
    for sx in (-1, 1):
        for sy in (-1, 1):
            mb.add(*box((sx * (wb + FAR) / 2, sy * (wa + sa / 2)), (FAR - wb, sa), 0.0, KERB),
                   props.SIDEWALK, pavement)
            mb.add(*box((sx * (wb + sb / 2), sy * (wa + FAR) / 2), (sb, FAR - wa), 0.0, KERB),
                   props.SIDEWALK, pavement)

    # camera on a corner, looking across the crossing
    cx, cy = rng.choice([-1, 1]), rng.choice([-1, 1])
    cam_xy = np.array([cx * (wb + sb * rng.uniform(0.4, 0.8)), cy * (wa + sa * rng.uniform(0.4, 0.8))])
    # look across the crossing: aim beyond its centre, towards the far corner
    focus = -cam_xy * rng.uniform(0.6, 1.4) + rng.uniform(-4.0, 4.0, 2)
    cam, pitch, yaw = aim_camera(cam_xy, KERB, focus, rng, pitch_range=(12.0, 22.0))
    camera_mast(mb, cam, yaw, KERB)
    clear = [cam_xy]

    kinds = ["urban", "urban", "urban", "park"]
    rng.shuffle(kinds)
    for (sx, sy), kind in zip([(-1, -1), (-1, 1), (1, -1), (1, 1)], kinds):
        x_in, y_in = sx * (wb + sb), sy * (wa + sa)
        lot_ground(mb, rng, (x_in, sx * extent), (y_in, sy * extent), KERB)
        if kind == "urban":
            depth = buildings_row(mb, rng, (x_in + sx * rng.uniform(0, 4), sx * extent), y_in, sy,
                                  "x", KERB, (7.0, 30.0))
            buildings_row(mb, rng, (y_in + sy * (depth + 3.0), sy * extent), x_in, sx, "y", KERB,
                          (7.0, 30.0))
        else:
            for p in scatter(rng, (x_in + sx * 4, sx * 60), (y_in + sy * 4, sy * 60), 22, 4.5):
                props.tree(mb, rng, tuple(p), KERB + 0.1, rng.uniform(0.8, 1.3))
            for p in scatter(rng, (x_in + sx * 3, sx * 50), (y_in + sy * 3, sy * 50), 10, 3.0):
                props.bush(mb, rng, tuple(p), KERB + 0.1)
            gap = rng.uniform(8, 20)
            props.fence(mb, rng, np.array([[sx * extent * 0.7, y_in + sy * 1.0],
                                           [x_in + sx * gap, y_in + sy * 1.0]]), KERB)
            props.fence(mb, rng, np.array([[x_in + sx * 1.0, y_in + sy * gap],
                                           [x_in + sx * 1.0, sy * extent * 0.7]]), KERB)
        _pavement_furniture(mb, rng, sx, sy, wa, wb, sa, sb, extent, clear)

    if park_a:
        _parked_cars(mb, rng, "x", na * LANE + 1.15, wb + sb + 10.0, extent)
    if park_b:
        _parked_cars(mb, rng, "y", nb * LANE + 1.15, wa + sa + 10.0, extent)

    # survey vehicle: eastbound in the rightmost lane, straight on or turning right (south)
    y0 = -(na - 0.5) * LANE
    if rng.random() < 0.5:
        drive = Polyline(np.array([[-extent, y0], [extent, y0]]))
    else:
        x1 = -(nb - 0.5) * LANE
        r = rng.uniform(7.0, 10.0)
        centre = np.array([x1 - r, y0 - r])
        drive = Polyline(np.concatenate([[[-extent, y0]], arc(centre, r, np.pi / 2, 0.0),
                                         [[x1, -extent]]]))
    lanes = [(p, 11.0) for p, k in lane_paths(na) if not (k == na - 1 and p.points[0, 0] < 0)]
    lanes += [(p, 10.0) for p, _ in lane_paths(nb, along_y=True)]
    walkways = []
    for s in (-1, 1):
        walkways.append(Walkway(Polyline(np.array([[-extent, s * (wa + sa / 2)],
                                                   [extent, s * (wa + sa / 2)]])), KERB))
        walkways.append(Walkway(Polyline(np.array([[s * (wb + sb / 2), -extent],
                                                   [s * (wb + sb / 2), extent]])), KERB))
    return Layout("junction", mb.build(), drive, rng.uniform(7.0, 9.0), focus, cam, pitch, yaw,
                  KERB, lanes, walkways, corners=(wa, wb, sa, sb))


def _pavement_furniture(mb: MeshBuilder, rng: np.random.Generator, sx: int, sy: int,
                        wa: float, wb: float, sa: float, sb: float, extent: float,
                        clear: list[np.ndarray]) -> None:
    """Street trees, lamp posts and signs on the two pavements of one junction corner."""
    ground = KERB
    # along road A (x axis) and along road B (y axis)
    for axis, w, s, w_other, s_other in (("x", wa, sa, wb, sb), ("y", wb, sb, wa, sa)):
        start = w_other + s_other + rng.uniform(6.0, 10.0)
        side = sy if axis == "x" else sx
        along_sign = sx if axis == "x" else sy

        def at(u: float, v: float) -> np.ndarray:
            return np.array([u, v]) if axis == "x" else np.array([v, u])

        toward_road = np.arctan2(*((-side, 0.0) if axis == "x" else (0.0, -side)))
        if rng.random() < 0.75:
            for u in row_positions(rng, start, extent, (8.0, 14.0)):
                p = at(along_sign * u, side * (w + 1.2))
                if far_from(p, clear, 8.0):
                    props.tree(mb, rng, tuple(p), ground)
        for u in row_positions(rng, start + 4.0, extent, (22.0, 32.0)):
            p = at(along_sign * u, side * (w + 0.5))
            if far_from(p, clear, 3.0):
                props.street_light(mb, rng, tuple(p), ground, toward_road)
        # signs near the crossing, facing traffic coming towards it
        p = at(along_sign * (w_other + s_other + rng.uniform(1.0, 4.0)), side * (w + 0.4))
        facing = np.arctan2(*((0.0, along_sign) if axis == "x" else (along_sign, 0.0)))
        if far_from(p, clear, 2.0):
            props.sign(mb, rng, tuple(p), ground, facing)
        for u in row_positions(rng, start + rng.uniform(10, 30), extent, (30.0, 60.0)):
            p = at(along_sign * u, side * (w + s - 0.4))
            if far_from(p, clear, 2.0):
                props.sign(mb, rng, tuple(p), ground, facing)


def _parked_cars(mb: MeshBuilder, rng: np.random.Generator, axis: str, offset: float,
                 start: float, extent: float) -> None:
    """Cars parked along both kerbs of a road (class car, static in the map)."""
    for side in (-1, 1):
        for sgn in (-1, 1):
            for u in row_positions(rng, start, extent - 5.0, (5.5, 8.0)):
                if rng.random() < 0.3:
                    continue
                heading = 0.0 if side < 0 else np.pi  # right-hand traffic
                xy = (sgn * u, side * offset) if axis == "x" else (side * offset, sgn * u)
                if axis == "y":
                    heading = np.pi / 2 if side > 0 else -np.pi / 2
                car = props.car_mesh(rng, props.CAR).moved(heading, (xy[0], xy[1], 0.0))
                mb.add_mesh(car)


# --------------------------------------------------------------------------------------------
# arterial

def arterial(rng: np.random.Generator) -> Layout:
    """A long straight multi-lane road: building frontage, side streets, trees, parking, median."""
    mb = MeshBuilder()
    far_ground(mb, rng)
    extent = 150.0
    n = int(rng.integers(2, 4))
    median = rng.uniform(2.0, 4.0) if rng.random() < 0.6 else 0.0
    park = rng.random() < 0.7
    drive_half = n * LANE
    w = median / 2 + drive_half + (2.3 if park else 0.0)
    s = rng.uniform(3.5, 6.0)
    asphalt = props.vary(rng, props.ASPHALT, 0.1)
    pavement = props.vary(rng, props.PAVEMENT, 0.08)
    mb.add(*quad(-FAR, FAR, -w, w, 0.0), props.ROAD, asphalt)

    # side streets (T-junctions), alternating sides
    streets = []
    for x in row_positions(rng, -extent + rng.uniform(20, 50), extent - 20, (60.0, 110.0)):
        streets.append((x, int(rng.choice([-1, 1])), rng.uniform(4.5, 6.5)))

    marks = []
    for sgn in (-1, 1):
        y_off = sgn * median / 2
        rects = road_markings(n, (-FAR, FAR), None, double_centre=False)
        rects = rects[(rects[:, 2] + rects[:, 3]) * sgn > 0]  # one carriageway's half
        rects[:, 2:] += y_off
        marks.append(rects)
    if median == 0:
        marks.append(dashes(-FAR, FAR, -0.12, 0.12, 0, 0))
        marks.append(dashes(-FAR, FAR, 0.12, 0.12, 0, 0))
    marks = np.concatenate(marks)
    for x, _, hw in streets:  # main-road markings run on past T-junctions; a crossing beside
        marks = np.concatenate([marks, zebra(x + hw + s + 2.5, w)])
    mb.add(*quads(marks, MARK_Z), props.LANE_MARKING, props.MARKING)
    if median > 0:
        mb.add(*box((0.0, 0.0), (2 * FAR, median), 0.0, KERB), props.SIDEWALK, pavement)
        lot_ground(mb, rng, (-FAR, FAR), (-median / 2 + 0.3, median / 2 - 0.3), KERB, cell=3.0)

    # pavements, broken by the side streets
    for side in (-1, 1):
        cuts = sorted([(x - hw, x + hw) for x, sd, hw in streets if sd == side])
        x_prev = -FAR
        for a, b in cuts + [(FAR, FAR)]:
            if a > x_prev:
                mb.add(*box(((x_prev + a) / 2, side * (w + s / 2)), (a - x_prev, s), 0.0, KERB),
                       props.SIDEWALK, pavement)
            x_prev = b
        for x, sd, hw in streets:
            if sd != side:
                continue
            y_start, y_end = side * w, side * extent
            mb.add(*quad(x - hw, x + hw, *sorted((y_start, y_end)), 0.0), props.ROAD, asphalt)
            for k in (-1, 1):
                mb.add(*box((x + k * (hw + s / 2), (y_start + side * s + y_end) / 2),
                            (s, abs(y_end - y_start) - s), 0.0, KERB), props.SIDEWALK, pavement)

    cam_x = rng.uniform(-15.0, 15.0)
    cam_side = int(rng.choice([-1, 1]))
    cam_xy = np.array([cam_x, cam_side * (w + s * rng.uniform(0.3, 0.7))])
    focus = np.array([cam_x + rng.choice([-1, 1]) * rng.uniform(18.0, 30.0), rng.uniform(-w, w) * 0.5])
    cam, pitch, yaw = aim_camera(cam_xy, KERB, focus, rng, pitch_range=(10.0, 25.0))
    camera_mast(mb, cam, yaw, KERB)
    clear = [cam_xy]

    for side in (-1, 1):
        keep = [(x - hw - s - 1, x + hw + s + 1) for x, sd, hw in streets if sd == side]
        lot_ground(mb, rng, (-extent, extent), (side * (w + s), side * 60.0), KERB, cell=2.0)
        for x0, x1 in ((-extent, 0.0), (0.0, extent)):
            buildings_row(mb, rng, (x0, x1), side * (w + s), side, "x", KERB, (9.0, 32.0), keep)
        toward = np.arctan2(-side, 0.0)
        for u in row_positions(rng, -extent, extent, (9.0, 13.0)):
            p = np.array([u, side * (w + 1.3)])
            if far_from(p, clear, 8.0) and not any(a < u < b for a, b in keep):
                props.tree(mb, rng, tuple(p), KERB)
        for u in row_positions(rng, -extent + rng.uniform(0, 20), extent, (25.0, 35.0)):
            p = np.array([u, side * (w + 0.5)])
            if far_from(p, clear, 3.0) and not any(a < u < b for a, b in keep):
                props.street_light(mb, rng, tuple(p), KERB, toward)
        for u in row_positions(rng, -extent + rng.uniform(0, 30), extent, (35.0, 70.0)):
            p = np.array([u, side * (w + s - 0.4)])
            if far_from(p, clear, 2.0) and not any(a < u < b for a, b in keep):
                props.sign(mb, rng, tuple(p), KERB, np.arctan2(0.0, side))
        if park:
            for u in row_positions(rng, -extent, extent - 5, (5.5, 8.0)):
                if rng.random() < 0.35 or any(a - 3 < u < b + 3 for a, b in keep):
                    continue
                heading = 0.0 if side < 0 else np.pi
                mb.add_mesh(props.car_mesh(rng, props.CAR).moved(
                    heading, (u, side * (w - 1.15), 0.0)))
    if median > 0:
        for u in row_positions(rng, -extent, extent, (10.0, 16.0)):
            if rng.random() < 0.7:
                props.tree(mb, rng, (u, rng.uniform(-0.3, 0.3)), KERB + 0.1, 0.8)

    y_drive = -median / 2 - (n - 0.5) * LANE
    drive = Polyline(np.array([[-extent, y_drive], [extent, y_drive]]))
    lanes = []
    for p, k in lane_paths(n, lane=LANE):
        offset = np.sign(p.points[0, 1]) * median / 2
        shifted = Polyline(p.points + [0.0, offset])
        if not (k == n - 1 and p.points[0, 0] < 0):
            lanes.append((shifted, 13.0))
    walkways = [Walkway(Polyline(np.array([[-extent, sd * (w + s / 2)], [extent, sd * (w + s / 2)]])),
                        KERB) for sd in (-1, 1)]
    return Layout("arterial", mb.build(), drive, rng.uniform(10.0, 13.0), focus, cam, pitch, yaw,
                  KERB, lanes, walkways)


# --------------------------------------------------------------------------------------------
# highway

def highway(rng: np.random.Generator) -> Layout:
    """A dual carriageway: barriers, embankments, sparse lights, signs, a gantry, few trees."""
    mb = MeshBuilder()
    far_ground(mb, rng)
    extent = 300.0  # the drive: 200 scans at up to 27 m/s need 540 m
    n = 3
    lane = 3.5
    shoulder = rng.uniform(2.0, 3.0)
    reserve = rng.uniform(2.5, 4.0)  # central reservation
    half = reserve / 2 + n * lane + shoulder  # edge of the paved area
    asphalt = props.vary(rng, props.ASPHALT, 0.1)
    mb.add(*quad(-FAR, FAR, -half, half, 0.0), props.ROAD, asphalt)

    marks = []
    for sgn in (-1, 1):
        inner = sgn * reserve / 2
        marks.append(dashes(-FAR, FAR, inner + sgn * 0.4, 0.15, 0, 0))
        for k in range(1, n):
            marks.append(dashes(-FAR, FAR, inner + sgn * (0.4 + k * lane), 0.15, 6.0, 12.0))
        marks.append(dashes(-FAR, FAR, inner + sgn * (0.4 + n * lane), 0.25, 0, 0))
    mb.add(*quads(np.concatenate(marks), MARK_Z), props.LANE_MARKING, props.MARKING)
    concrete = rng.random() < 0.5
    props.guard_rail(mb, np.array([-FAR, 0.0]), np.array([FAR, 0.0]), 0.0, concrete)

    # embankments: terrain rising or falling away from the shoulder, with bumps
    noise = SmoothNoise(rng, rng.uniform(15.0, 30.0), 0.35)
    slope = {sd: rng.uniform(-0.25, 0.4) for sd in (-1, 1)}
    for sd in (-1, 1):
        def height(gx: np.ndarray, gy: np.ndarray, sd: int = sd) -> np.ndarray:
            across = np.abs(gy) - half
            rise = np.clip(across, 0.0, 12.0) * slope[sd]
            return rise + np.abs(noise(gx, gy)) * np.clip(across / 4.0, 0.0, 1.0) - 0.02
        mb.add(*height_grid(-extent, extent, *sorted((sd * half, sd * 90.0)), 2.0, height),
               props.TERRAIN, props.vary(rng, (0.42, 0.45, 0.22), 0.1))

    def ground_at(y: float) -> float:
        sd = 1 if y > 0 else -1
        return float(np.clip(abs(y) - half, 0.0, 12.0) * slope[sd])

    for sd in (-1, 1):
        # outer guard rails in segments, wildlife fence further out
        for x0 in row_positions(rng, -extent, extent, (60.0, 140.0)):
            if rng.random() < 0.6:
                x1 = min(x0 + rng.uniform(40.0, 100.0), extent)
                props.guard_rail(mb, np.array([x0, sd * (half + 0.6)]),
                                 np.array([x1, sd * (half + 0.6)]), 0.0, False)
        y_fence = sd * (half + rng.uniform(14.0, 24.0))
        props.fence(mb, rng, np.array([[-extent, y_fence], [extent, y_fence]]),
                    ground_at(y_fence), "rails")
        for _ in range(int(rng.integers(3, 7))):  # clumps of trees and bushes
            cx = rng.uniform(-extent, extent)
            cy = sd * (half + rng.uniform(6.0, 40.0))
            for p in scatter(rng, (cx - 12, cx + 12), (cy - 6, cy + 6), int(rng.integers(2, 7)), 3.5):
                if abs(p[1]) > half + 4.0:
                    props.tree(mb, rng, tuple(p), ground_at(p[1]) - 0.1, rng.uniform(0.8, 1.3))
            for p in scatter(rng, (cx - 15, cx + 15), (cy - 8, cy + 8), 5, 2.5):
                if abs(p[1]) > half + 3.0:
                    props.bush(mb, rng, tuple(p), ground_at(p[1]) - 0.1)
        for u in row_positions(rng, -extent + rng.uniform(0, 80), extent, (80.0, 150.0)):
            props.sign(mb, rng, (u, sd * (half + 1.5)), 0.0, np.arctan2(0.0, -sd), 1.2)

    if rng.random() < 0.7:
        for u in row_positions(rng, -extent + rng.uniform(0, 30), extent, (35.0, 55.0)):
            for sd in (-1, 1):
                props.street_light(mb, rng, (u, sd * 0.5), 0.9, sd * np.pi / 2)
    gx = rng.uniform(-60.0, 60.0)
    props.gantry(mb, rng, gx, -half - 0.8, half + 0.8, 0.0, 0.0)

    cam_side = int(rng.choice([-1, 1]))
    cam_y = cam_side * (half + rng.uniform(2.0, 4.0))
    cam_xy = np.array([rng.uniform(-20.0, 20.0), cam_y])
    focus = np.array([cam_xy[0] + rng.choice([-1, 1]) * rng.uniform(30.0, 45.0), 0.0])
    cam, pitch, yaw = aim_camera(cam_xy, ground_at(cam_y), focus, rng, (6.0, 8.0), (12.0, 20.0))
    camera_mast(mb, cam, yaw, ground_at(cam_y))

    y_drive = -reserve / 2 - (n - 0.5) * lane
    drive = Polyline(np.array([[-extent, y_drive], [extent, y_drive]]))
    lanes = []
    for k in range(n):
        off = reserve / 2 + (k + 0.5) * lane
        if k != n - 1:
            lanes.append((Polyline(np.array([[-FAR, -off], [FAR, -off]])), 30.0 - 3 * k))
        lanes.append((Polyline(np.array([[FAR, off], [-FAR, off]])), 30.0 - 3 * k))
    return Layout("highway", mb.build(), drive, rng.uniform(22.0, 27.0), focus, cam, pitch, yaw,
                  ground_at(cam_y), lanes, [])
