"""A roundabout: a ring road around a planted island, three to five arms, buildings between.

What it adds to the other layouts: the survey vehicle's path is curved (in along one arm, around
the ring, out along another), so the scans are taken from headings that turn through 90-270 deg,
and the camera looks across a round island whose edges constrain all horizontal directions.

Arm frames: an arm leaves the centre in direction ``angle``; in its local frame x runs outwards
and y to the left. With right-hand traffic the inbound lanes are at +y and vehicles circulate
counter-clockwise.
"""

from __future__ import annotations

import numpy as np

from semcal_tools.scenes import props
from semcal_tools.scenes.actors import Polyline, arc
from semcal_tools.scenes.layouts import (
    FAR, KERB, LANE, MARK_Z, Layout, Walkway, aim_camera, camera_mast, dashes, far_from,
    far_ground,
    row_positions, scatter, zebra,
)
from semcal_tools.scenes.mesh import (
    MeshBuilder, SmoothNoise, annulus, box, height_grid, polar_height, quads, ring_wall,
    segment_box,
)

EXTENT = 110.0  # arms, buildings and the drive reach this far from the centre


class _Arm:
    """One approach road: direction, half width (lanes + splitter) and its local frame."""

    def __init__(self, angle: float, lanes: int, splitter: float, pavement: float) -> None:
        self.angle, self.lanes, self.splitter, self.pavement = angle, lanes, splitter, pavement
        self.half = splitter / 2 + lanes * LANE
        c, s = np.cos(angle), np.sin(angle)
        self.rot = np.array([[c, -s], [s, c]])

    def world(self, local: np.ndarray) -> np.ndarray:
        """Arm-local (x out, y left) points (N, 2) in the map frame."""
        return np.asarray(local, float).reshape(-1, 2) @ self.rot.T

    def local(self, xy: np.ndarray) -> np.ndarray:
        return np.asarray(xy, float).reshape(-1, 2) @ self.rot

    def lane_y(self, k: int, inbound: bool) -> float:
        """Lateral offset of lane k (0 = next to the splitter)."""
        y = self.splitter / 2 + (k + 0.5) * LANE
        return y if inbound else -y


def _rotated_rects(mb: MeshBuilder, arm: _Arm, rects: np.ndarray, z: float, label: int,
                   colour) -> None:
    """Axis-aligned rectangles of an arm's local frame as flat quads in the map frame."""
    verts, tris = quads(rects, z)
    verts[:, :2] = arm.world(verts[:, :2])
    mb.add(verts, tris, label, colour)


def _local_box(mb: MeshBuilder, arm: _Arm, x: tuple[float, float], y: tuple[float, float],
               z0: float, z1: float, label: int, colour) -> None:
    centre = arm.world(np.array([(x[0] + x[1]) / 2, (y[0] + y[1]) / 2]))[0]
    mb.add(*box(tuple(centre), (x[1] - x[0], y[1] - y[0]), z0, z1, arm.angle), label, colour)


def roundabout(rng: np.random.Generator) -> Layout:
    """The ring, its island, arms with splitter islands, and buildings or parks between arms."""
    mb = MeshBuilder()
    island = rng.uniform(7.0, 13.0)  # radius of the raised island, apron included
    apron = rng.uniform(1.5, 2.5)
    ring_lanes = int(rng.integers(1, 3))
    r_out = island + ring_lanes * rng.uniform(4.5, 5.2)  # outer edge of the circulating road
    walk = rng.uniform(3.0, 4.5)  # pavement width
    n_arms = int(rng.choice([3, 4, 4, 4, 5]))
    base = rng.uniform(0, 2 * np.pi)
    angles = np.sort((base + 2 * np.pi * np.arange(n_arms) / n_arms
                      + rng.uniform(-0.2, 0.2, n_arms)) % (2 * np.pi))
    arms = [_Arm(a, int(rng.integers(1, 3)) if ring_lanes == 2 else 1, rng.uniform(1.5, 3.0),
                 walk) for a in angles]
    asphalt = props.vary(rng, props.ASPHALT, 0.1)
    pavement = props.vary(rng, props.PAVEMENT, 0.08)

    # the wedges between the arms, and a paved car park in one of them (decided first: the
    # ground is sunk under every paved surface)
    gaps = [(arm.angle, np.arcsin(min(0.99, arm.half / r_out))) for arm in arms]
    sectors = []
    for k, (a, half_gap) in enumerate(gaps):
        b, half_next = gaps[(k + 1) % n_arms]
        b = b if b > a else b + 2 * np.pi
        sectors.append((a + half_gap, b - half_next))
    k_cam = int(rng.integers(n_arms))
    uses = ["urban"] * n_arms
    others = [k for k in rng.permutation(n_arms) if k != k_cam]
    uses[others[0]] = "park"
    lots: list = [None] * n_arms
    for k in [k_cam] + others[1:] + others[:1]:  # the first wedge wide enough
        lots[k] = _car_park(arms, *sectors[k], r_out + walk, rng)
        if lots[k] is not None:
            uses[k] = "car park"
            break

    far_ground(mb, rng)
    noise = SmoothNoise(rng, rng.uniform(8.0, 20.0), 0.12)

    def paved(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
        inside = np.hypot(gx, gy) < r_out + walk
        pts = np.stack([gx.ravel(), gy.ravel()], 1)
        for arm in arms:
            loc = arm.local(pts)
            inside |= ((loc[:, 0] > 0) & (np.abs(loc[:, 1]) < arm.half + walk)).reshape(gx.shape)
        for lot in lots:
            if lot is not None:
                centre, yaw, size = lot
                c, s = np.cos(yaw), np.sin(yaw)
                d = pts - centre
                u, v = d @ np.array([c, s]), d @ np.array([-s, c])
                inside |= ((np.abs(u) < size[0] / 2 + 0.5)
                           & (np.abs(v) < size[1] / 2 + 0.5)).reshape(gx.shape)
        return inside

    def lot_height(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
        return np.where(paved(gx, gy), -0.2, KERB + 0.03 + np.abs(noise(gx, gy)))

    mb.add(*height_grid(-EXTENT, EXTENT, -EXTENT, EXTENT, 1.0, lot_height), props.TERRAIN,
           props.vary(rng, props.GRASS, 0.1))

    # circulating road, arms, island
    mb.add(*annulus((0.0, 0.0), 0.0, r_out + 0.3, 0.0), props.ROAD, asphalt)
    for arm in arms:
        _rotated_rects(mb, arm, np.array([[0.0, FAR, -arm.half, arm.half]]), 0.0, props.ROAD,
                       asphalt)
    inner = island - apron
    mb.add(*annulus((0.0, 0.0), inner, island, 0.05), props.SIDEWALK,
           props.vary(rng, props.PAVEMENT, 0.1))
    mb.add(*ring_wall((0.0, 0.0), island, 0.0, 0.05), props.SIDEWALK, pavement)
    mb.add(*ring_wall((0.0, 0.0), inner, 0.05, KERB + 0.1), props.SIDEWALK, pavement)
    mound = rng.uniform(0.4, 1.5)
    mb.add(*polar_height((0.0, 0.0), inner, lambda r: KERB + 0.1 + mound * np.cos(
        np.clip(r / inner, 0, 1) * np.pi / 2) ** 2), props.TERRAIN,
        props.vary(rng, props.GRASS, 0.1))
    for p in scatter(rng, (-inner * 0.6, inner * 0.6), (-inner * 0.6, inner * 0.6),
                     int(rng.integers(1, 4)), 3.5):
        if np.hypot(*p) < inner * 0.6:
            ground = KERB + 0.1 + mound * np.cos(np.hypot(*p) / inner * np.pi / 2) ** 2
            props.tree(mb, rng, tuple(p), ground - 0.05, rng.uniform(0.8, 1.2))
    for p in scatter(rng, (-inner, inner), (-inner, inner), 6, 2.0):
        if np.hypot(*p) < inner - 1.0:
            props.bush(mb, rng, tuple(p), KERB + 0.1)

    # pavement ring between the arms, kerb faces, arm pavements and splitter islands
    for a0, a1 in sectors:
        mb.add(*annulus((0.0, 0.0), r_out, r_out + walk, KERB, a0, a1), props.SIDEWALK, pavement)
        mb.add(*ring_wall((0.0, 0.0), r_out, 0.0, KERB, a0, a1), props.SIDEWALK, pavement)
    marks = []
    for arm in arms:
        x0 = float(np.sqrt(max(r_out ** 2 - arm.half ** 2, 1.0)))
        for side in (-1, 1):
            _local_box(mb, arm, (x0, FAR), tuple(sorted((side * arm.half,
                                                         side * (arm.half + walk)))),
                       0.0, KERB, props.SIDEWALK, pavement)
        split_len = rng.uniform(10.0, 18.0)
        _local_box(mb, arm, (r_out + 1.0, r_out + 1.0 + split_len),
                   (-arm.splitter / 2 + 0.2, arm.splitter / 2 - 0.2), 0.0, KERB, props.SIDEWALK,
                   pavement)
        tip = arm.world(np.array([r_out + 1.6, 0.0]))[0]
        props.sign(mb, rng, tuple(tip), KERB, arm.angle, 0.6)  # keep right, facing inbound
        # markings (arm frame): edge lines, median lines beyond the splitter, lane lines,
        # give-way line across the inbound lanes, a zebra crossing
        end = r_out + 1.0 + split_len
        for sgn in (-1, 1):
            marks.append((arm, dashes(x0, FAR, sgn * (arm.half - 0.1), 0.15, 0, 0)))
            marks.append((arm, dashes(end, FAR, sgn * (arm.splitter / 2), 0.12, 0, 0)))
            for k in range(1, arm.lanes):
                marks.append((arm, dashes(end, FAR, sgn * (arm.splitter / 2 + k * LANE), 0.12,
                                          3.0, 6.0)))
        give_way = np.arange(arm.splitter / 2, arm.half, 0.9)
        marks.append((arm, np.c_[np.full(len(give_way), r_out + 0.2),
                                 np.full(len(give_way), r_out + 0.5), give_way, give_way + 0.5]))
        marks.append((arm, zebra(r_out + walk + 4.0, arm.half)))
    for arm, rects in marks:
        _rotated_rects(mb, arm, rects, MARK_Z, props.LANE_MARKING, props.MARKING)
    ring_marks = [(island + 0.25, 0.15, 0.0)]  # edge line along the apron
    if ring_lanes == 2:
        ring_marks.append(((island + r_out) / 2, 0.12, 3.0))
    for radius, width, dash in ring_marks:
        a = arc((0.0, 0.0), radius, 0.0, 2 * np.pi, 3.0 if dash else 1.0)
        for i, (p, q) in enumerate(zip(a[:-1], a[1:])):
            if dash and i % 2:
                continue
            mb.add(*segment_box(p, q, width, 0.0, MARK_Z), props.LANE_MARKING, props.MARKING)

    # camera on a mast at the pavement ring between two arms, looking across the island
    a0, a1 = sectors[k_cam]
    phi = rng.uniform(a0 + 0.3 * (a1 - a0), a1 - 0.3 * (a1 - a0))
    cam_xy = (r_out + walk * rng.uniform(0.4, 0.8)) * np.array([np.cos(phi), np.sin(phi)])
    focus = rng.uniform(-0.4, 0.4, 2) * r_out - cam_xy * rng.uniform(0.0, 0.4)
    cam, pitch, yaw = aim_camera(cam_xy, KERB, focus, rng, (6.0, 9.0), (12.0, 25.0))
    camera_mast(mb, cam, yaw, KERB)
    clear = [cam_xy]

    # lamp posts round the ring and along the arms, signs at the entries
    for a0, a1 in sectors:
        for ang in row_positions(rng, a0 + 0.05, a1 - 0.05, (20.0 / r_out, 30.0 / r_out)):
            p = (r_out + 0.5) * np.array([np.cos(ang), np.sin(ang)])
            if far_from(p, clear, 3.0):
                props.street_light(mb, rng, tuple(p), KERB, ang + np.pi)
    for arm in arms:
        for side in (-1, 1):
            for u in row_positions(rng, r_out + walk + rng.uniform(12, 25), EXTENT, (25.0, 35.0)):
                p = arm.world(np.array([u, side * (arm.half + 0.5)]))[0]
                if far_from(p, clear, 3.0):
                    props.street_light(mb, rng, tuple(p), KERB, arm.angle - side * np.pi / 2)
        p = arm.world(np.array([r_out + walk + rng.uniform(4.0, 9.0), arm.half + 0.4]))[0]
        if far_from(p, clear, 2.0):
            props.sign(mb, rng, tuple(p), KERB, arm.angle)

    # between the arms: buildings facing the ring, or a park, or a car park
    for (a0, a1), use, lot in zip(sectors, uses, lots):
        if lot is not None:
            _fill_car_park(mb, rng, lot)
        else:
            _sector(mb, rng, arms, a0, a1, r_out + walk, "urban" if use == "urban" else "park",
                    clear)

    drive = _through_path(arms, int(rng.integers(n_arms)), 0, r_out, island, rng)
    lanes = []
    for i in range(n_arms):
        for j in range(1, n_arms):
            lanes.append((_through_path(arms, i, j, r_out, island, rng, lane=True), 9.0))
    walkways = [Walkway(Polyline(arc((0.0, 0.0), r_out + walk / 2, 0.0, 2 * np.pi)), KERB)]
    for arm in arms:
        for side in (-1, 1):
            walkways.append(Walkway(Polyline(arm.world(np.array(
                [[r_out + walk, side * (arm.half + walk / 2)],
                 [EXTENT, side * (arm.half + walk / 2)]]))), KERB))
    return Layout("roundabout", mb.build(), drive, rng.uniform(6.0, 8.0), focus, cam, pitch,
                  yaw, KERB, lanes, walkways)


def _through_path(arms: list[_Arm], entry: int, turns: int, r_out: float, island: float,
                  rng: np.random.Generator, lane: bool = False) -> Polyline:
    """In along arm ``entry`` (outer inbound lane), counter-clockwise round the ring, out along
    an arm ``turns`` arms later (0: one drawn, the second to last arms preferred, so the
    survey drive turns through at least 180 deg when it can)."""
    n = len(arms)
    if turns == 0:
        turns = int(rng.integers(max(1, n // 2), n)) if n > 2 else 1
    a_in, a_out = arms[entry], arms[(entry + turns) % n]
    y_in = a_in.lane_y(a_in.lanes - 1, True)
    y_out = a_out.lane_y(a_out.lanes - 1, False)
    r_ring = r_out - 0.55 * LANE if not lane else (island + r_out) / 2
    start = a_in.world(np.array([[EXTENT, y_in], [r_out + 4.0, y_in]]))
    end = a_out.world(np.array([[r_out + 4.0, y_out], [EXTENT, y_out]]))
    t0 = a_in.angle + np.arcsin(min(0.95, abs(y_in) / r_ring))
    t1 = a_out.angle - np.arcsin(min(0.95, abs(y_out) / r_ring))
    while t1 <= t0:
        t1 += 2 * np.pi
    ring = arc((0.0, 0.0), r_ring, t0, t1)
    return Polyline(np.concatenate([start, ring, end]))


def _inside_arm(arms: list[_Arm], xy: np.ndarray, margin: float) -> bool:
    for arm in arms:
        loc = arm.local(xy)
        if np.any((loc[:, 0] > 0) & (np.abs(loc[:, 1]) < arm.half + arm.pavement + margin)):
            return True
    return False


def _sector(mb: MeshBuilder, rng: np.random.Generator, arms: list[_Arm], a0: float, a1: float,
            r_front: float, use: str, clear: list[np.ndarray]) -> None:
    """Fill the wedge between two arms (angles a0..a1, beyond radius r_front)."""
    if use == "park":
        fence = arc((0.0, 0.0), r_front + 1.5, a0, a1, 3.0)
        fence = fence[[not _inside_arm(arms, p, 1.0) for p in fence]]
        if len(fence) >= 2:
            props.fence(mb, rng, fence, KERB + 0.05)
        for _ in range(40):
            r, a = rng.uniform(r_front + 3.0, 70.0), rng.uniform(a0, a1)
            p = r * np.array([np.cos(a), np.sin(a)])
            if not _inside_arm(arms, p, 2.5) and far_from(p, clear, 6.0):
                if rng.random() < 0.6:
                    props.tree(mb, rng, tuple(p), KERB + 0.1, rng.uniform(0.8, 1.3))
                else:
                    props.bush(mb, rng, tuple(p), KERB + 0.1)
        return
    placed: list[tuple[np.ndarray, float]] = []  # centre and bounding radius
    for _ in range(40):
        if len(placed) >= 5:
            break
        width, depth = rng.uniform(12.0, 26.0), rng.uniform(10.0, 20.0)
        r, ang = r_front + rng.uniform(3.0, 30.0), rng.uniform(a0, a1)
        o = np.array([np.cos(ang), np.sin(ang)])
        yaw = ang - np.pi / 2
        t = np.array([np.cos(yaw), np.sin(yaw)])
        front = r * o
        corners = np.array([front + sx * t * width / 2 + d * o
                            for sx in (-1, 1) for d in (0.0, depth)])
        centre, radius = front + o * depth / 2, float(np.hypot(width, depth)) / 2
        if _inside_arm(arms, corners, 1.5) or not far_from(centre, clear, radius + 3.0):
            continue
        if any(np.hypot(*(centre - c)) < radius + rc for c, rc in placed):
            continue
        props.building(mb, rng, tuple(front), yaw, width, depth, KERB, rng.uniform(7.0, 26.0))
        placed.append((centre, radius))

def _car_park(arms: list[_Arm], a0: float, a1: float, r_front: float, rng: np.random.Generator
              ) -> tuple[np.ndarray, float, tuple[float, float]] | None:
    """Centre, yaw and size of a paved lot in the wedge a0..a1, long side facing the ring
    (None if the wedge is too narrow)."""
    mid = (a0 + a1) / 2
    yaw = mid - np.pi / 2
    along, out = np.array([np.cos(yaw), np.sin(yaw)]), np.array([np.cos(mid), np.sin(mid)])
    for r in r_front + rng.uniform(6.0, 10.0) + np.array([0.0, 10.0, 20.0, 30.0]):
        centre = (r + 9.0) * out
        for length in (36.0, 24.0, 14.0):
            corners = np.array([centre + sx * along * length / 2 + sy * out * 9.0
                                for sx in (-1, 1) for sy in (-1, 1)])
            if not _inside_arm(arms, corners, 1.0):
                return centre, yaw, (length, 18.0)
    return None


def _fill_car_park(mb: MeshBuilder, rng: np.random.Generator,
                   lot: tuple[np.ndarray, float, tuple[float, float]]) -> None:
    """The lot's surface (class parking) and two rows of parked cars (class car)."""
    centre, yaw, (length, depth) = lot
    along = np.array([np.cos(yaw), np.sin(yaw)])
    out = np.array([-np.sin(yaw), np.cos(yaw)])
    mb.add(*box(tuple(centre), (length, depth), 0.0, KERB + 0.05, yaw), props.PARKING,
           props.vary(rng, props.ASPHALT, 0.15))
    back = centre + out * (depth / 2 + 0.4)
    props.fence(mb, rng, np.array([back - along * length / 2, back + along * length / 2]), KERB)
    for row in (-1, 1):
        for u in np.arange(-length / 2 + 1.5, length / 2 - 1.5, 2.7):
            if rng.random() < 0.3:
                continue
            xy = centre + u * along + row * 5.0 * out
            heading = yaw + np.pi / 2 + (0.0 if row > 0 else np.pi) + rng.normal(0, 0.03)
            mb.add_mesh(props.car_mesh(rng, props.CAR).moved(heading, (*xy, KERB + 0.05)))
