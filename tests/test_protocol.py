"""The wire (wallcull.protocol): Accept negotiation, codecs, and per-tile packets with deltas.

The property behind every packet test: a render node that applies every packet it receives,
in order, holds exactly the list (and, for moved leaves, the world transforms) that a full
packet of the same frame would give, however it joins, skips, acknowledges late, reconnects or
falls out of the server's history.
"""

from __future__ import annotations

import contextlib
import json
import math
import signal

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from wallcull import protocol
from wallcull.errors import InputError
from wallcull.protocol import MSGPACK, FrameRecord, History
from wallcull.scene import Scene
from wallcull.service import Walls
from wallcull.wall import Wall

from .randscene import look_at_frame, random_scene

I64 = np.int64


# --------------------------------------------------------------------------- a render node


class Holder:
    """What a render node keeps between packets: the lists of the frames whose acknowledgement
    it has not yet seen used as a base, and the world transforms of moved leaves.

    A delta against frame ``b`` tells the node that the server has ``b`` as the tile's base; the
    server's bases only grow, so every list older than ``b`` can go.
    """

    def __init__(self):
        self.lists: dict[int, np.ndarray] = {}
        self.parts: dict[int, dict] = {}  # frame -> leaf -> draw ranges
        self.transforms: dict[int, list] = {}
        self.current: np.ndarray | None = None
        self.frame = -1
        self.full = 0
        self.deltas = 0

    def reset(self) -> None:
        """A node that restarts: it holds nothing."""
        self.__init__()

    def take(self, pkt: dict) -> np.ndarray:
        base = pkt["base"]
        assert pkt["frame"] > self.frame, "packets must arrive in frame order"
        if base is None:
            held = held_parts = None
            self.full += 1
        else:
            assert base in self.lists, f"delta against frame {base}, which this node never held"
            held, held_parts = self.lists[base], self.parts[base]
            self.deltas += 1
            for k in [k for k in self.lists if k < base]:
                del self.lists[k], self.parts[k]
        out = protocol.apply(held, pkt)
        assert np.all(np.diff(out) > 0), "a list is sorted and has no repeats"
        self.lists[pkt["frame"]] = out
        self.parts[pkt["frame"]] = protocol.apply_parts(held_parts, pkt, out)
        assert set(self.parts[pkt["frame"]]) <= set(out.tolist()), "ranges of listed leaves"
        moved = pkt.get("transforms")
        if moved:
            assert len(moved["ids"]) == len(moved["matrices"])
            assert set(moved["ids"]) <= set(out.tolist()), "transforms only for listed leaves"
            for leaf, m in zip(moved["ids"], moved["matrices"]):
                assert len(m) == 16
                self.transforms[leaf] = m
        self.current, self.frame = out, pkt["frame"]
        return out

    def check_transforms(self, world: dict[int, np.ndarray]) -> None:
        """Every listed leaf that ever moved has its world transform as of this frame; no other
        listed leaf has one (it is at rest)."""
        for leaf in self.current.tolist():
            if leaf in world:
                assert leaf in self.transforms, f"moved leaf {leaf} has no transform"
                np.testing.assert_array_equal(np.asarray(self.transforms[leaf]).reshape(4, 4),
                                              world[leaf], err_msg=f"leaf {leaf}")
            else:
                assert leaf not in self.transforms, f"leaf {leaf} never moved"


def make_record(number: int, lists: list[np.ndarray], changed=(), world=None,
                parts: list[dict] | None = None) -> FrameRecord:
    """A FrameRecord by hand. ``world``: leaf -> 4x4, of the leaves ``changed`` at least;
    ``parts``: per tile, leaf -> its draw ranges ``(k, 2)`` (listed leaves only)."""
    world = world or {}
    start = np.zeros(len(lists) + 1, dtype=I64)
    np.cumsum([len(x) for x in lists], out=start[1:])
    changed = np.array(sorted(set(changed)), dtype=I64)
    changed_world = np.array([world[k] for k in changed.tolist()]).reshape(len(changed), 4, 4)
    record_parts = None
    if parts is not None:
        part_start = np.zeros(len(lists) + 1, I64)
        np.cumsum([len(p) for p in parts], out=part_start[1:])
        items = [(leaf, r) for p in parts for leaf, r in sorted(p.items())]
        range_start = np.zeros(len(items) + 1, I64)
        np.cumsum([len(r) for _, r in items], out=range_start[1:])
        record_parts = (part_start, np.array([leaf for leaf, _ in items], I64), range_start,
                        np.concatenate([r for _, r in items]).astype(I64) if items
                        else np.zeros((0, 2), I64))
    return FrameRecord(number, float(number), start,
                       np.concatenate(lists).astype(I64) if lists else np.zeros(0, I64),
                       [{"view": [[float(number)]], "tag": t} for t in range(len(lists))],
                       changed, changed_world, record_parts)


def random_parts(rng, lists: list[np.ndarray], share: float) -> list[dict]:
    """Draw ranges for a random ``share`` of each tile's leaves: sorted, apart, from a few
    fixed patterns (so that they often repeat from frame to frame)."""
    patterns = [np.array([[0, 4]]), np.array([[0, 2], [5, 3]]), np.array([[3, 9]]),
                np.array([[1, 1], [4, 1], [9, 2]])]
    return [{int(leaf): patterns[int(rng.integers(len(patterns)))]
             for leaf in tile if rng.random() < share} for tile in lists]


@contextlib.contextmanager
def hang_guard(seconds: int):
    """Fail instead of hanging forever (a watchdog, not a speed requirement)."""
    def fire(*_):
        raise AssertionError(f"still running after {seconds} s: a hang")
    old = signal.signal(signal.SIGALRM, fire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


# --------------------------------------------------------------------------- Accept


@pytest.mark.parametrize("accept,expected", [
    (None, False), ("", False), ("*/*", False), ("application/json", False),
    ("application/msgpack", True), ("application/x-msgpack", True),
    ("application/msgpack, application/json", True),  # equal q: the first listed wins
    ("application/json, application/msgpack", False),
    ("application/json;q=0.9, application/msgpack", True),
    ("application/msgpack;q=0.1, application/json", False),
    ("application/msgpack; q=0.5, */*; q=0.1", True),
    ("*/*;q=0.8, application/msgpack;q=0.9", True),
    ("text/html, application/msgpack;q=0.2", True),  # html is not on offer
    ("application/msgpack;q=0", False),  # q=0: not acceptable
    ("application/json;q=0, application/msgpack;q=0", False),
    ("APPLICATION/MSGPACK", True),  # media types are case-insensitive
    ("application/msgpack;q=nonsense", False),
    ("text/html", False),
])
def test_accept_negotiation(accept, expected):
    assert protocol.wants_msgpack(accept) is expected


OFFERED = ["application/msgpack", "application/x-msgpack", "application/json", "*/*",
           "application/*", "text/html", "image/png"]


@given(st.lists(st.tuples(st.sampled_from(OFFERED),
                          st.one_of(st.none(), st.sampled_from([0, 0.001, 0.1, 0.5, 0.9, 1]))),
                max_size=6))
@settings(max_examples=300, derandomize=True, deadline=None)
def test_accept_picks_the_highest_q_and_the_first_on_ties(entries):
    header = ", ".join(m if q is None else f"{m};q={q}" for m, q in entries)
    ranked = [(1.0 if q is None else q, -i, m) for i, (m, q) in enumerate(entries)
              if m in OFFERED[:5] and (1.0 if q is None else q) > 0]
    expected = bool(ranked) and max(ranked)[2] in OFFERED[:2]
    assert protocol.wants_msgpack(header) is expected


# --------------------------------------------------------------------------- codecs

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-2**63, 2**63 - 1)
    | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=8),
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=6), kids,
                                                              max_size=4),
    max_leaves=25)


@given(json_values, st.booleans())
@settings(max_examples=200, derandomize=True, deadline=None)
def test_codecs_round_trip(value, binary):
    data = protocol.encode(value, binary)
    assert isinstance(data, bytes)
    assert protocol.decode(data, binary) == value
    if not binary:
        json.loads(data)  # plain JSON, what any client parses


@given(st.binary(max_size=64), st.booleans())
@settings(max_examples=400, derandomize=True, deadline=None)
def test_decode_fails_only_with_input_error(data, binary):
    try:
        protocol.decode(data, binary)
    except InputError as exc:
        assert ("msgpack" if binary else "JSON") in str(exc)


MALFORMED = [
    (b"[" * 100_000, False), (b'{"a":' * 50_000, False),  # deeper than Python's recursion
    (b"\x91" * 100_000, True),
    (b"\x92\x01", True), (b"\xc1", True), (b"\x81\x01\x02", True), (b"\x01\x02", True),
    (b"", True), (b"", False), (b"\xff", False), (b"{]", False),
]


@pytest.mark.parametrize("data,binary", MALFORMED,
                         ids=[f"{'msgpack' if b else 'json'}-{d[:6]!r}-{len(d)}"
                              for d, b in MALFORMED])
def test_malformed_bodies_are_input_errors(data, binary):
    with pytest.raises(InputError, match="malformed"):
        protocol.decode(data, binary)


def test_json_refuses_nan_and_msgpack_carries_it():
    with pytest.raises(ValueError):
        protocol.encode({"x": math.nan}, False)
    with pytest.raises(ValueError):
        protocol.encode({"x": math.inf}, False)
    assert math.isnan(protocol.decode(protocol.encode({"x": math.nan}, True), True)["x"])
    assert MSGPACK == "application/msgpack"
    assert msgpack.unpackb(protocol.encode({"a": b"\x00\x01"}, True)) == {"a": b"\x00\x01"}


def test_rows_is_row_by_row():
    m = np.arange(16.0).reshape(4, 4)
    assert protocol.rows(m)[1] == [4.0, 5.0, 6.0, 7.0]


# --------------------------------------------------------------------------- History


def test_history_keeps_the_last_frames_in_order():
    h = History(3)
    assert h.latest == -1 and h.oldest == -1 and h.get(0) is None
    for n in (0, 1, 4, 9, 10):
        h.add(make_record(n, [np.array([n], dtype=I64)]))
    assert list(h.frames) == [4, 9, 10]
    assert (h.oldest, h.latest) == (4, 10)
    assert h.get(1) is None and h.get(9).number == 9


def test_changed_since_spans_held_frames_across_gaps_in_numbering():
    h = History(8)
    for n, moved in ((3, [1]), (7, [2, 5]), (2**40, [5, 9]), (2**52, [4])):
        h.add(make_record(n, [np.zeros(0, I64)], changed=moved,
                          world={k: np.eye(4) for k in moved}))
    with hang_guard(20):
        assert h.changed_since(3, 2**40).tolist() == [2, 5, 9]
        assert h.changed_since(7, 2**52).tolist() == [4, 5, 9]
        assert h.changed_since(2**52, 2**52).tolist() == []


def test_packet_shapes_full_and_delta():
    h = History(4)
    h.add(make_record(0, [np.array([1, 2, 3]), np.array([], dtype=I64)]))
    h.add(make_record(1, [np.array([2, 3, 7]), np.array([5])]))
    full = protocol.packet(h, 1, 0, None)
    assert full["base"] is None and full["visible"] == [2, 3, 7] and full["count"] == 3
    assert "added" not in full and "removed" not in full and "transforms" not in full
    assert full["tag"] == 0 and full["view"] == [[1.0]] and full["time"] == 1.0
    delta = protocol.packet(h, 1, 0, 0)
    assert delta["base"] == 0 and delta["added"] == [7] and delta["removed"] == [1]
    assert "visible" not in delta and delta["count"] == 3
    assert protocol.packet(h, 1, 1, 0)["added"] == [5]
    # no delta against itself, a later frame, or a frame the history does not hold
    for base in (1, 2, 99, -1):
        assert protocol.packet(h, 1, 0, base)["base"] is None
    json.dumps(delta, allow_nan=False)
    msgpack.packb(delta)


def test_apply_checks_what_it_is_given():
    pkt = {"frame": 3, "base": 2, "added": [4], "removed": [1], "count": 3}
    assert protocol.apply(np.array([1, 2, 3]), pkt).tolist() == [2, 3, 4]
    with pytest.raises(InputError, match="not held"):
        protocol.apply(None, pkt)
    with pytest.raises(InputError, match="does not add up"):
        protocol.apply(np.array([1, 2, 3, 9]), pkt)
    with pytest.raises(InputError, match="does not add up"):
        protocol.apply(None, {"frame": 3, "base": None, "visible": [1, 2], "count": 3})


# --------------------------------------------------------------------------- walkthroughs

client_behaviours = st.fixed_dictionaries({
    "join": st.integers(0, 40),  # the frame index the node starts at
    "fetch": st.sampled_from([1.0, 0.8, 0.4]),  # chance it takes a given frame
    "ack": st.sampled_from([1.0, 0.7, 0.3, 0.0]),  # chance it acknowledges a frame it took
    "delay": st.integers(0, 6),  # frames an acknowledgement takes to reach the server
    "full": st.sampled_from([0.0, 0.05]),  # chance it asks for a full list
    "restart": st.sampled_from([0.0, 0.03]),  # chance it restarts, losing everything
})


@given(
    leaves=st.integers(1, 40), tiles=st.integers(1, 3), frames=st.integers(1, 70),
    history=st.integers(2, 9), churn=st.sampled_from([0.0, 0.05, 0.3, 1.0]),
    moving=st.sampled_from([0.0, 0.1, 0.5]),
    steps=st.lists(st.sampled_from([1, 1, 1, 2, 7, 2**36]), min_size=70, max_size=70),
    clients=st.lists(client_behaviours, min_size=3, max_size=3),
    seed=st.integers(0, 2**32 - 1))
@settings(max_examples=250, derandomize=True, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
def test_applied_packets_hold_the_true_lists(leaves, tiles, frames, history, churn, moving,
                                             steps, clients, seed):
    """Random per-tile lists over many frames; nodes join late, skip frames, acknowledge
    late (so the base is older than the last frame they received), ask for full lists,
    restart, and fall out of the history."""
    rng = np.random.default_rng(seed)
    universe = np.sort(rng.choice(10 * leaves + 5, size=leaves, replace=False)).astype(I64)
    h = History(history)
    truth = [np.sort(rng.choice(universe, size=int(rng.integers(0, leaves + 1)),
                                replace=False)) for _ in range(tiles)]
    world: dict[int, np.ndarray] = {}
    parts = [{} for _ in range(tiles)]
    nodes = [Holder() for _ in range(tiles)]
    server_ack = [-1] * tiles
    since = [-1] * tiles  # first frame a restarted node received: deltas only from there on
    in_flight: list[tuple[int, int, int]] = []  # (due index, tile, frame)
    number = -1
    with hang_guard(10):
        for i in range(frames):
            number += steps[i]
            for t in range(tiles):
                flip = rng.random(leaves) < churn
                now = np.isin(universe, truth[t])
                truth[t] = universe[now ^ flip]
            changed = universe[rng.random(leaves) < moving]
            for leaf in changed.tolist():
                world[leaf] = rng.normal(size=(4, 4))
            if rng.random() < churn + 0.2:  # leaves drawn in part change less than the lists
                parts = random_parts(rng, truth, 0.4)
            parts = [{leaf: r for leaf, r in p.items() if leaf in set(t.tolist())}
                     for p, t in zip(parts, truth)]
            h.add(make_record(number, truth, changed, world, parts))
            for due, t, frame in [a for a in in_flight if a[0] <= i]:
                server_ack[t] = max(server_ack[t], frame)
            in_flight = [a for a in in_flight if a[0] > i]
            for t, (node, how) in enumerate(zip(nodes, clients[:tiles])):
                if i < how["join"] or rng.random() >= how["fetch"]:
                    continue
                if rng.random() < how["restart"]:
                    node.reset()
                    since[t] = -1
                wants_full = node.frame < 0 or rng.random() < how["full"]
                ack = server_ack[t]
                base = None if wants_full or ack < 0 or ack < since[t] else ack
                pkt = protocol.packet(h, number, t, base)
                # a delta whenever the base is still held; else a full list
                assert pkt["base"] == (base if base is not None and h.get(base) else None)
                held = node.take(pkt)
                if since[t] < 0:
                    since[t] = number
                np.testing.assert_array_equal(held, truth[t])
                got = node.parts[number]
                assert got.keys() == parts[t].keys()
                for leaf, r in parts[t].items():
                    np.testing.assert_array_equal(got[leaf], r)
                node.check_transforms(world)
                if rng.random() < how["ack"]:
                    in_flight.append((i + 1 + how["delay"], t, number))


def test_a_node_behind_the_history_gets_a_full_list():
    h = History(3)
    node = Holder()
    lists = [np.array([1, 2]), np.array([2, 3]), np.array([3]), np.array([1, 3]),
             np.array([4])]
    h.add(make_record(0, [lists[0]]))
    node.take(protocol.packet(h, 0, 0, None))
    for n in range(1, 5):
        h.add(make_record(n, [lists[n]]))
    pkt = protocol.packet(h, 4, 0, 0)  # acknowledged frame 0, which has left the history
    assert pkt["base"] is None and pkt["visible"] == [4]
    assert node.take(pkt).tolist() == [4]


def test_transforms_in_deltas_cover_added_and_moved_leaves_only():
    m = {k: np.full((4, 4), float(k)) for k in range(10)}
    h = History(8)
    h.add(make_record(0, [np.array([1, 2, 3])], changed=[1, 5], world={1: m[1], 5: m[5]}))
    # frame 1: leaf 5 (moved earlier, not listed before) enters; leaf 2 moves; 3 is unchanged
    w1 = {1: m[1], 5: m[5], 2: m[2] + 1}
    h.add(make_record(1, [np.array([1, 2, 3, 5])], changed=[2], world=w1))
    full = protocol.packet(h, 1, 0, None)
    assert full["transforms"]["ids"] == [1, 2, 5]
    delta = protocol.packet(h, 1, 0, 0)
    assert delta["transforms"]["ids"] == [2, 5]
    assert delta["transforms"]["matrices"][0] == (m[2] + 1).reshape(16).tolist()
    # frame 2: nothing moves, nothing enters: no transforms at all
    h.add(make_record(2, [np.array([1, 2, 3, 5])], world=w1))
    assert "transforms" not in protocol.packet(h, 2, 0, 1)
    # ...but against frame 0 the move of leaf 2 in frame 1 is still news
    assert protocol.packet(h, 2, 0, 0)["transforms"]["ids"] == [2, 5]


@pytest.mark.parametrize("seed", range(4))
def test_poses_at_every_held_frame_are_those_of_that_frame(seed):
    """History.poses against a reckoning of every frame's poses: leaves moved at random, some
    often, some once long ago, numbers that skip; asked at every held frame, for all leaves."""
    rng = np.random.default_rng(seed)
    h = History(int(rng.integers(1, 6)))
    universe = np.arange(0, 300, 3, dtype=I64)
    world: dict[int, np.ndarray] = {}
    at: dict[int, dict[int, np.ndarray]] = {}
    number = -1
    for i in range(60):
        number += int(rng.choice([1, 1, 2, 9]))
        share = rng.choice([0.0, 0.02, 0.3])
        changed = universe[rng.random(len(universe)) < share]
        for leaf in changed.tolist():
            world[leaf] = rng.normal(size=(4, 4))
        at[number] = dict(world)
        h.add(make_record(number, [universe], changed, world))
        for n, record in h.frames.items():
            ids, got = h.poses(record, universe)
            assert ids.tolist() == sorted(at[n]), (i, n)
            for leaf, m in zip(ids.tolist(), got):
                np.testing.assert_array_equal(m, at[n][leaf])
        assert h.dynamic(record) == bool(world)


# --------------------------------------------------------------------------- WallSession


def small_scene(seed: int) -> Scene:
    return Scene.from_trimesh(random_scene(seed, leaves=14), name=f"rand{seed}")


@given(seed=st.integers(0, 2**16), frames=st.integers(1, 30), history=st.integers(2, 6),
       clients=st.lists(client_behaviours, min_size=4, max_size=4))
@settings(max_examples=25, derandomize=True, deadline=None,
          suppress_health_check=[HealthCheck.too_slow])
def test_wall_session_walkthrough_with_moving_nodes(seed, frames, history, clients):
    """Through service.WallSession: frames with node updates, per-tile acknowledgements, full
    requests and restarts. Lists equal an independent Session moved the same way, and every
    node holds the moved leaves' world transforms of that frame."""
    rng = np.random.default_rng(seed)
    scene = small_scene(seed % 7)
    wall = Wall.from_dict({"cols": 2, "rows": 2, "tile_size": [0.6, 0.4], "gap": [0.02, 0.0],
                           "distance": 1.5, "far": 200.0})
    walls = Walls()
    server = walls.create(scene, wall, "adaptive", "obb", False, history)
    replica = walls.create(scene, wall, "adaptive", "obb", False, 2).session
    movable = [n for i, n in enumerate(scene.names) if i > 0 and not scene.synthetic[i]]
    nodes = [Holder() for _ in range(wall.tiles)]
    since = [-1] * wall.tiles
    in_flight: list[tuple[int, int, int]] = []
    ever_moved: set[int] = set()
    center = scene.leaf_points[0].mean(axis=0)
    for i in range(frames):
        updates = {}
        for name in rng.choice(movable, size=int(rng.integers(0, 4)), replace=False):
            q = rng.normal(size=4)
            upd = {"position": (rng.normal(size=3) * 3).tolist(),
                   "orientation": (q / np.linalg.norm(q)).tolist()}
            if rng.random() < 0.2:
                upd["scale"] = rng.uniform(0.5, 2.0, 3).tolist()
            updates[str(name)] = upd
        frame = look_at_frame(rng, center, float(rng.uniform(6, 20)), wall.to_dict())
        refit = str(rng.choice(["obb", "aabb"])) if updates and rng.random() < 0.3 else None
        number, _ = server.post_frame(frame, updates, refit=refit)
        assert number == i
        replica.move(updates, refit)
        start, leaves = replica.frame(frame).visibility.leaf_lists()
        ever_moved.update(server.history.get(number).changed.tolist())
        world = {leaf: replica.state.world[leaf] for leaf in ever_moved}
        for due, t, f in [a for a in in_flight if a[0] <= i]:
            server.ack(t, f)
        in_flight = [a for a in in_flight if a[0] > i]
        for t, (node, how) in enumerate(zip(nodes, clients)):
            if i < how["join"] % 8 or rng.random() >= how["fetch"]:
                continue
            if rng.random() < how["restart"]:
                node.reset()
                since[t] = -1
            full = node.frame < 0 or rng.random() < how["full"]
            pkt = server.packet(t, number, full, since[t])
            node.take(pkt)
            if since[t] < 0:
                since[t] = number
            np.testing.assert_array_equal(node.current, leaves[start[t]:start[t + 1]])
            node.check_transforms(world)
            if rng.random() < how["ack"]:
                in_flight.append((i + how["delay"] % 3, t, number))


def test_a_rejected_frame_moves_nothing():
    """Updates and a bad frame in one request: the request is refused as a whole, so the next
    frame's lists and transforms are those of a scene that never moved."""
    scene = small_scene(3)
    wall = Wall.from_dict({"cols": 2, "rows": 1, "tile_size": [0.6, 0.4], "distance": 1.5})
    walls = Walls()
    server = walls.create(scene, wall, "adaptive", "obb", False, 8)
    replica = walls.create(scene, wall, "adaptive", "obb", False, 2).session
    rng = np.random.default_rng(0)
    frame = look_at_frame(rng, scene.leaf_points[0].mean(axis=0), 10.0, wall.to_dict())
    leaf = scene.names[int(scene.leaves[0])]
    far_away = {leaf: {"position": [1e4, 0, 0], "orientation": [1, 0, 0, 0]}}
    behind = dict(frame, eye=[0.0, 0.0, -5.0])
    with pytest.raises(InputError, match="in front of the wall"):
        server.post_frame(behind, far_away)
    with pytest.raises(InputError, match="unit quaternion"):
        server.post_frame(dict(frame, orientation=[1.0, 1.0, 0.0, 0.0]), far_away)
    assert server.latest == -1
    number, _ = server.post_frame(frame)
    start, leaves = replica.frame(frame).visibility.leaf_lists()
    pkt = server.packet(0, number)
    assert pkt["visible"] == leaves[start[0]:start[1]].tolist() and "transforms" not in pkt
    np.testing.assert_array_equal(server.session.state.world, replica.state.world)


def test_a_frame_record_keeps_the_transforms_of_its_own_moves_only():
    """A frame's record holds the world transforms of the leaves moved in that frame, not of
    every leaf moved before it (at a million nodes that grew to 6.4 GB a wall). Full packets
    and node messages still carry every moved leaf of their lists, at their frame's pose, also
    once the frames that moved them have left the history, and for a held frame older than a
    later move of the same leaf."""
    scene = small_scene(4)
    wall = Wall.from_dict({"cols": 2, "rows": 1, "tile_size": [0.6, 0.4], "distance": 1.5})
    walls = Walls()
    server = walls.create(scene, wall, "adaptive", "obb", False, 3)
    replica = walls.create(scene, wall, "adaptive", "obb", False, 2).session
    frame = look_at_frame(np.random.default_rng(1), scene.leaf_points[0].mean(axis=0), 40.0,
                          wall.to_dict())
    leaves = [int(i) for i in scene.leaves[:5]]
    moves = [[0], [1], [2, 3], [], [4], [], [0], [], [1]]  # leaves moved in each frame
    poses, ever, seen = {}, set(), set()
    for number, which in enumerate(moves):
        updates = {}
        for k in which:
            m = scene.local[leaves[k]].copy()
            m[:3, 3] += 0.05 * (number + 1)
            updates[scene.names[leaves[k]]] = m
        assert server.post_frame(frame, updates)[0] == number
        replica.move(updates)
        moved = set(scene.subtree_leaves(np.array(
            [scene.index[n] for n in updates], np.int64)).tolist()) if updates else set()
        ever |= moved
        poses[number] = {leaf: replica.state.world[leaf].copy() for leaf in ever}
        record = server.history.get(number)
        kept = sum(len(a) for a in vars(record).values()
                   if isinstance(a, np.ndarray) and a.shape[1:] == (4, 4))
        assert kept == len(moved), (number, kept, len(moved))
        for held in list(server.history.frames):  # every held frame, at its own pose
            for t in range(wall.tiles):
                node = Holder()
                node.take(server.packet(t, held, full=True))
                node.check_transforms(poses[held])
                seen |= set(node.transforms) & ever
            message = msgpack.unpackb(server.node_message(np.arange(wall.tiles), held,
                                                          full=True)[0], strict_map_key=False)
            lists = set().union(*(server.history.get(held).tile(t).tolist()
                                  for t in range(wall.tiles)))
            want = sorted(lists & set(poses[held]))
            got = message.get("transforms", {"ids": [], "matrices": []})
            assert got["ids"] == want
            for leaf, m in zip(got["ids"], got["matrices"]):
                assert m == poses[held][leaf].reshape(16).tolist()
    assert seen == ever  # the view showed every leaf that moved


@settings(max_examples=300, deadline=None)
@given(st.sets(st.integers(0, 80)), st.sets(st.integers(0, 80)), st.sets(st.integers(0, 80)))
def test_a_delta_is_applied_as_set_operations_would(held, removed, added):
    """The compiled merge a node applies a delta with equals numpy's set operations, also for
    ids removed that it does not hold and ids added that it holds."""
    from wallcull.protocol import _apply_delta

    def arr(values):
        return np.array(sorted(values), dtype=np.int64)

    want = np.union1d(np.setdiff1d(arr(held), arr(removed), assume_unique=True), arr(added))
    assert np.array_equal(_apply_delta(arr(held), arr(removed), arr(added)), want)


@settings(max_examples=200, deadline=None)
@given(ids=st.lists(st.integers(0, 60), max_size=12),
       leaves=st.lists(st.integers(0, 60), max_size=40), shuffled=st.booleans())
def test_which_held_leaves_are_still_listed_is_what_isin_says(ids, leaves, shuffled):
    """A node keeps a partial leaf's ranges when the tile still lists the leaf: found by binary
    search in the (sorted) list, or by ``np.isin`` when a list is not sorted."""
    leaves = np.array(sorted(set(leaves)) if not shuffled else leaves, np.int64)
    assert np.array_equal(protocol._listed(ids, leaves), np.isin(ids, leaves))
