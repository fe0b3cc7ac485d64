"""Surveys on Ray: every chunk of frames of every bag is one Ray task (one GPU each where the
cluster has GPUs, else one CPU core), on the cluster at an address or a local one. Ray is an
optional extra: ``pip install .[fleet]``."""

from __future__ import annotations

from typing import Any, Callable, Sequence

from ..recordings.bags import LogSpan
from ..errors import InputError
from ..params import Config
from ..stages.matching import set_host_threads
from .drive import ChunkResult, ChunkRunner, DriveTopics, Plan, observe_chunk


def ray_chunks(address: str | None = None) -> ChunkRunner:
    """The chunk runner of survey.survey that makes every chunk a Ray task
    (:func:`observe_on_ray`) on the cluster at ``address``, or a local one."""
    return lambda plans, config, progress: observe_on_ray(plans, config, address, progress)


def observe_on_ray(plans: Sequence[Plan], config: Config, address: str | None = None,
                   progress: Callable[[int, int], None] | None = None
                   ) -> list[list[ChunkResult]]:
    """:func:`~pothole_detector.survey.observe_chunk` of every (bag, topics, chunk spans)
    plan, a Ray task per chunk; per bag, in chunk order. The bags must be readable at the same
    path on every worker."""
    try:
        import ray
    except ImportError:
        raise InputError("--ray needs Ray: pip install 'pothole_detector[fleet]'") from None
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(address=address or None, include_dashboard=False, log_to_driver=False,
                 configure_logging=False)
    try:
        gpus = ray.cluster_resources().get("GPU", 0)
        backend = "gpu" if gpus and config.backend in ("auto", "gpu") else (
            "cpu" if config.backend == "auto" else config.backend)
        values = {**config.as_dict(), "backend": backend}
        task = ray.remote(num_gpus=1 if backend == "gpu" else 0,
                          num_cpus=1)(observe_chunk if backend == "gpu" else _observe_on_one_core)
        refs = [[task.remote(str(bag), topics, values, span) for span in spans]
                for bag, topics, spans in plans]
        flat = [ref for per_bag in refs for ref in per_bag]
        done, pending = 0, list(flat)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            done += len(ready)
            if progress is not None:
                progress(done, len(flat))
        return [[ray.get(ref) for ref in per_bag] for per_bag in refs]
    finally:
        if started_here:
            ray.shutdown()


def _observe_on_one_core(bag: str, topics: DriveTopics, values: dict[str, Any],
                         span: LogSpan) -> ChunkResult:
    """:func:`~pothole_detector.survey.observe_chunk` in a CPU task, which holds one core:
    OpenCV and the CPU matcher on one thread, so that a node's tasks do not crowd its cores."""
    set_host_threads(1)
    return observe_chunk(bag, topics, values, span)
