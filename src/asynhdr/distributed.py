"""Work spread over processes or machines with dask.distributed.

A driver, not an algorithm: it opens files (each worker opens the recording itself, so
only paths and cycle windows travel) and hands the algorithms their parts.

- :func:`scheduler_client`: a ``dask.distributed`` client on a ``LocalCluster`` of worker
  processes on this machine (``"local"``), or on an existing scheduler (its address).
- :func:`simulate_distributed`: a sensor split into pixel ranges, each simulated by a
  worker (:func:`asynhdr.simulate.simulate_cycles`: the same draws as one call), joined by
  :func:`asynhdr.simulate.finish_recording`: the events of one :func:`simulate` call,
  bit for bit.
- :func:`reconstruct_distributed`: a recording split by cycles: the client finds the
  cycles once (the serial command's policy), each worker reconstructs a run of consecutive
  cycles from the file; the images are those of the serial run, bit for bit. The readers
  have no seek by time, so a worker reads the file from its start up to its cycles: the
  decoding of the part before them is repeated, the reconstruction is shared.
- :func:`map_ordered`: independent runs (presets of a bench, scenes of an evaluation) on
  the workers, results in the order given.
"""

from __future__ import annotations

import itertools
import logging
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from asynhdr.events import Recording
from asynhdr.reconstruct import CycleWindows, reconstruct_cycles
from asynhdr.simulate import finish_recording, holds_pixels, simulate_cycles

__all__ = ["map_ordered", "reconstruct_distributed", "scheduler_client",
           "simulate_distributed"]

logger = logging.getLogger(__name__)

T = TypeVar("T")


@contextmanager
def scheduler_client(scheduler: str, *, workers: int | None = None) -> Iterator[Any]:
    """A ``distributed.Client``: ``"local"`` starts a ``LocalCluster`` of ``workers``
    single-threaded worker processes (default: one per core) and stops it on exit; any
    other value is the address of a running scheduler (``tcp://host:8786``)."""
    from distributed import Client, LocalCluster

    if scheduler == "local":
        n = workers or os.cpu_count() or 1
        if n < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        with LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                          dashboard_address=":0") as cluster, Client(cluster) as client:
            yield client
        return
    if workers is not None:
        logger.info("--workers is ignored with an existing scheduler (%s)", scheduler)
    try:
        client = Client(scheduler, timeout="5s")
    except OSError as exc:
        raise ValueError(f"cannot reach the dask scheduler at {scheduler!r}: {exc}") from exc
    with client:
        yield client


def _n_workers(client: Any) -> int:
    return max(1, len(client.scheduler_info().get("workers", {})))


def _split(n: int, parts: int) -> list[tuple[int, int]]:
    """``parts`` consecutive ranges covering ``0 .. n`` (the last ones may be empty)."""
    edges = np.linspace(0, n, parts + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in itertools.pairwise(edges)]


def simulate_distributed(client: Any, scene: Any, *, n_parts: int | None = None,
                         **kwargs: Any) -> Recording:
    """:func:`asynhdr.simulate.simulate` with the sensor split into ``n_parts`` pixel
    ranges (default: the number of workers) simulated on the workers; the result is the
    serial one's, bit for bit. A readout that holds its pixels couples them all
    (:class:`asynhdr.simulate.HeldReadout`): such a sensor is simulated whole, by one
    worker. ``kwargs`` as for ``simulate`` (no ``progress``)."""
    kwargs.pop("progress", None)
    radiance = getattr(scene, "radiance", scene)
    h, w = np.asarray(radiance).shape[-2:]
    parts = n_parts or _n_workers(client)
    if parts > 1 and holds_pixels(scene, **kwargs):
        logger.info("the readout holds its pixels, which couples them all: one worker "
                    "simulates the whole sensor")
        parts = 1
    ranges = _split(h * w, parts)
    shared = client.scatter(scene, broadcast=True)
    futures = [client.submit(simulate_cycles, shared, pixels=r, pure=False, **kwargs)
               for r in ranges]
    return finish_recording(client.gather(futures))


def _reconstruct_run(path: str, first: int, starts: np.ndarray, window_us: float,
                     warmup: int, options: dict[str, Any], source_options: dict[str, Any]
                     ) -> list[tuple[int, int, np.ndarray, dict[str, Any] | None]]:
    from asynhdr.io import open_source
    from asynhdr.io.cmap import load_cmap

    opts = dict(options)
    cmap = opts.pop("cmap", None)
    ml = opts.get("ml_options")
    sink: dict[str, Any] | None = None
    if ml is not None and "out" in ml:  # ml's per-cycle outputs, sent back with each image
        sink = {}
        opts["ml_options"] = dict(ml, out=sink)
    src = open_source(path, **source_options)
    plan = reconstruct_cycles(src, windows=CycleWindows(starts, window_us, warmup=warmup),
                              cmap=load_cmap(cmap) if cmap else None, **opts)
    return [(first + i, int(start), img, dict(sink) if sink is not None else None)
            for i, start, img in plan]


def reconstruct_distributed(client: Any, path: str | os.PathLike[str], windows: CycleWindows,
                            *, n_parts: int | None = None,
                            cmap: str | os.PathLike[str] | None = None,
                            progress: Callable[[str, int, int], None] | None = None,
                            source_options: dict[str, Any] | None = None,
                            **options: Any) -> Iterator[tuple[int, int, np.ndarray]]:
    """The images of :func:`asynhdr.reconstruct.reconstruct_cycles` over ``windows``
    (found once by the caller), the cycles split into ``n_parts`` runs of consecutive
    cycles (default: twice the workers) reconstructed on the workers from the file at
    ``path``, opened with ``source_options`` (``width``, ``height``, ... of
    :func:`asynhdr.io.open_source`). Yields ``(cycle, start_us, image)`` in cycle order.
    ``options``: method, k, thresholds, rig, ml_options, ... as for
    ``reconstruct_cycles``; ``cmap`` a c-map file. ``ml`` without calibrated thresholds
    learns them from cycle to cycle within each run (:class:`asynhdr.ml.LearnedThresholds`),
    so its images differ from the serial run's, where every cycle learns from all before
    it (the first cycle of each run starts from the nominal thresholds, and is fitted
    again from what the run's second cycle taught). As in the serial
    run, an ``"out"`` dict
    in ``ml_options`` holds the yielded cycle's uncertainty and flags when it is yielded."""
    n = windows.n_cycles
    parts = min(n, n_parts or 2 * _n_workers(client))
    opts = dict(options, cmap=str(cmap) if cmap else None)
    ml = opts.get("ml_options")
    sink = ml.get("out") if ml is not None else None
    futures = [client.submit(_reconstruct_run, str(Path(path)), a,
                             windows.start_us[a:b], windows.window_us,
                             max(0, min(windows.warmup - a, b - a)), opts,
                             dict(source_options or {}), pure=False)
               for a, b in _split(n, parts) if b > a]
    done = 0
    for fut in futures:
        for i, start, img, extra in fut.result():
            if sink is not None and extra is not None:
                sink.clear()
                sink.update(extra)
            yield i, start, img
            done += 1
            if progress is not None:
                progress("reconstruct", done, n)


def map_ordered(client: Any | None, fn: Callable[..., T], items: Sequence[Any],
                **kwargs: Any) -> list[T]:
    """``[fn(item, **kwargs) for item in items]``, on the workers when ``client`` is given
    (results in the order of ``items``)."""
    if client is None:
        return [fn(item, **kwargs) for item in items]
    futures = [client.submit(fn, item, pure=False, **kwargs) for item in items]
    return list(client.gather(futures))
