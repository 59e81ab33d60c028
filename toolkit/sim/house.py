"""Procedural house layouts from a seed: rooms, doorways, a corridor, furniture, routes.

Layout: a straight corridor along +x with a row of rooms on each side (north, y > 0 and
south, y < 0). Every room has a door to the corridor and a door to its neighbour in the
row, so the robot's route can be a loop: in through the first north room, through the
row, back out into the corridor, across into the last south room, back through the
south row and along the corridor to the start. People walk their own back-and-forth
routes between the corridor and a room, or between neighbouring rooms.

Furniture stands against walls or free in a room, never within ``CLEARANCE`` of the robot
route or a person's route, and never in front of a door. Some of it lies wholly above or
below the lidar plane (table tops, wall shelves, low boxes), so the camera sees geometry
the lidar cannot.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from toolkit.sim.scene import Box, Surface
from toolkit.sim.textures import PICTURES

WALL_T = 0.10  # wall thickness, metres
DOOR_H = 2.05  # door opening height
DOOR_W = 0.9  # door opening width
CLEARANCE = 0.5  # free distance from a route centre line to any furniture footprint
DOOR_KEEP = 0.95  # keep this far in front of/behind doors free

PAINTS = [  # wall paint colours (multipliers on a near-white base)
    (1.0, 0.97, 0.9), (0.85, 0.92, 1.0), (1.0, 0.95, 0.75), (0.82, 0.95, 0.82),
    (1.0, 0.88, 0.85), (0.93, 0.93, 0.95), (0.95, 0.85, 1.0), (0.8, 0.9, 0.92),
]
BRICKS = [(1.05, 0.62, 0.48), (1.0, 0.98, 0.95), (0.85, 0.8, 0.78), (0.95, 0.72, 0.55)]
WOODS = [(0.85, 0.6, 0.38), (0.7, 0.48, 0.3), (0.95, 0.78, 0.55), (0.55, 0.38, 0.26)]
FABRICS = [(0.5, 0.6, 0.85), (0.85, 0.45, 0.4), (0.55, 0.75, 0.5), (0.75, 0.7, 0.6),
           (0.45, 0.45, 0.5), (0.9, 0.75, 0.45)]
CARPETS = [(0.7, 0.7, 0.75), (0.6, 0.65, 0.9), (0.9, 0.8, 0.65), (0.85, 0.6, 0.6)]
ROOM_KINDS = ("living", "dining", "bedroom", "office", "kitchen")


@dataclass(frozen=True)
class HouseParams:
    """Sizes of a layout (metres)."""

    rooms_per_side: int = 2
    room_width: tuple[float, float] = (3.8, 4.6)
    room_depth: tuple[float, float] = (3.6, 4.3)
    corridor_width: tuple[float, float] = (1.5, 1.8)
    height: float = 2.5


PRESETS: dict[str, HouseParams] = {
    "small_house": HouseParams(),
    "large_building": HouseParams(rooms_per_side=5, room_width=(3.6, 5.2),
                                  room_depth=(3.6, 5.0), corridor_width=(1.8, 2.2), height=2.7),
}


@dataclass
class Room:
    name: str
    kind: str  # living | dining | ... | corridor
    rect: np.ndarray  # [4] x0 y0 x1 y1 to the wall centre lines

    @property
    def center(self) -> np.ndarray:
        return np.array([(self.rect[0] + self.rect[2]) / 2, (self.rect[1] + self.rect[3]) / 2])

    def inner(self, margin: float = 0.0) -> np.ndarray:
        """[4] free interior (inside the wall surfaces) shrunk by ``margin``."""
        m = WALL_T / 2 + margin
        return self.rect + np.array([m, m, -m, -m])

    def contains(self, p: np.ndarray) -> bool:
        x0, y0, x1, y1 = self.rect
        return bool(x0 <= p[0] <= x1 and y0 <= p[1] <= y1)


@dataclass
class Door:
    center: np.ndarray  # [2] on the wall centre line
    normal: np.ndarray  # [2] unit, across the wall
    rooms: tuple[str, str]
    width: float = DOOR_W

    def through(self, d: float = 0.55) -> tuple[np.ndarray, np.ndarray]:
        """Points ``d`` in front of and behind the door (a straight crossing)."""
        return self.center - d * self.normal, self.center + d * self.normal


@dataclass
class Item:
    """A piece of furniture: its boxes and its footprint for plots and clearance."""

    kind: str
    room: str
    boxes: list[Box]
    footprint: np.ndarray  # [4, 2]
    z_range: tuple[float, float]


@dataclass
class House:
    params: HouseParams
    rooms: list[Room]
    doors: list[Door]
    boxes: list[Box]  # everything static: walls, floors, ceiling, furniture
    items: list[Item]
    route: np.ndarray  # [K, 2] robot waypoints, a closed loop (first == last)
    start_yaw: float
    people_routes: list[np.ndarray]  # each [K, 2] walked back and forth
    wall_segments: np.ndarray  # [W, 2, 2] wall pieces (for plots)
    seed: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def bounds(self) -> np.ndarray:
        """[4] x0 y0 x1 y1 of the whole building."""
        r = np.array([room.rect for room in self.rooms])
        return np.array([r[:, 0].min(), r[:, 1].min(), r[:, 2].max(), r[:, 3].max()])

    def room_at(self, p: np.ndarray) -> Room | None:
        for room in self.rooms:
            if room.contains(p):
                return room
        return None

    def summary(self) -> dict[str, Any]:
        """JSON-ready description (written next to the ground truth, used by plots)."""
        return {
            "seed": self.seed,
            "height_m": self.params.height,
            "rooms": [{"name": r.name, "kind": r.kind, "rect": r.rect.tolist()}
                      for r in self.rooms],
            "doors": [{"center": d.center.tolist(), "normal": d.normal.tolist(),
                       "rooms": list(d.rooms), "width": d.width} for d in self.doors],
            "walls": self.wall_segments.tolist(),
            "furniture": [{"kind": it.kind, "room": it.room, "footprint": it.footprint.tolist(),
                           "z_range": list(it.z_range)} for it in self.items],
            "route": self.route.tolist(),
            "people_routes": [r.tolist() for r in self.people_routes],
        }


# ---------------------------------------------------------------------------- geometry


def _densify(poly: np.ndarray, step: float = 0.05) -> np.ndarray:
    """[P, 2] points every ``step`` metres along a polyline [K, 2]."""
    pts = [poly[:1]]
    for a, b in zip(poly[:-1], poly[1:], strict=True):
        n = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1)
        pts.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(pts)


def _aabb(fp: np.ndarray) -> np.ndarray:
    return np.array([fp[:, 0].min(), fp[:, 1].min(), fp[:, 0].max(), fp[:, 1].max()])


def _dist_to_aabb(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """[P] distances from points [P, 2] to an axis-aligned rectangle [4]."""
    dx = np.maximum(np.maximum(box[0] - points[:, 0], points[:, 0] - box[2]), 0.0)
    dy = np.maximum(np.maximum(box[1] - points[:, 1], points[:, 1] - box[3]), 0.0)
    return np.hypot(dx, dy)


def _overlap(a: np.ndarray, b: np.ndarray, margin: float) -> bool:
    return bool(a[0] < b[2] + margin and b[0] < a[2] + margin and a[1] < b[3] + margin
                and b[1] < a[3] + margin)


# ---------------------------------------------------------------------------- layout


def generate_house(preset: str | HouseParams = "small_house", seed: int = 0) -> House:
    """A house from a preset name (``small_house`` | ``large_building``) or parameters."""
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise ValueError(f"unknown house preset {preset!r}; choose from {sorted(PRESETS)}")
        params = PRESETS[preset]
    else:
        params = preset
    n = params.rooms_per_side
    if n < 2:
        raise ValueError("rooms_per_side must be at least 2 (the route loops through a row)")
    rng = np.random.default_rng(np.random.SeedSequence([seed, 1]))
    H = params.height
    c = rng.uniform(*params.corridor_width)
    widths_n = rng.uniform(*params.room_width, n)
    widths_s = rng.uniform(*params.room_width, n)
    widths_s *= widths_n.sum() / widths_s.sum()  # both rows span the same length
    dn, ds = rng.uniform(*params.room_depth, 2)
    L = float(widths_n.sum())
    xs_n = np.concatenate([[0.0], np.cumsum(widths_n)])
    xs_s = np.concatenate([[0.0], np.cumsum(widths_s)])
    xs_s[-1] = L

    kinds = list(rng.permutation(ROOM_KINDS))
    rooms: list[Room] = [Room("corridor", "corridor", np.array([0.0, -c / 2, L, c / 2]))]
    for i in range(n):
        rooms.append(Room(f"north{i}", str(kinds[(2 * i) % len(kinds)]),
                          np.array([xs_n[i], c / 2, xs_n[i + 1], c / 2 + dn])))
    for i in range(n):
        rooms.append(Room(f"south{i}", str(kinds[(2 * i + 1) % len(kinds)]),
                          np.array([xs_s[i], -c / 2 - ds, xs_s[i + 1], -c / 2])))
    by_name = {r.name: r for r in rooms}

    # Doors: each room to the corridor, each room to its row neighbour.
    doors: list[Door] = []
    for side, sgn, xs in (("north", 1.0, xs_n), ("south", -1.0, xs_s)):
        for i in range(n):
            x = rng.uniform(xs[i] + 0.5 + DOOR_W / 2, xs[i + 1] - 0.5 - DOOR_W / 2)
            # Normal points from the corridor into the room.
            doors.append(Door(np.array([x, sgn * c / 2]), np.array([0.0, sgn]),
                              ("corridor", f"{side}{i}")))
        depth = dn if sgn > 0 else ds
        for i in range(n - 1):
            y = sgn * (c / 2 + rng.uniform(0.7 + DOOR_W / 2, depth - 0.5 - DOOR_W / 2))
            doors.append(Door(np.array([xs[i + 1], y]), np.array([1.0, 0.0]),
                              (f"{side}{i}", f"{side}{i + 1}")))

    def door(a: str, b: str) -> Door:
        for d in doors:
            if set(d.rooms) == {a, b}:
                return d
        raise KeyError((a, b))

    def interior_point(room: Room, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        # Between the entry and exit doors, drawn a little towards the middle: the robot
        # sees the room, and the far side stays free for furniture.
        lo = room.inner(0.9)
        p = 0.5 * (a + b)
        # Doors close together: go deeper in, or the route folds back on itself.
        pull = 0.3 if np.linalg.norm(a - b) > 2.5 else 0.75
        p = p + pull * (room.center - p) + rng.uniform(-0.2, 0.2, 2)
        return np.clip(p, lo[:2], lo[2:])

    # Robot route: corridor -> north row west to east -> corridor -> south row east to
    # west -> corridor -> start. ``visit`` keeps each room's interior point for people.
    visit: dict[str, np.ndarray] = {}

    def cross_row(side: str, order: list[int], d_in: Door, d_out: Door) -> list[np.ndarray]:
        pts: list[np.ndarray] = []
        entry = d_in.through()[1]
        for k, i in enumerate(order):
            room = by_name[f"{side}{i}"]
            if k < len(order) - 1:
                j = order[k + 1]
                d = door(f"{side}{min(i, j)}", f"{side}{max(i, j)}")
                a, b = d.through()
                ex, nxt = (a, b) if room.contains(a) else (b, a)
            else:
                ex, nxt = d_out.through()[1], None
            visit[room.name] = interior_point(room, entry, ex)
            pts += [entry, visit[room.name], ex]
            entry = nxt if nxt is not None else entry
        return pts

    d0 = door("corridor", "north0")
    # Start (and end) well clear of the corridor's end wall: the last seconds, driving
    # towards it, should not show a blank wall at arm's length.
    x_door = float(d0.center[0])
    start = np.array([min(1.4, x_door - 0.5) if x_door >= 1.7 else x_door + 1.0, 0.0])
    dn_exit = door("corridor", f"north{n - 1}")
    ds_in = door("corridor", f"south{n - 1}")
    ds_exit = door("corridor", "south0")
    route = [start, np.array([d0.center[0], 0.0]), d0.through()[0]]
    route += cross_row("north", list(range(n)), d0, dn_exit)
    route += [dn_exit.through()[0], np.array([dn_exit.center[0], 0.0]),
              np.array([ds_in.center[0], 0.0]), ds_in.through()[0]]
    route += cross_row("south", list(range(n - 1, -1, -1)), ds_in, ds_exit)
    route += [ds_exit.through()[0], np.array([ds_exit.center[0], 0.0]), start]
    route_arr = _dedupe(np.array(route), keep_last=True)

    # People: back and forth between the corridor and a room, or between neighbouring
    # rooms, on lines beside the robot's (they give way to it, see people.py).
    def beside(room: Room) -> np.ndarray:
        ang = rng.uniform(0, 2 * np.pi)
        p = visit[room.name] + rng.uniform(0.8, 1.2) * np.array([np.cos(ang), np.sin(ang)])
        lo = room.inner(0.6)
        return np.clip(p, lo[:2], lo[2:])

    people_routes: list[np.ndarray] = []
    for k in range(2 * n):
        side = "north" if k % 2 == 0 else "south"
        i = int(rng.integers(n))
        room = by_name[f"{side}{i}"]
        if k % 3 == 2:
            j = i + 1 if i < n - 1 else i - 1
            d = door(f"{side}{min(i, j)}", f"{side}{max(i, j)}")
            a, b = d.through(0.6)
            if not room.contains(a):
                a, b = b, a
            pts = [beside(room), a, b, beside(by_name[f"{side}{j}"])]
        else:
            d = door("corridor", room.name)
            lane = float(rng.choice([-1.0, 1.0])) * min(0.35, c / 2 - 0.35)
            cx = float(np.clip(d.center[0] + rng.uniform(-3.0, 3.0), 0.6, L - 0.6))
            a, b = d.through(0.6)
            pts = [np.array([cx, lane]), np.array([d.center[0], lane]), a, b, beside(room)]
        people_routes.append(_dedupe(np.array(pts)))

    boxes, segments = _structure(rooms, doors, L, c, dn, ds, H, rng)
    keep_free = [_densify(route_arr)] + [_densify(r) for r in people_routes]
    items = _furnish(rooms, doors, np.concatenate(keep_free), rng, H)
    for it in items:
        boxes += it.boxes
    yaw0 = float(np.arctan2(*(route_arr[1] - route_arr[0])[::-1]))
    return House(params, rooms, doors, boxes, items, route_arr, yaw0, people_routes,
                 np.array(segments), seed=seed, extra={"corridor_width": c})


def _dedupe(pts: np.ndarray, eps: float = 0.05, keep_last: bool = False) -> np.ndarray:
    """[M, 2] of ``pts`` [N, 2] without points within ``eps`` of the one before.
    ``keep_last``: the last point is kept (in place of the one it is close to), since the
    route's end at its start is what makes the planner close the lap; dropped, the robot
    ended turned 90 deg from its start on seeds whose south door lay within 5 cm of it."""
    out = [pts[0]]
    last_kept = True
    for p in pts[1:]:
        last_kept = bool(np.linalg.norm(p - out[-1]) > eps)
        if last_kept:
            out.append(p)
    if keep_last and not last_kept:
        if len(out) > 1:
            out[-1] = pts[-1]
        else:
            out.append(pts[-1])
    return np.array(out)


def _structure(rooms: list[Room], doors: list[Door], L: float, c: float, dn: float, ds: float,
               H: float, rng: np.random.Generator) -> tuple[list[Box], list[np.ndarray]]:
    """Walls with door openings, floors and the ceiling."""
    # Looks: each room one wall style, one floor; an accent wall in some rooms.
    style: dict[str, dict[str, Any]] = {}
    for r in rooms:
        paint = PAINTS[int(rng.integers(len(PAINTS)))]
        if r.kind == "corridor":
            walls = Surface("plaster", paint)
            floor = Surface("wood", WOODS[int(rng.integers(4))],
                            uv_offset=tuple(rng.uniform(0, 512, 2)))
            accent = None
        else:
            pick = rng.random()
            if pick < 0.3:
                walls = Surface("stucco", paint)
            else:  # plain paint: the low-texture walls of real houses
                walls = Surface("plaster", paint)
            accent = (int(rng.integers(4)), Surface("brick", BRICKS[int(rng.integers(4))])) if (
                rng.random() < 0.6) else None
            fl = {"kitchen": "tiles", "bedroom": "carpet", "office": "carpet"}.get(r.kind, "wood")
            ftint = (WOODS if fl == "wood" else CARPETS)[int(rng.integers(4))]
            if fl == "tiles":
                ftint = (0.95, 0.93, 0.9)
            floor = Surface(fl, ftint, uv_offset=tuple(rng.uniform(0, 512, 2)))
        style[r.name] = {"walls": walls, "floor": floor, "accent": accent}

    trim = Surface("paint", (0.95, 0.95, 0.93))
    sides = {(0, 1.0): 0, (1, 1.0): 1, (0, -1.0): 2, (1, -1.0): 3}  # normal -> room side

    def wall_surface(center: np.ndarray, normal: np.ndarray, along: int) -> Surface:
        ax = int(np.argmax(np.abs(normal)))
        if ax == 2 or ax == along:
            return trim  # reveals of openings, ends, tops
        probe = center[:2] + 0.06 * normal[:2]
        for r in rooms:
            if r.contains(probe):
                st = style[r.name]
                # A face whose normal points +x belongs to the room's west side, etc.
                side = sides[(ax, float(np.sign(normal[ax])))]
                if st["accent"] is not None and st["accent"][0] == side:
                    return st["accent"][1]
                return st["walls"]
        return trim

    boxes: list[Box] = []
    segments: list[np.ndarray] = []
    y_s, y_n = -c / 2 - ds, c / 2 + dn

    def add_wall(p0: np.ndarray, p1: np.ndarray, gaps: list[tuple[float, float]]) -> None:
        along = 0 if abs(p1[0] - p0[0]) > abs(p1[1] - p0[1]) else 1
        a0, a1 = sorted((p0[along], p1[along]))
        a0 -= WALL_T / 2
        a1 += WALL_T / 2
        fixed = p0[1 - along]
        pieces: list[tuple[float, float, float, float]] = []  # along0, along1, z0, z1
        cur = a0
        for g0, g1 in sorted(gaps):
            pieces.append((cur, g0, 0.0, H))
            pieces.append((g0, g1, DOOR_H, H))  # lintel over the opening
            cur = g1
        pieces.append((cur, a1, 0.0, H))
        for b0, b1, z0, z1 in pieces:
            if b1 - b0 < 1e-6:
                continue
            ctr = np.zeros(3)
            size = np.zeros(3)
            ctr[along], ctr[1 - along], ctr[2] = (b0 + b1) / 2, fixed, (z0 + z1) / 2
            size[along], size[1 - along], size[2] = b1 - b0, WALL_T, z1 - z0
            box = Box(ctr, size, label="wall")
            for key, n in (("+x", (1, 0, 0)), ("-x", (-1, 0, 0)), ("+y", (0, 1, 0)),
                           ("-y", (0, -1, 0)), ("+z", (0, 0, 1)), ("-z", (0, 0, -1))):
                nn = np.array(n, float)
                fc = ctr + nn * size / 2
                box.faces[key] = wall_surface(fc, nn, along)
            boxes.append(box)
            if z0 == 0.0:
                e0, e1 = np.zeros(2), np.zeros(2)
                e0[along], e0[1 - along] = b0, fixed
                e1[along], e1[1 - along] = b1, fixed
                segments.append(np.stack([e0, e1]))

    def gaps_on(line_axis: int, fixed: float) -> list[tuple[float, float]]:
        out = []
        for d in doors:
            # A door lies on a wall along axis ``line_axis`` when its normal is across it.
            if abs(d.normal[1 - line_axis]) > 0.5 and abs(d.center[1 - line_axis] - fixed) < 1e-9:
                out.append((d.center[line_axis] - d.width / 2, d.center[line_axis] + d.width / 2))
        return out

    # Outer walls, corridor walls, partitions.
    add_wall(np.array([0.0, y_s]), np.array([L, y_s]), [])
    add_wall(np.array([0.0, y_n]), np.array([L, y_n]), [])
    add_wall(np.array([0.0, y_s]), np.array([0.0, y_n]), [])
    add_wall(np.array([L, y_s]), np.array([L, y_n]), [])
    add_wall(np.array([0.0, c / 2]), np.array([L, c / 2]), gaps_on(0, c / 2))
    add_wall(np.array([0.0, -c / 2]), np.array([L, -c / 2]), gaps_on(0, -c / 2))
    for r in rooms:
        if r.name.startswith("north") and r.rect[2] < L - 1e-6:
            x = r.rect[2]
            add_wall(np.array([x, c / 2]), np.array([x, y_n]),
                     [g for g in gaps_on(1, x) if g[0] > 0])
        if r.name.startswith("south") and r.rect[2] < L - 1e-6:
            x = r.rect[2]
            add_wall(np.array([x, y_s]), np.array([x, -c / 2]),
                     [g for g in gaps_on(1, x) if g[1] < 0])

    # Floors (top face at z = 0) and one ceiling (bottom face at z = H).
    for r in rooms:
        x0, y0, x1, y1 = r.rect
        fl = style[r.name]["floor"]
        boxes.append(Box([(x0 + x1) / 2, (y0 + y1) / 2, -0.05], [x1 - x0, y1 - y0, 0.1],
                         surface=trim, faces={"+z": fl}, label="floor"))
    boxes.append(Box([L / 2, (y_s + y_n) / 2, H + 0.05], [L + 1.0, y_n - y_s + 1.0, 0.1],
                     surface=Surface("ceiling", (0.97, 0.97, 0.97)), label="ceiling"))
    # Ceiling lamps: a little texture on the otherwise blank ceiling.
    for r in rooms:
        ctr = r.center
        boxes.append(Box([ctr[0], ctr[1], H - 0.04], [0.35, 0.35, 0.08],
                         surface=Surface("paint", (1.1, 1.1, 1.05)), label="lamp"))
    return boxes, segments


# ---------------------------------------------------------------------------- furniture


def _part(local_c: tuple[float, float, float], size: tuple[float, float, float],
          surf: Surface, faces: dict[str, Surface] | None = None, label: str = "") -> Box:
    return Box(np.array(local_c), np.array(size), 0.0, surf, faces or {}, label)


def _make_item(kind: str, rng: np.random.Generator, H: float) -> tuple[list[Box], float, float,
                                                                         bool]:
    """Boxes in the item frame (x along the wall, y away from it, z up; back at y = 0).

    Returns boxes, width, depth and whether the item is wall-mounted above the floor.
    """
    wood = Surface("wood", WOODS[int(rng.integers(len(WOODS)))], "local",
                   tuple(rng.uniform(0, 512, 2)))
    fabric = Surface("fabric", FABRICS[int(rng.integers(len(FABRICS)))], "local",
                     tuple(rng.uniform(0, 512, 2)))
    metal = Surface("metal", (0.45, 0.45, 0.48), "local")
    paint = Surface("paint", PAINTS[int(rng.integers(len(PAINTS)))], "local")
    parts: list[Box] = []
    if kind == "table":
        w, d, h = rng.uniform(1.1, 1.5), rng.uniform(0.75, 0.9), rng.uniform(0.72, 0.77)
        parts.append(_part((0, d / 2, h - 0.02), (w, d, 0.04), wood))
        for sx in (-1, 1):
            for sy in (0, 1):
                parts.append(_part((sx * (w / 2 - 0.06), 0.06 + sy * (d - 0.12), (h - 0.04) / 2),
                                   (0.05, 0.05, h - 0.04), wood))
        return parts, w, d, False
    if kind in ("chair", "chair_back"):
        s, hs = rng.uniform(0.4, 0.46), rng.uniform(0.44, 0.48)
        seat_surf = wood if rng.random() < 0.5 else fabric
        parts.append(_part((0, s / 2, hs - 0.02), (s, s, 0.04), seat_surf))
        for sx in (-1, 1):
            for sy in (0, 1):
                parts.append(_part((sx * (s / 2 - 0.03), 0.03 + sy * (s - 0.06), (hs - 0.04) / 2),
                                   (0.03, 0.03, hs - 0.04), metal))
        parts.append(_part((0, 0.015, hs + 0.22), (s, 0.03, 0.44), seat_surf))  # backrest
        return parts, s, s, False
    if kind == "shelf":  # bookcase with books: open front, lidar sees into it
        w, d, h = rng.uniform(0.8, 1.2), 0.32, rng.uniform(1.6, 2.0)
        for sx in (-1, 1):
            parts.append(_part((sx * (w / 2 - 0.01), d / 2, h / 2), (0.02, d, h), wood))
        parts.append(_part((0, 0.01, h / 2), (w, 0.02, h), wood))
        n_sh = 4
        for k in range(n_sh + 1):
            z = 0.05 + k * (h - 0.07) / n_sh
            parts.append(_part((0, d / 2, z), (w - 0.04, d, 0.02), wood))
            if k < n_sh:
                x = -w / 2 + 0.04
                while x < w / 2 - 0.08:
                    bw = rng.uniform(0.025, 0.06)
                    bh = rng.uniform(0.18, min(0.3, (h - 0.07) / n_sh - 0.04))
                    col = tuple(rng.uniform(0.25, 1.0, 3))
                    parts.append(_part((x + bw / 2, 0.03 + 0.11, z + 0.01 + bh / 2),
                                       (bw, 0.22, bh), Surface("paint", col, "local")))
                    x += bw + rng.uniform(0.0, 0.02)
        return parts, w, d, False
    if kind == "sofa":
        w, d = rng.uniform(1.6, 2.1), 0.85
        parts.append(_part((0, d / 2 + 0.05, 0.21), (w - 0.3, d - 0.2, 0.42), fabric))
        parts.append(_part((0, 0.1, 0.45), (w, 0.2, 0.9), fabric))
        for sx in (-1, 1):
            parts.append(_part((sx * (w / 2 - 0.08), d / 2, 0.3), (0.16, d, 0.6), fabric))
        return parts, w, d, False
    if kind == "coffee_table":
        w, d, h = rng.uniform(0.8, 1.1), rng.uniform(0.45, 0.6), 0.42
        parts.append(_part((0, d / 2, h - 0.025), (w, d, 0.05), wood))
        for sx in (-1, 1):
            for sy in (0, 1):
                parts.append(_part((sx * (w / 2 - 0.05), 0.05 + sy * (d - 0.1), (h - 0.05) / 2),
                                   (0.04, 0.04, h - 0.05), wood))
        return parts, w, d, False
    if kind == "low_box":  # lies wholly below the lidar plane
        w, d, h = rng.uniform(0.35, 0.7), rng.uniform(0.3, 0.5), rng.uniform(0.08, 0.17)
        surf = Surface("paint", tuple(rng.uniform(0.3, 1.0, 3)), "local") if rng.random() < 0.5 \
            else Surface("fabric", FABRICS[int(rng.integers(len(FABRICS)))], "local")
        parts.append(_part((0, d / 2, h / 2), (w, d, h), surf))
        return parts, w, d, False
    if kind == "wall_shelf":  # wholly above the lidar plane
        w, d, z = rng.uniform(0.8, 1.2), 0.25, rng.uniform(1.0, 1.5)
        parts.append(_part((0, d / 2, z), (w, d, 0.03), wood))
        for k in range(int(rng.integers(2, 5))):
            bw, bh = rng.uniform(0.1, 0.22), rng.uniform(0.08, 0.2)
            x = -w / 2 + (k + 0.5) * w / 5
            parts.append(_part((x, d / 2, z + 0.015 + bh / 2), (bw, 0.15, bh),
                               Surface("paint", tuple(rng.uniform(0.3, 1.0, 3)), "local")))
        return parts, w, d, True
    if kind == "bed":
        w, d = rng.uniform(1.4, 1.6), 2.0
        parts.append(_part((0, d / 2, 0.25), (w, d, 0.5), fabric))
        parts.append(_part((0, 0.03, 0.45), (w + 0.06, 0.06, 0.9), wood))
        parts.append(_part((0, 0.3, 0.55), (w - 0.3, 0.4, 0.1), Surface("plaster", (1, 1, 1))))
        return parts, w + 0.06, d, False
    if kind == "wardrobe":
        w, d = rng.uniform(1.0, 1.6), 0.6
        h = min(2.0, H - 0.2)
        parts.append(_part((0, d / 2, h / 2), (w, d, h), wood))
        return parts, w, d, False
    if kind == "cabinet":
        w, d, h = rng.uniform(0.8, 1.2), 0.45, rng.uniform(0.75, 1.0)
        parts.append(_part((0, d / 2, h / 2), (w, d, h), paint, {"+z": wood}))
        return parts, w, d, False
    if kind == "counter":  # kitchen counter with wall cabinets above
        w, d = rng.uniform(1.8, 2.6), 0.6
        parts.append(_part((0, d / 2, 0.45), (w, d, 0.9), paint,
                           {"+z": Surface("stone", (0.8, 0.8, 0.82), "local")}))
        parts.append(_part((0, 0.18, 1.8), (w, 0.35, 0.6), paint))
        return parts, w, d, False
    if kind == "picture":
        w, h = rng.uniform(0.5, 0.9), rng.uniform(0.4, 0.7)
        z = rng.uniform(1.3, 1.6)
        pic = PICTURES[int(rng.integers(len(PICTURES)))]
        frame = Surface("paint", (0.2, 0.18, 0.15), "local")
        parts.append(_part((0, 0.015, z), (w, 0.03, h), frame, {"+y": Surface(pic, (1, 1, 1),
                                                                              "fit")}))
        return parts, w, 0.03, True
    raise ValueError(f"unknown furniture kind {kind!r}")


# What goes in which room: (kind, placement) in priority order; every room gets pictures,
# and each has something below and something above the lidar plane.
_CATALOGUE: dict[str, list[tuple[str, str]]] = {
    "living": [("sofa", "wall"), ("coffee_table", "free"), ("chair", "free"), ("shelf", "wall"),
               ("low_box", "free"), ("wall_shelf", "wall"), ("cabinet", "wall")],
    "dining": [("dining", "free|wall"), ("chair", "free"), ("cabinet", "wall"), ("shelf", "wall"),
               ("low_box", "wall"), ("wall_shelf", "wall")],
    "bedroom": [("bed", "wall"), ("chair", "free"), ("wardrobe", "wall"), ("cabinet", "wall"),
                ("low_box", "wall"), ("wall_shelf", "wall")],
    "office": [("desk", "wall"), ("shelf", "wall"), ("shelf", "wall"), ("low_box", "free"),
               ("wall_shelf", "wall"), ("chair", "free")],
    "kitchen": [("counter", "wall"), ("dining", "free|wall"), ("cabinet", "wall"),
                ("low_box", "wall"), ("wall_shelf", "wall")],
}


def _compound(kind: str, rng: np.random.Generator, H: float) -> tuple[list[Box], float, float,
                                                                       bool]:
    """Table with chairs around it, desk with a chair; otherwise one item."""
    if kind == "dining":
        parts, w, d, _ = _make_item("table", rng, H)
        off = 0.35  # the table starts this far from the item's back edge (room for chairs)
        parts = [_shift(p, 0.0, off) for p in parts]
        n_side = 2 if w > 1.2 else 1
        for k in range(n_side):
            x = (k + 0.5) * w / n_side - w / 2
            # Chairs face the table with their front edge tucked 0.1 m under it.
            ch, s, _, _ = _make_item("chair", rng, H)
            parts += [_shift(p, x, off + 0.1 - s) for p in ch]
            ch, s, _, _ = _make_item("chair", rng, H)
            parts += [_rot180(p, x, off + d - 0.1 + s) for p in ch]
        return parts, w, d + 2 * off, False
    if kind == "desk":
        parts, w, d, _ = _make_item("table", rng, H)
        ch, s, _, _ = _make_item("chair", rng, H)
        parts += [_rot180(p, 0.0, d - 0.1 + s) for p in ch]
        return parts, w, d + s, False
    return _make_item(kind, rng, H)


def _shift(b: Box, dx: float, dy: float) -> Box:
    return Box(b.center + np.array([dx, dy, 0.0]), b.size, b.yaw, b.surface, b.faces, b.label)


def _rot180(b: Box, dx: float, dy: float) -> Box:
    """Turn a part by 180 deg about the item's z axis, then shift it by (dx, dy)."""
    c = b.center.copy()
    c[0], c[1] = -c[0] + dx, -c[1] + dy
    return Box(c, b.size, b.yaw + np.pi, b.surface, b.faces, b.label)


def _place(parts: list[Box], origin: np.ndarray, yaw: float, kind: str) -> list[Box]:
    """Item frame -> world: rotate by ``yaw`` about z, then move to ``origin`` [2]."""
    cz, sz = np.cos(yaw), np.sin(yaw)
    R = np.array([[cz, -sz], [sz, cz]])
    out = []
    for p in parts:
        c = p.center.copy()
        c[:2] = R @ c[:2] + origin
        out.append(Box(c, p.size, p.yaw + yaw, p.surface, p.faces, kind))
    return out


def _furnish(rooms: list[Room], doors: list[Door], keep_free: np.ndarray,
             rng: np.random.Generator, H: float) -> list[Item]:
    items: list[Item] = []
    door_zones = []
    for d in doors:
        t = np.array([-d.normal[1], d.normal[0]])
        pts = np.array([d.center + s1 * (d.width / 2 + 0.15) * t + s2 * DOOR_KEEP * d.normal
                        for s1 in (-1, 1) for s2 in (-1, 1)])
        door_zones.append(_aabb(pts))
    for room in rooms:
        placed: list[tuple[np.ndarray, float]] = []  # floor items: AABB, top height
        placed_wall: list[np.ndarray] = []  # AABBs of wall-mounted items
        inner = room.inner()
        plan = list(_CATALOGUE.get(room.kind, []))
        n_pics = int(rng.integers(1, 4)) if room.kind != "corridor" else int(rng.integers(2, 5))
        plan += [("picture", "wall")] * n_pics
        for kind, where_opts in plan:
            for attempt in range(60):
                opts = where_opts.split("|")
                where = opts[attempt % len(opts)]
                parts, w, d, mounted = _compound(kind, rng, H)
                if where == "wall":
                    side = int(rng.integers(4))
                    # Item back against the wall's inner surface, facing into the room.
                    x0, y0, x1, y1 = inner
                    yaw = [0.0, np.pi / 2, np.pi, -np.pi / 2][side]
                    span = [(x0, x1), (y0, y1), (x0, x1), (y0, y1)][side]
                    if span[1] - span[0] < w + 0.1:
                        continue
                    a = rng.uniform(span[0] + w / 2 + 0.05, span[1] - w / 2 - 0.05)
                    gap = 0.005
                    origin = [np.array([a, y0 + gap]), np.array([x1 - gap, a]),
                              np.array([a, y1 - gap]), np.array([x0 + gap, a])][side]
                else:
                    yaw = float(rng.choice([0.0, np.pi / 2])) + rng.uniform(-0.08, 0.08)
                    lo = inner[:2] + 0.3
                    hi = inner[2:] - 0.3
                    if np.any(hi - lo < max(w, d)):
                        continue
                    ctr = rng.uniform(lo, hi)
                    cz, sz = np.cos(yaw), np.sin(yaw)
                    # Origin so that the item's centre (0, d/2) lands on ``ctr``.
                    origin = ctr - np.array([-sz * d / 2, cz * d / 2])
                boxes = _place(parts, origin, yaw, kind)
                fp_local = np.array([[-w / 2, 0], [w / 2, 0], [w / 2, d], [-w / 2, d]])
                R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
                fp = fp_local @ R.T + origin
                bb = _aabb(fp)
                if bb[0] < inner[0] - 0.02 or bb[1] < inner[1] - 0.02 or \
                        bb[2] > inner[2] + 0.02 or bb[3] > inner[3] + 0.02:
                    continue
                if any(_overlap(bb, z, 0.0) for z in door_zones):
                    continue
                zs = [b.center[2] - b.size[2] / 2 for b in boxes] + \
                    [b.center[2] + b.size[2] / 2 for b in boxes]
                z_lo, z_hi = float(min(zs)), float(max(zs))
                if mounted:
                    if any(_overlap(bb, p, 0.1) for p in placed_wall):
                        continue
                    # Hang above furniture, not inside a wardrobe or behind a bookcase.
                    if any(_overlap(bb, p, 0.02) and top > z_lo - 0.05 for p, top in placed):
                        continue
                    placed_wall.append(bb)
                else:
                    if np.min(_dist_to_aabb(keep_free, bb)) < CLEARANCE:
                        continue
                    if any(_overlap(bb, p, 0.08) for p, _ in placed):
                        continue
                    if any(_overlap(bb, p, 0.02) for p in placed_wall) and z_hi > 0.95:
                        continue
                    placed.append((bb, z_hi))
                items.append(Item(kind, room.name, boxes, fp, (z_lo, z_hi)))
                break
    return items
