"""Every test run gets its own cache of prepared scenes (wallcull.prepared): tests never read
or write the user's ~/.cache/wallcull, and servers they start inherit the same folder."""

import os
import shutil
import tempfile


def pytest_configure(config):
    config.wallcull_cache = tempfile.mkdtemp(prefix="wallcull-test-cache-")
    os.environ["WALLCULL_CACHE"] = config.wallcull_cache


def pytest_unconfigure(config):
    shutil.rmtree(getattr(config, "wallcull_cache", ""), ignore_errors=True)
