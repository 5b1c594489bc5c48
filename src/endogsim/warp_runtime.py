"""NVIDIA Warp plumbing shared by every module that launches Warp kernels (the simulator in
:mod:`endogsim.physics`, the CPU renderer in :mod:`endogsim.gaussians.rasterize_warp`, the HexPlane
sampler in :mod:`endogsim.recon.hexplane_warp`): start-up, torch interop, split launches, and building the
kernels of a later stage in another process while an earlier one runs (:func:`kernels_built_aside`).

Warp runs a CPU launch serially, as native code, and releases the GIL while it runs; :func:`launch_split`
therefore splits a launch over independent items (pixels, points) into interleaved bands, one per torch
thread, launched from a small thread pool. Kernels launched that way take ``(band, n_bands)`` as their
last scalar arguments and handle item ``wp.tid() * n_bands + band``; a band must not write where another
band writes (accumulate into one buffer per band, then sum).
"""

from __future__ import annotations

import functools
import importlib
import os
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from contextlib import contextmanager
from typing import Callable, TypeVar

import torch
import warp as wp

__all__ = ["init_warp", "KERNEL_MODULES", "build_kernels", "kernels_built_aside", "warp_array", "warp_device",
           "float_vector", "n_bands", "launch_split", "independent_runs", "torch_threads",
           "simulations_side_by_side", "cpu_cores",
           "run_independent", "check_cancelled", "Cancelled", "simulation_bytes", "available_memory"]

_ready = False
_POOL: ThreadPoolExecutor | None = None
_LAUNCHED: set = set()  # (kernel, device, argument types) launched once already
_FIRST_LAUNCH = threading.Lock()  # a first launch (and the pool) from one thread at a time
_aside = False  # a kernels_built_aside process runs for this process
_side_by_side: int | None = None  # simulations_side_by_side's count (None: one per torch thread)
R = TypeVar("R")


def init_warp() -> None:
    """``wp.init()`` on first use, with Warp's start-up and module-load INFO lines silenced, and without
    the native "Could not find or load the NVIDIA CUDA driver" line on machines that have no GPU (CPU runs
    are the normal case here, not a fault); anything else Warp writes to stderr at start-up is kept."""
    global _ready
    if not _ready:
        wp.config.log_level = max(int(wp.config.log_level), 30)
        _quiet_native_stderr(wp.init, drop="Could not find or load the NVIDIA CUDA driver")
        _ready = True


def _quiet_native_stderr(fn: Callable, drop: str) -> None:
    """Call ``fn`` with file descriptor 2 captured (native code writes there directly, past ``sys.stderr``)
    and re-emit the captured lines except those containing ``drop``."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no real stderr (embedded interpreters): nothing to filter
        fn()
        return
    with tempfile.TemporaryFile(mode="w+b") as captured:
        os.dup2(captured.fileno(), 2)
        try:
            fn()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        kept = [ln for ln in captured.read().decode(errors="replace").splitlines(keepends=True) if drop not in ln]
    if kept:
        sys.stderr.write("".join(kept))


#: The Python modules that hold the pipeline's Warp kernels: the Gaussian renderer, the reconstruction's
#: HexPlane sampler, the simulator, and the hand-written adjoints of its transfers (identification).
KERNEL_MODULES = {
    "render": "endogsim.gaussians.rasterize_warp",
    "hexplane": "endogsim.recon.hexplane_warp",
    "simulate": "endogsim.physics.kernels",
    "adjoints": "endogsim.physics.transfer_adjoints",
}


def build_kernels(modules: Sequence[str], device: str = "cpu") -> None:
    """Build the Warp kernels of the Python ``modules`` (names) for ``device``, or find them in Warp's kernel
    cache (milliseconds): what their first launch would otherwise do."""
    init_warp()
    for name in modules:
        wp.load_module(importlib.import_module(name), device=device)


@contextmanager
def kernels_built_aside(modules: Sequence[str]) -> Iterator[subprocess.Popen | None]:
    """Build the CPU kernels of ``modules`` in a separate low-priority process while the body runs.

    Warp builds a module's native code on its first launch, once per machine (its kernel cache keeps it):
    20-30 s for the pipeline's kernels on a 2-core CPU, in the middle of a run that computes on one core.
    A stage's kernels built aside while an earlier stage runs are found in the cache when it starts.
    Nothing a run computes depends on it: a module the body reaches before the other process has written it
    is built by the body as usual (Warp writes each build under a per-process name and renames it into
    place, so the two never see half a module). The process ends with the body (stopped if it is still
    building). Inside another ``kernels_built_aside`` (the demo runs the pipeline) it starts nothing.
    """
    global _aside
    with _FIRST_LAUNCH:
        start = bool(modules) and not _aside
        _aside = _aside or start
    if not start:
        yield None
        return
    cmd = [sys.executable, "-c", "import os, sys\nif hasattr(os, 'nice'): os.nice(10)\n"
           "from endogsim.warp_runtime import build_kernels\nbuild_kernels(sys.argv[1:])", *modules]
    env = dict(os.environ, OMP_NUM_THREADS="1", CUDA_VISIBLE_DEVICES="")  # CPU kernels: no CUDA context
    try:
        proc = subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
    except (OSError, subprocess.SubprocessError):  # no process to spare: the body builds its kernels itself
        proc = None
    try:
        yield proc
    finally:
        _aside = False
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def warp_array(t: torch.Tensor, dtype=None):
    """A zero-copy Warp view of a (made contiguous) torch tensor; ``dtype`` a Warp vector type to view the
    last dimension as vectors."""
    init_warp()
    return wp.from_torch(t.contiguous(), dtype=dtype)


def warp_device(t: torch.Tensor) -> str:
    """The Warp device of a torch tensor."""
    return "cpu" if t.device.type == "cpu" else f"cuda:{t.device.index or 0}"


@functools.lru_cache(maxsize=None)
def float_vector(n: int):
    """The Warp vector type of ``n`` float32 channels (generic kernels compile one instance per length)."""
    return wp.types.vector(length=n, dtype=wp.float32)


def n_bands(device: str, n_items: int, min_items: int = 4096) -> int:
    """Bands a launch over ``n_items`` is split into: one per torch thread on CPU (at most 8), one on CUDA."""
    return 1 if device != "cpu" or n_items < min_items else max(1, min(torch.get_num_threads(), 8))


@contextmanager
def torch_threads(threads: int | None) -> Iterator[None]:
    """Run the body with ``threads`` torch threads (None: the process's setting), then put the process's
    setting back (the thread count is the budget of Warp's CPU bands and trials side by side too)."""
    before = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def independent_runs(device: str, bytes_per_run: int = 0) -> int:
    """How many independent simulations to run at a time on ``device`` (e.g. an interval's trials): on a
    CPU one per torch thread, or :func:`simulations_side_by_side`'s count where it is set, at most 4 (Warp
    runs each CPU launch on one core; ``OMP_NUM_THREADS`` or ``torch.set_num_threads`` is the budget: set it
    to 1 when timing beside other jobs), and no more than half the memory available now holds at
    ``bytes_per_run`` each (:func:`simulation_bytes`; at least one); on CUDA one (its launches share the GPU)."""
    budget = torch.get_num_threads() if _side_by_side is None else _side_by_side
    runs = 1 if device != "cpu" else max(1, min(budget, 4))
    free = available_memory() if runs > 1 and bytes_per_run > 0 else None
    if free is not None:
        runs = max(1, min(runs, int(0.5 * free // bytes_per_run)))
    return runs


@contextmanager
def simulations_side_by_side(workers: int | None) -> Iterator[None]:
    """Run the body with up to ``workers`` independent simulations at a time on a CPU (:func:`independent_runs`:
    an interval's trials, the backward pass's recomputed segments, the refined correction's simulations),
    whatever the torch thread count (None: one per torch thread). Each simulation computes what it would alone,
    so the results do not depend on ``workers``: a one-thread run (the same reductions on every machine) can
    still use every core for its simulations."""
    global _side_by_side
    if workers is not None and workers < 1:
        raise ValueError(f"workers = {workers} must be >= 1 (or None)")
    before, _side_by_side = _side_by_side, (workers if workers is not None else _side_by_side)
    try:
        yield
    finally:
        _side_by_side = before


def cpu_cores() -> int:
    """The cores this process may run on (its CPU affinity), no more than ``OMP_NUM_THREADS`` where that is
    set (the budget of a job timed beside others)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        cores = os.cpu_count() or 1
    try:
        cap = int(os.environ.get("OMP_NUM_THREADS", ""))
    except ValueError:
        cap = 0
    return max(1, min(cores, cap) if cap > 0 else cores)


def simulation_bytes(num_particles: int, num_frames: int, grid_res: int) -> int:
    """Memory (bytes) one simulation keeps while it runs: every frame's particle positions and deformation
    gradients (float32), its particle-grid transfer buffers and its grid (mass, momentum, velocity, collider
    marks)."""
    return 4 * (num_frames * num_particles * 12 + num_particles * 25 + grid_res ** 3 * 12)


def available_memory() -> int | None:
    """Bytes of memory new allocations can take now (Linux's MemAvailable), or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


class Cancelled(BaseException):
    """Raised in a task of :func:`run_independent` that starts work after another task failed (a
    ``BaseException``: no handler of the tasks' own errors catches it)."""


def run_independent(tasks: list[Callable[[], R]], workers: int, cancel: threading.Event | None = None) -> list[R]:
    """The results of independent ``tasks``, in order, computed ``workers`` at a time in threads.

    Warp runs a CPU launch serially and releases the GIL while it runs, so on a CPU each simulation keeps
    one core busy and two at a time use both cores of a 2-core laptop (renders split over the same cores:
    :func:`launch_split`). The results are the same for any ``workers``: each task computes what it would
    alone, and an error raised is that of the first task, in order, that failed. When a task fails, the
    tasks not started yet are dropped and ``cancel`` (if given) is set, for long tasks to stop between
    their steps (:func:`check_cancelled`); a running task cannot be interrupted (native code), so its step
    ends first. Ctrl-C returns at once.
    """
    if workers <= 1 or len(tasks) <= 1:
        return [task() for task in tasks]
    cancel = cancel if cancel is not None else threading.Event()
    pool = ThreadPoolExecutor(max_workers=min(workers, len(tasks)), thread_name_prefix="endogsim-task")
    futures = [pool.submit(task) for task in tasks]

    def stop_on_error(f) -> None:
        if not f.cancelled() and f.exception() is not None:
            cancel.set()
            for g in futures:
                g.cancel()  # the ones not started (a running one is not cancellable)

    for f in futures:
        f.add_done_callback(stop_on_error)
    try:
        wait(futures)
    except BaseException:  # Ctrl-C in the caller's thread
        cancel.set()
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=False)
    errors = [f.exception() for f in futures if not f.cancelled() and f.exception() is not None]
    if errors:
        raise next((e for e in errors if not isinstance(e, Cancelled)), errors[0])
    return [f.result() for f in futures]


def check_cancelled(cancel: threading.Event | None) -> None:
    """Raise :class:`Cancelled` when ``cancel`` is set (a task of :func:`run_independent` whose siblings failed)."""
    if cancel is not None and cancel.is_set():
        raise Cancelled()


def launch_split(kernel, n_items: int, device: str, bands: int, inputs: Callable[[int, int], list]) -> None:
    """Launch ``kernel`` over ``n_items`` items in ``bands`` interleaved bands, each from its own thread.

    Args:
        inputs: callable(band, n_bands) -> the kernel's argument list for that band.
    """
    global _POOL
    init_warp()
    args = [inputs(b, bands) for b in range(bands)]
    dims = [-(-(n_items - b) // bands) for b in range(bands)]
    # Warp builds a kernel overload on its first launch, which is not safe from several threads at once.
    key = (kernel.key, device, tuple(type(a) for a in args[0]), tuple(getattr(a, "dtype", None) for a in args[0]))
    if bands == 1:
        for dim, a in zip(dims, args):
            wp.launch(kernel, dim=dim, inputs=a, device=device)
        return
    with _FIRST_LAUNCH:  # several callers (run_independent's tasks) may launch at once
        if key not in _LAUNCHED:
            for dim, a in zip(dims, args):
                wp.launch(kernel, dim=dim, inputs=a, device=device)
            _LAUNCHED.add(key)
            return
        if _POOL is None or _POOL._max_workers < bands:
            _POOL = ThreadPoolExecutor(max_workers=bands, thread_name_prefix="endogsim-warp")
        pool = _POOL
    jobs = [pool.submit(wp.launch, kernel, dim=dim, inputs=a, device=device) for dim, a in zip(dims, args)]
    for job in jobs:
        job.result()
