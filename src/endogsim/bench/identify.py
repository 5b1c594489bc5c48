"""``endogsim bench identify``: the identification ablations of the paper, on the procedural benchmark scenes.

Tables (RE = mean relative error of E, nu, G, K; EPE in pixels against the ground-truth flow):
  1. initialisation (manual, prior) x optimisation (off, on): RE and EPE      (the paper's Table 3)
  2. object-wise material field vs one global material on ``two_tissues``    (the paper's Figure 4)
  3. loss: render only, flow only, joint
  4. gradient mode: last_substep, frame, full: RE reached and seconds

Scenes are synthesized once into ``--scenes-dir`` (reused afterwards). ``--quick`` runs tables 1, 3, 4 on
``tiny`` and table 2 on ``two_tissues`` at half image size and 12 frames, with 6 iterations, so the whole
bench takes minutes on a CPU; ``--scenes``, ``--iters``, ``--frames`` and ``--tables`` choose other settings.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

ALL_SCENES = ("press", "pull", "two_tissues", "stomach", "gallbladder")
SCENES_CACHE = Path.home() / ".cache" / "endogsim" / "bench_scenes"  # default of every bench's --scenes-dir


def ensure_scene(name: str, scenes_dir: Path, frames: int | None = None, scale: float | None = None,
                 seed: int = 0) -> Path:
    """The folder of benchmark scene ``name`` under ``scenes_dir``, synthesized if missing.

    Args:
        frames: number of frames (default: the suite's); scale: image-size factor (default 1).
        seed: the scene's texture, relief and noise (:func:`endogsim.synth.synthesize`; 0: the suite's figures).
            Another seed is the same experiment on another surface: the folder name says ``_seedS``.
    Raises:
        GroundTruthRefused: the ground truth of this seed fails the generator's own checks (no fair test).
    """
    from endogsim.errors import DataError
    from endogsim.synth import load_scene_spec, synthesize
    from endogsim.synth.suite import GENERATOR_REVISION

    tag = (name + ("" if frames is None else f"_f{frames}") + ("" if scale in (None, 1.0) else f"_s{scale:g}")
           + ("" if seed == 0 else f"_seed{seed}"))
    folder = scenes_dir / tag
    try:
        spec = load_scene_spec(folder)
        fresh = spec.generator == GENERATOR_REVISION and spec.seed == seed
    except DataError:  # missing or unreadable
        fresh = False
    if not fresh:  # a scene from an older generator has another ground truth
        synthesize(name, folder, seed=seed, frames=frames, scale=scale)
    return folder


def _run(scene: Path, out: Path, init: str, cfg, fresh: bool = True) -> dict:
    from endogsim.identify import run_identify

    t0 = time.perf_counter()
    m = run_identify(scene, out, init=init, config=cfg, resume=not fresh, video=False)
    m["wall_seconds"] = time.perf_counter() - t0
    return m


def run_bench(scenes_dir: Path, work_dir: Path, quick: bool = False, iters: int | None = None,
              scenes: list[str] | None = None, tables: list[str] | None = None, frames: int | None = None,
              log=print) -> dict:
    """Run the ablations; returns {"tables": {name: {"columns": [...], "rows": [[...]]}}, "runs": {...}}.

    Args:
        scenes_dir: where benchmark scenes are (or get) synthesized.
        work_dir: run folders of every identification.
        quick: ``tiny`` for tables 1, 3, 4; ``two_tissues`` at half size and 12 frames for table 2; 6 iterations.
        iters: iterations per optimised run (default 6 quick, else :class:`IdentifyConfig`'s).
        scenes: scenes of table 1 (default: ``tiny`` quick, else the five procedural scenes); the first is
            also the scene of tables 3 and 4 (default ``tiny`` quick, else ``press``).
        tables: subset of {"init", "field", "loss", "grad"}.
        frames: identify from the first ``frames`` frames only (default: all).
    """
    from endogsim.identify import GRAD_MODES, LOSSES, IdentifyConfig

    tables = tables or ["init", "field", "loss", "grad"]
    n_it = iters if iters is not None else (6 if quick else IdentifyConfig().iters)
    main_scenes = scenes or (["tiny"] if quick else list(ALL_SCENES))
    abl_scene = scenes[0] if scenes else ("tiny" if quick else "press")
    field_frames, field_scale = (12, 0.5) if quick else (None, None)  # two_tissues for table 2
    base = dict(iters=n_it, frames=frames, time_budget=None)  # no stop: figures independent of the machine's speed
    out: dict = {"tables": {}, "runs": {}, "settings": {"quick": quick, "iters": n_it, "frames": frames,
                                                          "config": IdentifyConfig(**base).to_json()}}

    def scene_dir(name: str) -> Path:
        return ensure_scene(name, scenes_dir, None)

    done: dict[str, dict] = {}  # identical runs (e.g. prior/on = joint loss = default grad mode) run once

    def run(key: str, folder: Path, init: str, **options) -> dict:
        cfg = IdentifyConfig(**{**base, **options})
        same = json.dumps([str(folder), init, cfg.to_json()], sort_keys=True)
        if same not in done:
            done[same] = _run(folder, work_dir / key, init, cfg)
        m = done[same]
        out["runs"][key] = {k: m.get(k) for k in ("scene", "init", "loss", "grad_mode", "global_material", "re_mean",
                                                   "re_E", "re_nu", "epe", "psnr", "ssim", "seconds", "iterations",
                                                   "materials")}
        log(f"  {key}: RE {m.get('re_mean', math.nan):.3f}  EPE {m['epe']:.3f} px  {m['seconds']:.0f} s")
        return m

    if "init" in tables:
        rows = []
        for sc in main_scenes:
            folder = scene_dir(sc)
            row = [sc]
            for init in ("manual", "prior"):
                for on in (False, True):
                    m = run(f"init/{sc}/{init}/{'on' if on else 'off'}", folder, init, iters=n_it if on else 0)
                    row += [m.get("re_mean", math.nan), m["epe"]]
            rows.append(row)
        if len(rows) > 1:
            rows.append(["mean"] + [sum(r[i] for r in rows) / len(rows) for i in range(1, len(rows[0]))])
        out["tables"]["init"] = {"title": "Initialisation x optimisation (RE / EPE px)",
                                 "columns": ["scene", "manual off RE", "EPE", "manual on RE", "EPE",
                                             "prior off RE", "EPE", "prior on RE", "EPE"], "rows": rows}
    if "field" in tables:
        folder = ensure_scene("two_tissues", scenes_dir, field_frames, field_scale)
        rows = []
        for glob in (False, True):
            m = run(f"field/two_tissues/{'global' if glob else 'field'}", folder, "prior", global_material=glob)
            mats = "; ".join(f"{n} {v['E']:.4g} Pa / {v['nu']:.3f}" for n, v in m["materials"].items() if not v["rigid"])
            rows.append(["global material" if glob else "material field", m.get("re_mean", math.nan), m["epe"], mats])
        out["tables"]["field"] = {"title": "Material field vs global material on two_tissues",
                                  "columns": ["variant", "RE", "EPE px", "identified"], "rows": rows}
    for table, option, values in (("loss", "loss", LOSSES), ("grad", "grad_mode", GRAD_MODES)):
        if table not in tables:
            continue
        folder = scene_dir(abl_scene)
        rows = []
        for v in values:
            m = run(f"{table}/{abl_scene}/{v}", folder, "prior", **{option: v})
            rows.append([v, m.get("re_mean", math.nan), m["epe"], m["seconds"], m["iterations"]])
        out["tables"][table] = {"title": f"{option} ablation on {abl_scene} (prior init)",
                                "columns": [option, "RE", "EPE px", "seconds", "iterations"], "rows": rows}
    return out
