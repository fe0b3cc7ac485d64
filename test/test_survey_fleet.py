"""Surveys on Ray: chunks as tasks on a local 2-CPU Ray give the sequential survey."""

from __future__ import annotations

import pytest

ray = pytest.importorskip("ray")

from conftest import REPO  # noqa: E402
from test_survey_drive import assert_same_potholes  # noqa: E402

from pothole_detector.params import Config  # noqa: E402
from pothole_detector.survey.fleet import cores_per_gpu, ray_chunks  # noqa: E402
from pothole_detector.survey.drive import survey  # noqa: E402


def test_ray_chunks_give_the_sequential_survey(survey_drive_bags):
    bags, _, _ = survey_drive_bags
    config = Config({"backend": "cpu", "chunk_frames": 12})
    drives = [bags["none"], REPO / "bags" / "sample_drive"]
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    done = []
    try:
        on_ray = survey(drives, config, chunks=ray_chunks(),
                        progress=lambda n, total: done.append((n, total)))
    finally:
        ray.shutdown()
    here = survey(drives, Config({"backend": "cpu"}))
    assert [len(d.potholes) for d in on_ray] == [6, 5]
    chunks = done[-1][1]
    assert chunks > 2 and [n for n, _ in done] == list(range(1, chunks + 1))
    for split, whole in zip(on_ray, here):
        assert_same_potholes(split, whole)


def test_a_gpu_task_asks_for_its_share_of_the_least_provisioned_gpu_node():
    nodes = [{"Alive": True, "Resources": {"CPU": 32.0, "GPU": 2.0}},
             {"Alive": True, "Resources": {"CPU": 48.0, "GPU": 4.0}},
             {"Alive": True, "Resources": {"CPU": 64.0}},
             {"Alive": False, "Resources": {"CPU": 4.0, "GPU": 4.0}}]
    assert cores_per_gpu(nodes) == 12
    assert cores_per_gpu([{"Alive": True, "Resources": {"CPU": 3.0, "GPU": 4.0}}]) == 1
    assert cores_per_gpu(nodes[2:3]) == 1
