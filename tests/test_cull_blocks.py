"""The block kernel of ``adaptive`` (wallcull.cull) lists exactly what the scalar kernel it
replaced listed, with as many box-plane tests, frame by frame: random scenes with clusters on
random grids (gaps, none, overlaps), mono and stereo, the power plant and Fatehpur Sikri on the
example grids and screens walls (the 64 x 64 wall's second frame in threads). The digests were
written by the scalar kernel (tests/adaptive_lists.py)."""

import json

from .adaptive_lists import DATA, digests


def test_adaptive_lists_what_the_scalar_kernel_listed():
    expect = json.loads(DATA.read_text())
    got = digests()
    assert got.keys() == expect.keys()
    for name in expect:
        assert got[name] == expect[name], name
    assert sum(len(rows) for rows in expect.values()) > 80
