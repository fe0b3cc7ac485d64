"""The CPU outputs on the bundled data are bit for bit those recorded in golden_outputs.json
(rewritten by ``python test/golden.py`` only for a change meant to alter results)."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("rosbags")

from golden import GOLDEN, cases  # noqa: E402


def test_cpu_outputs_equal_the_recorded_ones():
    recorded = json.loads(GOLDEN.read_text())
    found = cases()
    assert set(found) == set(recorded)
    for name, frames in recorded.items():
        assert len(found[name]) == len(frames), name
        for index, (got, want) in enumerate(zip(found[name], frames)):
            assert got == want, f"{name} frame {index}"
