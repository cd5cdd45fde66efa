"""Backends that run a list of cells: ``local`` (serial or N workers) and ``ray``.

Every backend runs each cell through :func:`~kneas_method.bench.cells.run_cell`
(an ordinary ``kneas-train`` subprocess) and reports each result through
``on_result(cell, result)`` as soon as it is known. A failed cell is recorded
and the others go on.

- :class:`LocalBackend` ``(workers=1)``: one run after another. ``workers=N``:
  N runs at a time; when CUDA GPUs are visible each worker gets its own GPU
  through ``CUDA_VISIBLE_DEVICES`` (worker i -> GPU i mod #GPUs), otherwise
  they are N CPU workers sharing the cores (``OMP_NUM_THREADS`` = cores / N).
- :class:`RayBackend` ``(address=None)``: one Ray task per cell. ``address``
  ``auto`` or ``HOST:PORT`` joins a running cluster (``ray start --head`` ...);
  without one, a local Ray instance is started (and stopped afterwards). On a
  cluster with GPUs each task asks for ``num_gpus=1`` (Ray then sets
  ``CUDA_VISIBLE_DEVICES``), else for ``cpus_per_cell`` CPUs. On a multi-machine
  cluster, ``--output-dir`` must be a folder every node sees at the same path
  (a shared file system) and kneas must be installed on every node.
"""

from __future__ import annotations

import os
import queue
import threading
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Callable, Optional, Sequence

from ..engine.run_dir import write_json
from ..errors import ConfigError, missing_optional
from .cells import CellResult, cell_dir, mark_interrupted, run_cell
from .grid import DEFAULT_TRAIN_PREFIX, Cell

OnResult = Callable[[Cell, CellResult], None]
OnStart = Callable[[Cell], None]


def visible_gpus() -> list[str]:
    """CUDA device ids this process may use (respects an existing ``CUDA_VISIBLE_DEVICES``)."""
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    if env is not None:
        return [d.strip() for d in env.split(",") if d.strip() and d.strip() != "-1"]
    try:
        import torch

        return [str(i) for i in range(torch.cuda.device_count())]
    except Exception:  # pragma: no cover - torch is a dependency
        return []


def cpu_count() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - non-Linux
        return os.cpu_count() or 1


class LocalBackend:
    """Runs cells on this machine: serially, or ``workers`` at a time."""

    name = "local"

    def __init__(self, workers: int = 1, gpus: Optional[Sequence[str]] = None):
        if workers < 1:
            raise ConfigError(f"--workers must be at least 1, got {workers}")
        self.workers = workers
        self.gpus = list(visible_gpus() if gpus is None else gpus)

    def describe(self) -> str:
        if self.workers == 1:
            return "local, one run after another" + (f" (GPU {self.gpus[0]})" if self.gpus else " (CPU)")
        if self.gpus:
            return f"local, {self.workers} workers on GPUs {', '.join(self.gpus)} (CUDA_VISIBLE_DEVICES per worker)"
        return f"local, {self.workers} CPU workers ({max(1, cpu_count() // self.workers)} threads each)"

    def _env(self, slot: int) -> Optional[dict[str, str]]:
        if self.workers == 1 and not self.gpus:
            return None
        env = dict(os.environ)
        if self.gpus:
            env["CUDA_VISIBLE_DEVICES"] = self.gpus[slot % len(self.gpus)]
        else:
            threads = str(max(1, cpu_count() // self.workers))
            env.setdefault("OMP_NUM_THREADS", threads)
            env.setdefault("MKL_NUM_THREADS", threads)
        return env

    def run(self, cells: Sequence[Cell], output_dir: str | Path, prefix: Sequence[str] = DEFAULT_TRAIN_PREFIX,
            on_result: Optional[OnResult] = None, on_start: Optional[OnStart] = None) -> list[CellResult]:
        results: list[CellResult] = []
        if self.workers == 1:
            for cell in cells:
                if on_start:
                    on_start(cell)
                r = run_cell(cell, output_dir, prefix, self._env(0))
                results.append(r)
                if on_result:
                    on_result(cell, r)
            return results
        slots: queue.Queue[int] = queue.Queue()
        for i in range(self.workers):
            slots.put(i)
        stop = threading.Event()

        def job(cell: Cell) -> CellResult:
            if stop.is_set():
                return CellResult(cell.id, "cancelled")
            slot = slots.get()
            try:
                if on_start:
                    on_start(cell)
                return run_cell(cell, output_dir, prefix, self._env(slot))
            finally:
                slots.put(slot)

        with ThreadPoolExecutor(max_workers=self.workers, thread_name_prefix="kneas-bench") as pool:
            futures = {pool.submit(job, c): c for c in cells}
            pending = set(futures)
            try:
                while pending:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for f in done:
                        r = f.result()
                        if r.status == "cancelled":
                            continue
                        results.append(r)
                        if on_result:
                            on_result(futures[f], r)
            except BaseException:
                stop.set()
                for f in pending:
                    f.cancel()
                raise
        return results


def _ray_run_cell(cell: Cell, output_dir: str, prefix: list[str], threads: Optional[int]) -> CellResult:
    """The Ray task: one cell on whichever node Ray picked (CUDA_VISIBLE_DEVICES set by Ray)."""
    env = dict(os.environ)
    if threads:
        env["OMP_NUM_THREADS"] = env["MKL_NUM_THREADS"] = str(threads)
    return run_cell(cell, output_dir, prefix, env)


def _raise_interrupt(signum, frame):  # pragma: no cover - signal path
    raise KeyboardInterrupt


def _sigterm_as_interrupt() -> None:
    """SIGTERM -> KeyboardInterrupt, so a killed kneas-bench cancels its runs and stops Ray it started."""
    import signal

    try:
        signal.signal(signal.SIGTERM, _raise_interrupt)
    except ValueError:  # not the main thread
        pass


def import_ray():
    try:
        import ray
    except ImportError:
        raise missing_optional("ray", "distributed", "the ray backend") from None
    return ray


class RayBackend:
    """One Ray task per cell, on a running cluster (``address``) or a local instance started here."""

    name = "ray"

    def __init__(self, address: Optional[str] = None, num_cpus: Optional[int] = None, cpus_per_cell: int = 1,
                 object_store_memory: int = 256 * 2**20):
        self.ray = import_ray()
        if cpus_per_cell < 1:
            raise ConfigError(f"--cpus-per-cell must be at least 1, got {cpus_per_cell}")
        self.address = address
        self.num_cpus = num_cpus
        self.cpus_per_cell = cpus_per_cell
        self.object_store_memory = object_store_memory
        self._started_here = False
        self._gpus = 0.0

    def describe(self) -> str:
        where = f"cluster at {self.address}" if self.address else "a local Ray instance started by kneas-bench"
        return f"ray ({where})"

    def start(self) -> dict:
        ray = self.ray
        if not ray.is_initialized():
            kwargs = dict(include_dashboard=False, log_to_driver=False, logging_level="ERROR")
            if self.address:
                try:
                    ray.init(address=self.address, **kwargs)
                except (ConnectionError, RuntimeError, ValueError) as exc:
                    first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                    raise ConfigError(f"could not connect to the Ray cluster at {self.address} ({first}); "
                                      "start one with 'ray start --head' or drop --address to start a local instance") from None
            else:
                ray.init(num_cpus=self.num_cpus or cpu_count(), object_store_memory=self.object_store_memory, **kwargs)
                self._started_here = True
        _sigterm_as_interrupt()  # ray.init installs a handler that aborts on SIGTERM; stop cleanly instead
        resources = ray.cluster_resources()
        self._gpus = float(resources.get("GPU", 0.0))
        return resources

    def stop(self) -> None:
        if self._started_here and self.ray.is_initialized():
            self.ray.shutdown()
            self._started_here = False

    def run(self, cells: Sequence[Cell], output_dir: str | Path, prefix: Sequence[str] = DEFAULT_TRAIN_PREFIX,
            on_result: Optional[OnResult] = None, on_start: Optional[OnStart] = None) -> list[CellResult]:
        ray = self.ray
        self.start()
        try:
            if self._gpus > 0:
                options = dict(num_gpus=1, num_cpus=self.cpus_per_cell)
            else:
                options = dict(num_cpus=self.cpus_per_cell)
            task = ray.remote(max_retries=0)(_ray_run_cell).options(**options)
            out = str(Path(output_dir).resolve())
            refs = {}
            for cell in cells:
                refs[task.remote(cell, out, list(prefix), None if self._gpus > 0 else self.cpus_per_cell)] = cell
            pending = list(refs)
            results: list[CellResult] = []
            try:
                while pending:
                    ready, pending = ray.wait(pending, num_returns=1)
                    for ref in ready:
                        cell = refs[ref]
                        try:
                            r = ray.get(ref)
                        except Exception as exc:  # the task itself died (worker crash, node lost)
                            msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
                            r = CellResult(cell.id, "failed", error=f"ray task failed: {msg}")
                            folder = cell_dir(output_dir, cell)
                            write_json(folder / "cell.json", {"cell": cell.to_dict(), "status": "failed", "error": r.error})
                        results.append(r)
                        if on_result:
                            on_result(cell, r)
            except BaseException:
                for ref in pending:
                    try:
                        ray.cancel(ref, force=True)
                    except Exception:
                        pass
                for ref in pending:
                    mark_interrupted(output_dir, refs[ref])
                raise
            return results
        finally:
            self.stop()


def make_backend(name: str, workers: int = 1, address: Optional[str] = None, cpus_per_cell: int = 1):
    if name == "local":
        if address:
            raise ConfigError("--address is for the ray backend; add --backend ray or drop --address")
        return LocalBackend(workers)
    if name == "ray":
        return RayBackend(address=address, num_cpus=None, cpus_per_cell=cpus_per_cell)
    raise ConfigError(f"unknown backend {name!r}; choose local or ray")
