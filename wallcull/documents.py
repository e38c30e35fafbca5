"""JSON documents given on a command line: inline text or a file path."""

from __future__ import annotations

import json
from pathlib import Path

from .errors import InputError


def read_json(text: str, what: str):
    """A JSON document given inline (starting with ``{`` or ``[``) or as a file path."""
    text = text.strip()
    if not text.startswith(("{", "[")):
        path = Path(text)
        if not path.is_file():
            raise InputError(f"{what} file not found: {text}")
        text = path.read_text()
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"malformed JSON in {what}: {exc}") from None
