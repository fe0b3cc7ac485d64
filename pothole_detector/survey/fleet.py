"""Surveys on Ray: the chunks of frames of every bag go to one worker per GPU of the cluster
(with the host cores that come with a GPU; on a cluster without GPUs, one per core), on the
cluster at an address or a local one. Ray is an optional extra: ``pip install .[fleet]``."""

from __future__ import annotations

import itertools
import queue
import threading
from typing import Any, Callable, Iterator, Sequence

from ..recordings.bags import LogSpan
from ..errors import InputError
from ..params import Config
from ..stages.matching import set_host_threads
from .drive import ChunkResult, ChunkRunner, DriveTopics, Plan, in_plan_order, observe_chunk


def ray_chunks(address: str | None = None) -> ChunkRunner:
    """The chunk runner of survey.survey that runs the chunks on Ray (:func:`observe_on_ray`),
    on the cluster at ``address``, or a local one."""
    return lambda plans, config, progress: observe_on_ray(plans, config, address, progress)


IN_FLIGHT = 2


def observe_on_ray(plans: Sequence[Plan], config: Config, address: str | None = None,
                   progress: Callable[[int, int], None] | None = None
                   ) -> Iterator[list[ChunkResult]]:
    """:func:`~pothole_detector.survey.observe_chunk` of every (bag, topics, chunk spans)
    plan on Ray; per bag, in chunk order, each bag as soon as its chunks are done. One
    :class:`ChunkWorker` actor per GPU of the cluster (per CPU core on the CPU backend) takes
    the chunks in turn, IN_FLIGHT of them queued at a time, so that a worker's next chunk is
    there when one ends: a worker keeps its process, GPU, compiled kernels, memory pool and
    bag readers from one chunk to the next (a Ray task that holds a GPU gets a fresh process
    each time). The chunks are handed out by a thread of this process, so that the workers
    are kept busy while the caller works on the bags given so far. The bags must be readable
    at the same path on every node."""
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
        counts = [len(spans) for _, _, spans, _ in plans]
        if not chunks:
            yield from ([] for _ in plans)
            return
        slots = gpus if on_gpu else int(resources.get("CPU", 1))
        actor = ray.remote(num_gpus=1 if on_gpu else 0, num_cpus=cores)(ChunkWorker)
        workers = [actor.remote(cores) for _ in range(max(1, min(slots, len(chunks))))]
        dispatch = Dispatch(ray, workers, chunks, values, progress)
        try:
            starts = list(itertools.accumulate(counts, initial=0))
            for plan in in_plan_order(counts, dispatch.finished()):
                yield dispatch.results[starts[plan]:starts[plan] + counts[plan]]
        finally:
            dispatch.stop()
            for worker in workers:
                ray.kill(worker)
            dispatch.join()
    finally:
        if started_here:
            ray.shutdown()


class Dispatch:
    """The chunks (bag, topics, span) handed to the ChunkWorker actors ``workers`` by a thread
    of its own: each worker has up to IN_FLIGHT chunks queued and takes the next one left as
    one of its own ends; ``results`` (in chunk order) fill in as they come."""

    def __init__(self, ray: Any, workers: Sequence[Any],
                 chunks: Sequence[tuple[str, DriveTopics, LogSpan]], values: dict[str, Any],
                 progress: Callable[[int, int], None] | None) -> None:
        self.results: list[Any] = [None] * len(chunks)
        self._ray, self._workers, self._chunks = ray, workers, chunks
        self._values, self._progress = values, progress
        self._done: queue.Queue = queue.Queue()
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ray-dispatch", daemon=True)
        self._thread.start()

    def finished(self) -> Iterator[int]:
        """The chunks' indices as their results come; raises what stopped the hand-out."""
        for _ in self._chunks:
            index = self._done.get()
            if isinstance(index, BaseException):
                raise index
            yield index

    def stop(self) -> None:
        """Hand out no more chunks."""
        self._stopping.set()

    def join(self, timeout_s: float = 30.0) -> None:
        """Wait (at most ``timeout_s``) for the thread to end: all results in, or the workers
        gone."""
        self._thread.join(timeout_s)

    def _run(self) -> None:
        ray = self._ray
        waiting = list(range(len(self._chunks)))[::-1]
        running: dict[Any, tuple[int, Any]] = {}

        def feed(worker: Any) -> None:
            if waiting and not self._stopping.is_set():
                index = waiting.pop()
                bag, topics, span = self._chunks[index]
                running[worker.observe.remote(bag, topics, self._values, span)] = (index,
                                                                                   worker)

        try:
            for _ in range(IN_FLIGHT):
                for worker in self._workers:
                    feed(worker)
            while running and not self._stopping.is_set():
                (ready,), _ = ray.wait(list(running), num_returns=1)
                index, worker = running.pop(ready)
                self.results[index] = ray.get(ready)
                if self._progress is not None:
                    self._progress(len(self._chunks) - len(waiting) - len(running),
                                   len(self._chunks))
                self._done.put(index)
                feed(worker)
        except BaseException as exc:  # noqa: BLE001 (handed to the caller's thread)
            self._done.put(exc)


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
