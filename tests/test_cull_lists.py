"""``adaptive`` (wallcull.cull) lists what it listed when its digests were written, with as
many box-plane tests, frame by frame: random scenes with clusters on random grids (gaps, none,
overlaps), mono and stereo, the power plant and Fatehpur Sikri on the example grids and
screens walls (the 64 x 64 wall's second frame in threads, where the separating-axis pass
drops thousands of pairs). A rewrite of the kernel or of that pass that promises the same
answers is held to it (tests/adaptive_lists.py writes the digests)."""

import json

from .adaptive_lists import DATA, digests


def test_adaptive_lists_what_it_listed():
    expect = json.loads(DATA.read_text())
    got = digests()
    assert got.keys() == expect.keys()
    for name in expect:
        assert got[name] == expect[name], name
    assert sum(len(rows) for rows in expect.values()) > 80
