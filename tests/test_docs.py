"""The README and the documentation site: the site builds with ``mkdocs build --strict`` (a
broken link or anchor fails it), the README's links lead to files of the repository, its two
set-up commands are the main job and, word for word, the test command CI runs, and nothing
points outside the repository."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()
LINK = re.compile(r"\]\(([^)\s]+)\)")


def test_the_site_builds_strictly(tmp_path):
    pytest.importorskip("mkdocs", reason="no mkdocs (pip install -e '.[docs]')")
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
                          str(tmp_path / "site")], cwd=ROOT, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    assert (tmp_path / "site" / "index.html").is_file()
    for page in ("contract", "concepts", "cli", "settings", "protocol", "deployment",
                 "performance", "BENCHMARKS", "testing"):
        assert (tmp_path / "site" / page / "index.html").is_file(), page


@pytest.mark.parametrize("doc", ["README.md", "scenes/README.md", "clients/README.md"])
def test_links_lead_into_the_repository(doc):
    text = (ROOT / doc).read_text()
    for target in LINK.findall(text):
        if target.startswith(("http://", "https://", "#")):
            continue
        path = (ROOT / doc).parent / target.split("#")[0]
        assert path.resolve().is_relative_to(ROOT), f"{doc}: {target} is outside the repository"
        assert path.exists(), f"{doc}: {target} does not exist"


def test_the_readme_is_short_and_has_the_two_commands():
    assert len(README.splitlines()) <= 150
    setup = README.split("## Set up on a fresh machine")[1].split("\n## ")[0]
    commands = [ln.strip() for ln in setup.splitlines() if ln.startswith("    ")]
    assert len(commands) == 2, commands
    main_job, tests = commands
    assert main_job.startswith("python3 -m venv .venv && ") and \
        main_job.endswith(" && .venv/bin/wallcull walk powerplant")
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()[-1]
    assert tests == ci, "the README's test command is word for word what CI runs"


def test_nothing_points_outside_the_repository():
    """No path out of the repository (a clone has nothing beside it) and no issue numbers
    (a reader cannot look them up)."""
    files = [ROOT / "README.md", ROOT / "mkdocs.yml", *ROOT.glob("docs/**/*.md"),
             *ROOT.glob("scenes/*.md"), *ROOT.glob("clients/*.md")]
    for path in files:
        text = path.read_text()
        assert "../shared" not in text and "/shared/" not in text, path
        assert not re.search(r"\bissues? \d", text, re.IGNORECASE), path
