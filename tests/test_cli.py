"""The command line of SPEC section 6: outputs, and one-line errors with exit status 2."""

import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from wallcull.cli import main
from wallcull.occlude import PARTS
from wallcull.paths import camera_path
from wallcull.scene import load
from wallcull.wall import Frusta, Wall

WALL = json.dumps({"cols": 3, "rows": 2, "tile_size": [0.6, 0.34], "gap": [0.01, 0.01],
                   "distance": 2.0})
FRAME = json.dumps({"position": [0, 20, 300], "orientation": [1, 0, 0, 0]})


@pytest.fixture(scope="module")
def glb(tmp_path_factory):
    """A small scene file: two boxes, one left and one right of the view axis."""
    s = trimesh.Scene()
    for name, x in (("left", -3.0), ("right", 3.0)):
        m = np.eye(4)
        m[:3, 3] = [x, 0, -10]
        s.add_geometry(trimesh.creation.box(extents=[1, 1, 1]), node_name=name, geom_name=name,
                       transform=m)
    path = tmp_path_factory.mktemp("scenes") / "two.glb"
    s.export(path)
    return str(path)


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_cull_json_follows_the_spec(capsys, glb):
    frame = json.dumps({"position": [0, 0, 0], "orientation": [1, 0, 0, 0]})
    code, out, err = run(capsys, "cull", glb, "--wall", WALL, "--frame", frame, "--json")
    assert code == 0, err
    doc = json.loads(out)
    assert [(t["id"], t["row"], t["col"]) for t in doc["tiles"]] == \
        [(0, 0, 0), (1, 0, 1), (2, 0, 2), (3, 1, 0), (4, 1, 1), (5, 1, 2)]
    seen = {name for t in doc["tiles"] for name in t["visible"]}
    assert seen == {"left", "right"}
    # left box in the left column only, right box in the right column only
    assert all(("left" in t["visible"]) == (t["col"] == 0) for t in doc["tiles"])
    assert all(("right" in t["visible"]) == (t["col"] == 2) for t in doc["tiles"])
    assert doc["stats"]["method"] == "adaptive" and doc["stats"]["cull_ms"] > 0
    for tile in doc["tiles"]:  # fitted frusta (SPEC section 6): 4x4 row by row
        assert np.asarray(tile["view"]).shape == (4, 4) == np.asarray(tile["projection"]).shape
        assert 0.1 <= tile["near"] < tile["far"] <= 1000


def test_cull_files_and_text_output(capsys, glb, tmp_path):
    (tmp_path / "wall.json").write_text(WALL)
    (tmp_path / "frame.json").write_text(json.dumps({"position": [0, 0, 0],
                                                     "orientation": [1, 0, 0, 0]}))
    code, out, _ = run(capsys, "cull", glb, "--wall", str(tmp_path / "wall.json"), "--frame",
                       str(tmp_path / "frame.json"), "--method", "naive", "--bounds", "sphere",
                       "--leaves")
    assert code == 0
    assert "tile   0 (row 0, col 0): depth " in out and "1 leaves: left" in out.splitlines()[1]


@pytest.mark.parametrize("argv,message", [
    (["cull", "nowhere.glb", "--wall", WALL, "--frame", FRAME], "not found"),
    (["cull", "powerplant", "--wall", "{not json", "--frame", FRAME], "malformed JSON"),
    (["cull", "powerplant", "--wall", WALL, "--frame",
      '{"position": [0,0,0], "orientation": [1,0,0,0.5]}'], "unit quaternion"),
    (["cull", "powerplant", "--wall", WALL, "--frame",
      '{"position": [0,0,0], "orientation": [1,0,0,0], "eye": [0,0,-5]}'], "in front"),
    (["cull", "powerplant", "--wall", WALL.replace('"cols": 3', '"cols": 0'), "--frame", FRAME],
     "at least 1"),
    (["cull", "powerplant", "--wall", "missing.json", "--frame", FRAME], "not found"),
    (["cull", "powerplant", "--wall", WALL, "--frame", FRAME, "--method", "fast"], "invalid choice"),
    (["cull", "no_such_bundled_scene", "--wall", WALL, "--frame", FRAME], "unknown scene"),
    (["bench", "powerplant", "--wall", WALL, "--methods", "oh,magic"], "unknown method"),
    (["frobnicate"], "invalid choice"),
    (["cull", "powerplant", "--wall", "", "--frame", FRAME], "--wall is empty"),
    (["cull", "powerplant", "--wall", "scenes/TestScene.bin", "--frame", FRAME], "not text"),
    (["cull", "powerplant", "--wall", "examples", "--frame", FRAME], "cannot read --wall file"),
    (["cull", "powerplant", "--wall", WALL, "--frame", FRAME, "--settings", "examples"],
     "cannot read settings file"),
    (["cull", "powerplant", "--wall", WALL, "--frame", FRAME, "--settings",
      "scenes/TestScene.bin"], "malformed JSON"),
    (["bench", "powerplant", "--wall", WALL, "--methods", ","], "at least one method"),
    (["bench", "powerplant", "--wall", WALL, "--bounds", ","], "at least one bound type"),
    (["bench", "powerplant", "--wall", WALL, "--fit", "--shadow-fit", ","], "needs an effort"),
    (["bench", "powerplant", "--wall", WALL, "--stereo", "50"], "interpupillary distance"),
    (["bench", "powerplant", "--wall", WALL, "--stereo", "0"], "interpupillary distance"),
    (["bench", "powerplant", "--wall", WALL, "--frames", "3", "--accuracy", "5"],
     "0 to 3 frames"),
    (["bench", "powerplant", "--wall", WALL, "--accuracy", "-3"], "not -3"),
    (["bench", "powerplant", "--wall", WALL, "--branching", "0"], "branching must be at least 2"),
    (["walk", "scenes/TestScene.gltf", "--frames", "99999999999999999999"],
     "frames must be 1 to 10,000,000"),
    (["overdraw", "scenes/TestScene.gltf", "--visible-resolution", "10000000x10000000"],
     "each 1 to 16384"),
    (["serve", "--port", "99999"], "--port must be 0 to 65535"),
    (["serve", "--token", ""], "--token must not be empty"),
    (["serve", "--log-level", "bogus"], "invalid choice"),
    (["serve", "--scenes", "/nonexistent", "--state", "none"], "does not exist"),
])
def test_bad_input_exits_2_with_one_line(capsys, argv, message):
    code, out, err = run(capsys, *argv)
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("wallcull: error:") and message in err


def test_settings_that_are_no_object_or_say_null_are_handled(capsys, tmp_path):
    for text in ("[1, 2]", "[]", "null"):  # the last two used to be taken for no settings
        (tmp_path / "list.json").write_text(text)
        code, _, err = run(capsys, "cull", "scenes/TestScene.gltf", "--wall", WALL, "--frame",
                           FRAME, "--settings", str(tmp_path / "list.json"))
        assert code == 2 and "settings must be an object" in err, text
    (tmp_path / "null.json").write_text('{"up": null}')  # the default: +y
    code, out, err = run(capsys, "walk", "scenes/TestScene.gltf", "--frames", "2", "--settings",
                         str(tmp_path / "null.json"))
    assert code == 0, err


def test_an_unreachable_broker_is_a_one_line_error_in_bounded_time():
    """``serve --nats`` asks the broker before it starts: an absent one is refused with the
    reason, after at most the timeout (the server never starts, and never hangs)."""
    from wallcull.errors import InputError
    from wallcull.server.nats import check_broker

    with pytest.raises(InputError, match="cannot reach the NATS broker at nats://127.0.0.1:1"):
        check_broker("nats://127.0.0.1:1", timeout=1.0)


def test_real_process_exit_status_and_no_traceback(glb):
    bad = subprocess.run([sys.executable, "-m", "wallcull.cli", "cull", glb, "--wall", WALL,
                          "--frame", '{"position": [0,0,0], "orientation": [0,0,0,0]}'],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    good = subprocess.run([sys.executable, "-m", "wallcull.cli", "scenes"], capture_output=True,
                          text=True)
    assert good.returncode == 0 and "fatehpur" in good.stdout and "powerplant" in good.stdout


def test_bench_json_follows_the_spec(capsys, glb):
    code, out, err = run(capsys, "bench", glb, "--wall", WALL, "--frames", "6", "--json",
                         "--bounds", "obb,aabb", "--accuracy", "1")
    assert code == 0, err
    doc = json.loads(out)
    assert set(doc["methods"]) == {"naive", "oh", "fh", "adaptive"}
    for m in doc["methods"].values():
        assert 0 < m["median_ms"] <= m["p99_ms"]
    assert set(doc["by_bounds"]) == {"obb", "aabb"}
    acc = doc["accuracy"]
    assert all(0 <= v["rate"] <= 1 for k in ("obb", "aabb") for v in acc[k].values())


def test_bench_times_the_methods_in_turns(capsys, glb, monkeypatch):
    """The methods' frames interleave, a turn of frames each, so that a ratio between two of
    them is of the same minutes on a shared machine (they ran one after the other)."""
    from wallcull import bench

    log, real = [], bench.timing

    def logged(*args, **kwargs):
        inner = real(*args, **kwargs)
        while True:
            try:
                next(inner)
            except StopIteration as done:
                return done.value
            log.append(args[3])
            yield

    monkeypatch.setattr(bench, "timing", logged)
    monkeypatch.setattr(bench, "TURN", 3)
    code, out, err = run(capsys, "bench", glb, "--wall", WALL, "--frames", "8", "--json",
                         "--methods", "adaptive,oh")
    assert code == 0, err
    turns = ["adaptive"] * 3 + ["oh"] * 3
    assert log == turns + turns + ["adaptive"] * 2 + ["oh"] * 2
    assert json.loads(out)["adaptive_speedup_vs_oh"] > 0


def test_bench_refuses_a_negative_frame_count_for_what_it_is(capsys, glb):
    code, _, err = run(capsys, "bench", glb, "--wall", WALL, "--frames", "-5")
    assert code == 2 and "--frames must be at least 1, got -5" in err


def test_bench_builds_the_hierarchy_of_its_branching(capsys, tmp_path):
    """``bench --branching N`` times the tree of N, as ``cull`` culls it (it timed the default
    tree whatever N was)."""
    s = trimesh.Scene()
    for k in range(40):
        m = np.eye(4)
        m[:3, 3] = [2.0 * (k % 8), 2.0 * (k // 8), -10]
        s.add_geometry(trimesh.creation.box(extents=[1, 1, 1]), node_name=f"b{k}",
                       geom_name=f"b{k}", transform=m)
    s.export(tmp_path / "flat.glb")
    internal = {}
    for n in (2, 16):
        code, out, err = run(capsys, "bench", str(tmp_path / "flat.glb"), "--wall", WALL,
                             "--frames", "1", "--methods", "adaptive", "--json",
                             "--branching", str(n), "--clusters", "off")
        assert code == 0, err
        internal[n] = json.loads(out)["scene"]["internal"]
    assert internal[2] == load(str(tmp_path / "flat.glb"), branching=2,
                               clusters=None).stats["internal"]
    assert internal[2] > internal[16]


def test_bench_dynamic_reports_refit_times(capsys, glb):
    code, out, _ = run(capsys, "bench", glb, "--wall", WALL, "--frames", "4", "--json",
                       "--methods", "adaptive", "--moving", "1.0", "--refit", "aabb")
    assert code == 0
    m = json.loads(out)["methods"]["adaptive"]
    assert m["refit_median_ms"] > 0


@pytest.mark.parametrize("name", ["fatehpur", "powerplant"])
def test_orbit_keeps_the_whole_scene_in_view(name):
    scene = load(name)
    wall = Wall.from_dict({**json.loads(WALL), "far": 5000.0})
    pts = scene.leaf_points[0]
    for frame in camera_path("orbit", pts.min(0), pts.max(0), wall, 12):
        primary = Frusta.build(wall, frame).primary
        assert (pts @ primary[:, :3].T + primary[:, 3] >= 0).all()


def test_fly_path_is_inside_the_scene_box():
    scene = load("fatehpur")
    wall = Wall.from_dict(json.loads(WALL))
    pts = scene.leaf_points[0]
    lo, hi = pts.min(0), pts.max(0)
    for frame in camera_path("fly", lo, hi, wall, 16):
        assert (frame.position >= lo).all() and (frame.position <= hi).all()


def test_bench_times_the_occlusion_dial(capsys):
    """``bench --occlusion``: the occlude stage and the triangles drawn, beside the same frames
    without it; ``auto`` skips the frames whose camera is outside the scene (the orbit)."""
    wall = json.dumps({"cols": 2, "rows": 2, "tile_size": [0.6, 0.34], "gap": [0.0, 0.0],
                       "distance": 2.0})
    docs = {}
    for path, setting in (("fly", "off"), ("fly", "on"), ("orbit", "auto")):
        code, out, err = run(capsys, "bench", "powerplant", "--wall", wall, "--frames", "4",
                             "--methods", "adaptive", "--path", path, "--occlusion", setting,
                             "--json")
        assert code == 0, err
        docs[path, setting] = doc = json.loads(out)
        assert doc["occlusion"] == setting
        stages = doc["stages"]
        assert stages["total"]["median_ms"] >= stages["occlude"]["median_ms"]
    off, on = docs["fly", "off"], docs["fly", "on"]
    assert off["stages"]["occlude"]["median_ms"] == 0 < on["stages"]["occlude"]["median_ms"]
    assert (on["methods"]["adaptive"]["triangles_per_frame"]
            < off["methods"]["adaptive"]["triangles_per_frame"])
    assert docs["orbit", "auto"]["stages"]["occlude"]["p99_ms"] == 0  # outside: never run
    # what occlusion costs where it hides nothing: inside the plant it always hides something,
    # from outside (auto) it never runs
    assert on["methods"]["adaptive"]["nothing_hidden"] == {"frames": 0}
    assert docs["orbit", "auto"]["methods"]["adaptive"]["nothing_hidden"] == {"frames": 0}
    assert "nothing_hidden" not in off["methods"]["adaptive"]
    # where its time goes, part by part, on the frames it ran
    parts = on["methods"]["adaptive"]["occlude_parts_median_ms"]
    assert list(parts) == list(PARTS) and all(v >= 0 for v in parts.values())
    assert docs["orbit", "auto"]["methods"]["adaptive"]["occlude_parts_median_ms"] == {}


def test_bench_times_occlusion_where_it_hides_nothing(capsys, tmp_path):
    """A lone box hides nothing but its own back: every frame counts, and is timed."""
    trimesh.creation.box(extents=[1, 1, 1]).export(tmp_path / "box.glb")
    wall = json.dumps({"cols": 2, "rows": 2, "tile_size": [0.6, 0.34], "distance": 2.0})
    code, out, err = run(capsys, "bench", str(tmp_path / "box.glb"), "--wall", wall, "--frames",
                         "4", "--methods", "adaptive", "--occlusion", "on", "--json")
    assert code == 0, err
    idle = json.loads(out)["methods"]["adaptive"]["nothing_hidden"]
    assert idle["frames"] == 4 and idle["occlude_median_ms"] > 0


def test_running_out_of_memory_is_said_as_such(monkeypatch, capsys):
    """A job the machine cannot hold says so in one line, exit 1: it read as an internal
    error (a bug) with numpy's allocation message."""
    import wallcull.scene as scene_mod

    def short(*args, **kwargs):
        raise MemoryError("Unable to allocate 93.8 MiB for an array")

    monkeypatch.setattr(scene_mod, "prepare", short)
    assert main(["prepare", "fatehpur"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("wallcull: out of memory")
    assert "internal error" not in err and "ulimit -v" in err


def test_a_tiled_scene_has_one_spelling():
    """``powerplant*0200`` is ``powerplant*200``: one name, one prepared file (it built a
    second 1.2 GB file for the same scene)."""
    from wallcull.scene import Source

    assert Source.of("powerplant*0040") == Source.of("powerplant*40")
    assert Source.of("powerplant*0040").identity("auto", 8, "auto") == \
        Source.of("powerplant*40").identity("auto", 8, "auto")
