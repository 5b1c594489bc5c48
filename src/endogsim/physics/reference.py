"""A pure-PyTorch MLS-MPM reference solver for the Warp simulator (gsplat style: a slow, readable
reference beside the fast path).

Same physics as :mod:`endogsim.physics` (quadratic B-splines, APIC/MLS transfer, every registered
constitutive model through its PyTorch twin, per particle; sticky kinematic capsule colliders, anchored
particles, gravity, closed box walls), written in
plain vectorised float64 PyTorch, forward only, no compile step. It exists to check the Warp kernels
(tests/test_physics.py); nothing in the pipeline runs it.

Units: world metres, seconds, kg, Pa (simulating in world units is the same as simulating in a unit sim
box with E_sim = s^2 E, DESIGN.md section 3; the box here only positions the grid).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from endogsim.errors import SimulationError
from endogsim.physics.constitutive import model_id, stress_torch

__all__ = ["Capsule", "MPMProblem", "MPMResult", "run_mpm"]


@dataclass
class Capsule:
    """A kinematic tool collider: segment a-b (metres, world, at frame 0) with radius (metres).

    ``offsets`` [T, 3] is the translation of the tool at each rendered frame (metres, offsets[0] = 0);
    between frames it moves at constant velocity. Grid nodes inside the capsule take the tool velocity
    (sticky contact). A grasping tool ``holds`` particles ([Ph] indices): they move with it from their rest
    positions, and nodes within ``hold_radius`` (metres) of them take its velocity too.
    """

    a: np.ndarray
    b: np.ndarray
    radius: float
    offsets: np.ndarray
    holds: np.ndarray | None = None
    hold_radius: float = 0.0


@dataclass
class MPMProblem:
    """Everything one simulation needs.

    Attributes:
        x: [P, 3] particle positions (metres). vol: [P] particle volumes (m^3).
        mu, lam: [P] Lame parameters (Pa); density: [P] (kg/m^3).
        anchored: [P] bool, particles held at their rest position (boundary conditions).
        box_lo: [3] world corner of the grid (metres); box_size: edge of the cubic grid (metres).
        grid: cells per edge. dt: substep (s). substeps: substeps per rendered frame.
        gravity: [3] m/s^2 (world). tools: kinematic colliders.
        damping: grid velocity decay rate (1/s), a simple model of tissue viscosity.
        model: [P] constitutive model id per particle (:func:`endogsim.physics.constitutive.model_id`);
            default fixed corotated for all.
    """

    x: np.ndarray
    vol: np.ndarray
    mu: np.ndarray
    lam: np.ndarray
    density: np.ndarray
    anchored: np.ndarray
    box_lo: np.ndarray
    box_size: float
    grid: int
    dt: float
    substeps: int
    frames: int
    gravity: np.ndarray
    tools: list[Capsule] = field(default_factory=list)
    damping: float = 0.0
    model: np.ndarray | None = None


@dataclass
class MPMResult:
    """x: [T, P, 3] particle positions (m); F: [T, P, 3, 3] deformation gradients."""

    x: np.ndarray
    F: np.ndarray


_OFFSETS = torch.stack(torch.meshgrid(*(torch.arange(3),) * 3, indexing="ij"), -1).reshape(27, 3)


def _weights(xg: torch.Tensor):
    """Quadratic B-spline stencil of positions in grid units xg [N, 3] -> base [N,3] int, w [N,27], dpos [N,27,3]."""
    base = torch.floor(xg - 0.5).long()
    fx = xg - base
    w = torch.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2], 1)  # [N, 3(stencil), 3(axis)]
    o = _OFFSETS.to(xg.device)
    wn = w[:, o[:, 0], 0] * w[:, o[:, 1], 1] * w[:, o[:, 2], 2]
    dpos = o[None].to(xg.dtype) - fx[:, None]  # grid units
    return base, wn, dpos


def _flat_index(base: torch.Tensor, n: int) -> torch.Tensor:
    idx = base[:, None] + _OFFSETS.to(base.device)[None]
    return (idx[..., 0] * n + idx[..., 1]) * n + idx[..., 2]


def _p2g(mass, momentum, affine, n, dx, stencil):
    """APIC particle to grid: node masses [n^3] and momenta [n^3, 3] of particles with mass [N], momentum
    [N, 3] and affine momentum [N, 3, 3] (node momentum += w (m v + A (node - x)))."""
    base, w, dpos = stencil
    idx = _flat_index(base, n).reshape(-1)
    node_mom = momentum[:, None, :] + torch.einsum("nij,nkj->nki", affine, dpos * dx)
    gm = torch.zeros(n ** 3, dtype=mass.dtype).index_add_(0, idx, (w * mass[:, None]).reshape(-1))
    gmv = torch.zeros(n ** 3, 3, dtype=mass.dtype).index_add_(0, idx, (w[..., None] * node_mom).reshape(-1, 3))
    return gm, gmv


def _g2p(gv, n, inv_dx, stencil):
    base, w, dpos = stencil
    idx = _flat_index(base, n)
    v_nb = gv[idx]  # [N, 27, 3]
    v = (w[..., None] * v_nb).sum(1)
    C = 4 * inv_dx * torch.einsum("nk,nki,nkj->nij", w, v_nb, dpos)
    return v, C


def run_mpm(p: MPMProblem, progress=None) -> MPMResult:
    """Simulate ``p.frames`` rendered frames (frame 0 is the rest state) and return trajectories.

    Raises :class:`SimulationError` when a value becomes NaN/inf or particles reach the grid border.
    """
    dtype = torch.float64
    n, L, dt = p.grid, float(p.box_size), float(p.dt)
    dx = L / n
    inv_dx = 1.0 / dx
    lo = torch.tensor(p.box_lo, dtype=dtype)
    x = torch.tensor(p.x, dtype=dtype) - lo
    x0 = x.clone()
    P = x.shape[0]
    v = torch.zeros_like(x)
    C = torch.zeros(P, 3, 3, dtype=dtype)
    F = torch.eye(3, dtype=dtype).repeat(P, 1, 1)
    vol = torch.tensor(p.vol, dtype=dtype)
    mass = vol * torch.tensor(p.density, dtype=dtype)
    mu, lam = torch.tensor(p.mu, dtype=dtype), torch.tensor(p.lam, dtype=dtype)
    model = torch.full((P,), model_id("fixed_corotated")) if p.model is None else torch.as_tensor(p.model).long()
    anchored = torch.tensor(p.anchored, dtype=torch.bool)
    g = torch.tensor(p.gravity, dtype=dtype)

    # Grid node coordinates (metres, box frame) for the collider test.
    ii = torch.arange(n + 1, dtype=dtype) * dx
    nodes = torch.stack(torch.meshgrid(ii, ii, ii, indexing="ij"), -1).reshape(-1, 3)
    n1 = n + 1
    pad = 2 * dx  # the quadratic stencil and the 2-cell wall band need this margin
    in_tool = []
    for tool in p.tools:
        a = torch.tensor(tool.a, dtype=dtype) - lo
        b = torch.tensor(tool.b, dtype=dtype) - lo
        holds = torch.as_tensor(tool.holds if tool.holds is not None else [], dtype=torch.long)
        in_tool.append((a, b, float(tool.radius), torch.tensor(tool.offsets, dtype=dtype), holds, tool.hold_radius))
    # Boundary: zero velocity in the outer 2 cells of the grid (a closed box).
    ijk = torch.stack(torch.meshgrid(*(torch.arange(n1),) * 3, indexing="ij"), -1).reshape(-1, 3)
    wall = ((ijk < 2) | (ijk > n - 2)).any(1)

    if ((x < pad) | (x > L - pad)).any():
        raise SimulationError("particles lie outside the sim box (or within 2 cells of its walls): enlarge the box")
    # Anchored particles pass on their elastic force but not their mass or momentum (their inertia is the
    # fixed anatomy's), and the nodes they dominate at rest hold still.
    mass_free = torch.where(anchored, torch.zeros_like(mass), mass)
    base0, w0, _ = _weights(x * inv_dx)
    idx0 = _flat_index(base0, n1).reshape(-1)
    w_pin = torch.zeros(n1 ** 3, dtype=dtype).index_add_(0, idx0, (w0 * anchored[:, None]).reshape(-1))
    w_free = torch.zeros(n1 ** 3, dtype=dtype).index_add_(0, idx0, (w0 * ~anchored[:, None]).reshape(-1))
    held = (w_pin > 0) & (w_pin >= w_free)
    xs, Fs = [x.clone()], [F.clone()]
    decay = math.exp(-p.damping * dt)
    for frame in range(1, p.frames):
        for sub in range(p.substeps):
            xg = x * inv_dx
            base, w, dpos = _weights(xg)
            stress = stress_torch(model, F, mu, lam)
            stress = -dt * 4 * inv_dx * inv_dx * vol[:, None, None] * stress
            affine = stress + mass_free[:, None, None] * C
            gm, gmv = _p2g(mass_free, mass_free[:, None] * v, affine, n1, dx, (base, w, dpos))
            has = gm > 1e-12
            gv = torch.zeros_like(gmv)
            gv[has] = gmv[has] / gm[has, None]
            gv[has] += dt * g
            gv *= decay
            for a, b, r, offs, holds, r_hold in in_tool:
                vel = (offs[frame] - offs[frame - 1]) / (p.substeps * dt)
                # Position of the tool during this substep (constant velocity between frames).
                shift = offs[frame - 1] + vel * (sub * dt)
                ab = b - a
                tpar = (((nodes - a - shift) @ ab) / (ab @ ab)).clamp(0, 1)
                d = torch.linalg.norm(nodes - (a + shift + tpar[:, None] * ab), dim=1)
                inside = d < r
                if len(holds):
                    inside |= (torch.cdist(nodes, x0[holds] + shift) <= r_hold).any(1)
                gv[inside] = vel
            gv[held] = 0
            gv[wall] = 0
            v, C = _g2p(gv, n1, inv_dx, (base, w, dpos))
            x = x + dt * v
            F = (torch.eye(3, dtype=dtype) + dt * C) @ F
            # Anchors: held at rest (Dirichlet boundary condition on particles); F still follows the grid.
            v[anchored] = 0
            C[anchored] = 0
            x[anchored] = x0[anchored]
            # Held particles: carried by their tool (its offset at the end of this substep).
            for a, b, r, offs, holds, r_hold in in_tool:
                if len(holds):
                    vel = (offs[frame] - offs[frame - 1]) / (p.substeps * dt)
                    x[holds] = x0[holds] + offs[frame - 1] + vel * ((sub + 1) * dt)
                    v[holds] = vel
            if not torch.isfinite(x).all():
                raise SimulationError(f"MPM diverged (NaN/inf) at frame {frame}: lower dt or E")
            if ((x < pad) | (x > L - pad)).any():
                raise SimulationError(f"particles reached the grid border at frame {frame}: enlarge the sim box")
        xs.append(x.clone())
        Fs.append(F.clone())
        if progress is not None:
            progress(frame)
    lo_np = p.box_lo.astype(np.float64)
    return MPMResult(
        x=torch.stack(xs).numpy() + lo_np,
        F=torch.stack(Fs).numpy(),
    )
