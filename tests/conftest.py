"""Every test run gets its own cache of prepared scenes (wallcull.prepared): tests never read
or write the user's ~/.cache/wallcull, and servers they start inherit the same folder."""

import os
import shutil
import tempfile

_CACHE = tempfile.mkdtemp(prefix="wallcull-test-cache-")
os.environ["WALLCULL_CACHE"] = _CACHE


def pytest_unconfigure(config):
    shutil.rmtree(_CACHE, ignore_errors=True)
