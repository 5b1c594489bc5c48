"""``endogsim validate``: calibrate on the first frames of a video, predict the rest, compare with what was filmed.

A real video has no ground-truth material, so the calibration is judged the way PhysTwin judges real
captures: on frames it never saw. The run folder ``OUT``:

  OUT/recon/, OUT/scene/     reconstruction and scenario of the whole clip (:func:`~endogsim.pipeline.run_pipeline`,
                             reused when already done)
  OUT/calibrate/             ``endogsim identify`` on the first ``train_fraction`` of the frames only
  OUT/validate/validate.json the figures below; ``heldout_*.png`` observed | predicted | flow error stills
  OUT/report.html            the calibration's report with the held-out section

Every method renders the held-out frames t >= T_train (and the flow pairs t -> t+1 for t >= T_train - 1,
the first of which reaches into the held-out frames) with the same Gaussians, renderer and cameras, each
frame exposed and cropped to the field of view as the endoscope filmed it (a moving endoscope's
reconstruction learns both; :func:`~endogsim.scene.forward.as_filmed`):

  prediction      the scene simulated over the whole clip with the calibrated materials (the tracked
                  instrument motion drives it); over the training frames it is the calibration's own rollout,
                  so the held-out frames continue from the calibrated state
  prior           the same simulation with the initial materials
  zero_motion     the calibrated simulation's state at the last training frame, held still
  border_interpolation
                  only where the tissue's border band follows the reconstruction's tracks (a real video's
                  default, ``RealScenario.border_motion``): the same drive without the physics, every particle
                  moved by the inverse-distance mean of its nearest band particles' motion
                  (:func:`border_interpolation`), its Gaussians undeformed. What the simulation adds to the
                  observed boundary motion is what it wins over this
  reconstruction  the 4D reconstruction's own Gaussians at each frame (it was fitted to every frame: an upper
                  bound, not a baseline to beat)

``epe``: mean end-point error (px, at ``eval_scale`` of the image) over tissue pixels against the observed
flow (the identification's estimator) of the held-out pairs; ``psnr_masked``: PSNR over the held-out frames'
tissue pixels.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np
import torch

from endogsim.errors import DataError
from endogsim.io.atomic import write_json_atomic
from endogsim.pipeline.run import PipelineConfig

__all__ = ["ValidateConfig", "run_validate", "split_frames", "heldout_scores", "heldout_per_frame", "compare_to",
           "border_interpolation", "METHODS"]

#: The rows of the comparison, in order: the calibrated prediction, then the baselines (border_interpolation
#: only for a scene whose border follows the tracks).
METHODS = ("prediction", "prior", "zero_motion", "border_interpolation", "reconstruction")


def border_interpolation(scene) -> torch.Tensor | None:
    """[T, P, 3] particle positions (metres) moved by the scene's tracked border alone, without physics: each
    particle by the inverse-square-distance mean of the motion of its 8 nearest band particles (every
    object's band together; :func:`~endogsim.scene.tracks.carry_by`), the band's own particles on
    their paths. None for a scene whose border holds still (no ``moving_anchors``)."""
    from endogsim.scene.tracks import carry_by

    moving = scene.scenario.moving_anchors
    if not moving:
        return None
    band = torch.cat([a.particles for a in moving]).numpy()
    band_paths = torch.cat([a.positions[:scene.num_frames] for a in moving], 1).numpy()
    out = carry_by(band_paths, scene.particles.x.double().numpy())
    out[:, band] = band_paths
    return torch.from_numpy(out).float()


@dataclass
class ValidateConfig:
    """Options of :func:`run_validate`.

    Attributes:
        train_fraction: the calibration sees the first round(fraction * T) frames (at least 2, at most T - 1).
        init: initial materials (manual | prior | mllm | replay | a material JSON file): the "prior" baseline.
        eval_scale: render and compare the held-out frames at this fraction of the image size.
        pipeline: the reconstruction, scenario and identification settings (``pipeline.identify.frames`` is
            set to the training frames).
        recon_run: an existing ``endogsim reconstruct`` run folder of the same data to use instead of
            reconstructing into OUT/recon (the scene is then rebuilt from it).
    """

    train_fraction: float = 0.67
    init: str = "prior"
    eval_scale: float = 0.5
    pipeline: PipelineConfig = field(default_factory=lambda: PipelineConfig(interaction=None))
    recon_run: Path | None = None

    def __post_init__(self) -> None:
        if not 0 < self.train_fraction < 1:
            raise DataError(f"--train-fraction {self.train_fraction} must lie in (0, 1)")
        if not 0 < self.eval_scale <= 1:
            raise DataError(f"eval_scale {self.eval_scale} must lie in (0, 1]")


def split_frames(num_frames: int, train_fraction: float) -> int:
    """T_train: the number of calibration frames of a ``num_frames`` clip (>= 2, <= T - 1)."""
    if num_frames < 3:
        raise DataError(f"a {num_frames}-frame clip cannot be split into calibration and held-out frames (need >= 3)")
    return int(min(max(round(train_fraction * num_frames), 2), num_frames - 1))


def heldout_scores(rgb: np.ndarray, flow: np.ndarray, observed: np.ndarray, observed_flow: np.ndarray,
                   tissue: np.ndarray, tissue_pairs: np.ndarray) -> dict[str, float]:
    """``{"epe", "psnr_masked"}`` of one method over the held-out frames.

    Args:
        rgb: [K, H, W, 3] the method's renders of the held-out frames; observed: the same frames filmed.
        flow: [K', H, W, 2] its flow over the held-out pairs (px); observed_flow: the observed estimate.
        tissue: [K, H, W] bool tissue pixels of the held-out frames; tissue_pairs: [K', H, W] of both frames.
    """
    from endogsim.evaluate.flow_metrics import epe
    from endogsim.evaluate.image_metrics import psnr

    e = epe(flow, observed_flow, tissue_pairs)
    p = psnr(torch.from_numpy(np.clip(rgb, 0, 1)), torch.from_numpy(observed), torch.from_numpy(tissue))
    return {"epe": float(e), "psnr_masked": float(p)}


def heldout_per_frame(rgb: np.ndarray, flow: np.ndarray, observed: np.ndarray, observed_flow: np.ndarray,
                      tissue: np.ndarray, tissue_pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same errors as :func:`heldout_scores`, frame by frame (the same metrics, one frame at a time): the
    tissue EPE of every held-out pair [K'] (px) and the tissue mean squared error of every held-out frame [K]
    (NaN where a frame has no tissue)."""
    from endogsim.evaluate.flow_metrics import epe
    from endogsim.evaluate.image_metrics import mse

    flow_err = np.array([epe(f, o, m) for f, o, m in zip(flow, observed_flow, tissue_pairs)])
    pred, seen = torch.from_numpy(np.clip(rgb, 0, 1)), torch.from_numpy(observed)
    image_err = np.array([float(mse(pred[k], seen[k], torch.from_numpy(m))) if m.any() else math.nan
                          for k, m in enumerate(tissue)])
    return flow_err, image_err


#: The least relative improvement over a baseline's error that counts as a win (identification's ``tol``).
MIN_RELATIVE_GAIN = 1e-3


def compare_to(prediction: tuple[np.ndarray, np.ndarray], baseline: tuple[np.ndarray, np.ndarray],
               min_relative: float = MIN_RELATIVE_GAIN) -> dict:
    """Does the prediction beat a baseline, beyond the frame-to-frame noise and by a margin that matters?

    Paired over the held-out frames (:func:`endogsim.identify.uncertainty.paired_z`): for the per-pair EPE
    and the per-frame squared error, the mean difference (prediction minus baseline; negative: better), the
    same relative to the baseline's mean, its z and the one-sided 95% critical value
    (:func:`~endogsim.identify.uncertainty.significant_z`). ``beats``: both lower, significantly (z below
    minus the critical value) and by at least ``min_relative`` of the baseline's error. Both tests are
    needed: two renders that differ in the 7th digit differ consistently, frame after frame, so a paired
    test alone calls 1e-7 px a significant win.
    """
    from endogsim.identify.uncertainty import paired_z, significant_z

    out = {}
    for what, a, b in (("epe", prediction[0], baseline[0]), ("mse", prediction[1], baseline[1])):
        ok = np.isfinite(a) & np.isfinite(b)
        delta, _, z = paired_z(dict(enumerate(a[ok].tolist())), dict(enumerate(b[ok].tolist())))
        n = int(ok.sum())
        mean_b = float(b[ok].mean()) if n else math.nan
        out[what] = {"difference": delta / max(n, 1), "relative": delta / max(n, 1) / mean_b if mean_b > 0 else 0.0,
                     "z": z if n > 1 else 0.0, "frames": n, "significant_z": significant_z(n)}
    out["beats"] = all(v["z"] < -v["significant_z"] and v["relative"] <= -min_relative for v in (out["epe"], out["mse"]))
    return out


def _reconstruction_renders(recon_dir: Path, scene, camera, frames: list[int], T: int) -> tuple[np.ndarray, np.ndarray]:
    """The reconstruction's renders of ``frames`` and its Gaussian flow t -> t+1 (t + 1 < T), seen by each
    frame's camera (``camera``: the evaluation intrinsics) and filmed as the simulations are (``scene``'s
    exposure and field of view, :func:`~endogsim.scene.forward.as_filmed`)."""
    from endogsim.gaussians.camera import Camera
    from endogsim.gaussians.flow import render_with_flow
    from endogsim.gaussians.rasterize_torch import world_to_camera
    from endogsim.gaussians.render import rasterize
    from endogsim.recon.model import load_reconstruction
    from endogsim.scene.forward import as_filmed, in_field_of_view

    rec = load_reconstruction(recon_dir)
    view = Camera(camera.K, camera.width, camera.height)

    def state(t: int):
        g = rec.gaussians_at(t, include_tools=True)
        return g, *world_to_camera(g.means, g.covariances(), rec.camera_at(t).viewmat.to(g.means))

    rgbs, flows = [], []
    with torch.no_grad():
        for t in frames:
            g, m, c = state(t)
            colors = g.colors_dc.clamp(0, 1).float()
            if t + 1 < T:
                _, mn, cn = state(t + 1)
                r = render_with_flow(m, g.opacities, colors, view, mn, covars=c, covars_next=cn)
                flows.append(in_field_of_view(scene, r.flow).numpy())
            else:
                r = rasterize(m, g.opacities, colors, view, covars=c)
            rgbs.append(as_filmed(scene, r.rgb, t).clamp(0, 1).numpy())
    return np.stack(rgbs), np.stack(flows) if flows else np.zeros((0, view.height, view.width, 2), np.float32)


def check_reconstruction_of(recon_dir: Path, data: Path) -> None:
    """Refuse a reconstruction (``--recon``) made from frames other than ``data``'s: its provenance record
    holds the hash of the frames it used, read again here at its resolution and frame count. A scene built
    from another clip's Gaussians would be validated against this clip's frames without a word."""
    import json

    from endogsim.io import load_scene
    from endogsim.io.runfolder import PROVENANCE, check_provenance, provenance

    if not (recon_dir / PROVENANCE).is_file():
        if not (recon_dir / "deformation.pt").is_file():
            raise DataError(f"{recon_dir}: not an `endogsim reconstruct` run folder (no deformation.pt)")
        check_provenance(recon_dir, {"data": str(data)})  # an older run: continued with a warning
        return
    try:
        cfg = json.loads((recon_dir / PROVENANCE).read_text()).get("config") or {}
        scale, max_frames = float(cfg.get("resolution_scale", 0.5)), cfg.get("max_frames")
    except (ValueError, TypeError, AttributeError) as exc:
        raise DataError(f"{recon_dir / PROVENANCE}: unreadable ({exc})") from None
    scene = load_scene(data, downscale=1.0 / scale, max_frames=max_frames)
    try:
        check_provenance(recon_dir, provenance(data, scene.frames, cfg))
    except DataError as exc:
        why = str(exc).split(": use")[0]
        raise DataError(f"--recon {recon_dir} is not a reconstruction of {data}: {why}") from None


def run_validate(data: str | Path, out: str | Path, config: ValidateConfig | None = None, *,
                 on_stage=None, log=print) -> dict:
    """Reconstruct (or reuse), calibrate on the first frames, predict the rest; returns validate.json's content.

    Args:
        data: the dataset folder or video.
        out: the run folder (module docstring).
        config: :class:`ValidateConfig`.
        on_stage: progress callback(stage, "start" | "done" | "skip") of the reconstruction and scenario stages.
        log: one-line progress messages.
    """
    from endogsim.evaluate.report_html import write_report
    from endogsim.identify import run_identify
    from endogsim.identify.loss import make_observations, observed_flow
    from endogsim.identify.optimize import planned_for
    from endogsim.identify.report import comparison_frames, flow_error_map
    from endogsim.io.runfolder import run_folder
    from endogsim.materials.field import MaterialField
    from endogsim.pipeline.run import run_pipeline
    from endogsim.scene.folder import load_sim_scene
    from endogsim.scene.forward import render_sequence
    from endogsim.warp_runtime import run_independent

    cfg = config or ValidateConfig()
    data, out = Path(data), Path(out)
    t_start = time.perf_counter()
    if cfg.recon_run is None:
        run_pipeline(data, out, cfg.pipeline, on_stage=on_stage, stop_after="scenario")
        recon_dir = out / "recon"
    else:
        recon_dir = Path(cfg.recon_run)
        check_reconstruction_of(recon_dir, data)
    with run_folder(out, "validate"):
        if cfg.recon_run is not None:
            from endogsim.pipeline.scene_from_recon import scene_from_reconstruction

            scene_from_reconstruction(recon_dir, data, out / "scene", scenario=cfg.pipeline.scenario)
        scene = load_sim_scene(out / "scene", device=cfg.pipeline.identify.device, refine=cfg.pipeline.identify.refine)
        T = scene.num_frames
        T_train = split_frames(T, cfg.train_fraction)
        log(f"calibrating on frames 0..{T_train - 1} of {T}")
        ident_cfg = replace(cfg.pipeline.identify, frames=T_train)
        m = run_identify(out / "scene", out / "calibrate", init=cfg.init, config=ident_cfg, resume=True,
                         video=cfg.pipeline.video,
                         progress=lambda k, n, rec: log(f"  iteration {k}/{n}: loss {rec['loss']:.5g}"),
                         on_trial=lambda t: log(f"  interval trial: {t['object']} {t['parameter']} = {t['value']:.4g}"
                                                f"{' Pa' if t['parameter'] == 'E' else ''} ({t['grid']} grid"
                                                f"{', ' + t['at'] if t.get('at') else ''})"))
        calibrated = MaterialField.load(out / "calibrate" / "materials_identified.json")
        # The calibration's own starting field: an MLLM asked again could answer otherwise.
        prior = MaterialField.load(out / "calibrate" / "materials_init.json")
        refine = float(calibrated.meta.get("refine", ident_cfg.refine))
        if refine != ident_cfg.refine:  # corrected to a refined discretisation: both predictions are made there
            scene = load_sim_scene(out / "scene", device=ident_cfg.device, refine=refine)
        # Planned at the prior as the calibration was: both predictions at the time step it simulated with.
        scene = planned_for(scene, prior, ident_cfg)

        log("predicting the held-out frames")
        cam = scene.camera.scaled(cfg.eval_scale)
        shown = list(range(T_train - 1, T))  # the last training frame starts the first held-out flow pair
        test = [t for t in shown if t >= T_train]
        renders: dict[str, tuple[np.ndarray, np.ndarray]] = {}

        def simulate_and_render(fld: MaterialField, keep: bool):
            """(the simulation if ``keep``, its renders and flow of ``shown``)."""
            with torch.no_grad():  # grad mode is per thread
                res = scene.simulator().simulate(fld.simulator_materials())
                r = render_sequence(scene, res.positions, res.F, cam, frames=shown)
            return (res if keep else None), (r.rgb.numpy(), r.flow.numpy())

        # The two simulations are independent: side by side where there are cores for both. The simulator is
        # built first, once; every kernel was launched (built) by the calibration's final evaluation.
        scene.simulator().engine  # noqa: B018 - builds it
        (res, renders["prediction"]), (_, renders["prior"]) = run_independent(
            [partial(simulate_and_render, calibrated, True), partial(simulate_and_render, prior, False)],
            scene.independent_simulations())
        with torch.no_grad():
            held = res.positions.clone(), res.F.clone()
            held[0][T_train - 1:] = res.positions[T_train - 1]
            held[1][T_train - 1:] = res.F[T_train - 1]
            r = render_sequence(scene, held[0], held[1], cam, frames=shown)
            renders["zero_motion"] = (r.rgb.numpy(), r.flow.numpy())
        moved = border_interpolation(scene)
        if moved is not None:
            with torch.no_grad():
                undeformed = torch.eye(3).expand(moved.shape[0], moved.shape[1], 3, 3)
                r = render_sequence(scene, moved, undeformed, cam, frames=shown)
            renders["border_interpolation"] = (r.rgb.numpy(), r.flow.numpy())
        renders["reconstruction"] = _reconstruction_renders(recon_dir, scene, cam, shown, T)

        vdir = out / "validate"
        vdir.mkdir(parents=True, exist_ok=True)
        U = observed_flow(scene.frames, cfg.pipeline.identify.flow, vdir / "observed_flow.npz")
        obs = make_observations(scene.frames, U, scene.object_masks, scene.deformable_ids, (cam.width, cam.height))
        k_test = [shown.index(t) for t in test]
        pairs = [t for t in shown if t + 1 < T]
        scores, per_frame = {}, {}
        methods = [name for name in METHODS if name in renders]
        for name in methods:
            rgb, flow = renders[name]
            args = (rgb[k_test], flow, obs.frames[test].numpy(), obs.flow[pairs].numpy(),
                    obs.valid_rgb[test].numpy(), obs.valid_flow[pairs].numpy())
            scores[name] = heldout_scores(*args)
            per_frame[name] = heldout_per_frame(*args)
        comparison = {k: compare_to(per_frame["prediction"], per_frame[k]) for k in methods
                      if k not in ("prediction", "reconstruction")}
        import imageio.v3 as iio

        rgb, flow = renders["prediction"]
        err = flow_error_map(scene, flow, obs.flow[pairs].numpy())
        panels = comparison_frames(obs.frames[shown].numpy(), np.clip(rgb, 0, 1), err)
        for t in sorted({test[0], test[len(test) // 2], test[-1]}):
            iio.imwrite(vdir / f"heldout_{t:04d}.png", (panels[shown.index(t)] * 255 + 0.5).astype(np.uint8))
        result = {
            "clip": str(data), "train_frames": T_train, "test_frames": T - T_train,
            "prediction": scores["prediction"],
            "baselines": {k: scores[k] for k in methods if k != "prediction"},
            "materials": m["materials"], "identifiable": m.get("identifiable", {}), "intervals": m.get("intervals", {}),
            "force_scales": m.get("force_scales"),
            "calibration": {"iterations": m.get("iterations"), "seconds": m.get("seconds"), "stopped": m.get("stopped"),
                            "seconds_per_iteration": (m["seconds"] / m["iterations"]) if m.get("iterations") else None,
                            "coverage": m.get("coverage")},
            "beats": {k: c["beats"] for k, c in comparison.items()},
            "comparison": {k: {w: c[w] for w in ("epe", "mse")} for k, c in comparison.items()},
            "eval_scale": cfg.eval_scale, "units": {"epe": "px at eval_scale", "psnr_masked": "dB", "seconds": "s"},
            "seconds": time.perf_counter() - t_start,
        }
        write_json_atomic(vdir / "validate.json", result)
        write_report(out / "calibrate", out=out / "report.html", validation=vdir,
                     title=f"EndoGSim validation: {data.name}")
    return result


def validation_table(result: dict) -> tuple[list[str], list[list]]:
    """(columns, rows) of a validate.json for printing (:func:`endogsim.evaluate.report_html.validation_rows`)."""
    from endogsim.evaluate.report_html import VALIDATION_COLUMNS, validation_rows

    return VALIDATION_COLUMNS, validation_rows(result)
