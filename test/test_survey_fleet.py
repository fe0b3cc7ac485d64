"""Surveys on Ray: chunks as tasks on a local 2-CPU Ray give the sequential survey."""

from __future__ import annotations

import pytest

ray = pytest.importorskip("ray")

from conftest import REPO  # noqa: E402
from test_survey_drive import assert_same_potholes  # noqa: E402

from pothole_detector.params import Config  # noqa: E402
from pothole_detector.survey.fleet import ray_chunks  # noqa: E402
from pothole_detector.survey.drive import survey  # noqa: E402


def test_ray_chunks_give_the_sequential_survey(survey_drive_bags):
    bags, _, _ = survey_drive_bags
    config = Config({"backend": "cpu", "chunk_frames": 12})
    drives = [bags["none"], REPO / "bags" / "sample_drive"]
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        on_ray = survey(drives, config, chunks=ray_chunks())
    finally:
        ray.shutdown()
    here = survey(drives, Config({"backend": "cpu"}))
    assert [len(d.potholes) for d in on_ray] == [6, 5]
    for split, whole in zip(on_ray, here):
        assert_same_potholes(split, whole)
