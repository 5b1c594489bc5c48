"""``endogsim bench mpm``: throughput and memory of the Warp MLS-MPM simulator.

For each device (CPU, and CUDA when Warp sees a GPU) and particle count (8k, 32k, 128k by default) on a
50^3 grid: forward particle-substeps per second, forward+backward (``frame`` gradient mode) particle-
substeps per second, the backward/forward time ratio, and (at 32k) the peak memory of a 20-frame
``full``-mode rollout, measured in a fresh child process so earlier cases do not count (CPU: peak resident
set size of that whole process, Python + torch + Warp included; CUDA: Warp's memory-pool high-water mark).

``--threads 1,2`` measures every case at each torch thread count, side by side in one run (this machine's
speed drifts between runs): a CPU launch runs on one core, and with two or more threads the backward pass
recomputes the next frame on a second thread while this frame's adjoints run (:mod:`endogsim.physics.rollout`).

Scene: a jelly block (8 particles per grid cell) under gravity on a fixed base, E = 1e4 Pa, nu = 0.3,
rho = 1000 kg/m^3 in a 0.1 m box, fixed corotated, 25 substeps of 2e-4 s per frame (the paper's numerics).
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time

GRID = 50
BOX = 0.1  # metres


def _scene(particles: int, device: str):
    import torch

    from endogsim.physics import Anchor, MPMConfig, Particles, Scenario, SimBox

    spacing = BOX / GRID / 2  # 8 particles per cell
    side = round(particles ** (1 / 3)) * spacing
    lo = (BOX - side) / 2
    parts = Particles.box((lo, lo, lo), (lo + side, lo + side, lo + side), spacing)
    scen = Scenario(SimBox((0.0, 0.0, 0.0), BOX), gravity=(0.0, -9.81, 0.0),
                    anchors=[Anchor(lo=(0.0, 0.0, 0.0), hi=(BOX, lo + 2 * spacing, BOX), kind="fixed")])
    cfg = MPMConfig(grid_res=GRID, substeps_per_frame=25, frame_dt=25 * 2e-4, device=device)
    mats = (torch.tensor([4.0], dtype=torch.float64), torch.tensor([0.3], dtype=torch.float64),
            torch.tensor([1000.0], dtype=torch.float64))
    return parts, scen, cfg, mats


def _materials(log10_E, nu, rho):
    from endogsim.physics import ObjectMaterials

    return ObjectMaterials.of(10.0 ** log10_E, nu, rho, "fixed_corotated")


def measure(particles: int, device: str, frames: int, threads: int | None = None) -> dict:
    """Forward and forward+backward (frame mode) throughput for one case, with ``threads`` torch threads
    (None: the process's setting, which is put back after)."""
    import torch

    from endogsim.warp_runtime import torch_threads

    with torch_threads(threads):
        return {"threads": torch.get_num_threads(), **_measure(particles, device, frames)}


def _measure(particles: int, device: str, frames: int) -> dict:
    import torch

    from endogsim.physics import mpm_rollout

    parts, scen, cfg, (lE, nu, rho) = _scene(particles, device)
    T = frames + 1
    # Warm-up (kernel compile / load, first allocations).
    mpm_rollout(parts, _materials(lE, nu, rho), scen, cfg, 2, grad_mode="frame")

    t0 = time.perf_counter()
    with torch.no_grad():
        pos, _ = mpm_rollout(parts, _materials(lE, nu, rho), scen, cfg, T, grad_mode="frame")
    t_fwd = time.perf_counter() - t0

    lE_, nu_, rho_ = (a.clone().requires_grad_(True) for a in (lE, nu, rho))
    t0 = time.perf_counter()
    pos, F = mpm_rollout(parts, _materials(lE_, nu_, rho_), scen, cfg, T, grad_mode="frame")
    t_mid = time.perf_counter()
    (pos[1:] - parts.x).square().sum().backward()
    t_end = time.perf_counter()
    work = len(parts) * cfg.substeps_per_frame * frames
    return {
        "device": device, "particles": len(parts), "grid": f"{GRID}^3",
        "forward_pss": work / t_fwd,
        "backward_pss": work / (t_end - t0),
        "backward_over_forward": (t_end - t_mid) / max(t_mid - t0, 1e-9),
        "peak_mem_mb": None,
    }


def _peak_child(particles: int, device: str, frames: int) -> None:
    """Run in a fresh process: a full-mode rollout with backward; print peak memory as JSON."""
    import torch
    import warp as wp

    from endogsim.physics import mpm_rollout

    parts, scen, cfg, (lE, nu, rho) = _scene(particles, device)
    lE = lE.clone().requires_grad_(True)
    pos, F = mpm_rollout(parts, _materials(lE, nu, rho), scen, cfg, frames + 1, grad_mode="full")
    (pos[1:] - parts.x).square().sum().backward()
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    gpu_mb = None
    if device.startswith("cuda"):
        gpu_mb = wp.get_mempool_used_mem_high(device) / 2**20
    print(json.dumps({"rss_mb": rss_mb, "gpu_mb": gpu_mb, "finite": bool(torch.isfinite(lE.grad).all())}))


def peak_memory_mb(particles: int, device: str, frames: int) -> float:
    code = f"from endogsim.bench.mpm import _peak_child; _peak_child({particles}, {device!r}, {frames})"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=3600)
    if out.returncode != 0:
        raise RuntimeError(f"full-mode memory run failed: {out.stderr[-2000:]}")
    rec = json.loads(out.stdout.strip().splitlines()[-1])
    return rec["gpu_mb"] if rec["gpu_mb"] is not None else rec["rss_mb"]


def run_bench(sizes: list[int], frames: int, mem_frames: int, devices: list[str], memory: bool = True,
              threads: list[int] | None = None) -> list[dict]:
    """One row per device, particle count and thread count (``threads``; None: the process's setting);
    the peak memory once per device at 32k particles."""
    cases = []
    for device in devices:
        for n in sizes:
            for k, t in enumerate(threads or [None]):
                row = measure(n, device, frames, t)
                if memory and n == 32768 and k == 0:
                    row["peak_mem_mb"] = peak_memory_mb(n, device, mem_frames)
                cases.append(row)
    return cases
