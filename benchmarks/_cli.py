"""The benchmarks' command lines: positional arguments, each with a default and a check, so
that a careless value is one line (``usage ...: error: ...``, status 2) and not a traceback
or a page of ``nan``. A wall file is looked for where it is given, then in the checkout (the
defaults are the checkout's examples)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from wallcull.errors import InputError

ROOT = Path(__file__).resolve().parent.parent


def count(least: int, most: int | None = None):
    """A whole number in ``[least, most]``."""
    def convert(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
        if value < least or (most is not None and value > most):
            span = f"at least {least}" if most is None else f"{least} to {most}"
            raise argparse.ArgumentTypeError(f"must be {span}, got {value}")
        return value
    return convert


def wall_file(text: str) -> str:
    """A wall file: as given, else in the checkout."""
    for path in (Path(text), ROOT / text):
        if path.is_file():
            return str(path)
    raise argparse.ArgumentTypeError(f"no wall file {text}")


def run(main, doc: str, *spec: tuple) -> None:
    """``main(*arguments)`` with the positional arguments of ``spec``: ``(name, default,
    convert, help)`` each, all optional in order."""
    parser = argparse.ArgumentParser(description=doc.strip().split("\n\n")[0])
    for name, default, convert, text in spec:
        parser.add_argument(name, nargs="?", default=default, type=convert, help=text)
    args = parser.parse_args()
    try:
        main(*vars(args).values())
    except InputError as exc:  # a scene or wall the project refuses: its one line
        parser.exit(2, f"{parser.prog}: error: {exc}\n")
