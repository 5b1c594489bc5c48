"""One call from a scene folder to a finished run folder: :func:`run_identify` (used by the CLI and the bench)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from endogsim.errors import DataError, MaterialError
from endogsim.identify.config import IdentifyConfig
from endogsim.identify.optimize import CHECKPOINT_NAME, identify, planned_for
from endogsim.identify.report import evaluate_field, reference_observed_flow, write_outputs
from endogsim.io.runfolder import check_npz, load_torch_file, run_folder
from endogsim.materials.field import MaterialField
from endogsim.materials.init import BACKENDS
from endogsim.scene.folder import SimScene, identification_settings, load_sim_scene

__all__ = ["initial_field", "check_init", "check_field_objects", "run_identify", "INIT_CHOICES"]

#: The named initialisations (the materials back-ends); anything else must be a material JSON file.
INIT_CHOICES = BACKENDS


def check_init(init: str, option: str = "--init") -> None:
    """Refuse an initialisation (given as ``option``) that is neither a materials back-end nor an existing
    material JSON file."""
    if init not in INIT_CHOICES and not Path(init).is_file():
        raise DataError(f"{option} {init!r} is neither one of {', '.join(INIT_CHOICES)} nor a material JSON file")


def initial_field(problem: SimScene, init: str = "prior") -> tuple[MaterialField, bool]:
    """The starting material field and whether it is an explicit user request (a file: strict stability).

    Args:
        init: "manual" | "prior" | "mllm" | "replay" (see :func:`endogsim.materials.initialise_materials`), or
            a material-field JSON file (e.g. ``materials.json`` of ``endogsim materials init``).
    """
    from endogsim.materials import MaterialInitConfig, initialise_materials

    if init in INIT_CHOICES:
        scene = None
        if init in ("mllm", "replay"):
            from endogsim.io.scene import Scene

            T = problem.num_frames
            scene = Scene(frames=problem.frames, times=np.arange(T) * problem.mpm.frame_dt,
                          K=problem.camera.K.double().numpy(), object_masks=problem.object_masks,
                          labels=problem.labels, source=str(problem.folder))
        return initialise_materials(problem.labels, MaterialInitConfig(backend=init), scene=scene), False
    check_init(init)
    return MaterialField.load(Path(init)), True


def run_identify(
    scene: str | Path,
    out: str | Path,
    init: str = "prior",
    config: IdentifyConfig | None = None,
    resume: bool = True,
    progress: Callable[[int, int, dict], None] | None = None,
    video: bool = True,
    evaluate_init: bool = False,
    problem: SimScene | None = None,
    on_trial: Callable[[dict], None] | None = None,
) -> dict:
    """Identify the materials of a scene folder and write the run folder ``out``; returns metrics.json's dict.

    Args:
        scene: a scene folder (``endogsim synth`` layout).
        out: run folder (created and locked for the run; a checkpoint there is resumed unless ``resume`` is
            False; a corrupt checkpoint or flow cache is refused before any work).
        init: initialiser or material JSON file (see :func:`initial_field`).
        config: identification options.
        progress: callback(iteration, iters, info) after every iteration.
        on_trial: callback(trial) after every simulation of the intervals that follow the iterations (see
            :func:`~endogsim.identify.uncertainty.parameter_intervals`; called from worker threads).
        video: write comparison.mp4.
        evaluate_init: also score the initial materials (metrics["init_metrics"]).
        problem: an already loaded problem for ``scene`` at ``config.refine`` (saves the loading).
    """
    cfg = config or IdentifyConfig()
    out = Path(out)
    with run_folder(out, "identify"):
        _check_resumable_state(out, resume)
        if problem is None:
            pb = load_sim_scene(scene, frames=cfg.frames, device=cfg.device, refine=cfg.refine)
        else:  # a caller's scene must be the one the configuration asks for
            pb, want = problem, identification_settings(problem.spec, cfg.refine)
            if (pb.settings.grid, pb.settings.substeps, pb.settings.particle_spacing) != (
                    want.grid, want.substeps, want.particle_spacing):
                raise DataError(f"{pb.folder}: the scene was loaded at {pb.settings}, not at the identification "
                                f"discretisation refined {cfg.refine:g}x that the configuration asks for")
        fld, strict = initial_field(pb, init)
        check_field_objects(pb, fld, init)
        pb = planned_for(pb, fld, cfg)  # as identify simulates it: its fields are evaluated and shown so
        # The identified field is evaluated while the intervals' last trials run, where they run side by side.
        result = identify(pb, fld, cfg, run_dir=out, resume=resume, progress=progress, strict=strict,
                          evaluate=lambda f, known: evaluate_field(pb, f, reference_observed_flow(pb, cfg, out), known),
                          on_trial=on_trial)
        return write_outputs(out, pb, result, cfg, init_name=init, video=video, evaluate_init=evaluate_init)


def _check_resumable_state(out: Path, resume: bool) -> None:
    """Refuse a corrupt checkpoint or flow cache in ``out`` before any work (offering --fresh); with
    ``resume`` False, remove the checkpoint and a corrupt cache (a readable one is keyed by the frames)."""
    ckpt, flow = out / CHECKPOINT_NAME, out / "observed_flow.npz"
    if not resume:
        ckpt.unlink(missing_ok=True)
    elif ckpt.is_file():
        load_torch_file(ckpt)
    if flow.is_file():
        try:
            check_npz(flow, ("flow", "key"), what="observed-flow cache")
        except DataError:
            if resume:
                raise
            flow.unlink()


def check_field_objects(problem: SimScene, fld: MaterialField, where: str) -> None:
    """Refuse a material field with records for objects the scene does not have (a file made for another
    scene); ``where`` names the field's origin for the message."""
    known = {o.id for o in problem.spec.objects}
    extra = [f"{r.name!r} (id {r.object_id})" for r in fld.records if r.object_id not in known]
    if extra:
        have = ", ".join(f"{o.name!r} (id {o.id})" for o in problem.spec.objects)
        raise MaterialError(f"{where}: material record(s) for {', '.join(extra)}, which scene {problem.spec.name!r} "
                            f"({problem.folder}) does not have; its objects are {have}")
