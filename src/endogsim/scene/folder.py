"""A scene folder loaded for simulation: what was observed and the world to simulate it in.

Shared by identification (:mod:`endogsim.identify`), new interactions (:mod:`endogsim.pipeline.simulate`) and
validation on held-out frames; the benchmark generator (:mod:`endogsim.synth`) writes such folders.

A scene folder (``endogsim synth``, or any folder laid out the same way) gives:
  * the observed video ``images/`` (and ``object_masks/`` for the valid pixels),
  * the frame-0 Gaussians ``gaussians_t0.ply`` with object ids,
  * ``scene.json``: objects (ids, names, classes, rigid flags, ground truth where known), camera, and the
    scenario: sim box, gravity, damping, boundary conditions, tool capsules with their per-frame rigid
    transforms (the observed tool trajectory) and the identification discretisation,
  * the particles are made from the deformable objects' frame-0 Gaussians, filling the scenario's
    thickness behind them (:mod:`endogsim.scene.particles`), with the boundary conditions of
    ``scene.json`` (a benchmark's ground-truth particles, ``particles_ground_truth.npz``, are never read).

:func:`load_sim_scene` turns that into an :class:`SimScene` holding the simulator's inputs
(:class:`~endogsim.physics.Particles`, :class:`~endogsim.physics.Scenario`, :class:`~endogsim.physics.MPMConfig`)
and the renderer's (Gaussians, camera, per-Gaussian binding to particles). Units: metres, seconds, Pa.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from endogsim.errors import DataError
from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import Gaussians
from endogsim.io.images import read_grey, read_rgb
from endogsim.io.scene import ObjectLabel
from endogsim.physics import (
    GaussianBinding,
    MPMConfig,
    ObjectMaterials,
    Particles,
    Scenario,
    SimBox,
    Simulator,
    bind_gaussians,
)
from endogsim.scene.discretisation import refine
from endogsim.scene.particles import particles_from_scene_gaussians, scenario_forces, tool_colliders
from endogsim.scene.schema import IMAGES_PATTERN, SceneSpec, SimSettings, load_scene_spec
from endogsim.scene.tracks import TissueTracks, read_tissue_tracks

__all__ = ["SimScene", "identification_settings", "load_sim_scene", "read_observations", "rediscretised"]


@dataclass
class SimScene:
    """Everything one identification needs, in world units.

    Attributes:
        folder: the scene folder.
        spec: the parsed ``scene.json`` (ground-truth materials are used only for metrics).
        labels: id -> ObjectLabel (tools are the rigid objects), for material initialisation.
        frames: [T, H, W, 3] float32 observed RGB in [0, 1].
        object_masks: [T, H, W] int32 object id per pixel (0 = background) or None.
        camera: the fixed endoscope (full resolution).
        gaussians: frame-0 Gaussians of every object (world metres).
        deformable_ids: ids of the simulated (non-rigid) objects.
        particles: the simulated particles (deformable objects only).
        scenario: sim box, gravity, anchors (pinned particles), tool colliders.
        mpm: the identification discretisation (grid, substeps, dt).
        settings: the discretisation the scene was read at (grid, particle spacing, substeps): the scenario's
            identification settings, refined by the factor given to :func:`load_sim_scene`.
        binding: how each Gaussian follows its k nearest particles.
        tool_transforms: {object id: [T, 4, 4] world rigid transforms per frame} for rigid Gaussians.
        tool_visible: {object id: [T] bool} the frames where the video shows the instrument, for the
            instruments that are not seen in every frame (``ToolCapsule.visible``); render hides it elsewhere.
        gt_flow: [T-1, H, W, 2] ground-truth flow (pixels) or None; gt_flow_valid: [T-1, H, W] bool or None.
        viewmats: [T, 4, 4] world -> camera per frame (a moving endoscope) or None (a still camera,
            ``camera.viewmat``).
        tracks: the reconstruction's tissue trajectories (``tracks.npz``) or None.
        exposure: [T, 2, 3] log gain and bias of every frame's exposure (``camera.exposure``) or None.
        field_of_view: [H, W] bool, the pixels inside the endoscope's image circle (``files.field_of_view``),
            or None (the whole image). Renders are black outside it, like the filmed frames.
    """

    folder: Path
    spec: SceneSpec
    labels: dict[int, ObjectLabel]
    frames: np.ndarray
    object_masks: np.ndarray | None
    camera: Camera
    gaussians: Gaussians
    deformable_ids: list[int]
    particles: Particles
    scenario: Scenario
    mpm: MPMConfig
    settings: SimSettings
    binding: GaussianBinding
    tool_transforms: dict[int, torch.Tensor]
    gt_flow: np.ndarray | None = None
    gt_flow_valid: np.ndarray | None = None
    viewmats: torch.Tensor | None = None
    tracks: TissueTracks | None = None
    tool_visible: dict[int, torch.Tensor] = field(default_factory=dict)
    exposure: torch.Tensor | None = None
    field_of_view: torch.Tensor | None = None
    _simulator: Simulator | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def num_frames(self) -> int:
        return int(self.frames.shape[0])

    def simulator(self) -> Simulator:
        """The scene's :class:`~endogsim.physics.Simulator` over all its frames, built once (its engine and
        backward buffers are reused by every rollout, e.g. every iteration of identification)."""
        if self._simulator is None:
            self._simulator = Simulator(self.particles, self.scenario, self.mpm, self.num_frames)
        return self._simulator

    def planned_at(self, materials: ObjectMaterials) -> SimScene:
        """This scene with its substeps per frame planned once, at ``materials``: no rollout of the returned
        scene takes fewer substeps than the CFL rule asks for ``materials`` (stiffer materials still take more).

        Identification plans at its initial materials (:func:`endogsim.identify.optimize.planned_for`): every
        trial then simulates with the same time step unless it needs a finer one, so the loss does not jump by a
        substep's time-discretisation error where a trial's CFL count would cross an integer; those jumps are as
        large as the loss rises that decide whether a parameter is identifiable. Returns ``self`` when its floor
        is already at least that count (planning twice is planning once)."""
        return self.with_substeps_at_least(self.simulator().timestep(materials, self.particles.v).substeps)

    def with_substeps_at_least(self, count: int) -> SimScene:
        """This scene with its floor of substeps per frame raised to ``count`` (never lowered; ``self`` when it is
        already there). A field simulated at the count it was identified with moves as identification saw it move:
        the motion is not converged in the time step (docs/IDENTIFICATION.md section 3), so an E belongs to the
        substeps it was fitted at as to the grid."""
        if count <= self.mpm.substeps_per_frame:
            return self
        return replace(self, mpm=replace(self.mpm, substeps_per_frame=int(count)))

    def independent_simulations(self) -> int:
        """How many simulations of this scene to run at a time (e.g. an interval's trials): one per torch
        thread on a CPU, as many as half the free memory holds (:func:`~endogsim.warp_runtime.independent_runs`)."""
        from endogsim.warp_runtime import independent_runs, simulation_bytes

        run_bytes = simulation_bytes(len(self.particles), self.num_frames, self.mpm.grid_res)
        return independent_runs(self.mpm.device, run_bytes)

    @property
    def has_ground_truth(self) -> bool:
        """Whether every deformable object has ground-truth E and nu (synthesized scenes; not a real video's
        scene built from a reconstruction, whose scene.json leaves them null)."""
        deformable = [o for o in self.spec.objects if not o.rigid]
        return bool(deformable) and all(o.E is not None and o.nu is not None for o in deformable)


def read_observations(folder: Path, spec: SceneSpec, frames: int) -> tuple[np.ndarray, np.ndarray | None,
                                                                           np.ndarray | None, np.ndarray | None]:
    """Observed frames [T, H, W, 3], object masks [T, H, W] (or None), ground-truth flow [T-1, H, W, 2] and
    its valid mask [T-1, H, W] (or None) of a scene folder."""
    pat = spec.files.get("images", IMAGES_PATTERN)
    imgs = [read_rgb(folder / (pat % t)) for t in range(frames)]
    out_frames = np.stack(imgs)
    masks = None
    mpat = spec.files.get("object_masks")
    if mpat and (folder / (mpat % 0)).is_file():
        masks = np.stack([read_grey(folder / (mpat % t)).astype(np.int32) for t in range(frames)])
    flow = valid = None
    fpat, vpat = spec.files.get("flow"), spec.files.get("flow_valid")
    if fpat and (folder / (fpat % 0)).is_file():
        flow = np.stack([np.load(folder / (fpat % t)).astype(np.float32) for t in range(frames - 1)])
        if vpat and (folder / (vpat % 0)).is_file():
            valid = np.stack([read_grey(folder / (vpat % t)) > 127 for t in range(frames - 1)])
        else:
            valid = np.ones(flow.shape[:3], bool)
    return out_frames, masks, flow, valid


def identification_settings(spec: SceneSpec, factor: float = 1.0) -> SimSettings:
    """The discretisation identification simulates ``spec`` at: the scenario's identification settings (with
    their particle spacing spelled out), refined by ``factor`` (:func:`endogsim.scene.discretisation.refine`;
    1: as they are). Refined without the objects' materials: a benchmark scene's are the ground truth, which
    identification never reads; the simulator plans the substeps for the materials it simulates."""
    sc = spec.scenario
    ident = replace(sc.identification, particle_spacing=sc.spacing(sc.identification))
    if factor == 1:
        return ident
    return refine(ident, (), float(sc.box_size), float(sc.frame_dt), factor=factor)


def load_sim_scene(folder: str | Path, frames: int | None = None, device: str = "cpu",
                   settings: SimSettings | None = None, refine: float = 1.0) -> SimScene:
    """Read a scene folder into an :class:`SimScene`.

    Args:
        folder: a folder with ``scene.json`` (``endogsim synth`` output layout).
        frames: use only the first ``frames`` frames (>= 2); default all.
        device: simulator device ("cpu" or "cuda").
        settings: the discretisation to simulate at (grid, particle spacing, substeps); default the
            scenario's identification settings refined by ``refine`` (:func:`identification_settings`).
        refine: with ``settings`` None, the factor on the scenario's identification discretisation (grid x
            ``refine``, particle spacing / ``refine``, substeps x ``refine``): a finer, costlier simulation that
            is nearer converged (docs/IDENTIFICATION.md section 3).
    """
    from endogsim.gaussians.ply import read_ply

    folder = Path(folder)
    if not (folder / "scene.json").is_file():
        raise DataError(f"{folder}: no scene.json; a simulation needs a scene folder with the scenario "
                        "(make one with `endogsim synth NAME --out DIR` or `endogsim run DATA`)")
    spec = load_scene_spec(folder)
    T = spec.frames if frames is None else int(frames)
    if T < 2 or T > spec.frames:
        raise DataError(f"{folder}: frames = {T} must lie in [2, {spec.frames}]")
    obs, masks, flow, valid = read_observations(folder, spec, T)
    cam_t = spec.camera
    camera = Camera(torch.tensor(cam_t.K, dtype=torch.float32), cam_t.width, cam_t.height,
                    torch.tensor(cam_t.viewmat, dtype=torch.float32))
    if obs.shape[1:3] != (camera.height, camera.width):
        raise DataError(f"{folder}: images are {obs.shape[2]}x{obs.shape[1]}, scene.json camera {camera.width}x{camera.height}")
    ply = folder / spec.files.get("gaussians_t0", "gaussians_t0.ply")
    if not ply.is_file():
        raise DataError(f"{ply}: frame-0 Gaussians missing")
    g = read_ply(ply)
    labels = {o.id: ObjectLabel(o.id, o.name, bool(o.rigid), o.klass) for o in spec.objects}
    deformable = [o.id for o in spec.objects if not o.rigid]
    if not deformable:
        raise DataError(f"{folder}: scene.json has no deformable object to identify")

    if settings is not None and refine != 1:
        raise DataError(f"{folder}: give either a discretisation or a refinement factor ({refine}), not both")
    sc = spec.scenario
    ident = identification_settings(spec, refine) if settings is None else settings
    box = SimBox(tuple(float(v) for v in sc.box_lo), float(sc.box_size))
    dx = box.size / ident.grid
    # Particles always come from the frame-0 Gaussians and the scenario's description, as on a real video
    # (a benchmark's ground-truth particles are never read: identifying from them would be an inverse crime).
    filled = particles_from_scene_gaussians(g, spec, camera, ident)
    particles = filled.particles

    tool_tf = {}
    for tool in sc.tools:
        tf = torch.tensor(tool.transforms, dtype=torch.float64)[:T]
        if tf.shape[0] < T:
            raise DataError(f"{folder}: tool {tool.object_id} has {tf.shape[0]} transforms for {T} frames")
        tool_tf[tool.object_id] = tf
        if tool.visible is not None and len(tool.visible) < T:
            raise DataError(f"{folder}: tool {tool.object_id} has visibility for {len(tool.visible)} frames, not {T}")
    tool_visible = {tool.object_id: torch.tensor(tool.visible[:T]) for tool in sc.tools
                    if tool.visible is not None and not all(tool.visible[:T])}
    colliders = tool_colliders(sc.tools, particles, ~filled.pinned, dx, tool_tf)
    tracks = None
    if spec.files.get("tracks"):
        tracks = read_tissue_tracks(folder / spec.files["tracks"], len(g.means), T)
    moving = []
    if filled.tracked_border().any():
        if tracks is None:
            raise DataError(f"{folder}: scene.json's border_motion 'tracked' needs the reconstruction's tissue "
                            "tracks (files.tracks), which this scene does not have")
        moving = filled.moving_anchors(tracks, g.object_ids[tracks.index].numpy(), dx)
    scenario = Scenario(box, gravity=tuple(float(v) for v in sc.gravity), anchors=filled.anchors(),
                        forces=scenario_forces(spec, particles), colliders=colliders, moving_anchors=moving,
                        settle_frames=int(sc.settle_frames), settle="subtract", settle_damping=sc.settle_damping,
                        mass_scaling=float(sc.mass_scaling))
    walls = next((int(b.get("cells", 2)) for b in sc.boundary_conditions if b.get("type") == "box_walls"), 2)
    mpm = MPMConfig(grid_res=int(ident.grid), frame_dt=float(sc.frame_dt), substeps_per_frame=int(ident.substeps),
                    dt=None, damping=float(sc.damping), wall="sticky", wall_padding=max(2, walls), device=device)
    binding = bind_gaussians(g.means, g.object_ids, particles)
    viewmats = None
    if cam_t.viewmats is not None:
        viewmats = torch.tensor(cam_t.viewmats, dtype=torch.float32)
        if viewmats.shape[1:] != (4, 4) or viewmats.shape[0] < T:
            raise DataError(f"{folder}: camera.viewmats has shape {tuple(viewmats.shape)}; expected [{T}, 4, 4]")
        viewmats = viewmats[:T]
    exposure = None
    if cam_t.exposure is not None:
        exposure = torch.tensor([cam_t.exposure["log_gain"], cam_t.exposure["bias"]], dtype=torch.float32)
        exposure = exposure.permute(1, 0, 2)[:T].contiguous()
    fov = None
    if spec.files.get("field_of_view"):
        fov_file = folder / spec.files["field_of_view"]
        fov = torch.from_numpy(read_grey(fov_file) > 127)  # written 0 / 255
        if tuple(fov.shape) != (camera.height, camera.width):
            raise DataError(f"{fov_file}: the field of view is {fov.shape[1]}x{fov.shape[0]}, the camera "
                            f"{camera.width}x{camera.height}")
    return SimScene(folder=folder, spec=spec, labels=labels, frames=obs, object_masks=masks, camera=camera,
                           gaussians=g, deformable_ids=deformable, particles=particles, scenario=scenario, mpm=mpm,
                           settings=ident, binding=binding, tool_transforms=tool_tf, gt_flow=flow, gt_flow_valid=valid,
                           viewmats=viewmats, tracks=tracks, tool_visible=tool_visible, exposure=exposure,
                           field_of_view=fov)


def rediscretised(scene: SimScene, factor: float) -> SimScene:
    """``scene`` read again from its folder at another discretisation: its grid times ``factor``, the particle
    spacing and the substeps scaled with it (:func:`endogsim.scene.discretisation.refine`); the same frames,
    camera, Gaussians and scenario. Identification's discretisation-error estimate
    (:func:`endogsim.identify.uncertainty.discretisation_error`, ``factor`` < 1) and its refined correction
    (:mod:`endogsim.identify.refined_correction`, ``factor`` > 1) compare the two."""
    sc = scene.spec.scenario
    # refined without the materials, as in identification_settings
    settings = refine(scene.settings, (), float(sc.box_size), float(sc.frame_dt), factor=factor)
    return load_sim_scene(scene.folder, scene.num_frames, scene.mpm.device, settings=settings)
