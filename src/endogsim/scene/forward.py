"""Simulate the scene for given materials and render it: the differentiable forward model of identification.

    materials (E, nu per object)  --Simulator.rollout-->  particle positions [T,P,3], F [T,P,3,3]
        --drive_gaussians-->  Gaussian means / covariances per frame (tools follow their rigid transforms)
        --render_with_flow-->  RGB [T,H,W,3] and Gaussian flow t -> t+1 [T-1,H,W,2] (or at every k-th frame)

A moving endoscope (``SimScene.viewmats``) is handled by rendering frame t in camera t's coordinates: the
flow t -> t+1 then compares camera t's view of frame t with camera t+1's view of frame t+1, which is what an
optical-flow estimator measures on the video.
Each frame's colours are then mapped by that frame's exposure and blacked out (and the flow set to 0) beyond
the endoscope's field of view, where the reconstruction learnt them (``SimScene.exposure``,
``SimScene.field_of_view``), so that a simulated frame differs from the filmed one by the motion, not by the
camera's light.

Every step is differentiable, so a loss on the renders back-propagates to E and nu (and through them to
the optimiser's log10 E and raw nu).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields, replace

import torch

from endogsim.gaussians.camera import Camera
from endogsim.gaussians.flow import render_with_flow
from endogsim.gaussians.rasterize_torch import world_to_camera
from endogsim.gaussians.render import rasterize
from endogsim.physics import GradMode, ObjectMaterials, SimResult, Simulator, drive_gaussians
from endogsim.recon.exposure import apply_exposure
from endogsim.scene.folder import SimScene

__all__ = ["Rendered", "simulate_materials", "same_materials", "Simulations", "frame_gaussians", "frame_opacities",
           "in_view", "in_field_of_view", "as_filmed", "render_sequence"]


@dataclass
class Rendered:
    """Renders of a simulated sequence at some of its frames.

    Attributes:
        rgb: [K, H, W, 3] in [0, 1], the frames ``frames`` (frame 0 is the rest state), as filmed
            (:func:`as_filmed`: the frame's exposure, black outside the field of view).
        flow: [K', H, W, 2] Gaussian flow t -> t+1 (pixels of the rendered resolution) for the rendered
            frames t with t + 1 < T (K' = K, or K - 1 when the last frame is rendered); 0 outside the field of
            view.
        alpha: [K, H, W] accumulated opacity.
        frames: the frame indices rendered (ascending).
        tracks: [K, N, 2] pixel positions (rendered resolution) of the scene's tracked Gaussians
            (``SimScene.tracks``) at those frames, or None when the scene has no tracks.
    """

    rgb: torch.Tensor
    flow: torch.Tensor
    alpha: torch.Tensor
    frames: list[int]
    tracks: torch.Tensor | None = None


def simulate_materials(scene: SimScene, materials: ObjectMaterials, grad_mode: GradMode = "frame") -> SimResult:
    """Differentiable rollout of the scene's particles over all its frames: its positions [T, P, 3] (m) and
    F [T, P, 3, 3] carry gradients to ``materials``' E, nu and density (the same numbers as a forward-only
    ``scene.simulator().simulate(materials)``)."""
    return scene.simulator().run(materials, grad_mode)


def same_materials(a: ObjectMaterials, b: ObjectMaterials) -> bool:
    """Whether the simulator gets the same materials from ``a`` and ``b``, to the last bit (every object's E,
    nu, density, constitutive model and yield stress; NaN, an id without a record, equals NaN): their
    simulations are then the same."""
    return all(_equal(getattr(a, f.name), getattr(b, f.name)) for f in fields(a))


def _equal(x, y) -> bool:
    """Equal values, or tensors equal entry by entry (NaN, an id without a record, equals NaN)."""
    if not isinstance(x, torch.Tensor):
        return x == y
    x, y = x.detach(), y.detach()
    return x.shape == y.shape and bool(((x == y) | (x.isnan() & y.isnan())).all())


class Simulations:
    """Simulations of one scene that were run already (e.g. an identification's iterates), found again by
    their materials: a field simulated anew with the same materials would give the same numbers."""

    def __init__(self) -> None:
        self._kept: dict[str, tuple[ObjectMaterials, SimResult]] = {}

    def keep(self, slot: str, materials: ObjectMaterials, result: SimResult) -> None:
        """Keep ``result`` (detached) as the simulation of ``materials`` under ``slot``, replacing the one there."""
        self._kept[slot] = (materials.detached(),
                            replace(result, positions=result.positions.detach(), F=result.F.detach()))

    def find(self, materials: ObjectMaterials, simulator: Simulator | None = None) -> SimResult | None:
        """A kept simulation of exactly ``materials``, or None. With the scene's ``simulator``, one whose
        materials give it the same inputs (:meth:`~endogsim.physics.Simulator.engine_inputs`) counts too."""
        found = next((r for m, r in self._kept.values() if same_materials(m, materials)), None)
        if found is None and simulator is not None and self._kept:
            want = simulator.engine_inputs(materials)
            found = next((r for m, r in self._kept.values()
                          if all(map(_equal, simulator.engine_inputs(m), want))), None)
        return found


def frame_gaussians(problem: SimScene, positions: torch.Tensor, F: torch.Tensor, cov0: torch.Tensor, t: int):
    """Means [N, 3] and covariances [N, 3, 3] of every Gaussian at frame t (float32, differentiable)."""
    g = problem.gaussians
    means, covs, _ = drive_gaussians(g, problem.binding, positions[t].float(), F[t].float(), rotate_colors=False)
    for oid, tf in problem.tool_transforms.items():
        sel = g.object_ids == oid
        if not bool(sel.any()):
            continue
        R = tf[t, :3, :3].float()
        tr = tf[t, :3, 3].float()
        moved = g.means[sel].float() @ R.T + tr
        means = means.clone()
        covs = covs.clone()
        means[sel] = moved
        covs[sel] = R @ cov0[sel] @ R.T
    return means, covs


def frame_opacities(problem: SimScene, opacities: torch.Tensor, t: int) -> torch.Tensor:
    """Opacities [N] of every Gaussian at frame t: those of an instrument the video does not show at t
    (``SimScene.tool_visible``) are 0, so that a tool that left the view is not drawn at its held pose."""
    hidden = [oid for oid, seen in problem.tool_visible.items() if not bool(seen[t])]
    if not hidden:
        return opacities
    keep = ~torch.isin(problem.gaussians.object_ids, torch.tensor(hidden, dtype=problem.gaussians.object_ids.dtype))
    return opacities * keep.to(opacities)


def in_view(problem: SimScene, means: torch.Tensor, covs: torch.Tensor | None, t: int):
    """Means [N, 3] (and covariances [N, 3, 3], or None) of frame t in camera t's coordinates (unchanged for
    a still camera, whose world is its camera frame)."""
    if problem.viewmats is None:
        return means, covs
    return world_to_camera(means, covs, problem.viewmats[t].to(means))


def in_field_of_view(problem: SimScene, image: torch.Tensor) -> torch.Tensor:
    """``image`` [..., H, W, C] zeroed outside the endoscope's field of view (``problem.field_of_view`` resized to
    the image's size, nearest: a scaled camera sees the same circle); unchanged without one."""
    if problem.field_of_view is None:
        return image
    fov = problem.field_of_view[None, None].to(image)
    size = tuple(image.shape[-3:-1])
    return image * torch.nn.functional.interpolate(fov, size=size, mode="nearest")[0, 0, ..., None]


def as_filmed(problem: SimScene, rgb: torch.Tensor, t: int) -> torch.Tensor:
    """``rgb`` [H, W, 3], a render of frame ``t``, as the endoscope filmed it: mapped by that frame's exposure
    (``problem.exposure``) and black outside the field of view (:func:`in_field_of_view`)."""
    if problem.exposure is not None:
        log_gain, bias = problem.exposure[t].to(rgb)
        rgb = apply_exposure(rgb, log_gain, bias)
    return in_field_of_view(problem, rgb)


def render_sequence(problem: SimScene, positions: torch.Tensor, F: torch.Tensor, camera: Camera,
                    backend: str = "auto", frames: Sequence[int] | None = None) -> Rendered:
    """Render frames of a simulation and the Gaussian flow from each to the next.

    Args:
        problem: the scene (Gaussians, binding, tool transforms).
        positions: [T, P, 3] particle positions (m); F: [T, P, 3, 3] deformation gradients.
        camera: the camera to render with (possibly scaled from ``problem.camera``).
        frames: frame indices to render (default all T); each t < T - 1 also gets its flow t -> t+1.
    Returns:
        :class:`Rendered` (differentiable in positions and F).
    """
    g = problem.gaussians
    T = positions.shape[0]
    frames = list(range(T)) if frames is None else sorted(set(int(t) for t in frames))
    cov0 = g.covariances().float().detach()
    opac = g.opacities.float().detach()
    colors = g.colors_dc.clamp(0, 1).float().detach() if g.sh_degree == 0 else g.sh.float().detach()
    needed = sorted(set(frames) | {t + 1 for t in frames if t + 1 < T})
    states = {t: in_view(problem, *frame_gaussians(problem, positions, F, cov0, t), t) for t in needed}
    view = Camera(camera.K, camera.width, camera.height) if problem.viewmats is not None else camera
    rgbs, flows, alphas, tracks = [], [], [], []
    for t in frames:
        m, c = states[t]
        opac_t = frame_opacities(problem, opac, t)
        if t + 1 < T:
            r = render_with_flow(m, opac_t, colors, view, states[t + 1][0], covars=c, covars_next=states[t + 1][1],
                                 backend=backend)
            flows.append(in_field_of_view(problem, r.flow))  # nothing is filmed, so nothing moves, beyond it
        else:
            r = rasterize(m, opac_t, colors, view, covars=c, backend=backend)
        rgbs.append(as_filmed(problem, r.rgb, t))
        alphas.append(r.alpha)
        if problem.tracks is not None:
            tracks.append(view.project(m[problem.tracks.index]))
    flow = torch.stack(flows) if flows else torch.zeros(0, camera.height, camera.width, 2)
    return Rendered(torch.stack(rgbs), flow, torch.stack(alphas), frames, torch.stack(tracks) if tracks else None)
