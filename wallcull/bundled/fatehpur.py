"""A look-alike of the paper's Fatehpur Sikri model: a Mughal palace city in red sandstone.

Target shape (the paper, section 5): about 770 nodes, 288 internal + 482 leaves, average
branching 2.67, 1.6 M triangles, on a site about 300 m x 300 m with buildings up to about 50 m.

The low branching factor of the real model comes from architecture being nested small
assemblies: an arcade is bays, a bay is a pier and an arch; a chhatri (roof kiosk) is a base and a
canopy, the canopy an eave, a dome and a finial. The generator builds exactly such assemblies and
composes them into complexes laid out like the real site (the mosque in the south-west, the
palace courts north-east of it, the fort wall around all). Each complex is turned by a few degrees,
as the real city follows its ridge rather than a grid, so the complexes' boxes are not
axis-aligned in the world. Triangles concentrate where the real stone carving is: columns,
domes, pierced jali screens.

Coordinates are metres, z up, the site centred on the origin; the tree root turns z up into y up.
"""

from __future__ import annotations

import numpy as np

from .tree import Tree, placements, rot_z, trs

SITE = 300.0  # m, the side of the square site


def build(seed: int = 0) -> Tree:
    """The Fatehpur Sikri look-alike for ``seed`` (layout fixed, proportions and details vary)."""
    rng = np.random.default_rng(seed)
    t = Tree("fatehpur")
    root = t.root

    def place(x: float, y: float, spread: float = 4.0) -> np.ndarray:
        """A complex's frame: at (x, y) plus a little jitter, turned by a few degrees."""
        j = rng.uniform(-spread, spread, 2)
        return trs((x + j[0], y + j[1], 0.0), rot_z(np.radians(rng.uniform(-9.0, 9.0))))

    jama_masjid(t, root, place(-75, -65), rng)
    diwan_i_am(t, root, place(65, -75), rng)
    palace = t.group(root, "palace", place(20, 45, 2.0))
    diwan_i_khas(t, palace, trs((25, -30, 0)), rng)
    panch_mahal(t, palace, trs((-25, 5, 0)), rng)
    anup_talao(t, palace, trs((30, 10, 0)), rng)
    khwabgah(t, palace, trs((60, 45, 0)), rng)
    jodh_bai_palace(t, root, place(-80, 75), rng)
    birbal_house(t, root, place(-10, 120), rng)
    hiran_minar(t, root, place(115, 115), rng)
    fort_wall(t, root, rng)
    return t


# ---------------------------------------------------------------------------------------------
# small assemblies


def chhatri(t: Tree, parent: str, name: str, at, size: float, height: float, yaw: float = 0.0) -> str:
    """A domed roof kiosk: a plinth and four pillars, then a canopy of eave, dome and finial."""
    g = t.group(parent, name, trs(at, rot_z(yaw)))
    base = 0.25 * size
    b = t.group(g, "base")
    t.leaf(b, "plinth", "box", trs((0, 0, base / 2), s=(1.15 * size, 1.15 * size, base)))
    t.leaf(b, "pillars", "pillars", trs((0, 0, base), s=(size, size, height)))
    c = t.group(g, "canopy", trs((0, 0, base + height)))
    t.leaf(c, "chhajja", "chhajja", trs((0, 0, -0.2 * size), s=(1.4 * size, 1.4 * size, 0.3 * size)))
    r = 0.42 * size
    t.leaf(c, "dome", "small_dome", trs((0, 0, 0.1 * size), s=r))
    t.leaf(c, "finial", "finial", trs((0, 0, 0.1 * size + 1.7 * r), s=(0.12 * r, 0.12 * r, 0.5 * r)))
    return g


def domed_roof(t: Tree, parent: str, name: str, at, radius: float) -> str:
    """A dome on a drum with a finial: the crown of a hall or tomb."""
    g = t.group(parent, name, trs(at))
    drum = 0.35 * radius
    t.leaf(g, "drum", "pipe32", trs((0, 0, drum / 2), s=(1.05 * radius, 1.05 * radius, drum)))
    t.leaf(g, "dome", "onion_dome", trs((0, 0, drum), s=radius))
    t.leaf(g, "finial", "finial", trs((0, 0, drum + 1.68 * radius), s=(0.1 * radius, 0.1 * radius, 0.45 * radius)))
    return g


def arcade(t: Tree, parent: str, name: str, matrix: np.ndarray, bays: int, bay: float, height: float,
           depth: float, rng: np.random.Generator, kiosks: int = 0) -> str:
    """One side of a cloister: ``bays`` arched bays along +x facing -y, an end pier, the back
    wall at ``y = depth``, the roof, and optionally a row of chhatris on the roof.

    Bays (a pier and the arch after it) are grouped in spans of two, so a long arcade is a
    shallow binary-ish tree of compact groups rather than one wide flat group."""
    g = t.group(parent, name, matrix)
    pier_r = 0.09 * bay
    for j in range(0, bays, 2):
        span = t.group(g, f"span{j // 2:02d}", trs((j * bay, 0, 0)))
        for i in range(j, min(j + 2, bays)):
            b = t.group(span, f"bay{i:02d}", trs(((i - j) * bay, 0, 0)))
            t.leaf(b, "pier", "pier", trs((0, 0, 0), s=(pier_r, pier_r, height)))
            t.leaf(b, "arch", "arch", trs((bay / 2, 0, 0), s=(bay, 0.8, height)))
    length = bays * bay
    t.leaf(g, "end_pier", "pier", trs((length, 0, 0), s=(pier_r, pier_r, height)))
    t.leaf(g, "back_wall", "battlement", trs((length / 2, depth, 0), s=(length, 0.9, height * 1.25)))
    t.leaf(g, "roof", "box", trs((length / 2, depth / 2, height + 0.3), s=(length, depth, 0.6)))
    if kiosks:
        k = t.group(g, "chhatris")
        xs = (np.arange(kiosks) + 0.5) * length / kiosks
        size = min(3.0, 0.8 * length / kiosks)
        for i, x in enumerate(xs):
            chhatri(t, k, f"chhatri{i:02d}", (x, depth / 2, height + 0.6), size, 1.1 * size)
    return g


def cloister(t: Tree, parent: str, name: str, matrix: np.ndarray, width: float, length: float,
             height: float, depth: float, rng: np.random.Generator, open_side: str = "",
             kiosks: int = 0) -> str:
    """A courtyard ringed by arcades on its sides (``"s", "e", "n", "w"`` minus ``open_side``);
    the court is ``width`` (x) by ``length`` (y), centred on the group's origin."""
    g = t.group(parent, name, matrix)
    t.leaf(g, "court", "box", trs((0, 0, -0.25), s=(width + 2 * depth, length + 2 * depth, 0.5)))
    sides = {  # first pier and yaw of each arcade, so it runs along the side with arches inward
        "s": ((width / 2, -length / 2, 0), np.pi, width),
        "e": ((width / 2, length / 2, 0), -np.pi / 2, length),
        "n": ((-width / 2, length / 2, 0), 0.0, width),
        "w": ((-width / 2, -length / 2, 0), np.pi / 2, length),
    }
    for side, (origin, yaw, span) in sides.items():
        if side in open_side:
            continue
        bays = max(3, int(round(span / rng.uniform(10.5, 12.5))))
        arcade(t, g, f"arcade_{side}", trs(origin, rot_z(yaw)), bays, span / bays, height, depth, rng, kiosks)
    return g


def gateway(t: Tree, parent: str, name: str, matrix: np.ndarray, width: float, height: float,
            kiosks: int, rng: np.random.Generator) -> str:
    """A monumental gate: an iwan (one great arch) between two flanking wings, steps, and a row of
    chhatris along the parapet."""
    g = t.group(parent, name, matrix)
    t.leaf(g, "iwan", "arch", trs((0, 0, 0), s=(0.5 * width, 6.0, height)))
    for side, x in (("west_wing", -0.375 * width), ("east_wing", 0.375 * width)):
        w = t.group(g, side, trs((x, 0, 0)))
        t.leaf(w, "wall", "box", trs((0, 0, 0.4 * height), s=(0.25 * width, 6.0, 0.8 * height)))
        t.leaf(w, "niche", "arch", trs((0, -3.2, 0.2 * height), s=(0.2 * width, 0.5, 0.45 * height)))
    t.leaf(g, "steps", "steps", trs((0, -6.0, 0), rot_z(-np.pi / 2), s=(8.0, 0.4 * width, 0.12 * height)))
    if not kiosks:
        return g
    k = t.group(g, "chhatris")
    size = min(3.0, 0.9 * width / kiosks)
    for i, x in enumerate(np.linspace(-0.42 * width, 0.42 * width, kiosks)):
        chhatri(t, k, f"chhatri{i:02d}", (x, 0, height), size, 1.2 * size)
    return g


def tomb(t: Tree, parent: str, name: str, matrix: np.ndarray, size: float, rng: np.random.Generator,
         screens_per_side: int) -> str:
    """A square marble tomb: a plinth, jali screens on all four sides, a deep eave, a dome."""
    g = t.group(parent, name, matrix)
    h = 0.55 * size
    t.leaf(g, "plinth", "box", trs((0, 0, 0.5), s=(1.3 * size, 1.3 * size, 1.0)))
    screens = t.group(g, "screens")
    w = size / screens_per_side
    for s, yaw in enumerate((0.0, np.pi / 2, np.pi, -np.pi / 2)):
        side = t.group(screens, f"side{s}", trs((0, 0, 1.0), rot_z(yaw)))
        x = (np.arange(screens_per_side) + 0.5) * w - size / 2
        t.leaves(side, "jali", "jali", placements(np.c_[x, np.full_like(x, -size / 2), 0 * x],
                                                  0.0, (w, 0.25, h)))
    t.leaf(g, "chhajja", "chhajja", trs((0, 0, 1.0 + h - 0.3 * size * 0.5), s=(1.35 * size, 1.35 * size, 0.3 * size)))
    t.leaf(g, "roof", "box", trs((0, 0, 1.0 + h + 0.25), s=(size, size, 0.5)))
    domed_roof(t, g, "crown", (0, 0, 1.5 + h), 0.36 * size)
    return g


def hall(t: Tree, parent: str, name: str, matrix: np.ndarray, cols: int, rows: int, bay: float,
         height: float, rng: np.random.Generator, variant: int) -> str:
    """A hypostyle hall: a grid of carved columns in rows, a flat roof, a parapet eave."""
    g = t.group(parent, name, matrix)
    x = (np.arange(cols) - (cols - 1) / 2) * bay
    for r in range(rows):
        row = t.group(g, f"row{r}", trs((0, (r - (rows - 1) / 2) * bay, 0)))
        v = (variant + r + np.arange(cols)) % 6
        t.leaves(row, "column", [f"column{k}" for k in v],
                 placements(np.c_[x, 0 * x, 0 * x], 0.0, (0.14 * bay, 0.14 * bay, height)))
    span = (cols - 1) * bay + 1.2 * bay, (rows - 1) * bay + 1.2 * bay
    t.leaf(g, "roof", "box", trs((0, 0, height + 0.25), s=(span[0], span[1], 0.5)))
    t.leaf(g, "chhajja", "chhajja", trs((0, 0, height - 0.6), s=(span[0] + 1.5, span[1] + 1.5, 1.0)))
    return g


# ---------------------------------------------------------------------------------------------
# the complexes


def jama_masjid(t: Tree, parent: str, matrix: np.ndarray, rng: np.random.Generator) -> str:
    """The Friday mosque: a vast cloistered court, the prayer hall on its west side with three
    domes, the Buland Darwaza (the 50 m victory gate) on the south, the Badshahi gate on the east,
    and the tombs of Salim Chishti and Islam Khan in the court."""
    g = t.group(parent, "jama_masjid", matrix)
    court_w, court_l = 100.0, 80.0
    cloister(t, g, "cloister", trs((0, 0, 0)), court_w, court_l, 7.0, 7.0, rng, open_side="w", kiosks=2)
    hall_ = t.group(g, "prayer_hall", trs((-court_w / 2 - 10, 0, 0), rot_z(np.pi / 2)))
    t.leaf(hall_, "facade", "arch", trs((0, -8, 0), s=(16.0, 3.0, 24.0)))
    arcade(t, hall_, "aisle_south", trs((-35, -7, 0)), 3, 9.0, 12.0, 14.0, rng)
    arcade(t, hall_, "aisle_north", trs((8, -7, 0)), 3, 9.0, 12.0, 14.0, rng)
    domes = t.group(hall_, "domes")
    for i, (x, r) in enumerate(((-24, 5.5), (0, 8.0), (24, 5.5))):
        domed_roof(t, domes, f"dome{i}", (x, 0, 13.0 if r < 8 else 20.0), r)
    gateway(t, g, "buland_darwaza", trs((0, -court_l / 2 - 12, 0)), 36.0, 42.0, 5, rng)
    gateway(t, g, "badshahi_darwaza", trs((court_w / 2 + 9, 0, 0), rot_z(np.pi / 2)), 16.0, 16.0, 3, rng)
    tomb(t, g, "salim_chishti_tomb", trs((10, -10, 0)), 14.0, rng, 3)
    tomb(t, g, "islam_khan_tomb", trs((20, 25, 0), rot_z(np.pi / 2)), 16.0, rng, 2)
    return g


def diwan_i_am(t: Tree, parent: str, matrix: np.ndarray, rng: np.random.Generator) -> str:
    """The hall of public audience: a long cloistered court with the emperor's pavilion, its jali
    screens either side of the throne bay, in the middle of the west side."""
    g = t.group(parent, "diwan_i_am", matrix)
    cloister(t, g, "cloister", trs((0, 0, 0)), 80.0, 50.0, 6.0, 6.0, rng, open_side="w")
    p = t.group(g, "pavilion", trs((-34, 0, 0)))
    t.leaf(p, "plinth", "box", trs((0, 0, 0.75), s=(10, 16, 1.5)))
    hall(t, p, "hall", trs((0, 0, 1.5)), 3, 3, 4.0, 6.0, rng, variant=2)
    screens = t.group(p, "screens")
    t.leaves(screens, "jali", "jali", placements([[3.2, -5.0, 1.5], [3.2, 5.0, 1.5]], np.pi / 2, (4.0, 0.3, 5.0)))
    return g


def diwan_i_khas(t: Tree, parent: str, matrix: np.ndarray, rng: np.random.Generator) -> str:
    """The hall of private audience: a cube whose single carved central pillar carries the
    emperor's seat, with four chhatris on the roof corners."""
    g = t.group(parent, "diwan_i_khas", matrix)
    s, h = 16.0, 13.0
    walls = t.group(g, "walls")
    for i, yaw in enumerate((0.0, np.pi / 2, np.pi, -np.pi / 2)):
        t.leaf(walls, f"wall{i}", "arch", trs(rot_z(yaw) @ np.array([0, -s / 2, 0]), rot_z(yaw), s=(s, 0.8, h)))
    interior = t.group(g, "interior")
    t.leaf(interior, "pillar", "column3", trs((0, 0, 0), s=(1.2, 1.2, 0.5 * h)))
    t.leaf(interior, "capital", "chhajja", trs((0, 0, 0.45 * h), s=(3.5, 3.5, 1.5)))
    t.leaf(interior, "gallery", "box", trs((0, 0, 0.5 * h + 0.8), s=(s - 2, 1.2, 0.3)))
    t.leaf(g, "roof", "chhajja", trs((0, 0, h - 0.8), s=(s + 2, s + 2, 1.6)))
    k = t.group(g, "chhatris")
    c = 0.36 * s
    for i, (x, y) in enumerate(((-c, -c), (c, -c), (c, c), (-c, c))):
        chhatri(t, k, f"chhatri{i}", (x, y, h + 0.8), 3.2, 3.6)
    return g


def panch_mahal(t: Tree, parent: str, matrix: np.ndarray, rng: np.random.Generator) -> str:
    """The five-storeyed pavilion: open colonnaded floors stepping back as they rise, the top one
    a single chhatri. Its many differently carved columns are the densest geometry of the site."""
    g = t.group(parent, "panch_mahal", matrix)
    t.leaf(g, "plinth", "box", trs((0, 0, 0.5), s=(30, 24, 1.0)))
    grids = ((5, 3), (4, 3), (3, 2), (2, 2))
    bay, h, z = 4.2, 3.6, 1.0
    for k, (cols, rows) in enumerate(grids):
        storey = t.group(g, f"storey{k}", trs((0, 0, z)))
        hall(t, storey, "colonnade", trs((0, 0, 0)), cols, rows, bay - 0.3 * k, h - 0.2 * k, rng, variant=k)
        z += h - 0.2 * k + 0.5
    chhatri(t, g, "kiosk", (0, 0, z), 4.5, 3.5)
    return g


def anup_talao(t: Tree, parent: str, matrix: np.ndarray, rng: np.random.Generator) -> str:
    """The peerless pool: a square tank, a central platform reached by four causeways."""
    g = t.group(parent, "anup_talao", matrix)
    t.leaf(g, "tank", "box", trs((0, 0, -0.75), s=(29, 29, 1.5)))
    t.leaf(g, "platform", "box", trs((0, 0, 0.4), s=(9, 9, 0.8)))
    c = t.group(g, "causeways")
    for i, yaw in enumerate((0.0, np.pi / 2, np.pi, -np.pi / 2)):
        t.leaf(c, f"causeway{i}", "box", trs(rot_z(yaw) @ np.array([9.5, 0, 0.3]), rot_z(yaw), s=(10, 1.8, 0.6)))
    return g


def khwabgah(t: Tree, parent: str, matrix: np.ndarray, rng: np.random.Generator) -> str:
    """The emperor's sleeping quarters: a two-storey block with a pillared roof pavilion."""
    g = t.group(parent, "khwabgah", matrix)
    lower = t.group(g, "lower")
    t.leaf(lower, "block", "box", trs((0, 0, 4), s=(20, 14, 8)))
    t.leaves(lower, "arch", "arch", placements([[-5, -7.2, 0], [5, -7.2, 0]], 0.0, (6, 0.6, 6)))
    upper = t.group(g, "upper", trs((0, 0, 8)))
    t.leaf(upper, "room", "box", trs((0, 0, 2.5), s=(8, 8, 5)))
    t.leaf(upper, "chhajja", "chhajja", trs((0, 0, 4.0), s=(10, 10, 1.5)))
    chhatri(t, upper, "kiosk", (0, 0, 5.2), 4.0, 3.6)
    return g


def jodh_bai_palace(t: Tree, parent: str, matrix: np.ndarray, rng: np.random.Generator) -> str:
    """The largest palace: an inner court ringed by two-storey wings, galleries along the north
    and south ones, domed pavilions in the middle of each wing, and a gate on the east."""
    g = t.group(parent, "jodh_bai_palace", matrix)
    w = 60.0
    t.leaf(g, "court", "box", trs((0, 0, -0.25), s=(w + 12, w + 12, 0.5)))
    wings = t.group(g, "wings")
    for i, (name, yaw) in enumerate((("south", 0.0), ("east", np.pi / 2), ("north", np.pi), ("west", -np.pi / 2))):
        wing = t.group(wings, name, trs(rot_z(yaw) @ np.array([0, -w / 2, 0]), rot_z(yaw)))
        t.leaf(wing, "range", "battlement", trs((0, -3, 0), s=(w, 6, 9.0)))
        if name in ("south", "north"):  # the galleries face each other across the court
            arcade(t, wing, "gallery", trs((-w / 2 + 4, 0.5, 0)), 3, (w - 8) / 3, 4.5, 0.5, rng)
        pav = t.group(wing, "pavilion", trs((0, -3, 9.0)))
        t.leaf(pav, "room", "box", trs((0, 0, 2.0), s=(10, 8, 4)))
        domed_roof(t, pav, "crown", (0, 0, 4.0), 3.2)
    gateway(t, g, "gate", trs((w / 2 + 7, 0, 0), rot_z(np.pi / 2)), 12.0, 11.0, 2, rng)
    return g


def birbal_house(t: Tree, parent: str, matrix: np.ndarray, rng: np.random.Generator) -> str:
    """Birbal's house: four rooms in a square, two upper rooms crowned by ribbed domes."""
    g = t.group(parent, "birbal_house", matrix)
    rooms = t.group(g, "rooms")
    for i, (x, y) in enumerate(((-5, -5), (5, -5), (5, 5), (-5, 5))):
        r = t.group(rooms, f"room{i}", trs((x, y, 0)))
        t.leaf(r, "walls", "box", trs((0, 0, 3.5), s=(9.4, 9.4, 7)))
        t.leaf(r, "door", "arch", trs((0, -4.8, 0), s=(4, 0.4, 5)))
    up = t.group(g, "upper", trs((0, 0, 7)))
    for i, x in enumerate((-5, 5)):
        u = t.group(up, f"room{i}", trs((x, 0, 0)))
        t.leaf(u, "walls", "box", trs((0, 0, 2.5), s=(8, 8, 5)))
        t.leaf(u, "chhajja", "chhajja", trs((0, 0, 4.2), s=(10, 10, 1.4)))
        domed_roof(t, u, "crown", (0, 0, 5.0), 3.0)
    return g


def hiran_minar(t: Tree, parent: str, matrix: np.ndarray, rng: np.random.Generator) -> str:
    """The deer tower: an octagonal base, a tapering shaft studded with stone tusks, a kiosk."""
    g = t.group(parent, "hiran_minar", matrix)
    t.leaf(g, "base", "pier", trs((0, 0, 0), s=(5, 5, 4)))
    shaft = t.group(g, "shaft", trs((0, 0, 4)))
    t.leaf(shaft, "core", "stack", trs((0, 0, 0), s=(2.6, 2.6, 17)))
    rings = t.group(shaft, "tusks")
    z = np.linspace(1.5, 15.5, 6)
    r = 2.6 * (1 - 0.3 * z / 17)
    t.leaves(rings, "ring", "tusks", placements(np.c_[0 * z, 0 * z, z], np.radians(15) * np.arange(6), np.c_[r, r, r]))
    chhatri(t, g, "kiosk", (0, 0, 21), 3.0, 2.6)
    return g


def fort_wall(t: Tree, parent: str, rng: np.random.Generator) -> str:
    """The crenellated city wall around the site: four runs of wall between round bastions, with
    a gate in the middle of each run."""
    g = t.group(parent, "fort_wall")
    half = SITE / 2 - 5
    for s, (name, yaw) in enumerate((("south", 0.0), ("east", np.pi / 2), ("north", np.pi), ("west", -np.pi / 2))):
        run = t.group(g, name, trs(rot_z(yaw) @ np.array([0, -half, 0]), rot_z(yaw)))
        n = 4
        seg = 2 * half / n
        gate = n // 2
        h = 10.0 + rng.uniform(-1, 1, n)
        for i in range(n):
            x0 = -half + i * seg  # the bastion at the start of the curtain, the wall after it
            if i == gate:
                gateway(t, run, "gate", trs((x0 + seg / 2, 0, 0)), seg - 6, 14.0, 0, rng)
            c = t.group(run, f"curtain{i}", trs((x0, 0, 0)))
            t.leaf(c, "bastion", "pier", trs((0, 0, 0), s=(4.0, 4.0, 13.0)))
            if i != gate:
                t.leaf(c, "wall", "battlement", trs((seg / 2, 0, 0), s=(seg - 6, 4.0, h[i])))
    return g
