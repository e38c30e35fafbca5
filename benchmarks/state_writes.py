"""What writing a wall's frame numbers down costs the state folder: bytes and write calls a
second at 60 frames/s, and CPU a frame, written every frame (what the server did before) and
ahead of use (``wallcull.service.FrameNumbers``, what it does), in a fresh state folder each.

    python benchmarks/state_writes.py [FRAMES]
"""

from __future__ import annotations

import tempfile
import time

from wallcull.credentials import Issued
from wallcull.persist import StateFolder
from wallcull.service import FrameNumbers
from _cli import count, run  # beside this file

RATE = 60  # frames a second


def written() -> tuple[int, int]:
    """Bytes this process has passed to write calls, and how many calls (Linux)."""
    with open("/proc/self/io") as f:
        fields = dict(line.split(": ") for line in f.read().splitlines() if line)
    return int(fields["wchar"]), int(fields["syscw"])


def main(frames: int = 3600) -> None:
    for name in ("every frame", "ahead"):
        with tempfile.TemporaryDirectory() as folder:
            state = StateFolder(folder)
            state.add_wall("w", time.time(), {}, Issued("w", [], []))
            number = (lambda n: state.set_last_frame("w", n)) if name == "every frame" \
                else FrameNumbers(state, "w", -1)
            bytes0, calls0 = written()
            cpu0 = time.process_time()
            for n in range(frames):
                number(n)
            cpu = (time.process_time() - cpu0) / frames
            bytes1, calls1 = written()
            state.close()
        seconds = frames / RATE
        print(f"{name:12s} {(bytes1 - bytes0) / seconds / 1024:8.1f} KiB and "
              f"{(calls1 - calls0) / seconds:6.1f} write calls a second at {RATE} frames/s, "
              f"{cpu * 1e6:5.2f} us of CPU a frame")


if __name__ == "__main__":
    run(main, __doc__, ("frames", 3600, count(1), "frames numbered"))
