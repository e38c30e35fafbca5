"""The one error type user input raises.

Everything that rejects a wall, a frame, a scene or an option raises :class:`InputError` with a
one-line message naming what is wrong; the command line turns it into exit status 2 and the
server into a 4xx. Anything else escaping is a bug.
"""


class InputError(ValueError):
    """Bad user input: a wall, frame, scene, option or update that violates the contract."""
