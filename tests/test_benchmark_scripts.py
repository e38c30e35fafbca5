"""The scripts in ``benchmarks/`` refuse careless arguments in one line, status 2 (they raised
tracebacks, divided by zero or printed ``nan`` for every number)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("script,args,said", [
    ("node_bytes.py", ["examples/wall-8x8.json", "4", "20"], "must be at least 31, got 20"),
    ("server_frame.py", ["examples/wall-8x8.json", "1", "900"], "must be 31 to 600, got 900"),
    ("server_frame.py", ["examples/wall-8x8.json", "0"], "must be at least 1, got 0"),
    ("state_writes.py", ["0"], "must be at least 1, got 0"),
    ("cull_alone.py", ["powerplant", "examples/wall-8x8.json", "x"], "not a whole number: 'x'"),
    ("stereo_passes.py", ["powerplant", "nowhere.json"], "no wall file nowhere.json"),
    ("numpy_frontier.py", ["nosuchscene"], "unknown scene 'nosuchscene'"),
    ("paired.py", ["HEAD", "--stage", "occlude"], "--stage occlude needs --occlusion"),
    ("paired.py", ["nosuchrev", "--frames", "5"], "unknown revision 'nosuchrev'"),
    ("paired.py", ["HEAD", "--stereo", "2"], "an interpupillary distance is over 0 and at most"),
    ("nats_fanout.py", ["examples/wall-4x4.json", "abc"], "not a whole number: 'abc'"),
    ("nats_fanout.py", ["examples/wall-4x4.json", "0", "10"], "must be at least 1, got 0"),
    ("nats_fanout.py", ["examples/wall-4x4.json", "4", "0"], "must be 1 to 600, got 0"),
    ("nats_fanout.py", ["nowhere.json"], "no wall file nowhere.json"),
    ("cull_alone.py", ["powerplant", "examples/wall-4x4.json", "1"], "must be at least 3, got 1"),
    ("stereo_passes.py", ["powerplant", "examples/wall-4x4.json", "1"],
     "must be at least 4, got 1"),
    ("numpy_frontier.py", ["powerplant", "examples/wall-4x4.json", "2"],
     "must be at least 4, got 2"),
    ("numpy_frontier.py", ["powerplant", "examples/wall-cave.json", "5"],
     "is a wall of screens: the numpy frontier culls grids"),
])
def test_careless_arguments_are_one_line(tmp_path, script, args, said):
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *args],
                          cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 2, done.stderr
    assert said in done.stderr and "Traceback" not in done.stderr
