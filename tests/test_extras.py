"""The base install runs the main job and the server: with every extra's packages made
unimportable (as in an install without extras), ``wallcull walk`` culls the bundled scene and
``wallcull serve`` serves walls, frames, the pages and the API docs; an option that needs an
extra is refused in one line that names it (exit 2), never a traceback."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from wallcull_clients.loadtest import free_port

ROOT = Path(__file__).resolve().parent.parent
#: What only the extras (and the clients' distribution, and the tests) install.
EXTRAS = ("scipy", "matplotlib", "psutil", "nats", "networkx", "lxml", "DracoPy", "moderngl", "PIL",
          "httpx", "wallcull_clients", "pytest", "hypothesis", "jsonschema", "playwright",
          "schemathesis", "openapi_spec_validator", "mkdocs")
BLOCK = f"""
import sys
class Blocked:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {EXTRAS!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}} (blocked: an extra)")
sys.meta_path.insert(0, Blocked())
import importlib.metadata as md  # and no distribution adds commands (the clients' loadtest)
entry_points = md.entry_points
md.entry_points = lambda **kw: [] if kw.get("group") == "wallcull.commands" else entry_points(**kw)
from wallcull.cli import main
sys.exit(main(sys.argv[1:]))
"""


def base(*argv, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", BLOCK, *argv], capture_output=True, text=True,
                          cwd=ROOT, timeout=600, **kwargs)


def test_the_main_job_needs_no_extra():
    run = base("walk", "powerplant", "--frames", "12")
    assert run.returncode == 0, run.stderr[-2000:]
    assert "culling time per frame" in run.stdout and "4 x 4 wall" in run.stdout


def test_lights_and_mirrors_need_no_extra():
    """The fits' compiled kernels call no BLAS or LAPACK (numba's ``@`` and ``np.linalg`` use
    SciPy's, an extra: without it the process stops with a fatal error)."""
    run = base("cull", "powerplant", "--wall", "examples/wall-4x4.json", "--frame",
               '{"position": [0, 30, 160], "orientation": [1, 0, 0, 0]}', "--settings",
               "scenes/powerplant-lights3.json")
    assert run.returncode == 0, run.stderr[-2000:]
    assert ", 3 shadows" in run.stdout and ", 1 mirrors;" in run.stdout


@pytest.mark.parametrize("argv, extra", [
    (["cull", "powerplant", "--wall", "examples/wall-4x4.json", "--frame",
      '{"position": [0, 30, 160], "orientation": [1, 0, 0, 0]}', "--bounds", "obb-hull"], "hull"),
    (["bench", "powerplant", "--wall", "examples/wall-4x4.json", "--frames", "3",
      "--bounds", "obb-min"], "hull"),
    (["bench", "powerplant", "--wall", "examples/wall-4x4.json", "--frames", "3",
      "--accuracy", "1"], "experiments"),
    (["experiment", "fig4", "--quick", "--out", "/nonexistent"], "experiments"),
    (["serve", "--nats", "nats://127.0.0.1:1", "--state", "none"], "nats"),
    (["cull", "scenes/FM1_satellite.3DXML", "--wall", "examples/wall-4x4.json", "--frame",
      '{"position": [0, 0, 10], "orientation": [1, 0, 0, 0]}'], "formats"),
])
def test_what_needs_an_extra_says_which(argv, extra):
    run = base(*argv)
    assert run.returncode == 2, (run.stdout[-500:], run.stderr[-2000:])
    assert run.stderr.count("\n") == 1 and f"pip install 'wallcull[{extra}]'" in run.stderr
    assert "needs None" not in run.stderr  # the module it lacks is named


def test_the_server_needs_no_extra(tmp_path):
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-c", BLOCK, "serve", "--port", str(port),
                             "--state", str(tmp_path / "state"), "--log-level", "warning"],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    url = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=url, timeout=60) as http:
            deadline = time.monotonic() + 180
            while True:
                assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
                assert time.monotonic() < deadline, "the server never answered /health"
                try:
                    if http.get("/health").status_code == 200:
                        break
                except httpx.TransportError:
                    time.sleep(0.3)
            wall = json.loads((ROOT / "examples" / "wall-4x4.json").read_text())
            r = http.post("/walls", json={"wall": wall, "scene": "powerplant"})
            assert r.status_code == 201, r.text
            wid = r.json()["id"]
            frame = {"position": [0, 30, 160], "orientation": [1, 0, 0, 0]}
            r = http.post(f"/walls/{wid}/frames", json={"frame": frame, "packets": True})
            assert r.status_code == 200 and len(r.json()["packets"]) == 16, r.text
            assert f"/walls/{wid}/console" in http.get("/").text
            assert "swagger-ui-bundle.js" in http.get("/docs").text
            assert http.get("/docs/assets/swagger-ui-bundle.js").status_code == 200
            assert http.get(f"/walls/{wid}/console").status_code == 200
    finally:
        proc.terminate()
        proc.wait(30)
