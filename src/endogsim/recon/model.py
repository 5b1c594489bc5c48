"""A reconstructed 4D scene: canonical Gaussians + tissue deformation field + rigid tool motion.

:func:`compose_at` is the one place that says how the pieces combine at a frame; training and the
reloaded :class:`Reconstruction` both call it. :func:`load_reconstruction` reads a run folder written by
:func:`endogsim.recon.train.reconstruct`.

Run-folder files (all written atomically):

=========================  ==================================================================
``canonical.ply``          canonical Gaussians, 3DGS layout + ``object_id`` (tissue then tools)
``frame0.ply``             the Gaussians at frame 0 (deformed tissue, tools at their frame-0 pose)
``deformation.pt``         torch file: the deformation field (architecture + state dict), the tool
                           motion state dict, frame times, camera (+ per-frame ``viewmats`` and
                           ``exposure`` of a moving endoscope, ``field_of_view`` of one with a
                           border), label table
``tool_trajectories.json`` per tool: id, name, [T, 4, 4] canonical -> frame transforms (world metres)
``tool_trajectories.npz``  the same arrays, ``object_<id>`` [T, 4, 4] and ``times`` [T] (seconds)
``objects.json``           id -> name, is_tool, class
``object_masks/*.png``     the masks reconstruction used, 16-bit ids of objects.json (one per instrument
                           after the instance split), 65535 = no object
``renders/test/*.png``     test-frame renders (tissue model); ``renders/test_full/`` with tools
``metrics.json``           PSNR/SSIM (both protocols), training seconds, Gaussian count, priors used
``config.json``            the configuration of the run
``provenance.json``        what the run was made from: data path, frame count and size, a content hash
                           of the frames, configuration (a resume with other frames is refused)
``checkpoint.pt``          training state for resuming
=========================  ==================================================================
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import torch

from endogsim.errors import ModelError
from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import Gaussians
from endogsim.io.scene import ObjectLabel
from endogsim.recon.deformation import DeformationField
from endogsim.recon.exposure import FrameExposure
from endogsim.recon.tools import ToolMotion

__all__ = ["compose_at", "Reconstruction", "ReconResult", "load_reconstruction"]


def compose_at(tissue: Gaussians, tools: Gaussians | None, deformation: DeformationField | None,
               motion: ToolMotion | None, time: float, frame: int, include_tools: bool = True) -> Gaussians:
    """Gaussians of the scene at one frame.

    Args:
        tissue: canonical tissue Gaussians.
        tools: canonical tool Gaussians (each tool in the pose of its reference frame) or None.
        deformation: tissue deformation field (None: static tissue, the coarse stage).
        motion: rigid tool motion (None: tools stay in their canonical pose).
        time: frame time (seconds) for the deformation field.
        frame: frame index for the tool poses.
        include_tools: append the tool Gaussians.
    """
    g = deformation(tissue, time) if deformation is not None else tissue
    if include_tools and tools is not None and len(tools) > 0:
        moved = motion.apply(tools, frame) if motion is not None else tools
        g = Gaussians.concat([g, moved])
    return g


#: ReconResult attribute -> file name in the run folder.
RUN_FILES = {"frame0_ply": "frame0.ply", "canonical_ply": "canonical.ply", "deformation": "deformation.pt",
             "tool_trajectories": "tool_trajectories.json", "tool_trajectories_npz": "tool_trajectories.npz",
             "objects": "objects.json", "metrics_path": "metrics.json"}


@dataclass(frozen=True, eq=False)
class ReconResult(Mapping):
    """What :func:`endogsim.recon.train.reconstruct` returns: the run folder's key files and its metrics.

    It is also a read-only mapping over ``metrics`` (``result["psnr_masked"]``), so code that treats the
    return value as the metrics dict keeps working.

    Attributes:
        run_dir: the run folder.
        frame0_ply: Gaussians of frame 0 (tissue deformed to frame 0, tools at their frame-0 pose), with
            an ``object_id`` per Gaussian; the simulator's initial state.
        canonical_ply: canonical Gaussians (tissue then tools), with object ids.
        deformation: ``deformation.pt`` (deformation field, tool motion, times, camera, labels).
        tool_trajectories: ``tool_trajectories.json``: per tool id, its name and [T, 4, 4] rigid transforms
            (canonical -> frame t, world metres); ``tool_trajectories_npz`` holds the same arrays.
        objects: ``objects.json``: id -> name, is_tool, class.
        metrics_path: ``metrics.json``.
        metrics: its content (PSNR / SSIM of both protocols, training seconds, Gaussian counts, ...).
    """

    run_dir: Path
    metrics: dict[str, Any]
    frame0_ply: Path = field(init=False)
    canonical_ply: Path = field(init=False)
    deformation: Path = field(init=False)
    tool_trajectories: Path = field(init=False)
    tool_trajectories_npz: Path = field(init=False)
    objects: Path = field(init=False)
    metrics_path: Path = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "run_dir", Path(self.run_dir))
        for attr, name in RUN_FILES.items():
            object.__setattr__(self, attr, self.run_dir / name)

    @staticmethod
    def from_run(run_dir: str | os.PathLike) -> "ReconResult":
        """The result of a finished run folder (reads ``metrics.json``)."""
        run = Path(run_dir)
        path = run / "metrics.json"
        if not path.is_file():
            raise ModelError(f"{path}: missing; is {run} a finished `endogsim reconstruct` run?")
        return ReconResult(run, json.loads(path.read_text()))

    def load(self, device: str = "cpu") -> "Reconstruction":
        """The full 4D model (:func:`load_reconstruction`)."""
        return load_reconstruction(self.run_dir, device)

    def __getitem__(self, key: str) -> Any:
        return self.metrics[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.metrics)

    def __len__(self) -> int:
        return len(self.metrics)


@dataclass
class Reconstruction:
    """A reloaded reconstruction.

    Attributes:
        tissue: canonical tissue Gaussians [N_tissue].
        tools: canonical tool Gaussians [N_tool] (may be empty).
        deformation: the tissue deformation field.
        motion: rigid tool motion (None without tools).
        times: [T] frame times (seconds).
        camera: the camera of the training resolution, at frame 0's pose (the world frame).
        labels: object table.
        viewmats: [T, 4, 4] world->camera transform of every frame for a moving endoscope (learnt poses),
            None for a fixed one.
        exposure: per-frame colour gain and bias of a moving endoscope (None: renders are the colours).
        field_of_view: [H, W] bool, pixels inside the endoscope's image circle (None: the whole image);
            :meth:`render` is black outside it.
    """

    tissue: Gaussians
    tools: Gaussians
    deformation: DeformationField
    motion: ToolMotion | None
    times: torch.Tensor
    camera: Camera
    labels: dict[int, ObjectLabel] = field(default_factory=dict)
    viewmats: torch.Tensor | None = None
    exposure: FrameExposure | None = None
    field_of_view: torch.Tensor | None = None

    @property
    def num_frames(self) -> int:
        return int(self.times.shape[0])

    @torch.no_grad()
    def gaussians_at(self, frame: int, include_tools: bool = True) -> Gaussians:
        """All Gaussians at frame ``frame`` (object ids preserved)."""
        if not 0 <= frame < self.num_frames:
            raise ModelError(f"frame {frame} outside 0..{self.num_frames - 1}")
        return compose_at(self.tissue, self.tools, self.deformation, self.motion, float(self.times[frame]), frame,
                          include_tools)

    def camera_at(self, frame: int) -> Camera:
        """The camera that saw frame ``frame``."""
        if self.viewmats is None:
            return self.camera
        return Camera(self.camera.K, self.camera.width, self.camera.height, self.viewmats[frame].to(self.camera.K))

    def tool_transforms(self) -> dict[int, torch.Tensor]:
        """Object id -> [T, 4, 4] canonical -> frame rigid transforms (world metres)."""
        if self.motion is None:
            return {}
        M = self.motion.transforms().detach()
        return {oid: M[k] for k, oid in enumerate(self.motion.tool_ids)}

    @torch.no_grad()
    def render(self, frame: int, include_tools: bool = True, backend: str = "auto"):
        """:class:`~endogsim.gaussians.render.RenderOutput` of frame ``frame`` (colours as that frame's camera
        exposed them, black outside its field of view)."""
        from dataclasses import replace

        from endogsim.gaussians.render import render_gaussians

        out = render_gaussians(self.gaussians_at(frame, include_tools), self.camera_at(frame), backend=backend)
        rgb = out.rgb if self.exposure is None else self.exposure(out.rgb, frame)
        if self.field_of_view is not None:
            rgb = rgb * self.field_of_view[..., None].to(rgb)
        return replace(out, rgb=rgb)


def load_reconstruction(run_dir: str | os.PathLike, device: str = "cpu") -> Reconstruction:
    """Read ``canonical.ply`` and ``deformation.pt`` from a run folder."""
    from endogsim.gaussians.ply import read_ply

    run = Path(run_dir)
    for name in ("canonical.ply", "deformation.pt"):
        if not (run / name).is_file():
            raise ModelError(f"{run / name}: missing; is {run} a finished `endogsim reconstruct` run?")
    g = read_ply(run / "canonical.ply")
    data = torch.load(run / "deformation.pt", map_location="cpu", weights_only=False)
    n_t = int(data["num_tissue"])
    deformation = DeformationField.from_export(data["deformation"]).eval()
    motion = None
    if data.get("tool_motion") is not None:
        tm = data["tool_motion"]
        motion = ToolMotion(tm["tool_ids"], tm["state_dict"]["centers"], tm["state_dict"]["rotation"].shape[1])
        motion.load_state_dict(tm["state_dict"])
    cam = data["camera"]
    camera = Camera(torch.as_tensor(cam["K"], dtype=torch.float32), int(cam["width"]), int(cam["height"]))
    labels = {int(k): ObjectLabel(int(k), v["name"], bool(v["is_tool"]), v["class"]) for k, v in data["labels"].items()}
    exposure = None
    if data.get("exposure") is not None:
        exposure = FrameExposure(data["exposure"]["log_gain"].shape[1]).requires_grad_(False)
        exposure.load_state_dict(data["exposure"])
    rec = Reconstruction(g.subset(torch.arange(n_t)), g.subset(torch.arange(n_t, len(g))), deformation, motion,
                         torch.as_tensor(data["times"], dtype=torch.float32), camera, labels, data.get("viewmats"),
                         exposure, data.get("field_of_view"))
    if device != "cpu":
        rec.tissue, rec.tools = rec.tissue.to(device), rec.tools.to(device)
        rec.deformation = rec.deformation.to(device)
        rec.motion = rec.motion.to(device) if rec.motion is not None else None
        rec.camera = rec.camera.to(device)
        rec.viewmats = rec.viewmats.to(device) if rec.viewmats is not None else None
        rec.exposure = rec.exposure.to(device) if rec.exposure is not None else None
        rec.field_of_view = rec.field_of_view.to(device) if rec.field_of_view is not None else None
    return rec
