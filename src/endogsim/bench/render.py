"""``endogsim bench render``: speed and peak memory of the differentiable renderer.

Cases: 5k Gaussians at 160x128, 50k at 320x256, 200k at 640x512, on a procedural tissue-like scene
(Gaussians spread over a wavy, textured surface that fills the view, each about one inter-Gaussian
spacing wide on screen, so every pixel is covered by ~20 overlapping splats as in a trained 3DGS model).

Method:
  * forward_s: one ``rasterize`` call with gradients enabled (as in a training step), median of repeats.
  * forward_backward_s: ``rasterize`` + backward of a loss on rgb, depth and alpha, median of repeats.
  * peak_mem_mb: every case runs in a fresh Python subprocess. On CPU this is the process's peak resident
    set size (``resource.getrusage(...).ru_maxrss``: everything, including the interpreter and torch's
    own ~0.3 GB; ``baseline_mb`` in the JSON is the RSS before the scene was built). On CUDA it is
    ``torch.cuda.max_memory_allocated``.
"""

from __future__ import annotations

import json
import math
import resource
import statistics
import subprocess
import sys
import time
from typing import Any

import torch

CASES = [(5_000, 160, 128), (50_000, 320, 256), (200_000, 640, 512)]


def make_bench_scene(n: int, width: int, height: int, seed: int = 0, device: str = "cpu") -> dict[str, Any]:
    """A tissue-like test scene: n Gaussians on a textured wavy surface 6-8 cm in front of the camera.

    Returns a dict with leaf tensors ``means`` [n, 3] (m), ``quats`` [n, 4], ``scales`` [n, 3] (m),
    ``opacities`` [n], ``colors`` [n, 3], and ``camera`` (focal = 0.8 width, about a 64 degree view).
    """
    from endogsim.gaussians.camera import Camera
    from endogsim.gaussians.model import rotmat_to_quat

    g = torch.Generator().manual_seed(seed)
    focal = 0.8 * width
    cam = Camera.from_focal(focal, width, height)
    # Jittered grid over the image (with a 3% margin outside it), then back-projected onto the surface.
    gx = max(1, round(math.sqrt(n * width / height)))
    gy = math.ceil(n / gx)
    cell = torch.randperm(gx * gy, generator=g)[:n]
    u = ((cell % gx + torch.rand(n, generator=g)) / gx * 1.06 - 0.03) * width
    v = ((cell // gx + torch.rand(n, generator=g)) / gy * 1.06 - 0.03) * height
    xn, yn = (u - width / 2) / focal, (v - height / 2) / focal
    z = 0.07 + 0.005 * torch.sin(9 * xn + 2) * torch.cos(7 * yn) + 0.01 * yn
    means = torch.stack([xn * z, yn * z, z], 1)
    # Surface normal from the depth gradient, a disc-like Gaussian in the tangent plane.
    dzdx = 0.005 * 9 * torch.cos(9 * xn + 2) * torch.cos(7 * yn) / z
    dzdy = (-0.005 * 7 * torch.sin(9 * xn + 2) * torch.sin(7 * yn) + 0.01) / z
    normal = torch.nn.functional.normalize(torch.stack([-dzdx, -dzdy, torch.ones_like(z)], 1), dim=1)
    t1 = torch.nn.functional.normalize(torch.linalg.cross(normal, torch.randn(n, 3, generator=g)), dim=1)
    t2 = torch.linalg.cross(normal, t1)
    quats = rotmat_to_quat(torch.stack([t1, t2, normal], 2))
    spacing_px = math.sqrt(width * height / n)
    sigma_px = 0.8 * spacing_px * torch.exp(0.25 * torch.randn(n, 2, generator=g))
    scales = torch.cat([sigma_px * (z / focal)[:, None], (0.1 * spacing_px * z / focal)[:, None]], 1)
    # Pink tissue with darker vessel-like streaks and some specular-ish spots.
    vessels = torch.sin(40 * xn + 6 * torch.sin(25 * yn)) * torch.cos(31 * yn + 4 * torch.sin(19 * xn))
    base = torch.tensor([0.78, 0.42, 0.40]) + 0.05 * torch.randn(n, 3, generator=g)
    colors = (base - 0.25 * vessels.clamp_min(0)[:, None] * torch.tensor([0.3, 1.0, 1.0])).clamp(0, 1)
    opacities = (0.55 + 0.44 * torch.rand(n, generator=g))
    out = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors)
    out = {k: t.to(device).requires_grad_(True) for k, t in out.items()}
    out["camera"] = cam.to(device)
    return out


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20


def run_case(n: int, width: int, height: int, backend: str = "torch", repeats: int = 3) -> dict[str, Any]:
    """Time one case in this process (call it in a fresh process to get its peak memory)."""
    from endogsim.gaussians.render import rasterize

    device = "cuda" if backend == "gsplat" else "cpu"
    baseline = _rss_mb()
    scene = make_bench_scene(n, width, height, device=device)
    params = [scene[k] for k in ("means", "quats", "scales", "opacities", "colors")]
    wts = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(1)).to(device)

    def sync():
        if device == "cuda":
            torch.cuda.synchronize()

    def forward():
        return rasterize(scene["means"], scene["opacities"], scene["colors"], scene["camera"], quats=scene["quats"],
                         scales=scene["scales"], backend=backend)

    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    fwd, both = [], []
    out = None
    for i in range(repeats + 1):  # the first round warms up allocators and kernels
        sync()
        t0 = time.perf_counter()
        out = forward()
        sync()
        t1 = time.perf_counter()
        loss = (out.rgb * wts).sum() + out.depth.sum() + out.alpha.sum()
        torch.autograd.grad(loss, params)
        sync()
        t2 = time.perf_counter()
        if i > 0:
            fwd.append(t1 - t0)
            both.append(t2 - t0)
        del loss
    if device == "cuda":
        peak = torch.cuda.max_memory_allocated() / 2**20
    else:
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    return {
        "backend": out.meta["backend"], "gaussians": n, "width": width, "height": height,
        "forward_s": statistics.median(fwd), "forward_backward_s": statistics.median(both),
        "peak_mem_mb": round(peak, 1), "baseline_mb": round(baseline, 1) if device == "cpu" else 0.0,
        "pairs": int(out.meta["n_pairs"]), "coverage": float((out.alpha > 0.5).float().mean()),
    }


def run_case_subprocess(n: int, width: int, height: int, backend: str, repeats: int) -> dict[str, Any]:
    """``run_case`` in a fresh interpreter, so peak memory is this case's alone."""
    code = (
        "import json, sys; from endogsim.bench.render import run_case; "
        f"print('@@' + json.dumps(run_case({n}, {width}, {height}, {backend!r}, {repeats})))"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("@@")]
    if proc.returncode != 0 or not lines:
        from endogsim.errors import EndoGSimError

        raise EndoGSimError(f"benchmark case {n} Gaussians @ {width}x{height} ({backend}) failed: {proc.stderr[-2000:]}")
    return json.loads(lines[-1][2:])
