"""No credential in the server's log: ``?token=`` values and ``Authorization`` headers are
redacted from every log record the process makes.

uvicorn logs each WebSocket handshake with its path and query (``"WebSocket
/walls/W/nodes/stream?tiles=0&token=..." [accepted]``, through ``uvicorn.error``, at INFO),
its access log (``uvicorn ... --factory``) each request's, and websockets' debug lines each
header: the operator's token, the nodes' and drivers' credentials and wrong guesses alike
went to ``docker logs`` and journald. :func:`install` wraps the process's log record factory,
so every record, whichever logger makes it and however logging is configured afterwards,
has ``token=<redacted>`` in its message and arguments, and ``<redacted>`` for the value after
an ``authorization`` argument. ``wallcull serve`` and :func:`~wallcull.server.make_app_from_env`
install it.
"""

from __future__ import annotations

import logging
import re

HIDDEN = "<redacted>"
#: A ``token`` parameter's value in a path or query (``?token=...``, ``&token=...``, also
#: percent-encoded separators), and an ``Authorization`` header written out.
SECRETS = re.compile(r"((?:[?&;]|%26|%3[fF])token(?:=|%3[dD]))[^&;#\s\"']*"
                     r"|((?:^|[\s\"'(])authorization\s*[:=]\s*)[^\r\n\"']*", re.IGNORECASE)
SENSITIVE = ("authorization", b"authorization", "proxy-authorization", b"proxy-authorization")


def redact(value):
    """``value`` (a str, bytes or anything) with its secrets hidden; others as they are."""
    if isinstance(value, str):
        return SECRETS.sub(_hide, value) if "token" in value.lower() or \
            "authorization" in value.lower() else value
    if isinstance(value, (bytes, bytearray)):
        return redact(bytes(value).decode("latin-1")).encode("latin-1")
    return value


def _hide(match) -> str:
    return (match.group(1) or match.group(2)) + HIDDEN


def _redacted(record: logging.LogRecord) -> logging.LogRecord:
    record.msg = redact(record.msg)
    args = record.args
    if isinstance(args, tuple):
        out = []
        for k, arg in enumerate(args):
            out.append(HIDDEN if k and isinstance(args[k - 1], (str, bytes)) and
                       args[k - 1].lower() in SENSITIVE else redact(arg))
        record.args = tuple(out)
    elif isinstance(args, dict):
        record.args = {key: redact(arg) for key, arg in args.items()}
    return record


def install() -> None:
    """Redact every log record made from now on (once per process)."""
    made = logging.getLogRecordFactory()
    if getattr(made, "redacts", False):
        return

    def factory(*args, **kwargs):
        return _redacted(made(*args, **kwargs))

    factory.redacts = True
    logging.setLogRecordFactory(factory)
