"""docker-compose.yml, the Dockerfile and .dockerignore, without a Docker engine.

The file is parsed (pyyaml) and held to what it promises: the services, health check, token and
start order; every command names a real entry point whose argument parser accepts the given
arguments; everything the Dockerfile copies exists and is not excluded from the build context.
Then the same commands the compose file runs (variables interpolated as compose does, the
service host name and port mapped to a free loopback port) run here, bounded: the health check
against the server, the nodes and the driver for 60 frames with the swap barrier.
"""

import fnmatch
import importlib
import importlib.util
import json
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from wallcull_clients.loadtest import free_port

ROOT = Path(__file__).resolve().parent.parent
COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
SERVICES = COMPOSE["services"]
TOKEN = "test-token-123"

_VAR = re.compile(r"\$\$|\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?[-?])([^}]*))?\}|\$([A-Za-z_][A-Za-z0-9_]*)")


def interpolate(text: str, env: dict) -> str:
    """Compose's variable substitution: ``${VAR}``, ``${VAR:-default}``, ``${VAR-default}``,
    ``${VAR:?error}``, ``${VAR?error}``, ``$VAR`` and ``$$`` for a literal dollar."""

    def sub(m):
        if m.group(0) == "$$":
            return "$"
        name = m.group(1) or m.group(4)
        op, arg = m.group(2), m.group(3)
        value = env.get(name)
        if op in (":-", ":?") and not value:
            value = None
        if value is None:
            if op in ("-", ":-"):
                return arg
            if op in ("?", ":?"):
                raise KeyError(f"{name}: {arg}")
            return ""
        return value

    return _VAR.sub(sub, text)


def command(service: str, env: dict) -> list[str]:
    cmd = SERVICES[service]["command"]
    assert isinstance(cmd, list), "exec form: no shell between compose and the program"
    return [interpolate(c, env) for c in cmd]


def environment(service: str, env: dict) -> dict:
    return {k: interpolate(str(v), env) for k, v in SERVICES[service]["environment"].items()}


def on_loopback(cmd: list[str], port: int) -> list[str]:
    """The compose command with the service network mapped to this machine."""
    out = []
    for arg in cmd:
        arg = arg.replace("http://server:8000", f"http://127.0.0.1:{port}")
        arg = arg.replace("http://127.0.0.1:8000", f"http://127.0.0.1:{port}")
        out.append({"0.0.0.0": "127.0.0.1", "8000": str(port)}.get(arg, arg))
    return out


def run_python(cmd: list[str]) -> list[str]:
    """``python ...`` and console scripts run with this interpreter (the image's would)."""
    if cmd[0] == "python":
        return [sys.executable, *cmd[1:]]
    if cmd[0] == "wallcull":
        return [sys.executable, "-m", "wallcull.cli", *cmd[1:]]
    raise AssertionError(f"unknown program {cmd[0]!r}")


ENV = {"WALLCULL_TOKEN": TOKEN}


# --------------------------------------------------------------------------- the file


def test_services_and_start_order():
    assert set(SERVICES) == {"server", "clients", "driver"}
    images = {s["image"] for s in SERVICES.values()}
    assert len(images) == 1, "one image for all three"
    for name, service in SERVICES.items():
        # a fresh host has no wallcull image and no registry holds one: each service builds
        # it from this folder, and compose never tries to pull it
        assert (ROOT / service["build"] / "Dockerfile").is_file(), name
        assert service["pull_policy"] == "build", name
    for name in ("clients", "driver"):
        assert SERVICES[name]["depends_on"]["server"] == {"condition": "service_healthy"}
    assert SERVICES["driver"]["depends_on"]["clients"]["condition"] == "service_started"
    assert SERVICES["server"]["ports"] and interpolate(SERVICES["server"]["ports"][0], {}) == "8000:8000"


def test_state_stays_on_its_volume():
    """The server's state folder is the named volume's mount point, whatever the environment
    says, and the image declares the same folder a volume."""
    volumes = [v.split(":") for v in SERVICES["server"]["volumes"]]
    (volume, target), = [(name, target) for name, target in volumes if name in COMPOSE["volumes"]]
    for env in (ENV, {**ENV, "WALLCULL_STATE": "/tmp/elsewhere",
                      "WALLCULL_STATE_DIR": "/tmp/elsewhere"}):
        assert environment("server", env)["WALLCULL_STATE"] == target == "/var/lib/wallcull"
    assert f'VOLUME ["{target}"]' in (ROOT / "Dockerfile").read_text()
    assert not any("STATE" in k for s in ("clients", "driver")
                   for k in SERVICES[s].get("environment", {}))


def test_health_check_is_on_health():
    hc = SERVICES["server"]["healthcheck"]
    assert hc["test"][0] == "CMD" and "/health" in " ".join(hc["test"])
    assert hc["retries"] >= 3 and "start_period" in hc
    compile(hc["test"][3], "healthcheck", "exec")  # python -c CODE: valid Python


def test_token_comes_from_the_environment(monkeypatch):
    for name in SERVICES:
        assert environment(name, ENV)["WALLCULL_TOKEN"] == TOKEN
    with pytest.raises(KeyError, match="WALLCULL_TOKEN"):  # compose refuses to start without
        environment("server", {})
    # the programs read it from the environment: nobody passes it on a command line
    for name in SERVICES:
        assert not any("token" in a.lower() for a in command(name, ENV))
    from wallcull_clients.driver import parser as driver_parser
    from wallcull_clients.sim import parser as sim_parser

    monkeypatch.setenv("WALLCULL_TOKEN", "from-env")
    assert sim_parser().parse_args([]).token == "from-env"
    assert driver_parser().parse_args([]).token == "from-env"


@pytest.mark.parametrize("service", sorted(SERVICES))
def test_commands_are_real_entry_points(service):
    import tomllib

    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    for env in (ENV, {**ENV, "WALLCULL_MODE": "pull", "WALLCULL_TILES": "0-3,7",
                      "WALLCULL_WALL": "examples/wall-8x8.json", "WALLCULL_WAIT_CLIENTS": "0"}):
        cmd = command(service, env)
        if cmd[0] == "wallcull":
            module, _, func = scripts["wallcull"].partition(":")
            mod = importlib.import_module(module)
            assert callable(getattr(mod, func))
            args = mod.parser().parse_args(cmd[1:])  # raises on anything it does not accept
            assert args.command == "serve"
        else:
            assert cmd[:2] == ["python", "-m"]
            assert importlib.util.find_spec(cmd[2]) is not None, cmd[2]
            mod = importlib.import_module(cmd[2])
            assert callable(mod.main)
            with pytest.raises(SystemExit) as exit_:  # argparse exits 2 on a bad argument
                mod.parser().parse_args([*cmd[3:], "--no-such-option"])
            assert exit_.value.code == 2
            mod.parser().parse_args(cmd[3:])
        for arg in cmd:
            if arg.endswith(".json") and not arg.startswith("{"):
                assert (ROOT / arg).is_file(), f"{arg} is not in the image"


def _dockerignore():
    lines = (ROOT / ".dockerignore").read_text().splitlines()
    return [ln.strip() for ln in lines if ln.strip() and not ln.startswith("#")]


def _ignored(path: str, patterns) -> bool:
    parts = path.split("/")
    for p in patterns:
        p = p.rstrip("/")
        for k in range(1, len(parts) + 1):
            if fnmatch.fnmatch("/".join(parts[:k]), p) or \
                    (p.startswith("**/") and fnmatch.fnmatch(parts[k - 1], p[3:])):
                return True
    return False


def test_dockerfile_copies_what_exists_and_is_in_the_context():
    lines = (ROOT / "Dockerfile").read_text().replace("\\\n", " ").splitlines()
    instructions = [ln.split(None, 1) for ln in lines if ln.strip() and not ln.startswith("#")]
    assert instructions[0][0] == "FROM" and "python:3.1" in instructions[0][1]
    patterns = _dockerignore()
    copied = []
    for op, rest in instructions:
        if op == "COPY":
            *sources, _ = shlex.split(rest)
            copied += sources
    assert {"pyproject.toml", "README.md", "wallcull", "examples"} <= set(copied)
    for src in copied:
        assert (ROOT / src).exists(), src
        assert not _ignored(src, patterns), f"{src} is excluded by .dockerignore"
    # every package setuptools installs is copied before `pip install .`
    import tomllib

    include = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "packages"]["find"]["include"]
    assert {pkg.rstrip("*") for pkg in include} <= set(copied)
    cmd = next(json.loads(rest) for op, rest in instructions if op == "CMD")
    assert cmd[:2] == ["wallcull", "serve"]
    assert _ignored("tests/test_e2e.py", patterns) and _ignored("wallcull/__pycache__/x.pyc", patterns)
    assert not _ignored("wallcull/server.py", patterns)


# --------------------------------------------------------------------------- the same commands, run


def test_compose_commands_run_on_loopback(tmp_path):
    """server (until healthy, by its own health check), then nodes, then the driver: 60 frames
    of the default 4 x 4 wall with the barrier, every frame acknowledged by every tile."""
    port = free_port()
    # generous timeouts (tests, not the product): on a loaded machine a barrier or a node's
    # next packet can take longer than the defaults allow
    env = {**ENV, "WALLCULL_FRAMES": "60", "WALLCULL_IDLE_TIMEOUT": "10",
           "WALLCULL_BARRIER_TIMEOUT": "10"}

    def proc_env(service):  # the server's volume, mapped to a folder here as its network is
        out = {**os.environ, **environment(service, env)}
        if "WALLCULL_STATE" in out:
            out["WALLCULL_STATE"] = str(tmp_path / "state")
        return out
    health = SERVICES["server"]["healthcheck"]["test"][1:]
    health = run_python(on_loopback([a.replace(":8000/", f":{port}/") for a in health], port))

    def healthy() -> bool:
        return subprocess.run(health, capture_output=True, timeout=10).returncode == 0

    assert not healthy(), "the health check fails while no server runs"
    procs = []
    try:
        server = subprocess.Popen(run_python(on_loopback(command("server", env), port)),
                                  env=proc_env("server"), stdout=subprocess.DEVNULL,
                                  stderr=subprocess.PIPE, cwd=ROOT)
        procs.append(server)
        deadline = time.monotonic() + 120
        while not healthy():  # depends_on: condition: service_healthy
            assert server.poll() is None, server.stderr.read().decode()[-2000:]
            assert time.monotonic() < deadline, "the server never became healthy"
            time.sleep(0.5)
        nodes = subprocess.Popen(run_python(on_loopback(command("clients", env), port)),
                                 env=proc_env("clients"), stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, cwd=ROOT, text=True)
        procs.append(nodes)
        driver = subprocess.run(run_python(on_loopback(command("driver", env), port)),
                                env=proc_env("driver"), capture_output=True, text=True,
                                cwd=ROOT, timeout=180)
        assert driver.returncode == 0, driver.stderr[-2000:]
        out, err = nodes.communicate(timeout=120)
        assert nodes.returncode == 0, err[-2000:]
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                p.wait(10)
    lines = [json.loads(ln) for ln in driver.stdout.splitlines() if ln.startswith("{")]
    assert lines[0]["tiles"] == 16 and lines[1] == {"subscribers": 16}
    summary = lines[-1]["summary"]
    # a driver behind its schedule (a busy machine) skips the slots it missed
    assert summary["frames"] + summary["skipped"] == 60 and summary["barrier_incomplete"] == 0
    ready = json.loads(out.splitlines()[0])
    assert ready["ready"] and ready["tiles"] == list(range(16))


def test_the_image_compiles_the_kernels_at_build_as_the_server_user():
    """A fresh container must not compile for a minute before its health check answers: the
    kernels are compiled at build (wallcull.warm), by the user that runs the server, into the
    NUMBA_CACHE_DIR it runs with."""
    lines = (ROOT / "Dockerfile").read_text().replace("\\\n", " ").splitlines()
    instructions = [ln.split(None, 1) for ln in lines if ln.strip() and not ln.startswith("#")]
    ops = [op for op, _ in instructions]
    runs = [rest for op, rest in instructions if op == "RUN"]
    warm = next(k for k, (op, rest) in enumerate(instructions)
                if op == "RUN" and "wallcull.warm" in rest)
    user = max(k for k, op in enumerate(ops) if op == "USER")
    assert user < warm and instructions[user][1].strip() == "wallcull"
    env = " ".join(rest for op, rest in instructions if op == "ENV")
    cache = env.split("NUMBA_CACHE_DIR=")[1].split()[0]
    assert any(cache in r and "chown wallcull" in r for r in runs)  # writable by the user
    import importlib

    assert hasattr(importlib.import_module("wallcull.warm"), "main")
