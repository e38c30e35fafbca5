"""The compiled kernels' cache follows every kernel module's source (``wallcull._kernel_cache``).

numba keys a cached kernel on its own file alone: a kernel calling another module's kept the
old code of that module after it changed. A package made of wallcull's ``__init__`` and two
kernel modules, one calling the other, shows it in fresh processes."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import wallcull

CALLER = """from numba import njit
from . import callee


@njit(cache=True)
def twice():
    return 2 * callee.value()
"""

CALLEE = """from numba import njit


@njit(cache=True)
def value():
    return {}
"""


def _run(root: Path, env: dict) -> str:
    return subprocess.run([sys.executable, "-c", "import pkg.caller as c; print(c.twice())"],
                          cwd=root, env=env, capture_output=True, text=True, check=True,
                          timeout=600).stdout.strip()


def test_a_kernel_calling_another_modules_sees_its_change(tmp_path):
    package = tmp_path / "pkg"
    package.mkdir()
    shutil.copy(Path(wallcull.__file__), package / "__init__.py")
    (package / "caller.py").write_text(CALLER)
    (package / "callee.py").write_text(CALLEE.format(1))
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    assert _run(tmp_path, env) == "2"
    assert _run(tmp_path, env) == "2"  # from the cache
    (package / "callee.py").write_text(CALLEE.format(5))
    assert _run(tmp_path, env) == "10"  # was 2: the caller's cache kept the old callee
    folders = sorted((package / "__pycache__").glob("kernels-*"), key=os.path.getmtime)
    assert len(folders) == 2
    # a process started by one that chose the folder (its variable inherited) keys it again
    env["NUMBA_CACHE_DIR"] = str(folders[0])
    (package / "callee.py").write_text(CALLEE.format(7))
    assert _run(tmp_path, env) == "14"
    # and a folder given by the user holds the digest folders
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "mine")
    assert _run(tmp_path, env) == "14"
    assert [p.name.startswith("kernels-") for p in (tmp_path / "mine").iterdir()] == [True]
