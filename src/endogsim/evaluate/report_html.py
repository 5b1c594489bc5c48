"""One HTML page per run that opens offline: videos, flow error maps, plots, materials and metrics.

:func:`write_report` reads a run folder (``endogsim identify`` layout, see :mod:`endogsim.identify.report`)
and optionally ``endogsim simulate`` output folders, and writes ``report.html``:

  * videos side by side: the run's ``comparison.mp4`` (observed | simulated | flow error) and each
    simulation's ``simulation.mp4``, linked by relative path (the page and the folders move together);
  * stills of the first, middle and last frame split into observed / simulated / flow error map
    (inferno, 0..1 px), decoded from ``comparison.mp4`` and embedded as base64 PNG;
  * ``loss.png`` and ``parameters.png`` embedded as base64 PNG;
  * the material table (identified and initial values, ground truth where the scene has it, E range,
    source, confidence) and the metrics (RE, EPE, PSNR, SSIM, FID when Inception weights are given).

Nothing is fetched from the network: no scripts, fonts or stylesheets from elsewhere.
"""

from __future__ import annotations

import base64
import html
import json
import math
import os
from pathlib import Path

import numpy as np

from endogsim.errors import DataError, ModelError
from endogsim.io.atomic import write_text_atomic

__all__ = ["write_report", "read_video", "comparison_panels"]

_CSS = """
body{font-family:system-ui,Segoe UI,Helvetica,Arial,sans-serif;margin:1.5em;color:#222;max-width:1400px}
h1{font-size:1.5em}h2{font-size:1.2em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.5em}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f3f3f3}td.l,th.l{text-align:left}.row{display:flex;flex-wrap:wrap;gap:1em;align-items:flex-start}
figure{margin:0}figcaption{font-size:.85em;color:#555}video,img{max-width:100%}pre{background:#f7f7f7;padding:.6em}
.note{color:#666;font-size:.9em}
"""


def read_video(path: str | os.PathLike) -> np.ndarray:
    """All frames of a video file as uint8 [T, H, W, 3] (decoded with imageio-ffmpeg)."""
    import imageio_ffmpeg

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: video not found")
    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    w, h = meta["size"]
    frames = [np.frombuffer(b, np.uint8).reshape(h, w, 3) for b in gen]
    if not frames:
        raise DataError(f"{path}: no frames")
    return np.stack(frames)


def comparison_panels(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split comparison frames [T, H, 3W(+pad), 3] into observed, simulated, flow error [T, H, W, 3] each."""
    w = frames.shape[2] // 3
    return frames[:, :, :w], frames[:, :, w:2 * w], frames[:, :, 2 * w:3 * w]


def _png_data_uri(img: np.ndarray) -> str:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img[..., ::-1]))
    if not ok:
        raise DataError("could not encode a PNG for the report")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def _file_data_uri(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def _e(v) -> str:
    return html.escape(str(v), quote=True)


def _fmt(v, digits: int = 4) -> str:
    if v is None:
        return "&ndash;"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return "n/a" if math.isnan(v) else f"{v:.{digits}g}"
    return _e(v)


def _table(columns: list[str], rows: list[list], left: int = 1) -> str:
    head = "".join(f'<th class="l">{_e(c)}</th>' if i < left else f"<th>{_e(c)}</th>" for i, c in enumerate(columns))
    body = "".join("<tr>" + "".join(f'<td class="l">{_fmt(v)}</td>' if i < left else f"<td>{_fmt(v)}</td>"
                                    for i, v in enumerate(r)) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _load_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text()) if path.is_file() else None
    except json.JSONDecodeError as exc:
        raise DataError(f"{path}: not valid JSON ({exc})") from None


def _scene_of(metrics: dict, run: Path) -> tuple[Path | None, dict | None]:
    """The scene folder a run's ``metrics.json`` names (``folder`` as written, else ``folder_from_run``
    relative to the run folder: both moved) and its ``scene.json``; (None, None) when neither is there."""
    named, relative = metrics.get("folder"), metrics.get("folder_from_run")
    for f in (named, relative and run / relative):
        if f and (Path(f) / "scene.json").is_file():
            return Path(f), _load_json(Path(f) / "scene.json")
    return None, None


def _material_rows(run: Path, metrics: dict, scene: dict | None) -> tuple[list[str], list[list]]:
    ident = _load_json(run / "materials_identified.json") or {"objects": []}
    init = {o["object_id"]: o for o in (_load_json(run / "materials_init.json") or {"objects": []})["objects"]}
    truth = {o["id"]: o for o in (scene or {}).get("objects", [])}
    re_obj = metrics.get("re_objects") or {}
    cols = ["object", "id", "class", "model", "E (Pa)", "nu", "density (kg/m^3)", "E range (Pa)", "source",
            "confidence", "init E (Pa)", "init nu", "init source", "true E (Pa)", "true nu", "RE"]
    rows = []
    for o in ident["objects"]:
        i0 = init.get(o["object_id"], {})
        t = truth.get(o["object_id"], {})
        rng = (f"{o['E_min']:.3g} – {o['E_max']:.3g}" if o.get("E_min") is not None and o.get("E_max") is not None
               else None)
        re = (re_obj.get(o["name"]) or {}).get("mean")
        rows.append([o["name"], o["object_id"], o.get("klass"), o.get("model"), o["E"], o["nu"], o["density"], rng,
                     o.get("source"), o.get("confidence"), i0.get("E"), i0.get("nu"), i0.get("source"),
                     None if o.get("rigid") else t.get("E"), None if o.get("rigid") else t.get("nu"), re])
    return cols, rows


def _fid_cell(observed: np.ndarray | None, simulated: np.ndarray | None, fid_weights) -> tuple[float | str, str]:
    """(FID or 'n/a', note)."""
    from endogsim.evaluate.fid import FID_WEIGHTS_ENV, fid

    if fid_weights is None and not os.environ.get(FID_WEIGHTS_ENV):
        return "n/a", f"FID: n/a (no Inception weights; pass --fid-weights FILE or set ${FID_WEIGHTS_ENV})"
    if observed is None or len(observed) < 2:
        return "n/a", "FID: n/a (no comparison.mp4 to take frames from)"
    try:
        return fid(observed, simulated, fid_weights), "FID between the observed and simulated panels of comparison.mp4"
    except ModelError as exc:
        return "n/a", f"FID: n/a ({exc})"


#: Columns of :func:`validation_rows`.
VALIDATION_COLUMNS = ["method", "EPE (px)", "masked PSNR (dB)",
                      "beaten by the prediction? (paired z and change: EPE, MSE)"]


def validation_rows(v: dict) -> list[list[str]]:
    """Rows (:data:`VALIDATION_COLUMNS`, as text) of a validate.json: the prediction, then each baseline with
    whether the prediction beats it beyond the frame-to-frame noise (a validate.json from before that test:
    "-"). EPE to 1e-6 px and PSNR to 1e-4 dB, so that a tie in the 5th digit reads as one."""
    def fixed(x: float, decimals: int) -> str:
        return f"{x:.{decimals}f}" if math.isfinite(x) else str(x)

    def verdict(name: str) -> str:
        c = v.get("comparison", {}).get(name)
        if c is None:
            return "upper bound" if name == "reconstruction" else "-"
        e, m = c["epe"], c["mse"]
        return (f"{'yes' if v['beats'][name] else 'no'} (z {e['z']:+.2f}, {m['z']:+.2f}; "
                f"{100 * e.get('relative', 0.0):+.3g}%, {100 * m.get('relative', 0.0):+.3g}%)")

    rows = [["prediction (calibrated)", v["prediction"], ""]] + [[name, b, verdict(name)] for name, b in v["baselines"].items()]
    return [[name, fixed(sc["epe"], 6), fixed(sc["psnr_masked"], 4), said] for name, sc, said in rows]


def settling_text(settle: dict) -> str:
    """What the settling before frame 0 left, from metrics.json's ``settling`` record
    (:func:`endogsim.identify.report.settling_record`), and whether that is settled."""
    verdict = "settled" if settle["settled"] else (
        "NOT settled: the rest moves in the clip (a real video starts at equilibrium; a fit reads that motion "
        "as the tissue's response)")
    # A record from before "gravity" was recorded keeps the wording it was written with.
    acting = ("under gravity" if settle.get("gravity", True)
              else "without gravity, the instruments at their frame-0 pose,")
    return (f"{settle['frames']} frames {acting} before frame 0; in the last, a particle still moved "
            f"{1e3 * settle['last_frame_motion_m']:.4f} mm ({100 * settle['cells']:.2f}% of a grid cell; tolerance "
            f"{100 * settle['tolerance_cells']:.0f}%): {verdict}")


def simulated_at_text(d: dict) -> str:
    """'grid 49 (2.24 mm cells), 24,505 particles, 8 substeps a frame at these materials (1x the scene's
    identification discretisation)' from metrics.json's ``discretisation`` record
    (:func:`endogsim.identify.report.discretisation_record`; 'at least N substeps a frame' where it has no
    materials' count)."""
    at = d.get("substeps_at_materials")
    substeps = f"at least {d['substeps']}" if at is None else f"{at}"
    return (f"grid {d['grid']} ({d['cell_m'] * 1e3:.2f} mm cells), {d['particles']:,} particles, {substeps} "
            f"substeps a frame{'' if at is None else ' at these materials'} ({d['refine']:g}x the scene's "
            "identification discretisation)")


def correction_text(d: dict) -> str:
    """'sheet E 2421 -> 1960 Pa, sheet nu 0.400 -> 0.423 at grid 74 (...): the loss there 0.04801 -> 0.04402
    (2 steps, converged)' from metrics.json's ``refined_correction`` record
    (:func:`endogsim.identify.report.correction_record`)."""
    moves = [f"{name} {10 ** a:.4g} -> {10 ** b:.4g} Pa" if name.endswith(" E") else f"{name} {a:.3f} -> {b:.3f}"
             for name, a, b in zip(d["parameters"], d["before"], d["after"])]
    losses = d["refined_loss"]
    if not d["applied"]:
        return (f"{d['factor']:g}x the grid: no step taken ({d['stopped']}; the loss there {losses[0]:.5g}); the "
                "materials stay as identified")
    return (f"{', '.join(moves)}, for {simulated_at_text(d['discretisation'])}: its loss {losses[0]:.5g} -> "
            f"{losses[-1]:.5g} ({len(losses) - 1} step{'s' if len(losses) > 2 else ''}, {d['stopped']})")


def force_scale_text(d: dict) -> str:
    """'weight (gravity 9.81 m/s^2 along (0, 1, 0)) and inertia (frames 33.3 ms apart, masses x4, damping
    100/s); ...' from metrics.json's ``force_scales`` record (:func:`endogsim.identify.report.force_scale_record`)."""
    g = math.hypot(*d["gravity_m_s2"])
    parts = []
    if "weight" in d["scales"]:
        along = ", ".join(f"{v / g + 0.0:.2g}" for v in d["gravity_m_s2"])  # + 0.0: no "-0"
        parts.append(f"weight (gravity {g:.3g} m/s^2 along ({along}))")
    mass = f", masses x{d['mass_scaling']:g}" if d["mass_scaling"] != 1 else ""
    parts.append(f"inertia (frames {1e3 * d['frame_dt_s']:.3g} ms apart{mass}, damping {d['damping_per_s']:g}/s)")
    parts += [f"{n} {what}" for n, what in ((d["applied_forces"], "applied force(s)"), (d["impulses"], "impulse(s)"))
              if n]
    return (" and ".join(parts) + "; an E fitted to the video holds for these values and moves with them (instruments "
            "and held borders prescribe motion, which alone fixes nu and the ratios of E, not E)")


def discretisation_text(parameter: str, disc: dict, search_box: list[float] | None = None) -> str:
    """'+-0.63 decades (the optimum on a grid 1.42x coarser: 6474 Pa, -0.0888 decades)' from the dict of a
    :class:`~endogsim.identify.uncertainty.DiscretisationError` of ``parameter`` ("E", in Pa, or "nu"); with the
    parameter's ``search_box`` (Pa for E), an error bar wider than the box says so (the interval is clipped to it:
    "+-3.16 decades, wider than the search box's 4.3" reads as what it is, no statement about E beyond the box)."""
    unit, scale = (" Pa", " decades") if parameter == "E" else ("", "")
    beyond = ", or beyond" if disc.get("lower_bound") else ""
    wider = ""
    if search_box is not None:
        lo, hi = search_box
        width = math.log10(hi / lo) if parameter == "E" else hi - lo
        if 2.0 * disc["half_width"] >= width:
            wider = f", wider than the search box's {width:.3g}{scale}"
    return (f"+-{disc['half_width']:.3g}{scale}{wider} (the optimum on a grid {disc['ratio']:.2f}x coarser: "
            f"{disc['coarse_best']:.4g}{unit}, {disc['shift']:+.3g}{scale}{beyond})")


def _validation_section(folder: Path, rel) -> list[str]:
    """The held-out comparison of an ``endogsim validate`` folder (validate.json, heldout_*.png)."""
    v = _load_json(folder / "validate.json")
    if v is None:
        raise DataError(f"{folder}: no validate.json (not an `endogsim validate` output folder)")
    rows = validation_rows(v)
    out = [f'<h2>Held-out validation</h2><p class="note">calibrated on frames 0..{v["train_frames"] - 1}, '
           f"predicted frames {v['train_frames']}..{v['train_frames'] + v['test_frames'] - 1} from the calibrated "
           "state with the tracked instrument motion; EPE over tissue pixels against the observed flow of the "
           "held-out frames, PSNR over their tissue pixels. The reconstruction is an upper bound, not a baseline "
           "to beat. The prediction beats a baseline when both its per-pair EPE and its per-frame squared error "
           "are lower beyond the frame-to-frame noise (paired test over the held-out frames, one-sided 95%) and "
           "by at least 0.1% of the baseline's.</p>",
           _table([""] + VALIDATION_COLUMNS[1:], rows)]
    stills = sorted(folder.glob("heldout_*.png"))
    if stills:
        out.append('<p class="note">observed | predicted | flow error |U_pred - U_obs| (inferno, 0..1 px)</p>')
        out.append("".join(f'<figure><img alt="{_e(p.stem)}" src="{_file_data_uri(p)}"><figcaption>{_e(p.stem)}'
                           "</figcaption></figure>" for p in stills))
    return out


#: Colours (RGB) of the instruments drawn in the report's "Instruments" still, in order.
_TOOL_COLOURS = [(255, 60, 60), (60, 140, 255), (60, 220, 90), (255, 200, 40), (220, 80, 255)]


def _instruments_section(folder: Path | None, doc: dict | None) -> list[str]:
    """The instruments of a real video's scene (``doc``: the ``scene.json`` of ``folder``; its ``colliders``
    are written by ``pipeline/scene_from_recon.py``): how each capsule was fitted, and frame 0 with each
    capsule's axis and working end (its tip, where jaws bite) drawn; nothing for a scene without fitted
    colliders (a benchmark scene takes its ground truth's)."""
    import cv2

    from endogsim.io.images import read_rgb
    from endogsim.scene.schema import IMAGES_PATTERN

    if not doc or not doc.get("colliders"):
        return []
    names = {o["id"]: o.get("name", str(o["id"])) for o in doc.get("objects", [])}
    tools = {t["object_id"]: t for t in doc.get("scenario", {}).get("tools", [])}
    K = np.asarray(doc["camera"]["K"], float)
    rows, still = [], None
    image = folder / (doc.get("files", {}).get("images", IMAGES_PATTERN) % 0)
    if image.is_file():
        still = np.round(read_rgb(image) * 255.0).astype(np.uint8)
    for k, c in enumerate(doc["colliders"]):
        tip, end = np.asarray(c["tip"], float), np.asarray(c["end"], float)
        tool = tools.get(c["object_id"], {})
        seen = tool.get("visible")
        rows.append([names.get(c["object_id"], c["object_id"]), f"{c['radius'] * 1e3:.2f}",
                     f"{np.linalg.norm(tip - end) * 1e3:.1f}", c.get("working_end_from", "depth"),
                     None if c.get("jaws_extension_m") is None else f"{c['jaws_extension_m'] * 1e3:.1f}",
                     f"{c.get('pushed_m', 0.0) * 1e3:.2f}",
                     c.get("tissue_particles_inside_before_push", 0), tool.get("contact", "sticky"),
                     f"{sum(map(bool, seen))} of {len(seen)}" if seen else "all"])
        if still is not None and tip[2] > 0 and end[2] > 0:
            # pixels, clipped far outside the image (cv2 takes int32 coordinates)
            (u0, v0), (u1, v1) = (np.clip((K @ p)[:2] / (K @ p)[2], -1e4, 1e4).astype(int) for p in (end, tip))
            colour = _TOOL_COLOURS[k % len(_TOOL_COLOURS)]
            cv2.line(still, (int(u0), int(v0)), (int(u1), int(v1)), colour, 2, cv2.LINE_AA)
            cv2.circle(still, (int(u1), int(v1)), 5, colour, -1, cv2.LINE_AA)
    out = ["<h2>Instruments</h2>" + _table(
        ["instrument", "radius (mm)", "length (mm)", "working end from", "extended to the jaws (mm)",
         "moved out of the tissue (mm)", "tissue particles inside as fitted", "contact", "frames seen"], rows)]
    if still is not None:
        out.append(f'<figure><img alt="instruments at frame 0" src="{_png_data_uri(still)}"><figcaption>frame 0: '
                   "each instrument's capsule axis, the dot on its working end (colours in the table's order)"
                   "</figcaption></figure>")
    out.append('<p class="note">One capsule collider per instrument, fitted to its grey core at frame 0 and moved '
               "with its reconstructed rigid motion; its working end is the end deeper inside the field of view "
               "(\"image\"; \"depth\" where both ends are as deep), extended along the axis to the jaws; a "
               "capsule that held tissue is moved towards the camera (docs/REAL_VIDEO.md section 2).</p>")
    return out


def write_report(run_dir: str | os.PathLike, simulations: list[str | os.PathLike] | tuple = (),
                 out: str | os.PathLike | None = None, fid_weights: str | os.PathLike | None = None,
                 title: str | None = None, validation: str | os.PathLike | None = None) -> Path:
    """Write the HTML report of a run folder; returns its path (default ``run_dir/report.html``).

    Args:
        run_dir: an ``endogsim identify`` run folder (metrics.json required).
        simulations: ``endogsim simulate`` output folders to show (summary.json, simulation.mp4).
        validation: an ``endogsim validate`` output folder whose held-out comparison to show.
        out: the HTML file to write; linked files are referenced relative to its folder.
        fid_weights: local Inception-v3 weights for FID (else FID is "n/a" with the reason).
        title: page title (default from the scene name).
    """
    run = Path(run_dir)
    metrics = _load_json(run / "metrics.json")
    if metrics is None:
        raise DataError(f"{run}: no metrics.json (not an `endogsim identify` run folder)")
    missing = [k for k in ("scene", "loss", "iterations", "materials") if k not in metrics]
    if missing:
        raise DataError(f"{run / 'metrics.json'} lacks {', '.join(missing)}: not the metrics of an `endogsim "
                        "identify` run (a reconstruction's? an interrupted run's?)")
    out = Path(out) if out is not None else run / "report.html"
    base = out.parent
    rel = lambda p: Path(os.path.relpath(Path(p).resolve(), base.resolve())).as_posix()  # noqa: E731
    scene = metrics.get("scene", "scene")
    title = title or f"EndoGSim report: {scene}"
    parts = [f"<h1>{_e(title)}</h1>",
             f'<p class="note">run folder {_e(run)}; scene folder {_e(metrics.get("folder", "?"))}; '
             f'init {_e(metrics.get("init"))}; loss {_e(metrics.get("loss"))}; '
             f'{_e(metrics.get("iterations"))} iterations ({_e(metrics.get("stopped"))}), '
             f'{_fmt(metrics.get("seconds"), 3)} s'
             + (f'; simulated at {_e(simulated_at_text(metrics["discretisation"]))}'
                if isinstance(metrics.get("discretisation"), dict) else "")
             + (f'; corrected to a refined discretisation: {_e(correction_text(metrics["refined_correction"]))}'
                if isinstance(metrics.get("refined_correction"), dict) else "") + '</p>']
    parts += [f'<p class="note">note: {_e(n)}</p>' for n in metrics.get("notes", [])]  # e.g. a time-budget stop

    # Videos side by side.
    vids = []
    comp = run / "comparison.mp4"
    if comp.is_file():
        vids.append((rel(comp), "observed | simulated | flow error |U_sim - U_ref| (0..1 px) with the identified materials"))
    sims = []
    for d in simulations:
        d = Path(d)
        s = _load_json(d / "summary.json")
        if s is None:
            raise DataError(f"{d}: no summary.json (not an `endogsim simulate` output folder)")
        sims.append((d, s))
        if (d / s["files"]["video"]).is_file():
            vids.append((rel(d / s["files"]["video"]), f"new interaction {s['interaction']['name']!s}: "
                                                         f"{s['interaction'].get('description', '')}"))
    parts.append("<h2>Videos</h2>")
    if vids:
        parts.append('<div class="row">' + "".join(
            f'<figure><video controls loop muted playsinline src="{_e(src)}"></video>'
            f"<figcaption>{_e(cap)} (<a href=\"{_e(src)}\">{_e(src)}</a>)</figcaption></figure>"
            for src, cap in vids) + "</div>")
    else:
        parts.append('<p class="note">no video in the run folder (identify ran with --no-video)</p>')

    # Stills: observed / simulated / flow error map.
    observed = simulated = None
    if comp.is_file():
        frames = read_video(comp)
        observed, simulated, err = comparison_panels(frames)
        T = len(frames)
        parts.append("<h2>Observed, simulated and flow error maps</h2>")
        parts.append('<p class="note">flow error = |simulated Gaussian flow - reference flow| per pixel '
                     "(reference: ground truth when the scene has it, else the observed-flow estimate); "
                     "inferno colour scale, black 0 px, yellow &ge; 1 px</p>")
        for t in sorted({0, T // 2, T - 1}):
            parts.append(f"<h3>frame {t}</h3><div class=\"row\">" + "".join(
                f'<figure><img alt="{_e(n)} frame {t}" src="{_png_data_uri(im[t])}"><figcaption>{_e(n)}</figcaption></figure>'
                for n, im in (("observed", observed), ("simulated", simulated), ("flow error", err))) + "</div>")

    # Plots.
    plots = [(n, run / n) for n in ("loss.png", "parameters.png") if (run / n).is_file()]
    if plots:
        parts.append("<h2>Optimisation</h2><div class=\"row\">" + "".join(
            f'<figure><img alt="{_e(n)}" src="{_file_data_uri(p)}"><figcaption>{_e(n)}</figcaption></figure>'
            for n, p in plots) + "</div>")

    # Materials.
    scene_folder, scene_doc = _scene_of(metrics, run)
    cols, rows = _material_rows(run, metrics, scene_doc)
    parts.append("<h2>Material field</h2>" + _table(cols, rows, left=4))
    parts.append('<p class="note">E in Pa, density in kg/m^3; the range is the prior\'s plausible E interval '
                 "(from the initialiser); RE = mean relative error of E, nu, G, K against the ground truth.</p>")

    # What the video determines.
    ident = metrics.get("identifiable") or {}
    if ident:
        irows = []
        for obj, params in ident.items():
            for par, v in params.items():
                unit = " Pa" if par == "E" else ""
                lo, hi = v["interval"]
                stat, disc = v.get("statistical_interval"), v.get("discretisation")
                irows.append([obj, par, f"{v['best']:.4g}{unit}", f"[{lo:.4g}, {hi:.4g}]{unit}",
                              "" if stat is None else f"[{stat[0]:.4g}, {stat[1]:.4g}]{unit}",
                              "" if disc is None else discretisation_text(par, disc, v.get("search_box")),
                              "yes" if v["identifiable"] else "NO", v["reason"]])
        parts.append("<h2>Identifiability</h2>" + _table(
            ["object", "parameter", "optimum", "90% interval", "of which the video's noise", "discretisation",
             "identifiable", "evidence"], irows, left=8))
        parts.append('<p class="note">The optimum is where the loss was least; the value kept is in the material '
                     "table. A parameter the video does not determine (its loss changes by less than the "
                     "loss's own frame-to-frame noise across the search box, or its gradient was zero) keeps its "
                     'initial value, labelled "prior (not identifiable from this video)". The 90% interval '
                     "combines the loss's frame-to-frame noise with the discretisation's error: the grid "
                     "convergence index of the optimum found again on a coarser grid (docs/IDENTIFICATION.md "
                     "section 1).</p>")
    cov = metrics.get("coverage")
    if isinstance(cov, dict) and cov.get("worst"):
        w = cov["worst"]
        where = f" (object id {w['object_id']}, frame {w['frame']})" if w.get("object_id") is not None and w["drop"] else ""
        parts.append(f"<h2>Tissue coverage</h2><p>largest drop of the rendered tissue coverage: "
                     f"{100 * w['drop']:.2f}% of the footprint beyond what the video shows{_e(where)} (limit {100 * cov['limit']:.0f}%: a larger "
                     "drop means the simulated tissue tore, and the run fails)</p>")
    scales = metrics.get("force_scales")
    if isinstance(scales, dict):
        parts.append(f"<h2>What sets E's scale</h2><p>{_e(force_scale_text(scales))}</p>")
    settle = metrics.get("settling")
    if isinstance(settle, dict) and settle.get("frames"):
        parts.append(f"<h2>Settling</h2><p>{_e(settling_text(settle))}</p>")

    try:
        parts += _instruments_section(scene_folder, scene_doc)
    except (KeyError, TypeError, ValueError, IndexError) as exc:  # an optional section never fails the report
        parts.append(f'<h2>Instruments</h2><p class="note">scene.json\'s colliders could not be read ({_e(exc)})</p>')

    if validation is not None:
        parts += _validation_section(Path(validation), rel)

    # Metrics.
    fid_value, fid_note = _fid_cell(observed, simulated, fid_weights)
    keys = [("re_mean", "RE mean"), ("re_E", "RE E"), ("re_nu", "RE nu"), ("re_G", "RE G"), ("re_K", "RE K"),
            ("epe", "EPE (px)"), ("psnr", "PSNR (dB)"), ("ssim", "SSIM"), ("best_loss", "best loss"),
            ("iterations", "iterations"), ("seconds", "seconds")]
    mrows = [[label, metrics[k]] for k, label in keys if k in metrics]
    mrows.append(["FID", fid_value])
    init_m = metrics.get("init_metrics")
    if isinstance(init_m, dict):
        mrows += [[f"init {k}", v] for k, v in init_m.items() if k != "non_finite"]
    parts.append("<h2>Metrics</h2>" + _table(["metric", "value"], mrows) + f'<p class="note">{_e(fid_note)}</p>')

    # Simulations.
    for d, s in sims:
        parts.append(f"<h2>Simulation: {_e(s['interaction']['name'])}</h2>")
        srows = [[name, v.get("max_mm"), v.get("max_last_mm"), v.get("mean_last_mm")] for name, v in s["displacement"].items()]
        parts.append(_table(["object", "max displacement (mm)", "max at last frame (mm)", "mean at last frame (mm)"], srows))
        mats = "; ".join(f"{n}: E {v['E']:.4g} Pa, nu {v['nu']:.3f} ({v['source']})"
                         for n, v in s["materials"].items() if not v["rigid"])
        ply = s["files"].get("ply") or []
        ply_link = f'; PLY sequence: <a href="{_e(rel(d / ply[0]))}">{_e(rel(d / ply[0]))}</a> ... ({len(ply)} files)' if ply else ""
        parts.append(f'<p class="note">{s["frames"]} frames of {s["frame_dt"] * 1e3:.3g} ms, {s["substeps"]} substeps; '
                     f"materials {_e(mats)}{ply_link}</p>")
        for b in s.get("grasp_bites", []):  # summaries written before stop 56 have none
            held = ("TORE OUT of the tissue (numerical fracture)" if b["torn"] else "stayed in the tissue")
            parts.append(f'<p class="note">the grasp ({b["held_particles"]} particles held) {held}: the tissue around '
                         f'its bite came at most {b["ring_cells_max"]:.2f} grid cells (median) from it, frame '
                         f'{b["frame_of_max"]} (tolerance {b["tolerance_cells"]:g})</p>')

    summary = run / "summary.txt"
    if summary.is_file():
        parts.append(f"<h2>Summary</h2><pre>{_e(summary.read_text())}</pre>")
    doc = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
           f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>\n" + "\n".join(parts) + "\n</body></html>\n")
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out, doc)
    return out
