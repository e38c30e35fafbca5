"""A look-alike of the paper's UNC power plant: a coal-fired station as a scene graph of parts.

Target shape (the paper, section 5, and the project brief): about 5,000 nodes, ~1,118 internal +
~3,919 leaves, average branching about 4.5, about one million triangles, in a volume about
80 m x 80 m x 60 m.

The plant is laid out as the real kind is: a steel-framed turbine hall on the west, four boiler
units in a row on the east (each a boiler inside its own steel, platforms, a stair tower, pumps,
heaters, a fan and many pipe runs), a tank farm to the north, a pipe rack and the stack to the
south, and an inclined coal conveyor. The graph is grouped the way plant CAD is: a unit, a
system, an assembly (a pipe run, a pump set, a storey of steel), then spools or joints of a few
parts. Every group is spatially compact and every leaf is one coherent part.

Parts have the mix that makes oriented boxes pay off: long thin pipes and beams, flat gratings
and slabs, compact pumps and valves; and a good share of them off the axes: diagonal braces,
45-degree pipe legs, pipe runs and equipment turned about the vertical, an inclined conveyor.

Coordinates are metres, z up, the plant centred on the origin in x and y with the ground at
z = 0; the tree root turns z up into y up.
"""

from __future__ import annotations

import numpy as np

from .tree import Tree, frames, members, placements, polyline_pipe, rot_y, rot_z, trs

HALL_X = np.arange(7) * 8.0 - 38.0  # turbine hall column lines (x), 6 bays of 8 m
HALL_Y = np.arange(8) * 8.0 - 28.0  # and along y, 7 bays of 8 m
STOREY = 8.0  # m, storey height of all steel
UNIT_Y = (-30.0, -10.0, 10.0, 30.0)  # boiler units along the east side
UNIT_X = 26.0

_AXES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)


def build(seed: int = 0) -> Tree:
    """The power plant look-alike for ``seed`` (layout fixed, routes and details vary)."""
    rng = np.random.default_rng(seed)
    t = Tree("powerplant")
    root = t.root
    turbine_hall(t, root, rng)
    units = t.group(root, "units")
    for i, y in enumerate(UNIT_Y):
        boiler_unit(t, units, f"unit{i}", trs((UNIT_X, y, 0.0)), rng)
    tank_farm(t, root, rng)
    pipe_rack(t, root, rng)
    stack(t, root, rng)
    conveyor(t, root, rng)
    return t


# ---------------------------------------------------------------------------------------------
# assemblies


def pipe_run(t: Tree, parent: str, name: str, matrix: np.ndarray, points: np.ndarray, radius: float,
             rng: np.random.Generator, spool: int = 2, valves: int = 1) -> str:
    """A pipe along a route of corner ``points`` (local to ``matrix``): straight pipes, long-radius
    bends at the corners, flanges at both ends and ``valves`` gate valves on the longest legs.

    Straight pipes and the bend after each are grouped in spools of ``spool`` legs, as piping is
    fabricated and as a culling hierarchy wants it: a long run is a few compact groups."""
    g = t.group(parent, name, matrix)
    ends, bends, angles = polyline_pipe(points, radius)
    if not np.all(np.isclose(angles, 90.0) | np.isclose(angles, 45.0)):
        raise ValueError(f"{g}: corners must turn by 90 or 45 degrees to fit a bend, got {angles}")
    big = radius >= 0.15
    pipe = "pipe32" if big else "pipe16"
    straight = members(ends[:, 0], ends[:, 1], (2 * radius, 2 * radius))
    legs = len(straight)
    for s in range(0, legs, spool):
        sg = t.group(g, f"spool{s // spool}")
        for k in range(s, min(s + spool, legs)):
            t.leaf(sg, f"pipe{k:02d}", pipe, straight[k])
            if k < len(bends):
                kind = "elbow90" if angles[k] > 67.5 else "elbow45"  # exactly 90 or 45, checked above
                t.leaf(sg, f"bend{k:02d}", f"{kind}_{32 if big else 16}", bends[k])
    # flanges: short fat discs at both ends, and valves in the middle of the longest legs
    axis = ends[:, 1] - ends[:, 0]
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    tips = np.stack([ends[0, 0], ends[-1, 1]])
    out = np.stack([-axis[0], axis[-1]])
    t.leaves(g, "flange", "pipe32", members(tips - 0.125 * radius * out, tips + 0.125 * radius * out,
                                             (3.2 * radius, 3.2 * radius)), width=1)
    longest = np.argsort(-np.linalg.norm(ends[:, 1] - ends[:, 0], axis=-1), kind="stable")[:valves]
    for i, k in enumerate(sorted(longest.tolist())):
        t.leaf(g, f"valve{i}", "valve", trs(ends[k].mean(0), frames(axis[k][None])[0], s=radius))
    return g


def route(rng: np.random.Generator, start: np.ndarray, lo: np.ndarray, hi: np.ndarray, legs: int,
          first: int, length: tuple[float, float] = (3.0, 9.0), diagonal: float = 0.25) -> np.ndarray:
    """Corner points of a pipe route from ``start`` inside the box ``[lo, hi]``.

    Legs follow the axes and turn by 90 degrees, or now and then take a 45-degree leg and turn
    back onto an axis, so every corner matches an elbow template (90 or 45 degrees).
    ``first`` indexes the first direction in ``_AXES``. Leg lengths are drawn from ``length``
    and shortened to stay in the box; a route that cannot continue stops early.
    """
    p = [np.asarray(start, dtype=np.float64)]
    d = _AXES[first]
    for k in range(legs):
        if k > 0:
            if np.count_nonzero(d) == 2:  # leave a diagonal onto one of its two axes
                options = [np.sign(d[i]) * np.eye(3)[i] for i in np.flatnonzero(d)]
            else:
                options = [a for a in _AXES if abs(a @ d) < 0.5]
                if rng.random() < diagonal:
                    options = [(d + a) / np.sqrt(2.0) for a in options]
            fits = [options[j] for j in rng.permutation(len(options)) if _room(p[-1], options[j], lo, hi) >= length[0]]
            if not fits:
                break
            d = fits[0]
        room = _room(p[-1], d, lo, hi)
        if room < length[0]:
            break
        p.append(p[-1] + d * min(rng.uniform(*length), room))
    return np.array(p)


def _room(p: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """How far one can go from ``p`` along ``d`` and stay in the box ``[lo, hi]``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (hi - p) / d, np.where(d < 0, (lo - p) / d, np.inf))
    return float(max(0.0, t.min()))


def steel_storey(t: Tree, parent: str, name: str, xs: np.ndarray, ys: np.ndarray, z0: float,
                 rng: np.random.Generator, brace_every: int = 2, floor: float = 0.0) -> str:
    """One storey of a steel frame on the grid ``xs`` x ``ys``: grouped by grid line, each line
    in panels of two columns with the beams framing into them (a compact, erectable unit), then
    the storey's perimeter bracing and floor gratings."""
    g = t.group(parent, name, trs((0, 0, z0)))
    z1 = STOREY
    col = (0.4, 0.4)
    for j, y in enumerate(ys):
        row = t.group(g, f"line{j}", trs((0, y, 0)))
        for p in range(0, len(xs), 2):  # a panel: two columns and the beams from them
            i = np.arange(p, min(p + 2, len(xs)))
            pan = t.group(row, f"panel{p // 2}", trs((xs[p], 0, 0)))
            foot = np.c_[xs[i] - xs[p], np.zeros((len(i), 2))]
            top = foot + [0, 0, z1 - 0.25]
            t.leaves(pan, "column", "ibeam", members(foot, foot + [0, 0, z1], col), start=int(i[0]), width=1)
            n_x = int(np.count_nonzero(i + 1 < len(xs)))
            if n_x:
                span = np.c_[xs[i[:n_x] + 1] - xs[i[:n_x]], np.zeros((n_x, 2))]
                t.leaves(pan, "beam_x", "ibeam", members(top[:n_x], top[:n_x] + span, (0.25, 0.5)),
                         start=int(i[0]), width=1)
            if j + 1 < len(ys):  # a beam across to the next line at the panel's first column
                t.leaf(pan, "beam_y", "ibeam", members(top[:1], top[:1] + [0, ys[j + 1] - y, 0], (0.25, 0.5))[0])
    # X-bracing in some perimeter bays: long diagonals, the reason frames want oriented boxes
    br = t.group(g, "bracing")
    faces = [(xs[i], ys[0], xs[i + 1], ys[0]) for i in range(len(xs) - 1)]
    faces += [(xs[-1], ys[j], xs[-1], ys[j + 1]) for j in range(len(ys) - 1)]
    faces += [(xs[i], ys[-1], xs[i + 1], ys[-1]) for i in range(len(xs) - 1)]
    faces += [(xs[0], ys[j], xs[0], ys[j + 1]) for j in range(len(ys) - 1)]
    pick = np.flatnonzero(np.arange(len(faces)) % brace_every == rng.integers(brace_every))
    p0, p1 = [], []
    for i in pick:
        xa, ya, xb, yb = faces[i]
        p0 += [(xa, ya, 0.3), (xb, yb, 0.3)]
        p1 += [(xb, yb, z1 - 0.6), (xa, ya, z1 - 0.6)]
    t.leaves(br, "brace", "box", members(np.array(p0), np.array(p1), (0.2, 0.2)))
    if floor > 0:
        fl = t.group(g, "floor")
        cells = [(x, y) for x in (xs[:-1] + xs[1:]) / 2 for y in (ys[:-1] + ys[1:]) / 2]
        take = np.flatnonzero(rng.random(len(cells)) < floor)
        c = np.array([cells[i] for i in take]).reshape(-1, 2)
        dx, dy = np.diff(xs).mean(), np.diff(ys).mean()
        t.leaves(fl, "grating", "grating", placements(np.c_[c, np.full(len(c), z1 + 0.05)], 0.0, (dx, dy, 0.1)))
    return g


def platform(t: Tree, parent: str, name: str, z: float, half: float, width: float,
             rng: np.random.Generator) -> str:
    """A walkway ringing a square (the boiler) at height ``z``: four gratings, four railings on
    the outer edge, and a ladder."""
    g = t.group(parent, name, trs((0, 0, z)))
    side = 2 * half + 2 * width
    for k in range(4):
        yaw = k * np.pi / 2
        r = rot_z(yaw)
        s = t.group(g, f"side{k}", trs(r @ np.array([0, -(half + width / 2), 0]), r))
        t.leaf(s, "grating", "grating", trs((0, 0, -0.05), s=(side, width, 0.1)))
        t.leaf(s, "railing", "railing", trs((0, -width / 2, 0), s=(side, 1.0, 1.1)))
    t.leaf(g, "ladder", "ladder", trs((half + width, half * 0.5, -STOREY), rot_z(np.pi / 2), s=(0.5, 0.3, STOREY)))
    return g


def stair_tower(t: Tree, parent: str, name: str, matrix: np.ndarray, storeys: int) -> str:
    """Switchback stairs, two flights per storey, each flight with its landing and rails."""
    g = t.group(parent, name, matrix)
    rise = STOREY / 2
    for k in range(2 * storeys):
        back = k % 2  # every other flight runs back the other way
        f = t.group(g, f"flight{k:02d}", trs((0, 0, k * rise), rot_z(np.pi * back)))
        t.leaf(f, "stairs", "stairs", trs((0, -0.6, rise / 2), s=(5.0, 1.1, rise)))
        t.leaf(f, "landing", "grating", trs((3.3, 0, rise - 0.05), s=(1.6, 2.6, 0.1)))
        pitch = np.arctan2(rise, 5.0)
        t.leaf(f, "rail", "railing", trs((0, -1.2, rise / 2), rot_y(-pitch), s=(np.hypot(5.0, rise), 1.0, 1.1)))
    return g


def pump_set(t: Tree, parent: str, name: str, at, yaw: float, size: float, radius: float) -> str:
    """A pump on its skid with suction and discharge pipes and a valve: a compact assembly,
    turned to wherever the pipes came from."""
    g = t.group(parent, name, trs(at, rot_z(yaw)))
    t.leaf(g, "pump", "pump", trs((0, 0, 0), s=size))
    x = 0.25 * size
    z = 0.4 * size
    t.leaf(g, "suction", "pipe16", members([[x, 0, z]], [[x, 0, z + 2.5]], (2 * radius, 2 * radius))[0])
    t.leaf(g, "discharge", "pipe16", members([[x + 0.1 * size, 0, 0.3 * size]], [[x + 2.0, 0, 0.3 * size]], (2 * radius, 2 * radius))[0])
    t.leaf(g, "valve", "valve", trs((x, 0, z + 1.5), s=radius))
    t.leaf(g, "foundation", "box", trs((0, 0, -0.15), s=(1.2 * size, 0.6 * size, 0.3)))
    return g


def horizontal_vessel(t: Tree, parent: str, name: str, at, yaw: float, length: float, radius: float) -> str:
    """A feedwater heater or drum lying on two saddles, with two nozzles on top."""
    g = t.group(parent, name, trs(at, rot_z(yaw)))
    lie = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])  # the vessel's axis (z) along x
    t.leaf(g, "shell", "vessel", trs((-length / 2, 0, radius + 0.5), lie, s=(radius, radius, length)))
    for i, x in enumerate((-0.3 * length, 0.3 * length)):
        t.leaf(g, f"saddle{i}", "box", trs((x, 0, 0.4), s=(0.5, 1.6 * radius, 0.8)))
    z = 2 * radius + 0.5
    t.leaves(g, "nozzle", "pipe16", members([[-0.2 * length, 0, z - 0.2], [0.25 * length, 0, z - 0.2]],
                                            [[-0.2 * length, 0, z + 0.8], [0.25 * length, 0, z + 0.8]],
                                            (0.5 * radius, 0.5 * radius)), width=1)
    return g


# ---------------------------------------------------------------------------------------------
# the plant


def turbine_hall(t: Tree, parent: str, rng: np.random.Generator) -> str:
    """The steel frame of the turbine hall and bunker bay, two turbine-generator sets on their
    pedestals, their condensers, feed pumps and the main steam lines to the boilers."""
    g = t.group(parent, "turbine_hall")
    frame = t.group(g, "frame")
    for k in range(5):
        steel_storey(t, frame, f"storey{k}", HALL_X, HALL_Y, k * STOREY, rng, floor=0.6 if k else 0.0)
    enclosure(t, g, HALL_X, HALL_Y, 5 * STOREY)
    switchgear = t.group(g, "switchgear", trs((-30.0, -20.0, STOREY + 0.1)))
    for i in range(4):
        lineup = t.group(switchgear, f"lineup{i}", trs((0, 4.0 * i, 0)))
        x = np.arange(10) * 0.9
        t.leaves(lineup, "cabinet", "box", placements(np.c_[x, 0 * x, 0 * x + 1.1], 0.0, (0.85, 0.7, 2.2)))
    stairs = t.group(g, "stairs")
    for i, (x, y) in enumerate(((-34.0, -25.0), (6.0, 25.0))):
        stair_tower(t, stairs, f"tower{i}", trs((x, y, 0), rot_z(np.pi * i)), 5)
    for i, y in enumerate((-13.0, 13.0)):
        tg = t.group(g, f"turbine{i}", trs((-14.0, y, 0)))
        t.leaf(tg, "pedestal", "box", trs((0, 0, 2.5), s=(30, 7, 5)))
        casing = t.group(tg, "casing", trs((0, 0, 5)))
        lie = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
        for k, (x0, ln, r) in enumerate(((-14, 5, 1.6), (-8.5, 6, 2.2), (-2, 6, 2.6), (4.5, 6, 2.6))):
            t.leaf(casing, f"cylinder{k}", "vessel", trs((x0, 0, r), lie, s=(r, r, ln)))
        gen = t.group(tg, "generator", trs((12, 0, 5)))
        t.leaf(gen, "stator", "vessel", trs((-3, 0, 2.0), lie, s=(2.0, 2.0, 7)))
        t.leaf(gen, "exciter", "drum", trs((4.5, 0, 1.0), lie, s=(0.9, 0.9, 2.0)))
        t.leaf(tg, "condenser", "box", trs((0, 0, 2.0), s=(12, 9, 4)))
        pumps = t.group(tg, "feed_pumps")
        for k in range(3):
            pump_set(t, pumps, f"pump{k}", (-10 + 6 * k, 7.5 if y > 0 else -7.5, 0.3),
                     np.radians(rng.uniform(-30, 30)), 2.0, 0.12)
        pipes = t.group(tg, "pipes")
        for k in range(6):
            start = np.array([rng.uniform(-12, 12), rng.uniform(-3, 3), 10.0])
            pts = route(rng, start, np.array([-24.0, -6.0, 1.0]), np.array([24.0, 6.0, 14.0]), 5, 4 + (k % 2))
            pipe_run(t, pipes, f"run{k}", trs(r=rot_z(np.radians(rng.uniform(-20, 20)))), pts,
                     0.2 if k % 3 == 0 else 0.1, rng)
    steam = t.group(g, "main_steam")
    for i, y in enumerate(UNIT_Y):
        jog = 0.4 * abs(y)  # a 45-degree jog in plan gathers the four lines toward the turbines
        pts = np.array([[UNIT_X - 6, y, 46.0], [UNIT_X - 13, y, 46.0], [UNIT_X - 13, y, 30.0],
                        [10.0, y, 30.0], [10.0 - jog, 0.6 * y, 30.0], [-10.0, 0.6 * y, 30.0],
                        [-10.0, 0.6 * y, 9.0]])
        pipe_run(t, steam, f"line{i}", np.eye(4), pts, 0.3, rng, spool=2, valves=2)
    return g


def enclosure(t: Tree, parent: str, xs: np.ndarray, ys: np.ndarray, height: float) -> str:
    """Roof deck panels, a row per bay line, and wall cladding on the top two storeys: the big
    flat parts of the hall."""
    g = t.group(parent, "enclosure")
    roof = t.group(g, "roof", trs((0, 0, height + 0.2)))
    cx = (xs[:-1] + xs[1:]) / 2
    for j, y in enumerate((ys[:-1] + ys[1:]) / 2):
        row = t.group(roof, f"row{j}", trs((0, y, 0)))
        t.leaves(row, "deck", "box", placements(np.c_[cx, 0 * cx, 0 * cx], 0.0, (np.diff(xs).mean(), np.diff(ys).mean(), 0.15)), width=1)
    clad = t.group(g, "cladding")
    spans = [((xs[i], ys[0]), (xs[i + 1], ys[0])) for i in range(len(xs) - 1)]
    spans += [((xs[i], ys[-1]), (xs[i + 1], ys[-1])) for i in range(len(xs) - 1)]
    spans += [((xs[0], ys[j]), (xs[0], ys[j + 1])) for j in range(len(ys) - 1)]
    spans += [((xs[-1], ys[j]), (xs[-1], ys[j + 1])) for j in range(len(ys) - 1)]
    a, b = np.array([s[0] for s in spans]), np.array([s[1] for s in spans])
    for k in (3, 4):
        z = (k + 0.5) * STOREY
        level = t.group(clad, f"storey{k}")
        t.leaves(level, "panel", "box", members(np.c_[a, np.full(len(a), z)], np.c_[b, np.full(len(b), z)], (0.1, STOREY)),
                 width=2)
    return g


def boiler_unit(t: Tree, parent: str, name: str, matrix: np.ndarray, rng: np.random.Generator) -> str:
    """One boiler with everything around it, in a 20 m x 20 m bay with a stair tower and fan
    outside it on the east: the boiler (casing, buckstays, drum, downcomers, risers, burners),
    its support steel, platforms, pumps, heaters, coal mills and the unit's pipe runs."""
    g = t.group(parent, name, matrix)
    b = t.group(g, "boiler")
    t.leaf(b, "casing", "box", trs((0, 0, 26), s=(10, 10, 36)))
    t.leaf(b, "hopper", "box", trs((0, 0, 6), r=np.eye(3), s=(6, 6, 4)))
    t.leaf(b, "penthouse", "box", trs((0, 0, 46), s=(11, 11, 4)))
    stays = t.group(b, "buckstays")
    for k, z in enumerate(np.arange(10.0, 44.0, 3.0)):
        lv = t.group(stays, f"level{k:02d}", trs((0, 0, z)))
        ends = np.array([[-5.4, -5.4, 0], [5.4, -5.4, 0], [5.4, 5.4, 0], [-5.4, 5.4, 0]])
        t.leaves(lv, "stay", "ibeam", members(ends, np.roll(ends, -1, axis=0), (0.35, 0.5)), width=1)
    drum = t.group(b, "drum", trs((0, 0, 49)))
    lie = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    t.leaf(drum, "shell", "drum", trs((-6, 0, 1.0), lie, s=(1.0, 1.0, 12)))
    t.leaves(drum, "saddle", "box", placements([[-4, 0, 0], [4, 0, 0]], 0.0, (0.6, 1.8, 0.4)), width=1)
    down = t.group(b, "downcomers")
    xy = np.array([[-5.8, -4.0], [-5.8, 4.0], [5.8, -4.0], [5.8, 4.0]])
    t.leaves(down, "pipe", "pipe32", members(np.c_[xy, np.full(4, 8.0)], np.c_[xy, np.full(4, 49.0)], (0.5, 0.5)))
    risers = t.group(b, "risers")
    x = np.linspace(-4, 4, 6)
    t.leaves(risers, "pipe", "pipe16", members(np.c_[x, np.full(6, 5.5), np.full(6, 44.0)],
                                                 np.c_[x * 0.3, np.full(6, 0.8), np.full(6, 49.5)], (0.3, 0.3)))
    burners = t.group(b, "burners")
    for w, y in (("front", -5.0), ("rear", 5.0)):
        wall = t.group(burners, w, trs((0, y, 0), rot_z(0.0 if y < 0 else np.pi)))
        for k, (x, z) in enumerate([(x, z) for z in (14.0, 18.0) for x in (-3.0, 0.0, 3.0)]):
            bu = t.group(wall, f"burner{k}", trs((x, 0, z)))
            throat = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # the drum's axis (z) out along -y
            t.leaf(bu, "register", "drum", trs((0, 0, 0), throat, s=(0.6, 0.6, 1.0)))
            t.leaf(bu, "igniter", "pipe16", members([[0.5, -1.0, 0.4]], [[0.2, 0.0, 0.2]], (0.12, 0.12))[0])
            t.leaf(bu, "scanner", "pipe16", members([[-0.5, -1.0, 0.4]], [[-0.2, 0.0, 0.2]], (0.1, 0.1))[0])
    # support steel: a 3 x 3 grid of columns around the boiler
    xs = np.array([-9.0, 0.0, 9.0])
    steel = t.group(g, "steel")
    for k in range(6):
        steel_storey_light(t, steel, f"storey{k}", xs, k * STOREY, rng)
    plats = t.group(g, "platforms")
    for k, z in enumerate((8.0, 16.0, 24.0, 32.0, 40.0)):
        platform(t, plats, f"level{k}", z, 5.6, 1.4, rng)
    stair_tower(t, g, "stairs", trs((11.5, 1.0, 0), rot_z(np.pi / 2)), 5)
    pumps = t.group(g, "pumps")
    for k in range(4):
        pump_set(t, pumps, f"pump{k}", (-8.0, -6.0 + 4.0 * k, 0.3), np.radians(90 + rng.uniform(-40, 40)), 1.6, 0.1)
    heaters = t.group(g, "heaters")
    for k in range(2):
        horizontal_vessel(t, heaters, f"heater{k}", (-2.0 + 4.5 * k, 7.6, 0.0),
                          np.radians(rng.uniform(-20, 20)), 4.0, 0.7)
    mills = t.group(g, "mills")
    for k, x in enumerate((-3.5, 0.0, 3.5)):
        mill(t, mills, f"mill{k}", np.array([x, -7.6, 0.0]), rng)
    fan = t.group(g, "id_fan", trs((12.5, -7.5, 0.0), rot_z(np.radians(rng.uniform(20, 40)))))
    t.leaf(fan, "housing", "drum", trs((0, 1.2, 2.0), np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]), s=(2.0, 2.0, 2.4)))
    t.leaf(fan, "motor", "pump", trs((0, -2.2, 0), s=(2.0, 2.0, 2.0)))
    t.leaf(fan, "duct_in", "box", members([[0, 1.2, 4.0]], [[0, 1.2, 12.0]], (1.6, 1.6))[0])
    t.leaf(fan, "duct_out", "box", members([[0, 1.2, 12.0]], [[-3.0, 6.0, 20.0]], (1.6, 1.6))[0])
    tray = t.group(g, "cable_tray")
    z = np.arange(6) * STOREY
    foot = np.c_[np.full(6, -9.6), np.full(6, 9.6), z + 0.5]
    t.leaves(tray, "riser", "box", members(foot, foot + [0, 0, STOREY - 0.5], (0.6, 0.12)), width=1)
    t.leaves(tray, "branch", "box", members(foot[1:] + [0.4, 0, 0], foot[1:] + [9.0, 0, 0], (0.12, 0.6)), width=1)
    pipes = t.group(g, "pipes")
    lo, hi = np.array([-9.5, -9.5, 1.0]), np.array([9.5, 9.5, 47.0])
    for k in range(24):
        # start on a face of the boiler and wander through the bay
        face = k % 4
        u = rng.uniform(-4.0, 4.0)
        start = [(-6.0, u), (6.0, u), (u, -6.0), (u, 6.0)][face]
        start = np.array([start[0], start[1], rng.uniform(6.0, 44.0)])
        first = (1, 0, 3, 2)[face]  # away from the boiler
        pts = route(rng, start, lo, hi, int(rng.integers(4, 8)), first)
        if len(pts) < 3:
            pts = np.array([start, start + _AXES[first] * 2.5, start + _AXES[first] * 2.5 + [0, 0, 3.0]])
        # some runs are turned about their start: diagonal to the building, as field routing is
        yaw = 0.0 if rng.random() < 0.6 else np.radians(rng.uniform(15, 75))
        r = float(rng.choice([0.06, 0.1, 0.15, 0.25]))
        run = trs(start, rot_z(yaw)) @ trs(-start)
        pipe_run(t, pipes, f"run{k:02d}", run, pts, r, rng, spool=2, valves=int(rng.integers(0, 3)))
    return g


def mill(t: Tree, parent: str, name: str, at: np.ndarray, rng: np.random.Generator) -> str:
    """A coal pulveriser: body, classifier, drive, and the coal pipe up to its burner."""
    g = t.group(parent, name, trs(at))
    t.leaf(g, "body", "vessel", trs((0, 0, 0), s=(1.1, 1.1, 3.2)))
    t.leaf(g, "classifier", "drum", trs((0, 0, 3.1), s=(0.7, 0.7, 1.2)))
    drive = rng.uniform(-np.pi, 0.0)  # the drive sits on the side away from the boiler, at any angle
    t.leaf(g, "drive", "pump", trs(1.5 * np.array([np.cos(drive), np.sin(drive), 0.0]), rot_z(drive), s=1.4))
    # the coal pipe leaves the top, rises, and bends in toward its burner on the furnace wall
    pts = np.array([[0.0, 0.0, 4.3], [0.0, 0.0, 9.0], [0.0, 1.6, 9.0 + 1.6], [0.0, 1.6, 13.0]])
    pipe_run(t, g, "coal_pipe", np.eye(4), pts, 0.2, rng, spool=2, valves=0)
    return g


def steel_storey_light(t: Tree, parent: str, name: str, xs: np.ndarray, z0: float,
                       rng: np.random.Generator) -> str:
    """A storey of a boiler's support steel on the square grid ``xs`` x ``xs``, leaving out the
    middle column (the boiler stands there): columns, ring beams and one X-brace per face."""
    g = t.group(parent, name, trs((0, 0, z0)))
    grid = np.array([(x, y) for y in xs for x in xs if (x, y) != (0.0, 0.0)])
    cols = np.c_[grid, np.zeros(len(grid))]
    t.leaves(g, "column", "ibeam", members(cols, cols + [0, 0, STOREY], (0.45, 0.45)), width=1)
    ring = np.array([[xs[0], xs[0]], [xs[-1], xs[0]], [xs[-1], xs[-1]], [xs[0], xs[-1]]])
    top = np.c_[ring, np.full(4, STOREY - 0.3)]
    t.leaves(g, "beam", "ibeam", members(top, np.roll(top, -1, axis=0), (0.3, 0.6)), width=1)
    face = int(rng.integers(4))
    a, b = ring[face], ring[(face + 1) % 4]
    t.leaves(g, "brace", "box", members([[*a, 0.3], [*b, 0.3]], [[*b, STOREY - 0.6], [*a, STOREY - 0.6]], (0.22, 0.22)),
             width=1)
    return g


def tank_farm(t: Tree, parent: str, rng: np.random.Generator) -> str:
    """Storage tanks north of the hall: each a vertical vessel on a ring foundation, with a
    ladder, a roof vent and two nozzles."""
    g = t.group(parent, "tanks")
    for i, x in enumerate(np.arange(5) * 9.5 - 35.0):
        r = rng.uniform(2.6, 3.6)
        h = rng.uniform(7.0, 12.0)
        tk = t.group(g, f"tank{i}", trs((x, 35.0 + rng.uniform(-1, 1), 0.0), rot_z(rng.uniform(0, 2 * np.pi))))
        t.leaf(tk, "foundation", "pipe32", trs((0, 0, 0.2), s=(r + 0.4, r + 0.4, 0.4)))
        t.leaf(tk, "shell", "vessel", trs((0, 0, 0.4), s=(r, r, h)))
        t.leaf(tk, "ladder", "ladder", trs((r + 0.3, 0, 0.4), rot_z(np.pi / 2), s=(0.5, 0.3, h)))
        t.leaf(tk, "vent", "pipe16", members([[0, 0, h]], [[0, 0, h + 1.2]], (0.3, 0.3))[0])
        t.leaves(tk, "nozzle", "pipe16", members([[r - 0.2, 0, 1.0], [0, r - 0.2, 1.5]], [[r + 1.2, 0, 1.0], [0, r + 1.2, 1.5]],
                                                  (0.4, 0.4)), width=1)
    return g


def pipe_rack(t: Tree, parent: str, rng: np.random.Generator) -> str:
    """The pipe rack along the south edge, east of the stack: steel bents every 6 m carrying a
    bundle of long pipes that leave the rack to feed the units."""
    g = t.group(parent, "pipe_rack", trs((0, -35.0, 0)))
    bents = t.group(g, "bents")
    xs = np.arange(-26.0, 20.0, 6.0)
    for i, x in enumerate(xs):
        b = t.group(bents, f"bent{i:02d}", trs((x, 0, 0)))
        t.leaves(b, "column", "ibeam", members([[0, -2, 0], [0, 2, 0]], [[0, -2, 9], [0, 2, 9]], (0.3, 0.3)), width=1)
        t.leaves(b, "beam", "ibeam", members([[0, -2.2, 6], [0, -2.2, 9]], [[0, 2.2, 6], [0, 2.2, 9]], (0.25, 0.35)), width=1)
    pipes = t.group(g, "pipes")
    for k in range(14):
        z = 6.3 if k < 7 else 9.3
        y = -1.8 + 0.6 * (k % 7)
        x_end = 16.0 + 1.5 * (k % 7)
        # along the rack, then up or down and north into a unit's bay (a 45-degree leg for some)
        pts = [[-27.0, y, z], [x_end, y, z]]
        if k % 3 == 0:
            pts += [[x_end + 3.0, y + 3.0, z], [x_end + 3.0, y + 12.0, z]]
        else:
            pts += [[x_end, y, z + 4.0], [x_end, y + 10.0, z + 4.0]]
        pipe_run(t, pipes, f"line{k}", np.eye(4), np.array(pts), 0.12 + 0.04 * (k % 3), rng, spool=2, valves=1)
    return g


def stack(t: Tree, parent: str, rng: np.random.Generator) -> str:
    """The chimney south-west of the hall with its access platforms and ladder."""
    g = t.group(parent, "stack", trs((-32.0, -36.0, 0)))
    t.leaf(g, "shell", "stack", trs((0, 0, 0), s=(3.0, 3.0, 60.0)))
    plats = t.group(g, "platforms")
    for k, z in enumerate((20.0, 40.0, 58.0)):
        r = 3.0 * (1 - 0.3 * z / 60.0) + 1.2
        p = t.group(plats, f"level{k}", trs((0, 0, z)))
        t.leaf(p, "deck", "pipe32", trs((0, 0, 0), s=(r, r, 0.15)))
        t.leaf(p, "rail", "pipe32", trs((0, 0, 1.0), s=(r + 0.05, r + 0.05, 0.05)))
    t.leaf(g, "ladder", "ladder", trs((3.2, 0, 0), rot_z(np.pi / 2), s=(0.5, 0.3, 58.0)))
    return g


def conveyor(t: Tree, parent: str, rng: np.random.Generator) -> str:
    """The inclined coal conveyor gallery from the yard up into the bunker bay: truss sections
    (four chords and diagonals each), a walkway and a roof, on trestles. Turned and tilted, so
    none of its parts is axis-aligned."""
    start = np.array([-38.0, 39.0, 1.0])
    end = np.array([-10.0, 24.0, 24.0])
    d = end - start
    length = float(np.linalg.norm(d))
    yaw = float(np.arctan2(d[1], d[0]))
    pitch = float(np.arcsin(d[2] / length))
    c, s = np.cos(pitch), np.sin(pitch)
    tilt = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])  # local x climbs toward local z
    top = t.group(parent, "conveyor")
    g = t.group(top, "gallery", trs(start, rot_z(yaw) @ tilt))
    sections = 8
    seg = length / sections
    w, h = 2.4, 2.2
    for i in range(sections):
        sec = t.group(g, f"section{i}", trs((i * seg, 0, 0)))
        ys = np.array([-w / 2, w / 2, -w / 2, w / 2])
        zs = np.array([0.0, 0.0, h, h])
        t.leaves(sec, "chord", "box", members(np.c_[np.zeros(4), ys, zs], np.c_[np.full(4, seg), ys, zs], (0.15, 0.15)),
                 width=1)
        t.leaves(sec, "diagonal", "box", members([[0, -w / 2, 0], [0, w / 2, 0]], [[seg, -w / 2, h], [seg, w / 2, h]],
                                                  (0.12, 0.12)), width=1)
        t.leaf(sec, "walkway", "grating", trs((seg / 2, 0, 0.05), s=(seg, w, 0.1)))
        t.leaf(sec, "roof", "box", trs((seg / 2, 0, h + 0.1), s=(seg, w + 0.4, 0.05)))
    tr = t.group(top, "trestles")
    for i in range(1, 4):
        p = start + d * i / 4
        b = t.group(tr, f"trestle{i}", trs((p[0], p[1], 0), rot_z(yaw)))
        legs = np.array([[-0.8, -1.4, 0], [0.8, -1.4, 0], [-0.8, 1.4, 0], [0.8, 1.4, 0]])
        t.leaves(b, "leg", "ibeam", members(legs, legs * [0.5, 0.7, 0] + [0, 0, p[2] - 0.3], (0.3, 0.3)), width=1)
    return top
