"""Typed configuration of the 4D reconstruction, loadable from JSON or TOML.

A config file holds any subset of the fields below (unknown keys are refused); the nested
``[deformation]`` table sets :class:`~endogsim.recon.deformation.DeformationConfig` and ``[flow]`` the
:class:`~endogsim.priors.flow.FlowConfig` of the point tracks. Example TOML::

    iters = 2000
    resolution_scale = 0.5
    lambda_dssim = 0.2
    [deformation]
    feature_dim = 16
    resolution = [32, 32, 32]

Defaults are for a 2-core CPU, where the cost of an iteration is the number of (pixel, Gaussian) pairs
the rasteriser composites plus the deformation of every Gaussian: half resolution, ~10k Gaussians from
every 3rd pixel with small initial footprints, point tracks and a track warm-up, bounded densification,
2000 iterations (``time_budget_s`` only stops a run early; it never changes the schedule). :func:`default_config`
("cuda") switches to full resolution and the Endo-4DGS iteration counts.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Literal, get_args

from endogsim.errors import DataError
from endogsim.priors.depth import DEPTH_BACKENDS
from endogsim.priors.flow import FlowConfig
from endogsim.priors.segmentation import SEGMENTATION_BACKENDS
from endogsim.recon.deformation import DeformationConfig
from endogsim.typed import check_typed_fields

#: "on", "off", or "auto" (decided from the data).
Switch = Literal["auto", "on", "off"]

__all__ = ["ReconConfig", "default_config", "load_config"]


@dataclass
class ReconConfig:
    """Every knob of :func:`endogsim.recon.train.reconstruct`.

    Data and priors:
        resolution_scale: image scale used for training (0.5 = half the stored width and height).
        max_frames: use only the first frames (None = all).
        depth_method / depth_weights: see :mod:`endogsim.priors.depth` ("auto": dataset depth, else the
            offline bowl fallback).
        seg_method / seg_checkpoint / seg_config: see :mod:`endogsim.priors.segmentation`.
        tool_instances: one object per instrument (:mod:`endogsim.priors.instances`: each tool class of
            the masks split into instances tracked through time) "on", "off", or "auto": on when the
            masks give one id per tool class (EndoNeRF masks, CholecSeg8K, the fallback), off when they
            already give one per instrument (SAM 2 tracks, scene folders of ``endogsim synth``).
        working_distance: metres, for the depth fallback and model-depth rescaling.
        tool_depth_factor: with non-metric depth, tools start at this fraction of the tissue depth
            (instruments sit between the camera and the tissue).
        camera_motion: learn a pose per frame for a moving endoscope ("on"), keep the camera fixed
            ("off"), or "auto": on when the dataset gives neither camera poses nor depth (CholecSeg8K,
            plain videos), off otherwise (EndoNeRF's fixed endoscope, procedural scenes). Poses start
            from :func:`endogsim.priors.camera.estimate_camera_rotations`.
        exposure: learn a per-frame colour gain and bias (:mod:`endogsim.recon.exposure`: the endoscope's
            light moves with it) "on", "off", or "auto": on exactly when the camera moves.
        point_tracks: start the deformation from point tracks (chained optical flow; False: train without).
        flow: the optical flow of the point tracks (:class:`~endogsim.priors.flow.FlowConfig`: "dis",
            offline, or "raft" with a local weights file).
    Schedule:
        iters: total iterations (coarse + deformation).
        coarse_fraction: share of ``iters`` spent on Endo-4DGS's static coarse stage (default 0: with point
            tracks the warm-up starts the deformation stage better than a static fit, which blurs whatever
            moves; use e.g. 0.05 with ``point_tracks=False``).
        seed: RNG seed (frame order, initial planes).
        checkpoint_every: iterations between checkpoints (resume after an interruption).
        eval_every: evaluate the test frames every n iterations into the history (0: only at the end);
            the evaluation time is not counted as training time.
        time_budget_s: a safety stop: stop training once this many training seconds are spent (None: no
            limit) and export what there is; ``metrics.json`` then says ``stopped_by_budget``. The
            schedules (coarse stage, learning-rate decay, densification window) run on iterations only,
            so what a run computes does not depend on the machine's speed: a stopped run is an unstopped
            one cut short (its learning rates not fully decayed).
    Initialisation:
        init_stride: back-project every ``init_stride``-th pixel in x and y.
        init_scale: initial standard deviation in units of the grid spacing (smaller: fewer pixel-Gaussian
            pairs, i.e. a cheaper CPU render, still without holes down to ~0.4).
        init_opacity: initial opacity of every Gaussian.
        sh_degree: SH degree of the colours (0: a fixed endoscope sees each point from one direction).
    Losses (weights):
        lambda_dssim: D-SSIM term (1 - SSIM) next to L1.
        lambda_depth: L1 on depth / median depth, only with metric depth (dataset).
        lambda_plane_tv, lambda_time_smooth, lambda_time_l1: HexPlane regularisers.
        lambda_tool_alpha: tool-model alpha vs tool mask.
        lambda_pose_smooth: frame-to-frame smoothness of tool poses.
        lambda_track: point-track term (:mod:`endogsim.priors.tracks`): Huber (1 px) distance between the
            motion of a tracked Gaussian's projected centre from its seed frame and its track's; decays
            log-linearly to ``lambda_track_final`` over the run (tracks drift, the photometric loss does not).
        track_batch: tracked Gaussians drawn per iteration for that term.
        track_warmup_iters: steps fitting the deformation field to the tracks alone (no rendering) before
            the photometric stages, so large motions start right instead of at the identity.
        tool_every: optimise the tool model every n-th iteration (it costs a second render).
    Learning rates (Adam; positions scale with the scene extent, per 3DGS):
        lr_means, lr_means_final: per unit extent, decayed exponentially over the run.
        lr_sh, lr_opacity, lr_scales, lr_quats: 3DGS values.
        lr_grid, lr_mlp: HexPlane planes and MLP heads (Endo-4DGS values), decayed by 10x.
        lr_tool_rot (rad), lr_tool_trans (per unit extent); lr_camera_rot, lr_camera_trans likewise;
        lr_exposure: per-frame log gain and bias.
        lr_camera_decay: the camera-pose and exposure learning rates decay log-linearly to this fraction
            of their start over the run. Each frame's pose is stepped about once per pass over the
            training frames and Adam's normalised step has a fixed size, so at a constant rate the poses
            keep oscillating by a few Adam steps (~0.2 degrees, a pixel or two) around their optimum.
    Densification (3DGS):
        densify_from, densify_until (fractions of iters), densify_every, densify_grad_threshold
        (view-space gradient, NDC units), percent_dense, prune_opacity, max_gaussians;
        densify_max_growth: one densification step adds at most this fraction of the current count.
    Evaluation:
        test_pose_steps: a moving endoscope has no pose for a held-out frame but the interpolation of its
            neighbours'. The final evaluation registers it to the frame: that pose is refined alone, for
            this many Adam steps with the model frozen (the test-time pose optimisation by which BARF and
            NoPe-NeRF evaluate unposed video), and the metrics use the result; the interpolated pose's
            stay under ``*_interpolated_pose``. 0 keeps the interpolated pose.
    Device:
        device: "auto", "cpu" or "cuda"; backend: render backend ("auto", "torch", "warp", "gsplat";
            see :func:`endogsim.gaussians.render.resolve_backend`).
    """

    resolution_scale: float = 0.5
    max_frames: int | None = None
    depth_method: str = "auto"
    depth_weights: str | None = None
    seg_method: str = "auto"
    seg_checkpoint: str | None = None
    seg_config: str | None = None
    tool_instances: Switch = "auto"
    working_distance: float = 0.07
    tool_depth_factor: float = 0.85
    camera_motion: Switch = "auto"
    exposure: Switch = "auto"
    point_tracks: bool = True
    flow: FlowConfig = field(default_factory=FlowConfig)

    iters: int = 2000
    coarse_fraction: float = 0.0
    seed: int = 0
    checkpoint_every: int = 250
    eval_every: int = 0
    time_budget_s: float | None = None

    init_stride: int = 3
    init_scale: float = 0.45
    init_opacity: float = 0.7
    sh_degree: int = 0

    lambda_dssim: float = 0.2
    lambda_depth: float = 0.1
    lambda_plane_tv: float = 2e-4
    lambda_time_smooth: float = 1e-3
    lambda_time_l1: float = 1e-4
    lambda_tool_alpha: float = 0.2
    lambda_pose_smooth: float = 1.0
    lambda_track: float = 0.01
    lambda_track_final: float = 0.001
    track_batch: int = 8192
    track_warmup_iters: int = 300
    tool_every: int = 2

    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_sh: float = 2.5e-3
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_grid: float = 1.6e-3
    lr_mlp: float = 1.6e-4
    lr_tool_rot: float = 2e-3
    lr_tool_trans: float = 2e-3
    lr_camera_rot: float = 5e-4
    lr_camera_trans: float = 5e-4
    lr_exposure: float = 1e-3
    lr_camera_decay: float = 0.01

    densify_from: float = 0.1
    densify_until: float = 0.6
    densify_every: int = 100
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    max_gaussians: int = 60_000
    densify_max_growth: float = 0.25

    test_pose_steps: int = 100

    device: Literal["auto", "cpu", "cuda"] = "auto"
    backend: Literal["auto", "torch", "warp", "gsplat"] = "auto"
    deformation: DeformationConfig = field(default_factory=DeformationConfig)

    def to_dict(self) -> dict:
        return asdict(self)

    def __post_init__(self) -> None:
        if isinstance(self.flow, dict):
            self.flow = FlowConfig(**self.flow)
        if isinstance(self.deformation, dict):
            self.deformation = DeformationConfig(**self.deformation)
        if not isinstance(self.flow, FlowConfig) or not isinstance(self.flow.method, str):
            raise DataError(f"flow {self.flow!r} must be a table such as {{\"method\": \"dis\"}}")
        if not isinstance(self.deformation, DeformationConfig):
            raise DataError(f"deformation {self.deformation!r} must be a table of deformation options")
        check_typed_fields(self)
        for name in ("checkpoint_every", "densify_every", "track_batch", "tool_every", "max_gaussians"):
            if getattr(self, name) < 1:
                raise DataError(f"{name} {getattr(self, name)} must be >= 1")
        for name in ("eval_every", "track_warmup_iters", "seed"):
            if getattr(self, name) < 0:
                raise DataError(f"{name} {getattr(self, name)} must be >= 0")
        for f in fields(self):
            if f.name.startswith("lr_") and getattr(self, f.name) <= 0:
                raise DataError(f"{f.name} {getattr(self, f.name)} must be > 0")
            if f.name.startswith("lambda_") and getattr(self, f.name) < 0:
                raise DataError(f"{f.name} {getattr(self, f.name)} must be >= 0")
        if not 0 <= self.sh_degree <= 3:
            raise DataError(f"sh_degree {self.sh_degree} must be 0, 1, 2 or 3")
        if self.max_frames is not None and self.max_frames < 2:
            raise DataError(f"max_frames {self.max_frames} must be >= 2 (or None: all)")
        if self.depth_method != "auto":
            DEPTH_BACKENDS.get(self.depth_method)
        if self.seg_method != "auto":
            SEGMENTATION_BACKENDS.get(self.seg_method)
        if not 0 < self.resolution_scale <= 4:
            raise DataError(f"resolution_scale {self.resolution_scale} must be in (0, 4]")
        if self.iters < 1:
            raise DataError(f"iters {self.iters} must be >= 1")
        if not 0 <= self.coarse_fraction <= 1:
            raise DataError(f"coarse_fraction {self.coarse_fraction} must be in [0, 1]")
        if self.init_stride < 1:
            raise DataError(f"init_stride {self.init_stride} must be >= 1")
        if self.init_scale <= 0:
            raise DataError(f"init_scale {self.init_scale} must be positive")
        if self.test_pose_steps < 0:
            raise DataError(f"test_pose_steps {self.test_pose_steps} must be >= 0")
        if not 0 < self.lr_camera_decay <= 1:
            raise DataError(f"lr_camera_decay {self.lr_camera_decay} must be in (0, 1]")
        if not 0 < self.init_opacity < 1:
            raise DataError(f"init_opacity {self.init_opacity} must be in (0, 1)")
        if self.time_budget_s is not None and not self.time_budget_s > 0:  # nan too
            raise DataError(f"time_budget_s {self.time_budget_s} must be positive (or None)")
        for name, choices in (("camera_motion", get_args(Switch)), ("exposure", get_args(Switch)),
                              ("tool_instances", get_args(Switch)),
                              ("device", ("auto", "cpu", "cuda")), ("backend", ("auto", "torch", "warp", "gsplat"))):
            if getattr(self, name) not in choices:
                raise DataError(f"{name} {getattr(self, name)!r} must be one of {', '.join(choices)}")

    @staticmethod
    def from_dict(data: dict, base: "ReconConfig | None" = None, source: str = "config") -> "ReconConfig":
        cfg = base or ReconConfig()
        names = {f.name for f in fields(ReconConfig)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise DataError(f"{source}: unknown reconstruction option(s) {unknown}")
        for key in ("deformation", "flow"):
            if not isinstance(data.get(key, {}), dict):
                raise DataError(f"{source}: {key} = {data[key]!r} must be a table of {key} options")
        values = {k: v for k, v in data.items() if k not in ("deformation", "flow")}
        flow = {**asdict(cfg.flow), **data.get("flow", {})}
        bad = sorted(set(data.get("flow", {})) - {f.name for f in fields(FlowConfig)})
        if bad:
            raise DataError(f"{source}: unknown flow option(s) {bad}")
        deform = asdict(cfg.deformation)
        if "deformation" in data:
            dn = {f.name for f in fields(DeformationConfig)}
            bad = sorted(set(data["deformation"]) - dn)
            if bad:
                raise DataError(f"{source}: unknown deformation option(s) {bad}")
            deform.update(data["deformation"])
        for key in ("resolution", "multires"):
            if not isinstance(deform[key], (list, tuple)):
                raise DataError(f"{source}: deformation.{key} = {deform[key]!r} must be a list of integers")
            deform[key] = tuple(deform[key])
        merged = {**asdict(cfg), **values}
        try:
            merged["deformation"] = DeformationConfig(**deform)
            merged["flow"] = FlowConfig(**flow)
            return ReconConfig(**merged)
        except DataError as exc:
            if str(exc).startswith(f"{source}:"):
                raise
            raise DataError(f"{source}: {exc}") from None


def default_config(device: str = "cpu") -> ReconConfig:
    """Defaults for ``device``: "cpu" (half resolution, 2000 iterations) or "cuda" (full resolution,
    Endo-4DGS-like 1000 coarse + 6000 fine iterations, a larger HexPlane)."""
    if device == "cuda":
        return ReconConfig(resolution_scale=1.0, iters=7000, coarse_fraction=1 / 7, init_stride=2, init_scale=0.6,
                           max_gaussians=300_000, device="cuda", checkpoint_every=1000,
                           deformation=DeformationConfig(feature_dim=32, resolution=(64, 64, 64)))
    return ReconConfig(device="cpu")


def load_config(path: str | Path | None = None, defaults_for: str = "cpu", **overrides) -> ReconConfig:
    """The defaults for device ``defaults_for``, then a JSON/TOML file, then ``overrides`` (None ignored)."""
    cfg = default_config(defaults_for)
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise DataError(f"{path}: config file does not exist")
        text = path.read_text()
        try:
            if path.suffix.lower() == ".toml":
                import tomllib

                data = tomllib.loads(text)
            else:
                data = json.loads(text)
        except Exception as exc:  # json.JSONDecodeError / tomllib.TOMLDecodeError
            raise DataError(f"{path}: cannot parse config ({exc})") from None
        if not isinstance(data, dict):
            raise DataError(f"{path}: config must be a table/object of options")
        cfg = ReconConfig.from_dict(data, cfg, str(path))
    over = {k: v for k, v in overrides.items() if v is not None}
    return ReconConfig.from_dict(over, cfg, "command line") if over else cfg
