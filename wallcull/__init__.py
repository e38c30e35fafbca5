"""wallcull: a culling server for tiled display walls.

The object hierarchy of a scene (:mod:`wallcull.scene`, :mod:`wallcull.bounds`) is culled to the
frustum hierarchy of a wall (:mod:`wallcull.wall`) by the traversals of :mod:`wallcull.cull`;
:class:`wallcull.pipeline.Session` runs it frame after frame.
"""

import hashlib
import os
import shutil
import sys
import time

__version__ = "0.1.0"


def _kernel_cache() -> None:
    """Where numba caches the compiled kernels: a folder named by a digest of every module
    that compiles any (``kernels-<digest>``), in ``$NUMBA_CACHE_DIR`` if set, else in the
    package's ``__pycache__`` where it can be written, else in ``~/.cache/wallcull``.

    numba keys a cached kernel on its own file alone, so a kernel calling another module's
    kept that module's old code after an edit (a ``git pull``) until its own file changed:
    a fix to the Low-Ilie fit's spot-light test did not reach the shadows' kernel in another
    module. A changed kernel module now compiles every kernel afresh. Older folders untouched
    for a week are removed as a new one is made."""
    here = os.path.dirname(os.path.abspath(__file__))
    digest = hashlib.sha256()
    for folder, dirs, files in sorted(os.walk(here)):
        dirs.sort()
        for name in sorted(files):
            if name.endswith(".py"):
                with open(os.path.join(folder, name), "rb") as source:
                    text = source.read()
                if b"import numba" in text or b"from numba" in text:
                    digest.update(name.encode() + b"\0" + text)
    name = f"kernels-{digest.hexdigest()[:16]}"
    given = os.environ.get("NUMBA_CACHE_DIR", "").rstrip(os.sep)
    if os.path.basename(given).startswith("kernels-"):  # chosen by the process that started
        given = os.path.dirname(given)  # this one (the same code: the same folder again)
    if given:
        base = given
    elif os.access(os.path.join(here, "__pycache__"), os.W_OK) or os.access(here, os.W_OK):
        base = os.path.join(here, "__pycache__")
    else:
        base = os.path.join(os.path.expanduser("~"), ".cache", "wallcull")
    target = os.path.join(base, name)
    if not os.path.isdir(target):
        week = time.time() - 7 * 86400
        try:
            for old in os.scandir(base):
                if (old.name.startswith("kernels-") and old.is_dir()
                        and old.stat().st_mtime < week):
                    shutil.rmtree(old.path, ignore_errors=True)
        except OSError:
            pass  # no folder yet, or none to read: nothing to tidy
    os.environ["NUMBA_CACHE_DIR"] = target
    if "numba" in sys.modules:  # imported before wallcull: it read the variable already
        sys.modules["numba"].core.config.reload_config()


_kernel_cache()
