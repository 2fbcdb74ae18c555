"""Synthetic indoor scenes: textured rectangles in the world frame W.

W is the AHRS world of docs/design.md: gravity-aligned, z down (x north,
y east, z down). The floor is the plane z = 0, the ceiling z = -height.

A scene is a list of `Surface`s, each a rectangle `origin + a u + b v`
(a in [0, size_u], b in [0, size_v]) seen from the side its normal u x v
points to, with a procedural material. Rooms, boxes and columns are built
from them; nothing else is needed to render exact depth (every face is a
plane) and the renderer culls the faces seen from behind.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onboard import NislamError

_UP_W = np.array([0.0, 0.0, -1.0])  # z is down
_DOWN_W = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Surface:
    """A textured rectangle. `axis_u` runs along texture columns, `axis_v`
    along texture rows; `normal = axis_u x axis_v` points to the visible side."""

    name: str
    origin_W_m: np.ndarray  # (3,)
    axis_u: np.ndarray  # (3,) unit
    axis_v: np.ndarray  # (3,) unit, orthogonal to axis_u
    size_m: tuple[float, float]  # extent along u, along v
    material: str

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.axis_u, self.axis_v)

    def corners_W_m(self) -> np.ndarray:
        """(4, 3) corners in order o, o+U, o+U+V, o+V (a convex loop)."""
        du = self.axis_u * self.size_m[0]
        dv = self.axis_v * self.size_m[1]
        o = self.origin_W_m
        return np.stack([o, o + du, o + du + dv, o + dv])


@dataclass(frozen=True)
class Box:
    """An axis-aligned box (for collision checks), min/max corners in W."""

    name: str
    min_W_m: np.ndarray
    max_W_m: np.ndarray

    def distance_m(self, p_W_m: np.ndarray) -> np.ndarray:
        """Euclidean distance from points (N, 3) to the box (0 inside)."""
        d = np.maximum(np.maximum(self.min_W_m - p_W_m, p_W_m - self.max_W_m), 0.0)
        return np.linalg.norm(d, axis=-1)


@dataclass(frozen=True)
class Scene:
    """Surfaces to render, the free interior (room box) and the obstacles."""

    name: str
    surfaces: tuple[Surface, ...]
    interior: Box
    obstacles: tuple[Box, ...]

    def clearance_m(self, p_W_m: np.ndarray) -> np.ndarray:
        """Distance from points (N, 3) to the nearest wall, floor, ceiling or obstacle."""
        p = np.atleast_2d(p_W_m)
        to_walls = np.minimum(p - self.interior.min_W_m, self.interior.max_W_m - p).min(axis=1)
        dists = [to_walls] + [b.distance_m(p) for b in self.obstacles]
        return np.min(np.stack(dists), axis=0)


def _rect(name: str, centre: np.ndarray, normal: np.ndarray, size_u: float, size_v: float,
          material: str) -> Surface:
    """A rectangle centred at `centre` facing `normal`: vertical faces get
    texture rows pointing down (upright pictures), horizontal ones rows along
    -y (floor) or +y (ceiling) with columns along +x."""
    n = normal / np.linalg.norm(normal)
    if abs(n[2]) < 0.5:  # vertical face
        v = _DOWN_W.copy()
        u = np.cross(v, n)  # then u x v = n
    else:
        u = np.array([1.0, 0.0, 0.0])
        v = np.cross(n, u)
    origin = centre - 0.5 * size_u * u - 0.5 * size_v * v
    return Surface(name, origin, u, v, (float(size_u), float(size_v)), material)


def room_surfaces(name: str, lo: np.ndarray, hi: np.ndarray, wall_material: str = "plaster",
                  floor_material: str = "wood", ceiling_material: str = "tiles") -> list[Surface]:
    """The six inner faces of the box [lo, hi] (z down: hi[2] is the floor)."""
    c = 0.5 * (lo + hi)
    ext = hi - lo
    out = [
        _rect(f"{name}.floor", np.array([c[0], c[1], hi[2]]), _UP_W, ext[0], ext[1],
              floor_material),
        _rect(f"{name}.ceiling", np.array([c[0], c[1], lo[2]]), _DOWN_W, ext[0], ext[1],
              ceiling_material),
    ]
    for axis, side in ((0, -1), (0, 1), (1, -1), (1, 1)):
        centre = c.copy()
        centre[axis] = lo[axis] if side < 0 else hi[axis]
        normal = np.zeros(3)
        normal[axis] = -side  # facing the inside
        width = ext[1 - axis]
        out.append(_rect(f"{name}.wall_{'xy'[axis]}{'-+'[side > 0]}", centre, normal, width,
                         ext[2], wall_material))
    return out


def box_surfaces(box: Box, material: str, floor_z_m: float | None = 0.0,
                 ceiling_z_m: float | None = None) -> list[Surface]:
    """The outer faces of an axis-aligned box; a face lying on the floor or
    the ceiling is left out (never seen, and coplanar with it)."""
    lo, hi = box.min_W_m, box.max_W_m
    c = 0.5 * (lo + hi)
    ext = hi - lo
    out = []
    for axis in range(3):
        for side in (-1, 1):
            z_face = lo[2] if (axis == 2 and side < 0) else hi[2]
            on_floor = floor_z_m is not None and abs(z_face - floor_z_m) < 1e-9
            on_ceiling = ceiling_z_m is not None and abs(lo[2] - ceiling_z_m) < 1e-9
            if axis == 2 and ((side > 0 and on_floor) or (side < 0 and on_ceiling)):
                continue
            centre = c.copy()
            centre[axis] = lo[axis] if side < 0 else hi[axis]
            normal = np.zeros(3)
            normal[axis] = side
            others = [a for a in range(3) if a != axis]
            if axis == 2:
                size_u, size_v = ext[0], ext[1]
            else:
                size_u, size_v = ext[others[0]], ext[2]
            tag = f"{'xyz'[axis]}{'-+'[side > 0]}"
            out.append(_rect(f"{box.name}.{tag}", centre, normal, size_u, size_v, material))
    return out


def _box(name: str, x: tuple[float, float], y: tuple[float, float], height_m: float,
         base_z_m: float = 0.0) -> Box:
    """A box standing on the plane z = base_z_m (z down: it reaches up to -height)."""
    return Box(name, np.array([x[0], y[0], base_z_m - height_m]), np.array([x[1], y[1], base_z_m]))


def room_scene() -> Scene:
    """An 8 m x 7 m x 2.8 m room: a column to orbit, shelves and crates along
    the walls, a table in a corner. Flights keep clear of all of them."""
    lo, hi = np.array([-4.0, -3.5, -2.8]), np.array([4.0, 3.5, 0.0])
    column = Box("column", np.array([-0.25, 0.75, -2.8]), np.array([0.25, 1.25, 0.0]))
    shelves = [
        _box("shelf_n", (3.55, 4.0), (-2.6, -0.8), 1.9),
        _box("shelf_w", (-4.0, -3.6), (0.4, 2.2), 1.6),
        _box("cabinet_e", (1.2, 2.6), (3.05, 3.5), 1.1),
    ]
    crates = [
        _box("crate_a", (3.2, 3.8), (1.4, 2.0), 0.6),
        _box("crate_b", (3.3, 3.7), (1.5, 1.9), 0.4, base_z_m=-0.6),
        _box("crate_c", (-3.8, -3.1), (-3.3, -2.6), 0.7),
        _box("crate_d", (-1.6, -0.9), (3.0, 3.5), 0.5),
        _box("table", (-3.8, -2.6), (2.6, 3.4), 0.75),
    ]
    surfaces = room_surfaces("room", lo, hi)
    surfaces += box_surfaces(column, "concrete", ceiling_z_m=lo[2])
    for b in shelves:
        surfaces += box_surfaces(b, "wood")
    for b in crates:
        surfaces += box_surfaces(b, "cardboard")
    return Scene("room", tuple(surfaces), Box("interior", lo, hi),
                 (column, *shelves, *crates))


def corridor_scene() -> Scene:
    """A 14 m x 2.2 m x 2.6 m corridor with cabinets and crates along its walls."""
    lo, hi = np.array([-7.0, -1.1, -2.6]), np.array([7.0, 1.1, 0.0])
    boxes = [
        _box("cabinet_1", (-5.5, -4.3), (-1.1, -0.75), 1.2),
        _box("cabinet_2", (1.0, 2.0), (0.75, 1.1), 1.8),
        _box("crate_1", (-1.5, -1.0), (0.6, 1.1), 0.5),
        _box("crate_2", (4.0, 4.6), (-1.1, -0.6), 0.8),
    ]
    surfaces = room_surfaces("corridor", lo, hi, wall_material="plaster",
                             floor_material="tiles_floor", ceiling_material="tiles")
    for b in boxes:
        surfaces += box_surfaces(b, "cardboard" if b.name.startswith("crate") else "wood")
    return Scene("corridor", tuple(surfaces), Box("interior", lo, hi), tuple(boxes))


def plane_scene(distance_m: float = 2.0, size_m: float = 20.0) -> Scene:
    """One wall facing the origin from +x (tests: its depth is known in closed form)."""
    s = _rect("plane", np.array([distance_m, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]),
              size_m, size_m, "plaster")
    half = size_m / 2
    return Scene("plane", (s,), Box("interior", np.array([-half, -half, -half]),
                                    np.array([distance_m, half, half])), ())


def half_painted_scene() -> Scene:
    """The room's size, its east half (x > 0) painted plain (textureless: walls,
    floor, ceiling and the boxes there), its west half textured as the room.
    Facing east a keypoint tracker finds almost nothing; the painted boxes'
    faces, lit differently, still give the correlation tracker edges."""
    lo, hi = np.array([-4.0, -3.5, -2.8]), np.array([4.0, 3.5, 0.0])
    west = room_surfaces("west", lo, np.array([0.0, hi[1], hi[2]]))
    east = room_surfaces("east", np.array([0.0, lo[1], lo[2]]), hi, wall_material="paint",
                         floor_material="paint", ceiling_material="paint")
    # Each half's own x = 0 face would close the room in two: leave both out.
    surfaces = [s for s in west if not s.name.endswith("wall_x+")]
    surfaces += [s for s in east if not s.name.endswith("wall_x-")]
    painted = [
        _box("block_n", (3.3, 4.0), (-1.8, -0.6), 1.4),
        _box("block_e", (1.5, 2.5), (2.8, 3.5), 1.0),
        _box("block_s", (2.0, 2.8), (-3.5, -2.9), 1.7),
        _box("plinth", (3.4, 4.0), (1.0, 1.6), 0.8),
    ]
    textured = [
        _box("shelf_w", (-4.0, -3.6), (0.4, 2.2), 1.6),
        _box("crate_c", (-3.8, -3.1), (-3.3, -2.6), 0.7),
        _box("crate_d", (-1.6, -0.9), (3.0, 3.5), 0.5),
    ]
    for b in painted:
        surfaces += box_surfaces(b, "paint")
    for b in textured:
        surfaces += box_surfaces(b, "cardboard")
    return Scene("half-painted", tuple(surfaces), Box("interior", lo, hi),
                 (*painted, *textured))


SCENES = {"room": room_scene, "corridor": corridor_scene, "plane": plane_scene,
          "half-painted": half_painted_scene}


def make_scene(name: str) -> Scene:
    try:
        return SCENES[name]()
    except KeyError:
        raise NislamError(f"unknown scene {name!r} (known: {', '.join(SCENES)})") from None
