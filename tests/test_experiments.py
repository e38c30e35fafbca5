"""``wallcull experiment``: every experiment's quick version runs, and its output has the shape
and the invariants the report relies on."""

import json
import re

import numpy as np
import pytest

from wallcull import bench
from wallcull import experiments as E
from wallcull.bounds import KINDS
from wallcull.cli import main
from wallcull.cull import METHODS
from wallcull.experiments import common as C
from wallcull.experiments import fig5
from wallcull.pipeline import Session

pytest.importorskip("matplotlib")

PNG = b"\x89PNG\r\n\x1a\n"


def check_output(out, name: str, result: dict) -> dict:
    """The files of one run: JSON, PNGs, markdown that shows every PNG."""
    on_disk = json.loads((out / f"{name}.json").read_text())
    assert on_disk["experiment"] == name and on_disk["quick"] is True
    assert set(on_disk) >= {"seed", "wall_clock_s", "command", "machine", "plots", "results"}
    assert on_disk["wall_clock_s"] > 0
    assert on_disk["plots"], "every experiment draws something"
    md = (out / f"{name}.md").read_text()
    assert md.startswith("## ")
    for png in on_disk["plots"]:
        data = (out / png).read_bytes()
        assert data[:8] == PNG and len(data) > 5000, png
        assert f"]({png})" in md, f"{name}.md does not show {png}"
    assert f"({name}.json)" in md and "wallcull experiment" in md
    assert result["results"].keys() == on_disk["results"].keys()
    return on_disk["results"]


def check_times(summary: dict) -> None:
    assert 0 < summary["min_ms"] <= summary["median_ms"] <= summary["max_ms"]
    assert summary["median_ms"] <= summary["p99_ms"] <= summary["max_ms"]
    assert summary["tests_per_frame"] > 0 and summary["frames"] > 0


def check_accuracy(by_method: dict) -> None:
    """Same bounds: naive and oh report the same leaves; fh reports among them, adaptive at
    least fh's (it lists a leaf's small clusters whole: wallcull.cull.FINE)."""
    acc = {m: r["accuracy"] for m, r in by_method.items()}
    for key in ("false_positives", "reported", "geometry_bytes_per_frame"):
        assert acc["naive"][key] == acc["oh"][key], key
    assert acc["fh"]["reported"] <= acc["naive"]["reported"]
    assert acc["fh"]["false_positives"] <= acc["naive"]["false_positives"]
    assert acc["fh"]["reported"] <= acc["adaptive"]["reported"]
    assert acc["fh"]["false_positives"] <= acc["adaptive"]["false_positives"]
    for a in acc.values():
        assert 0 <= a["false_positives"] <= a["reported"] and 0 <= a["rate"] <= 1
        assert a["packet_bytes_per_frame"] == a["false_positives"] * C.ID_BYTES / a["frames"]
        assert (a["geometry_bytes_per_frame"] > 0) == (a["false_positives"] > 0)


@pytest.fixture(scope="module")
def out(tmp_path_factory):
    return tmp_path_factory.mktemp("experiments")


def test_fig4(out):
    # through the command line, as a user runs it
    assert main(["experiment", "fig4", "--quick", "--out", str(out), "--seed", "3"]) == 0
    res = check_output(out, "fig4", json.loads((out / "fig4.json").read_text()))
    assert json.loads((out / "fig4.json").read_text())["seed"] == 3
    assert set(res["scenes"]) == {"fatehpur", "powerplant"}
    for entry in res["scenes"].values():
        assert set(entry["methods"]) == set(METHODS) == set(entry["series"])
        for m in METHODS:
            check_times(entry["methods"][m])
            assert len(entry["series"][m]["cull_ms"]) == res["frames"]
            assert min(entry["series"][m]["cull_ms"]) > 0
        assert sum(entry["fastest_share"].values()) == pytest.approx(1)
        # the lists are the method's, the tests differ: naive tests the most
        assert entry["methods"]["naive"]["tests_per_frame"] >= max(
            entry["methods"][m]["tests_per_frame"] for m in METHODS)


def test_fig5(out):
    result = E.run("fig5", out, quick=True, progress=False)
    res = check_output(out, "fig5", result)
    for entry in res["scenes"].values():
        assert set(entry["families"]) == {"fixed", "growing"}
        for family in entry["families"].values():
            walls = family["walls"]
            assert [(w["cols"], w["rows"]) for w in walls] == list(fig5.QUICK_WALLS)
            for w in walls:
                assert w["tiles"] == w["cols"] * w["rows"]
                for m in METHODS:
                    check_times(w["methods"][m])
    # the fixed family keeps the wall's size; the growing one keeps the tile's
    fixed = res["scenes"]["powerplant"]["families"]["fixed"]["walls"]
    growing = res["scenes"]["powerplant"]["families"]["growing"]["walls"]
    assert np.allclose([w["wall_size"] for w in fixed], C.FIXED_SIZE)
    assert np.allclose([w["tile_size"] for w in growing], C.SPEC_TILE)
    # one tile: every method makes the same first-level tests
    one = next(w for w in fixed if w["tiles"] == 1)
    assert len({one["methods"][m]["tests_per_frame"] for m in METHODS}) == 1


def test_fig6(out):
    result = E.run("fig6", out, quick=True, progress=False)
    res = check_output(out, "fig6", result)
    rows = res["rows"]
    assert {(r["fraction"], r["refit"]) for r in rows if r["fraction"]} == {
        (f, refit) for f in (0.1, 1.0) for refit in ("obb", "aabb")}
    for r in rows:
        check_times(r)
        a = r["accuracy"]
        assert 0 <= a["false_positives"] <= a["reported"]
        if r["fraction"]:
            assert r["moving"] > 0 and r["update"]["median_ms"] > 0
        else:
            assert r["moving"] == 0 and "update" not in r
    # axis-aligned refits are never tighter than the moved eigenvector OBBs, on the same poses
    by = {(r["fraction"], r["refit"]): r for r in rows}
    assert by[(1.0, "aabb")]["accuracy"]["reported"] >= by[(1.0, "obb")]["accuracy"]["reported"]
    d = res["drift"]
    assert d["obb"]["volume_ratio_mean"] == pytest.approx(1, rel=1e-6)


def test_bounds(out):
    result = E.run("bounds", out, quick=True, progress=False)
    res = check_output(out, "bounds", result)
    for entry in res["scenes"].values():
        assert set(entry["kinds"]) == set(KINDS)
        for kind, v in entry["kinds"].items():
            assert v["preprocess"]["bounds_s"] > 0
            assert set(v["methods"]) == set(METHODS)
            for r in v["methods"].values():
                check_times(r)
            check_accuracy(v["methods"])
        # the front is non-empty, and nothing off it beats a point on it in both
        front = entry["pareto"]
        assert front
        points = [(r["median_ms"], r["accuracy"]["rate"]) for v in entry["kinds"].values()
                  for r in v["methods"].values()]
        for p in front:
            assert not any(t < p["median_ms"] and f < p["rate"] for t, f in points)


def test_frusta(out):
    result = E.run("frusta", out, quick=True, progress=False)
    r = check_output(out, "frusta", result)
    q = r["quads"]
    assert 1 <= q["refined_over_best"]["max"] <= q["greedy_over_best"]["max"] + 1e-9
    assert q["refined_over_best"]["median"] <= q["greedy_over_best"]["median"] + 1e-12
    assert all(v["refined_over_greedy"] <= 1 + 1e-12 for v in q["large"].values())
    f = r["frusta"]["summary"]
    assert f["refined"]["coverage"]["min"] >= f["symmetric"]["coverage"]["min"]
    assert 0 < f["refined"]["coverage"]["median"] <= 1 and f["refined"]["ms"]["median"] > 0
    for v in r["depth"].values():  # a fitted range is never wider than the wall's
        assert max(v["samples"]) <= v["wall_bits"] + 1e-9 and v["gained_mean"] >= 0


def test_frame(out):
    result = E.run("frame", out, quick=True, progress=False)
    r = check_output(out, "frame", result)
    assert len(r["stages"]) == 9
    for s in r["stages"].values():  # the total is the sum of the stages, frame by frame, so
        # its median is at least each stage's (and how much more depends on the machine's load)
        parts = max(s[k]["median_ms"] for k in ("cull", "leaves", "fit", "encode"))
        assert 0 < parts <= s["total"]["median_ms"] and s["packet_bytes_per_frame"] > 0
    lit, plain = r["stages"]["8x8 / lamp + mirror"], r["stages"]["8x8 / none"]
    assert lit["packet_bytes_per_frame"] > plain["packet_bytes_per_frame"]  # shadows, mirrors
    for per in r["efforts"].values():  # the dial: the quads fill more of the shadow map
        assert per["refined"]["coverage_mean"] >= per["sphere"]["coverage_mean"]
        assert per["greedy"]["coverage_mean"] > per["sphere"]["coverage_mean"]


def test_walls(out):
    result = E.run("walls", out, quick=True, progress=False)
    r = check_output(out, "walls", result)
    assert set(r["walls"]) == {"8 x 8 grid", "angled, 3 panels", "CAVE + floor, 5",
                               "CAVE2-like, 72"}
    for w in r["walls"].values():
        for eyes in ("mono", "stereo"):
            per = w[eyes]
            assert per["adaptive"]["nodes_per_frame"] > 0
            assert per["fh"]["tests_per_frame"] > 0
        # two eyes see at least what one does (the same frames, the eyes about the head)
        assert w["stereo"]["fh"]["tests_per_frame"] >= w["mono"]["fh"]["tests_per_frame"]
    cave2 = r["walls"]["CAVE2-like, 72"]["mono"]
    assert cave2["adaptive"]["tests_per_frame"] < cave2["oh"]["tests_per_frame"]


def test_clusters(out):
    result = E.run("clusters", out, quick=True, progress=False)
    r = check_output(out, "clusters", result)
    assert {"powerplant", "fatehpur", "sportsCar", "FM1_satellite"} <= set(r["scenes"])
    for paths in r["scenes"].values():
        for s in paths.values():
            by = {e["clusters"]: e for e in s["settings"] if not e["occlusion"]}
            assert set(by) == {"off", *r["sizes"]}
            # nothing below the floor (the culler is conservative), nothing above no culling
            assert all(s["none"] >= e["triangles"] >= s["floor"] for e in by.values())
    sats = {e["clusters"]: e for e in r["scenes"]["FM1_satellite"]["fly"]["settings"]
            if not e["occlusion"]}
    assert sats[min(r["sizes"])]["triangles"] < sats["off"]["triangles"] / 3  # they bite
    md = (out / "clusters.md").read_text()
    assert "<= 1.5" in md and "wallcull overdraw" in md


def test_oracle_bookkeeping_matches_bench_accuracy():
    """The experiments' memoized oracle counts what ``wallcull.bench.accuracy`` counts."""
    scene = C.Pristine("fatehpur").fresh()
    wall = C.spec_wall(2, 2)
    frames = C.path_frames(scene, wall, "orbit", 4)
    expected = bench.accuracy(scene, wall, frames[1:2], ["naive", "adaptive"], ["sphere"])
    oracle = C.Oracle(scene, wall)
    for method in ("naive", "adaptive"):
        part = oracle.false_pairs(1, frames[1], C.leaf_pairs(Session(scene, wall, method, "sphere"),
                                                            frames[1]))
        want = expected["sphere"][method]
        assert (part["false_positives"], part["reported"]) == (want["false_positives"],
                                                             want["reported"])


def test_real(out):
    result = E.run("real", out, quick=True, progress=False)
    if not result["results"]["scenes"]:  # (the case without scenes is tested below)
        pytest.skip(f"no third-party scenes in {result['results']['folder']}")
    res = check_output(out, "real", result)
    for name, entry in res["scenes"].items():
        for runs in entry["walls"].values():
            for m in METHODS:
                check_times(runs[m])
        for v in entry["bounds"]["kinds"].values():
            check_accuracy(v["methods"])
    if "sportsCar.zip" in res["scenes"]:
        h = res["scenes"]["sportsCar.zip"]["hierarchy"]
        assert h["file"]["scene"]["synthetic"] == 0 < h["auto"]["scene"]["synthetic"]
        assert h["file"]["scene"]["leaves"] == h["auto"]["scene"]["leaves"] == 1075
        assert "adaptive+pseudo" in h["auto"]["walls"]["8x8"]


def test_real_without_scenes(tmp_path):
    result = E.run("real", tmp_path, quick=True, progress=False, scenes_dir=tmp_path / "none")
    assert result["results"]["scenes"] == {}
    assert "not found" in (tmp_path / "real.md").read_text()


def test_all_assembles_the_report(tmp_path, monkeypatch):
    """``all`` runs the registry in order and the report holds every fragment with working
    links; a new experiment needs one registry entry."""

    def tiny(ctx):
        plt = C.pyplot()
        fig, ax = plt.subplots()
        ax.plot(np.arange(100) ** 2)
        link = ctx.savefig(fig, f"{ctx.name}.png", "a plot")
        return {"value": 1}, f"## Tiny {ctx.name}\n\n{link}\n"

    monkeypatch.setattr(E, "REGISTRY", {"one": tiny, "two": tiny})
    out = tmp_path / "docs" / "experiments"
    report = tmp_path / "docs" / "BENCHMARKS.md"
    summary = E.run_all(out, quick=True, report=report, progress=False)
    assert list(summary["experiments"]) == ["one", "two"]
    text = report.read_text()
    assert text.startswith(E.INTRO.splitlines()[0])
    for name in ("one", "two"):
        assert f"## Tiny {name}" in text
        assert f"](experiments/{name}.png)" in text and f"](experiments/{name}.json)" in text
        assert f"wallcull experiment {name} --quick" in text
    assert "wallcull experiment all --quick" in text
    for link in re.findall(r"\]\((experiments/[^)#]+)\)", text):
        assert (report.parent / link).is_file(), link
    assert json.loads((out / "all.json").read_text())["total_s"] > 0


def test_a_fragment_says_how_to_run_it_again_with_its_folders(tmp_path, monkeypatch):
    """The "Reproduce:" line of a run into another folder names it (a quick run's line was
    refused as printed: --quick needs --out)."""
    def tiny(ctx):
        return {"value": 1}, f"## Tiny {ctx.name}\n"

    monkeypatch.setattr(E, "REGISTRY", {"one": tiny})
    result = E.run("one", tmp_path, quick=True, progress=False, scenes_dir=tmp_path)
    said = f"wallcull experiment one --quick --out {tmp_path} --scenes {tmp_path}"
    assert result["command"] == said and f"Reproduce: `{said}`" in (tmp_path / "one.md").read_text()


def test_unknown_experiment_is_bad_input(capsys):
    assert main(["experiment", "fig7", "--quick"]) == 2
    assert "invalid choice" in capsys.readouterr().err


@pytest.mark.parametrize("extra,said", [
    (["--seed", "-1", "--out", "OUT"], "--seed must be 0 or more"),
    (["--quick"], "--quick needs --out DIR"),
    (["--out", "FILE"], "is a file, not a folder"),
    (["--out", "/proc/nope"], "cannot write into --out /proc/nope"),
    (["--out", "OUT", "--report", "OUT"], "--report is where `all` writes BENCHMARKS.md")])
def test_careless_experiment_options_are_one_line(tmp_path, capsys, extra, said):
    """A negative seed, a quick run into the published pages, an output folder that is a
    file: one line and status 2 (they were internal errors, or overwrote the docs' numbers)."""
    (tmp_path / "FILE").write_text("not a folder")
    extra = [str(tmp_path / a) if a in ("OUT", "FILE") else a for a in extra]
    assert main(["experiment", "fig6", *extra]) == 2
    err = capsys.readouterr().err
    assert said in err and len(err.strip().splitlines()) == 1


def test_scale(out):
    """Each step in its own process: a first prepare, then a prepared load and its culling."""
    res = check_output(out, "scale", E.run("scale", out, quick=True, progress=False))
    rows = res["scenes"]
    assert [r["scene"] for r in rows] == ["powerplant", "powerplant*2"]
    assert rows[1]["nodes"] == 2 * rows[0]["nodes"]
    assert rows[1]["triangles"] == 2 * rows[0]["triangles"]
    for r in rows:
        assert r["prepare_s"] > 0 and r["load_s"] > 0 and r["file_mb"] > 0
        assert 0 < r["load_rss_mb"] <= r["load_peak_mb"] and r["prepare_peak_mb"] > 0
        assert set(r["cull"]) == {"wall-8x8.json", "wall-64x64.json"}
        for c in r["cull"].values():
            assert 0 < c["median_ms"] <= c["p99_ms"] and c["tests_per_frame"] > 0


def test_occluders(out):
    """Each way of choosing occluders hides something, and nothing adds to what is drawn."""
    r = check_output(out, "occluders", E.run("occluders", out, quick=True, progress=False))
    s = r["scenes"]["powerplant"]
    assert {(e["choice"], e["budget"], e["texels"]) for e in s["settings"]} == {
        (c, b, r["default"][2]) for c in r["choices"] for b in r["budgets"]} | {
        (*r["default"][:2], t) for t in r["texels"]}
    for e in s["settings"]:
        assert 0 < e["ratio"] < 1 and e["triangles"] < s["without"]
        assert 0 < e["occluder_triangles"] <= e["budget"] and e["occlude_ms_median"] > 0
    assert "## Choosing occluders" in (out / "occluders.md").read_text()


def test_a_step_reports_its_own_peak_memory():
    """A step started by a big parent (``experiment all`` after the other experiments) reports
    its own peak, not the parent's: Linux keeps ``ru_maxrss`` across fork and exec (every
    scene of the scale table said 4,307 MB)."""
    import subprocess
    import sys

    ballast = np.ones(800 * 2**20 // 8)  # 800 MB, touched
    done = subprocess.run([sys.executable, "-c", "from wallcull.bench import peak_rss_mb; "
                           "print(peak_rss_mb())"], capture_output=True, text=True, check=True)
    assert float(done.stdout) < 400 < bench.peak_rss_mb(), done.stdout
    del ballast
