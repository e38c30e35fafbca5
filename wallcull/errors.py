"""The one error type user input raises.

Everything that rejects a wall, a frame, a scene or an option raises :class:`InputError` with a
one-line message naming what is wrong; the command line turns it into exit status 2 and the
server into a 4xx. An option this install cannot serve (its extra is not installed) is refused
the same way (:func:`optional`). Anything else escaping is a bug.
"""


class InputError(ValueError):
    """Bad user input: a wall, frame, scene, option or update that violates the contract."""


class WriteFailed(InputError):
    """A file the work needs written could not be (a prepared scene in a full or read-only
    cache folder): ``errno`` says why. The command line says so in one line like any
    :class:`InputError`; the server answers 507 or 503, a disk problem of its own."""

    def __init__(self, message: str, errno: int | None = None):
        super().__init__(message)
        self.errno = errno

    def __reduce__(self):  # handed back from a child process (:mod:`wallcull.sandbox`)
        return type(self), (str(self), self.errno)


def optional(module: str, extra: str, what: str):
    """``module``, a dependency only some uses need (an extra of the install): imported, or
    refused in one line that names the extra installing it. ``what``: the use that needs it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise InputError(f"{what} needs {module.split('.')[0]}, which this install lacks: "
                         f"pip install 'wallcull[{extra}]'") from None
