"""Surveys on Ray: every chunk of frames of every bag is one Ray task (one GPU each where the
cluster has GPUs, else one CPU core), on the cluster at an address or a local one. Ray is an
optional extra: ``pip install .[fleet]``."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

from .errors import InputError
from .params import Config
from .survey import DriveTopics, FrameObservation, observe_chunk


def observe_on_ray(plans: Sequence[tuple[Path, DriveTopics, list[tuple[int, int]]]],
                   config: Config, address: str | None = None,
                   progress: Callable[[int, int], None] | None = None
                   ) -> list[list[FrameObservation]]:
    """Observations of every (bag, topics, chunk ranges) plan, a Ray task per chunk; per bag,
    in chunk order. The bags must be readable at the same path on every worker."""
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
                          num_cpus=1)(observe_chunk)
        refs = [[task.remote(str(bag), topics, values, first, stop) for first, stop in ranges]
                for bag, topics, ranges in plans]
        flat = [ref for per_bag in refs for ref in per_bag]
        done, pending = 0, list(flat)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            done += len(ready)
            if progress is not None:
                progress(done, len(flat))
        return [[obs for ref in per_bag for obs in ray.get(ref)] for per_bag in refs]
    finally:
        if started_here:
            ray.shutdown()
