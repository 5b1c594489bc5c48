"""Training loop of the 4D reconstruction (Endo-4DGS style) and the run-folder outputs.

Entry point: :func:`reconstruct` (data folder -> run folder, resumable). Stages:

0. **tracks** (:mod:`endogsim.priors.tracks`): every initial tissue Gaussian is tracked through the
   training frames by chained optical flow (test frames are never read), and the deformation field is
   fitted to those tracks alone for ``track_warmup_iters`` steps (no rendering). Endoscopic tissue moves
   by tens of pixels over a clip, far beyond what a photometric gradient sees from an identity start.
1. **coarse** (``coarse_fraction`` of the iterations, 0 by default: the warm-up gives the deformation
   its start): static tissue Gaussians fitted to random training frames, as in Endo-4DGS; tools already
   follow their per-frame rigid poses.
2. **deformation**: the HexPlane field deforms the tissue per frame; densification (clone/split by
   view-space gradient) and pruning (low opacity) run in the first part of the run.

Losses per iteration (frame t drawn from a shuffled list of training frames):

* tissue render vs frame t on tissue pixels only: L1 + ``lambda_dssim`` (1 - SSIM) (non-tissue pixels
  are replaced by the target before SSIM, so they carry no gradient); with metric depth,
  ``lambda_depth`` * L1(depth / median depth); in the deformation stage the HexPlane regularisers and the
  track term (``lambda_track``, decaying: the photometric loss refines what the tracks start).
* every ``tool_every`` iterations, the tool model: the tools visible in frame t rendered alone and
  composited over the (detached) tissue render, L1 on tool pixels, plus ``lambda_tool_alpha`` *
  |alpha - tool mask| over the image (the tools must cover their mask and nothing else) and pose
  smoothness. A tool out of view or occluded in frame t is not rendered there: its pose at t follows only
  the smoothness term, and the export fills it from its visible neighbours (held beyond the first and last).

The tissue model never sees tool pixels, so instruments leave no smear in the tissue.

A moving endoscope (``camera_motion``; on by default for data with neither poses nor depth) gets a
learnt pose per frame (:class:`~endogsim.recon.camera_motion.CameraMotion`, started from tracked tissue
features) and, as its light moves with it, a per-frame exposure (:mod:`endogsim.recon.exposure`); the
tissue that pans into view gets initial Gaussians from the frame that first shows it. Every frame is
rendered from its pose, test frames from poses and exposures interpolated between their training
neighbours in frame time (repeated frames of a frame-rate conversion share their time:
:func:`~endogsim.recon.data.repeated_frames`). The final evaluation registers each test frame's pose to
the frame with the model frozen, as unposed-video methods are evaluated (no interpolation can follow
the jerks of a hand-held endoscope); the exported poses of the test frames are those registered ones.

Every schedule runs on :meth:`Trainer.progress`, the share of ``iters`` done: what a run computes does not
depend on the machine's speed. ``time_budget_s`` is only a safety stop (the training seconds include the
priors of the initialisation, the tracking and the warm-up): a run it stops is the same run as an unstopped
one up to the iteration where it stopped, and ``metrics.json`` says ``stopped_by_budget``.
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import Callable

import torch

from endogsim.determinism import deterministic
from endogsim.errors import DataError
from endogsim.evaluate.image_metrics import masked_l1, ssim_map
from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import Gaussians
from endogsim.gaussians.render import render_gaussians
from endogsim.io.atomic import save_torch_atomic, write_json_atomic
from endogsim.io.runfolder import PROVENANCE, check_provenance, load_torch_file, provenance, run_folder
from endogsim.recon.camera_motion import CameraMotion
from endogsim.recon.config import ReconConfig
from endogsim.recon.data import PreparedScene, prepare_scene
from endogsim.recon.deformation import DeformationField
from endogsim.recon.exposure import FrameExposure
from endogsim.recon.init import initial_gaussians
from endogsim.recon.model import ReconResult, compose_at
from endogsim.recon.params import GaussianParams, log_linear_lr
from endogsim.recon.tools import ToolMotion

__all__ = ["reconstruct", "Trainer", "Interrupted"]

ProgressFn = Callable[[int, int, dict], None]


class Interrupted(Exception):
    """Raised by :meth:`Trainer.run` when ``stop_after`` iterations were done (the checkpoint is saved)."""


def _resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise DataError("device 'cuda' requested but CUDA is not available")
    return torch.device(name)


def _wants_exposure(mode: str, moving_camera: bool) -> bool:
    """"auto": per-frame exposure exactly when the endoscope (and its light) moves."""
    return moving_camera if mode == "auto" else mode == "on"


def _wants_camera_motion(mode: str, prep: PreparedScene) -> bool:
    """"auto": a moving endoscope is assumed when the dataset gives neither poses nor depth."""
    if mode == "auto":
        return prep.scene.poses is None and prep.scene.depth is None
    return mode == "on"


class Trainer:
    """State of one reconstruction run (built fresh or from a checkpoint).

    Args:
        prep: the prepared scene (frames, masks, depth, split).
        config: the run configuration.
        out_dir: run folder (checkpoints, outputs).
    """

    def __init__(self, prep: PreparedScene, config: ReconConfig, out_dir: Path) -> None:
        self.prep, self.cfg, self.out = prep, config, Path(out_dir)
        self.device = _resolve_device(config.device)
        sc = prep.scene
        dev = self.device
        self.frames = torch.as_tensor(sc.frames, device=dev)
        self.tissue_mask = torch.as_tensor(prep.tissue, device=dev, dtype=torch.float32)
        self.tool_mask = torch.as_tensor(prep.tool, device=dev, dtype=torch.float32)
        self.depth = torch.as_tensor(prep.depth, device=dev) if prep.depth_metric else None
        self.times = torch.as_tensor(sc.times if prep.times is None else prep.times, dtype=torch.float32)
        self.camera = Camera(torch.as_tensor(sc.K, dtype=torch.float32), sc.width, sc.height).to(dev)
        self.field_of_view = (None if prep.field_of_view is None
                              else torch.as_tensor(prep.field_of_view, device=dev, dtype=torch.float32)[..., None])
        self.iteration = 0
        self.elapsed = 0.0
        self.history: list[dict] = []
        self.stopped_by_budget = False
        self.gen = torch.Generator().manual_seed(config.seed)
        self._order: list[int] = []

    # ------------------------------------------------------------------ construction
    def _gauss_lrs(self) -> dict[str, float]:
        c = self.cfg
        return {"means": c.lr_means * self.extent, "quats": c.lr_quats, "log_scales": c.lr_scales,
                "opacity_logits": c.lr_opacity, "sh": c.lr_sh}

    def _build_optimizers(self) -> None:
        c = self.cfg
        self.deform_opt = torch.optim.Adam([
            {"params": list(self.deformation.hexplane.parameters()), "lr": c.lr_grid, "name": "grid"},
            {"params": [p for n, p in self.deformation.named_parameters() if not n.startswith("hexplane.")],
             "lr": c.lr_mlp, "name": "mlp"},
        ], eps=1e-15)
        self.camera_opt = None
        if self.camera_motion is not None:
            self.camera_opt = torch.optim.Adam([
                {"params": [self.camera_motion.rotation], "lr": c.lr_camera_rot, "name": "rot"},
                {"params": [self.camera_motion.translation], "lr": c.lr_camera_trans * self.extent, "name": "trans"},
            ])
        self.exposure_opt = None
        if self.exposure is not None:
            self.exposure_opt = torch.optim.Adam(self.exposure.parameters(), lr=c.lr_exposure)
        self.motion_opt = None
        if self.motion is not None:
            self.motion_opt = torch.optim.Adam([
                {"params": [self.motion.rotation], "lr": c.lr_tool_rot, "name": "rot"},
                {"params": [self.motion.translation], "lr": c.lr_tool_trans * self.extent, "name": "trans"},
            ])

    def init_fresh(self) -> None:
        c, prep = self.cfg, self.prep
        torch.manual_seed(c.seed)
        t0 = time.perf_counter()
        moving = _wants_camera_motion(c.camera_motion, prep)
        rotations = flows = None
        if moving:
            from endogsim.priors.camera import estimate_camera_rotations

            rotations = estimate_camera_rotations(prep.scene.frames, prep.tissue, prep.scene.K, prep.train)
        if c.point_tracks:
            from endogsim.priors.tracks import consecutive_flows

            flows = consecutive_flows(prep.scene.frames, prep.train, self._flow_estimator())
        ini = initial_gaussians(prep, c.init_stride, c.init_opacity, c.sh_degree, c.tool_depth_factor, c.init_scale,
                                flows[1] if (moving and flows is not None) else None, rotations)
        if len(ini.tissue) == 0:
            raise DataError(f"{prep.scene.source}: no tissue pixel with depth in the training frames")
        lo = ini.tissue.means.min(0).values
        hi = ini.tissue.means.max(0).values
        pad = 0.15 * (hi - lo).max()
        bounds = torch.stack([lo - pad, hi + pad])
        self.extent = float((hi - lo).max())
        self.init_info = {"tissue_gaussians": len(ini.tissue), "disoccluded_gaussians": ini.n_disoccluded,
                          "tool_gaussians": len(ini.tools), "tool_ids": ini.tool_ids, "tool_ref_frames": ini.ref_frames}
        self.track_seeds = None
        track_ids = None
        if c.point_tracks:
            # one track per initial tissue Gaussian, from the pixel it was back-projected from
            self.track_seeds = {"pixels": torch.as_tensor(ini.tissue_pixels), "frames": torch.as_tensor(ini.tissue_frames)}
            track_ids = torch.arange(len(ini.tissue))
        self.tissue = GaussianParams(ini.tissue.to(self.device), self._gauss_lrs(), track_ids)
        self.tools = GaussianParams(ini.tools.to(self.device), self._gauss_lrs()) if len(ini.tools) else None
        t = self.times
        self.deformation = DeformationField(c.deformation, bounds, (float(t[0]), float(t[-1]) if len(t) > 1 else 1.0),
                                            len(t)).to(self.device)
        self.motion = None
        self.tool_visible = None
        if ini.tool_ids:
            self.motion = ToolMotion(ini.tool_ids, ini.centers, len(t), ini.init_translation).to(self.device)
            with torch.no_grad():
                self.motion.rotation.copy_(ini.init_rotation)
            self.tool_visible = ini.visible
        self.camera_motion = CameraMotion(len(t), torch.as_tensor(rotations)).to(self.device) if moving else None
        self.exposure = FrameExposure(len(t)).to(self.device) if _wants_exposure(c.exposure, moving) else None
        self._build_optimizers()
        self._build_tracks(flows)
        if self.tracks is not None and c.track_warmup_iters > 0:
            self.init_info["track_warmup_loss"] = self._fit_tracks(c.track_warmup_iters)
        self.elapsed += time.perf_counter() - t0  # the priors, tracking and the warm-up are part of training

    def state(self) -> dict:
        return {
            "iteration": self.iteration, "elapsed": self.elapsed, "extent": self.extent, "history": self.history,
            "init_info": self.init_info, "config": self.cfg.to_dict(),
            "tissue": self.tissue.state(), "tools": self.tools.state() if self.tools is not None else None,
            "deformation": self.deformation.export(), "deform_opt": self.deform_opt.state_dict(),
            "motion": None if self.motion is None else {"tool_ids": self.motion.tool_ids,
                                                        "state_dict": self.motion.state_dict()},
            "motion_opt": None if self.motion_opt is None else self.motion_opt.state_dict(),
            "camera_motion": None if self.camera_motion is None else self.camera_motion.state_dict(),
            "camera_opt": None if self.camera_opt is None else self.camera_opt.state_dict(),
            "exposure": None if self.exposure is None else self.exposure.state_dict(),
            "exposure_opt": None if self.exposure_opt is None else self.exposure_opt.state_dict(),
            "tool_visible": self.tool_visible, "gen": self.gen.get_state(), "order": list(self._order),
            "track_seeds": self.track_seeds,
            "torch_rng": torch.get_rng_state(),
        }

    def load_state(self, st: dict) -> None:
        self.iteration, self.elapsed, self.extent = st["iteration"], st["elapsed"], st["extent"]
        self.history, self.init_info = st["history"], st["init_info"]
        self.tissue = GaussianParams.from_state(st["tissue"], self._gauss_lrs()).to(self.device)
        self.tools = GaussianParams.from_state(st["tools"], self._gauss_lrs()).to(self.device) if st["tools"] else None
        self.deformation = DeformationField.from_export(st["deformation"]).to(self.device)
        self.motion = None
        if st["motion"] is not None:
            sd = st["motion"]["state_dict"]
            self.motion = ToolMotion(st["motion"]["tool_ids"], sd["centers"], sd["rotation"].shape[1])
            self.motion.load_state_dict(sd)
            self.motion = self.motion.to(self.device)
        self.tool_visible = st["tool_visible"]
        self.camera_motion = None
        if st.get("camera_motion") is not None:
            self.camera_motion = CameraMotion(st["camera_motion"]["rotation"].shape[1])
            self.camera_motion.load_state_dict(st["camera_motion"])
            self.camera_motion = self.camera_motion.to(self.device)
        self.exposure = None
        if st.get("exposure") is not None:
            self.exposure = FrameExposure(st["exposure"]["log_gain"].shape[1])
            self.exposure.load_state_dict(st["exposure"])
            self.exposure = self.exposure.to(self.device)
        self._build_optimizers()
        if self.camera_opt is not None:
            self.camera_opt.load_state_dict(st["camera_opt"])
        if self.exposure_opt is not None:
            self.exposure_opt.load_state_dict(st["exposure_opt"])
        self.deform_opt.load_state_dict(st["deform_opt"])
        if self.motion_opt is not None:
            self.motion_opt.load_state_dict(st["motion_opt"])
        self.gen.set_state(st["gen"])
        self._order = list(st["order"])
        torch.set_rng_state(st["torch_rng"])
        self.track_seeds = st.get("track_seeds")
        self._build_tracks()  # deterministic: recomputed rather than stored

    def save_checkpoint(self) -> None:
        save_torch_atomic(self.state(), self.out / "checkpoint.pt")

    # ------------------------------------------------------------------ point tracks
    def _flow_estimator(self):
        from endogsim.priors.flow import flow_estimator

        return flow_estimator(self.cfg.flow, device=str(self.device))

    def _build_tracks(self, flows=None) -> None:
        """Track every seeded tissue point through the training frames (:func:`~endogsim.priors.tracks.track_points`);
        ``flows``: their :func:`~endogsim.priors.tracks.consecutive_flows` when already computed."""
        self.tracks = None
        if self.track_seeds is None:
            return
        from endogsim.priors.tracks import track_points

        prep = self.prep
        tracks = track_points(prep.scene.frames, prep.tissue, self.track_seeds["pixels"].numpy(),
                              self.track_seeds["frames"].numpy(), prep.train,
                              self._flow_estimator() if flows is None else None, flows)
        self.tracks = tracks.to(self.device)
        self.init_info["tracked_share"] = round(float(tracks.valid[:, prep.train].float().mean()), 4)

    def _project(self, points: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        """Pixel coordinates [M, 2] of points [M, 3] seen from frames [M] (each point its own frame)."""
        from endogsim.gaussians.camera import project_points

        if self.camera_motion is None:
            return self.camera.project(points)
        return project_points(points, self.camera.K, self.camera_motion.transforms()[0][frames])

    def _track_loss(self, frame: int, deformed_means: torch.Tensor | None = None) -> torch.Tensor | None:
        """Mean Huber (1 px) distance between how far tracked Gaussians move on screen, from their canonical
        position seen in their seed frame to their deformed position in ``frame``, and how far their tracks
        move; None when no tracked Gaussian is valid in ``frame``.

        A Gaussian is seeded at its pixel's back-projection, so this pins each canonical position to its
        seed frame (and gives the deformation a gradient from the start, unlike a difference of two
        deformed positions, which an untrained, time-independent field makes exactly zero).

        ``deformed_means``: [N] tissue centres already deformed to ``frame`` (the render's), reused."""
        tid = self.tissue.track_ids
        ok = tid >= 0
        ok[ok.clone()] = self.tracks.valid[tid[ok], frame]
        idx = torch.nonzero(ok).squeeze(1)
        if len(idx) == 0:
            return None
        if len(idx) > self.cfg.track_batch:
            idx = idx[torch.randperm(len(idx), generator=self.gen)[: self.cfg.track_batch].to(idx.device)]
        k = tid[idx]
        seed = self.tracks.seed_frame[k]
        if deformed_means is None:
            at_t = self.deformation(self.tissue.gaussians().subset(idx), float(self.times[frame])).means
        else:
            at_t = deformed_means[idx]
        moved = self._project(at_t, torch.full_like(seed, frame)) - self._project(self.tissue.params["means"][idx], seed)
        target = self.tracks.positions[k, frame] - self.tracks.positions[k, seed]
        return torch.nn.functional.huber_loss(moved, target, delta=1.0)

    def _fit_tracks(self, iters: int) -> float:
        """Fit the deformation field to the tracks alone (canonical Gaussians fixed); returns the last track
        loss (pixels, Huber)."""
        loss = None
        for _ in range(iters):
            loss = self._track_loss(self._next_frame())
            if loss is None:
                continue
            loss.backward()
            self.deform_opt.step()
            self.deform_opt.zero_grad(set_to_none=True)
            self.tissue.optimizer.zero_grad(set_to_none=True)
        self._order = []
        return float(loss.detach()) if loss is not None else float("nan")

    # ------------------------------------------------------------------ one iteration
    def view(self, frame: int) -> Camera:
        """The camera of ``frame``: fixed, or posed by the learnt camera motion (differentiable)."""
        return self.camera if self.camera_motion is None else self.camera_motion.camera(self.camera, frame)

    def expose(self, rgb: torch.Tensor, frame: int) -> torch.Tensor:
        """A render [H, W, 3] as frame ``frame``'s camera exposed it: its per-frame exposure, if learnt, and
        black outside the lens's field of view, if the data has a border."""
        rgb = rgb if self.exposure is None else self.exposure(rgb, frame)
        return rgb if self.field_of_view is None else rgb * self.field_of_view

    def _next_frame(self) -> int:
        if not self._order:
            perm = torch.randperm(len(self.prep.train), generator=self.gen).tolist()
            self._order = [self.prep.train[i] for i in perm]
        return self._order.pop()

    def progress(self) -> float:
        """Share of the run done, in [0, 1]: iterations over ``iters``.

        Every schedule (coarse/fine switch, learning-rate decay, densification window) runs on this and
        never on the clock, so a run computes the same on a slow machine as on a fast one; a time budget
        can only stop it early (:meth:`run`).
        """
        return min(self.iteration / self.cfg.iters, 1.0)

    def _set_lrs(self, f: float) -> None:
        c = self.cfg
        for gp in (self.tissue, self.tools):
            if gp is not None:
                gp.set_lr("means", log_linear_lr(f, c.lr_means * self.extent, c.lr_means_final * self.extent))
        c0 = c.coarse_fraction
        fine_f = (f - c0) / (1 - c0) if c0 < 1 else 0.0
        for g in self.deform_opt.param_groups:
            base = c.lr_grid if g["name"] == "grid" else c.lr_mlp
            g["lr"] = log_linear_lr(fine_f, base, base * 0.1)
        decay = log_linear_lr(f, 1.0, c.lr_camera_decay)
        if self.camera_opt is not None:
            for g in self.camera_opt.param_groups:
                g["lr"] = decay * (c.lr_camera_rot if g["name"] == "rot" else c.lr_camera_trans * self.extent)
        if self.exposure_opt is not None:
            for g in self.exposure_opt.param_groups:
                g["lr"] = decay * c.lr_exposure

    def step(self) -> dict:
        c = self.cfg
        f = self.progress()
        fine = c.coarse_fraction < 1 and f >= c.coarse_fraction
        t = self._next_frame()
        time_t = float(self.times[t])
        self._set_lrs(f)
        gt = self.frames[t]
        m = self.tissue_mask[t]
        g = compose_at(self.tissue.gaussians(), None, self.deformation if fine else None, None, time_t, t, False)
        if not g.means.is_leaf:
            g.means.retain_grad()
        out = render_gaussians(g, self.view(t), backend=c.backend)
        means2d = out.meta.get("means2d")
        if means2d is not None and means2d.requires_grad and out.meta.get("backend") in ("torch", "warp"):
            means2d.retain_grad()
        rgb = self.expose(out.rgb, t)
        loss = (1 - c.lambda_dssim) * masked_l1(rgb, gt, m)
        if c.lambda_dssim > 0:
            filled = rgb * m[..., None] + gt * (1 - m[..., None])
            loss = loss + c.lambda_dssim * (1 - ssim_map(filled, gt).mean())
        if self.depth is not None and c.lambda_depth > 0:
            d = self.depth[t]
            valid = (m > 0) & (d > 0) & (out.alpha > 0.5)
            if valid.any():
                loss = loss + c.lambda_depth * (out.depth[valid] - d[valid]).abs().mean() / d[valid].median()
        if fine:
            loss = loss + self.deformation.regularization(c.lambda_plane_tv, c.lambda_time_smooth, c.lambda_time_l1)
            if self.tracks is not None and c.lambda_track > 0:
                track = self._track_loss(t, g.means)
                if track is not None:
                    loss = loss + log_linear_lr(f, c.lambda_track, c.lambda_track_final) * track
        loss.backward()
        self._accumulate_view_gradient(g, out, means2d)
        info = {"loss": float(loss.detach()), "frame": t, "n": len(self.tissue)}

        if self.tools is not None and self.iteration % c.tool_every == 0 and self.tool_visible[:, t].any():
            tg = self.motion.apply(self._tools_visible_at(t), t)
            tout = render_gaussians(tg, self.view(t), backend=c.backend)
            tm = self.tool_mask[t]
            comp = self.expose(tout.rgb + (1 - tout.alpha)[..., None] * out.rgb.detach(), t)
            tloss = masked_l1(comp, gt, tm) + c.lambda_tool_alpha * (tout.alpha - tm).abs().mean()
            tloss = tloss + c.lambda_pose_smooth * self.motion.smoothness(self.extent)
            tloss.backward()
            self.tools.step()
            self.motion_opt.step()
            self.motion_opt.zero_grad(set_to_none=True)
            info["tool_loss"] = float(tloss.detach())

        self.tissue.step()
        for opt in (self.camera_opt, self.exposure_opt):
            if opt is not None:
                opt.step()
                opt.zero_grad(set_to_none=True)
        if fine:
            self.deform_opt.step()
        self.deform_opt.zero_grad(set_to_none=True)

        it = self.iteration + 1
        f_done = min(it / c.iters, 1.0)  # the progress including this iteration
        if c.densify_from < f_done <= c.densify_until and it % c.densify_every == 0:
            # A bounded growth per step: adding most of the set at once drops the PSNR for a while (the
            # children start as opaque as their parents) and makes every later iteration slower.
            cap = min(c.max_gaussians, int(len(self.tissue) * (1 + c.densify_max_growth)))
            info["densify"] = self.tissue.densify_and_prune(
                c.densify_grad_threshold, c.percent_dense, self.extent, c.prune_opacity, cap, self.gen)
        self.iteration = it
        return info

    def _tools_visible_at(self, frame: int) -> Gaussians:
        """The canonical Gaussians of the tools visible in training frame ``frame`` (``tool_visible``): one
        that left the view or is occluded there is not rendered, so it neither covers the other tools'
        pixels nor gets a gradient pushing it out of the picture."""
        g = self.tools.gaussians()
        visible = self.tool_visible[:, frame]
        if bool(visible.all()):
            return g
        ids = [oid for oid, v in zip(self.motion.tool_ids, visible.tolist()) if v]
        return g.subset(torch.isin(g.object_ids, torch.as_tensor(ids, device=g.object_ids.device)))

    def _accumulate_view_gradient(self, g, out, means2d) -> None:
        """Densification statistics: the view-space gradient of every Gaussian's projected centre.

        The torch backend exposes the projected centres in the graph; for other backends (gsplat returns
        a view that holds no gradient) the pixel-space gradient is recovered from the camera-space one,
        d L / d u = (z / f) d L / d x, which ignores the small perspective term along z.
        """
        radii = out.meta["radii"]
        visible = radii.gt(0).any(-1) if radii.ndim == 2 else radii.gt(0)
        if means2d is not None and means2d.grad is not None:
            grad2d = means2d.grad
        elif g.means.grad is not None:
            z = out.meta["depths"].detach().clamp_min(1e-6)
            K = self.camera.K
            grad2d = torch.stack([g.means.grad[:, 0] * z / K[0, 0], g.means.grad[:, 1] * z / K[1, 1]], -1)
        else:
            return
        self.tissue.add_stats(grad2d.detach(), visible, self.camera.width, self.camera.height)

    # ------------------------------------------------------------------ loop
    def run(self, progress: ProgressFn | None = None, stop_after: int | None = None) -> None:
        """Train up to ``config.iters``, checkpointing every ``checkpoint_every`` iterations.

        ``stop_after``: stop (checkpoint, then raise :class:`Interrupted`) after this many iterations of
        this call, to test resuming. A KeyboardInterrupt also writes the checkpoint first.
        """
        c = self.cfg
        done_here = 0
        try:
            while self.iteration < c.iters:
                if c.time_budget_s is not None and self.elapsed >= c.time_budget_s:
                    self.stopped_by_budget = True  # a safety stop: nothing else depends on the clock
                    break
                t0 = time.perf_counter()
                info = self.step()
                self.elapsed += time.perf_counter() - t0  # training time only (no evaluation, no I/O)
                done_here += 1
                if self.iteration % 50 == 0 or self.iteration == c.iters:
                    self.history.append({"iteration": self.iteration, "seconds": round(self.elapsed, 2),
                                         "loss": round(info["loss"], 6), "gaussians": len(self.tissue)})
                if c.eval_every and self.iteration % c.eval_every == 0 and self.prep.test:
                    ev = self.evaluate(self.prep.test)
                    self.history.append({"iteration": self.iteration, "seconds": round(self.elapsed, 2),
                                         "test_psnr_masked": round(ev["psnr_masked"], 3),
                                         "test_psnr_endonerf": round(ev["psnr_endonerf"], 3)})
                if progress is not None:
                    progress(self.iteration, c.iters, info)
                if self.iteration % c.checkpoint_every == 0 and self.iteration < c.iters:
                    self.save_checkpoint()
                if stop_after is not None and done_here >= stop_after and self.iteration < c.iters:
                    self.save_checkpoint()
                    raise Interrupted(f"stopped after {done_here} iterations (checkpoint at {self.iteration})")
        except KeyboardInterrupt:
            self.save_checkpoint()
            raise

    # ------------------------------------------------------------------ outputs
    @torch.no_grad()
    def gaussians_at(self, frame: int, include_tools: bool = True):
        return compose_at(self.tissue.gaussians().detach(), self.tools.gaussians().detach() if self.tools else None,
                          self.deformation, self.motion, float(self.times[frame]), frame, include_tools)

    def evaluate(self, frames: list[int], render_dir: Path | None = None, register_poses: bool = False) -> dict:
        """Test metrics on ``frames`` (:func:`endogsim.recon.evaluation.evaluate_frames`)."""
        from endogsim.recon.evaluation import evaluate_frames

        return evaluate_frames(self, frames, render_dir, register_poses)

    def export(self) -> dict:
        """Write every run output (:func:`endogsim.recon.export.export_run`) and return the metrics."""
        from endogsim.recon.export import export_run

        return export_run(self)


@deterministic()
def reconstruct(data: str | Path, out_dir: str | Path, config: ReconConfig | None = None, *,
                progress: ProgressFn | None = None, resume: bool = True, stop_after: int | None = None) -> ReconResult:
    """Reconstruct a dataset into a run folder.

    Returns a :class:`~endogsim.recon.model.ReconResult`: the paths of the frame-0 Gaussians PLY (object
    ids), the tool trajectories and ``metrics.json``, and the metrics (it reads like the metrics dict).
    Resuming a finished run folder trains no further and writes its outputs again.

    Args:
        data: EndoNeRF / CholecSeg8K / procedural folder or a video file.
        out_dir: run folder; if it holds ``checkpoint.pt`` and ``resume``, training continues from it.
        config: :class:`ReconConfig` (default: CPU defaults).
        progress: callback(iteration, total, info) after every iteration.
        resume: continue from ``out_dir/checkpoint.pt`` when it exists (refused when the folder was made
            from other frames: ``provenance.json`` records the data path, frame count and size, a content
            hash of the frames and the configuration).
        stop_after: test hook: stop after this many iterations with a checkpoint (raises Interrupted).
    """
    cfg = config or ReconConfig()
    out = Path(out_dir)
    with run_folder(out, "reconstruct"):
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            prep = prepare_scene(data, cfg)
        trainer = Trainer(prep, cfg, out)
        made_from = provenance(data, prep.scene.frames, cfg.to_dict())
        ckpt = out / "checkpoint.pt"
        if resume and ckpt.is_file():
            check_provenance(out, made_from)
            st = load_torch_file(ckpt)
            if st["config"] != cfg.to_dict():
                warnings.warn(f"{ckpt}: the checkpoint was made with a different configuration; continuing with "
                              "the checkpoint's model and the new schedule", stacklevel=2)
            trainer.load_state(st)
        else:
            trainer.init_fresh()
        write_json_atomic(out / PROVENANCE, made_from)
        write_json_atomic(out / "config.json", cfg.to_dict())
        trainer.run(progress, stop_after)
        metrics = trainer.export()
        trainer.save_checkpoint()
    return ReconResult(out, metrics)
