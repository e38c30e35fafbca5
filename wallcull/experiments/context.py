"""The run of one experiment: where it writes, its size and seed, its progress bar, and the
machine it ran on. Light to import: the command line builds its parser from it."""

from __future__ import annotations

import json
import os
import platform
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np


def _root() -> Path:
    """The checkout whose ``examples/`` and ``scenes/`` the experiments read and whose
    ``docs/`` they write: the package's own (installed with ``pip install -e``), else the
    current folder's."""
    for root in (Path(__file__).resolve().parents[2], Path.cwd()):
        if (root / "examples" / "wall-8x8.json").is_file():
            return root
    return Path.cwd()


ROOT = _root()


@dataclass
class Context:
    """One experiment's run: where it writes, how big it is, its seed, its progress bar."""

    name: str
    out: Path
    quick: bool = False
    seed: int = 0
    # the project's third-party scenes (scenes/), or wherever --scenes says
    scenes_dir: Path = ROOT / "scenes"
    progress: Any = None  # a rich Progress, or None
    plots: list[str] = field(default_factory=list)

    def size(self, full, quick):
        """The full or the quick value of a parameter."""
        return quick if self.quick else full

    def task(self, description: str, total: int):
        return Task(self.progress, description, total)

    def savefig(self, fig, filename: str, caption: str) -> str:
        """Write a figure as PNG; returns the markdown that shows it."""
        fig.savefig(self.out / filename, dpi=100)
        import matplotlib.pyplot as plt

        plt.close(fig)
        self.plots.append(filename)
        return f"![{caption}]({filename})"


class Task:
    """A progress-bar task, or nothing when there is no bar."""

    def __init__(self, progress, description: str, total: int):
        self.progress = progress
        self.id = progress.add_task(description, total=total) if progress else None

    def advance(self, n: int = 1) -> None:
        if self.progress is not None:
            self.progress.advance(self.id, n)

    def done(self) -> None:
        if self.progress is not None:
            self.progress.remove_task(self.id)


def progress_bar():
    from rich.console import Console
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                               TimeElapsedColumn)

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TimeElapsedColumn(), console=Console(stderr=True), transient=True)


def to_json(value):
    """JSON-ready: numpy scalars and arrays to Python numbers and lists."""
    if isinstance(value, dict):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_json(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def write_json(path: Path, data: dict) -> None:
    """Indented JSON, with lists of numbers (the per-frame series) kept on one line."""
    text = json.dumps(to_json(data), indent=1)
    text = re.sub(r"\[\s*(-?[0-9][-0-9.eE+]*(?:,\s*-?[0-9][-0-9.eE+]*)*)\s*\]",
                  lambda m: "[" + re.sub(r"\s+", "", m.group(1)) + "]", text)
    path.write_text(text + "\n")


def machine() -> dict:
    """The machine and software the numbers were measured on."""
    import numba
    import scipy
    import trimesh

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "system": platform.system(),
            "python": platform.python_version(), "numpy": np.__version__,
            "numba": numba.__version__, "scipy": scipy.__version__,
            "trimesh": trimesh.__version__}


def loadavg() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


Experiment = Callable[[Context], tuple[dict, str]]
