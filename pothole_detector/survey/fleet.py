"""Surveys on Ray: the chunks of frames of every bag go to one worker per GPU of the cluster
(with the host cores that come with a GPU; on a cluster without GPUs, one per core), on the
cluster at an address or a local one. Ray is an optional extra: ``pip install .[fleet]``."""

from __future__ import annotations

from typing import Any, Callable, Sequence

from ..recordings.bags import LogSpan
from ..errors import InputError
from ..params import Config
from ..stages.matching import set_host_threads
from .drive import ChunkResult, ChunkRunner, DriveTopics, Plan, observe_chunk


def ray_chunks(address: str | None = None) -> ChunkRunner:
    """The chunk runner of survey.survey that runs the chunks on Ray (:func:`observe_on_ray`),
    on the cluster at ``address``, or a local one."""
    return lambda plans, config, progress: observe_on_ray(plans, config, address, progress)


IN_FLIGHT = 2


def observe_on_ray(plans: Sequence[Plan], config: Config, address: str | None = None,
                   progress: Callable[[int, int], None] | None = None
                   ) -> list[list[ChunkResult]]:
    """:func:`~pothole_detector.survey.observe_chunk` of every (bag, topics, chunk spans)
    plan on Ray; per bag, in chunk order. One :class:`ChunkWorker` actor per GPU of the
    cluster (per CPU core on the CPU backend) takes the chunks in turn, IN_FLIGHT of them
    queued at a time, so that a worker's next chunk is there when one ends: a worker keeps
    its process, GPU, compiled kernels and memory pool from one chunk to the next (a Ray task
    that holds a GPU gets a fresh process each time). The bags must be readable at the same
    path on every node."""
    try:
        import ray
    except ImportError:
        raise InputError("--ray needs Ray: pip install 'pothole_detector[fleet]'") from None
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(address=address or None, include_dashboard=False, log_to_driver=False,
                 configure_logging=False)
    try:
        resources = ray.cluster_resources()
        gpus = int(resources.get("GPU", 0))
        backend = "gpu" if gpus and config.backend in ("auto", "gpu") else (
            "cpu" if config.backend == "auto" else config.backend)
        values = {**config.as_dict(), "backend": backend}
        on_gpu = backend == "gpu"
        cores = cores_per_gpu(ray.nodes()) if on_gpu else 1
        chunks = [(str(bag), topics, span) for bag, topics, spans, _ in plans
                  for span in spans]
        if not chunks:
            return [[] for _ in plans]
        slots = gpus if on_gpu else int(resources.get("CPU", 1))
        actor = ray.remote(num_gpus=1 if on_gpu else 0, num_cpus=cores)(ChunkWorker)
        workers = [actor.remote(cores) for _ in range(max(1, min(slots, len(chunks))))]
        try:
            results = _dispatch(ray, workers, chunks, values, progress)
        finally:
            for worker in workers:
                ray.kill(worker)
        per_bag, at = [], 0
        for _, _, spans, _ in plans:
            per_bag.append(results[at:at + len(spans)])
            at += len(spans)
        return per_bag
    finally:
        if started_here:
            ray.shutdown()


def _dispatch(ray: Any, workers: Sequence[Any], chunks: Sequence[tuple[str, DriveTopics,
                                                                       LogSpan]],
              values: dict[str, Any], progress: Callable[[int, int], None] | None
              ) -> list[ChunkResult]:
    """The results of ``chunks`` (bag, topics, span) on the ChunkWorker actors ``workers``,
    in order: each worker has up to IN_FLIGHT chunks queued and takes the next one left as
    one of its own ends."""
    results: list[Any] = [None] * len(chunks)
    waiting = list(range(len(chunks)))[::-1]
    running: dict[Any, tuple[int, Any]] = {}

    def feed(worker: Any) -> None:
        if waiting:
            index = waiting.pop()
            bag, topics, span = chunks[index]
            running[worker.observe.remote(bag, topics, values, span)] = (index, worker)

    for _ in range(IN_FLIGHT):
        for worker in workers:
            feed(worker)
    while running:
        (ready,), _ = ray.wait(list(running), num_returns=1)
        index, worker = running.pop(ready)
        results[index] = ray.get(ready)
        if progress is not None:
            progress(len(chunks) - len(waiting) - len(running), len(chunks))
        feed(worker)
    return results


class ChunkWorker:
    """A survey's worker as a Ray actor: on one GPU (the one Ray gave it) or core, with
    OpenCV and the CPU matcher on ``cores`` threads, its share of the node's cores; it
    observes chunks (:func:`~pothole_detector.survey.observe_chunk`) one after the other in
    the same process."""

    def __init__(self, cores: int) -> None:
        set_host_threads(cores)

    def observe(self, bag: str, topics: DriveTopics, values: dict[str, Any],
                span: LogSpan) -> ChunkResult:
        """observe_chunk of one chunk."""
        return observe_chunk(bag, topics, values, span)


def cores_per_gpu(nodes: Sequence[dict[str, Any]]) -> int:
    """The host cores that come with one GPU on the least provisioned live GPU node of
    ``nodes`` (``ray.nodes()``), at least 1: what a GPU worker asks for beside its GPU, so
    that it fits on every GPU node and the GPU workers of a node share its cores."""
    shares = [node["Resources"].get("CPU", 0.0) / node["Resources"]["GPU"] for node in nodes
              if node.get("Alive", True) and node.get("Resources", {}).get("GPU", 0) > 0]
    return max(1, int(min(shares))) if shares else 1
