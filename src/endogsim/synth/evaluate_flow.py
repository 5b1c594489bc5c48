"""EPE of an optical-flow estimator against the ground-truth flow of synthesized scene folders (all values in
pixels per frame at the scene's resolution), and the generation time of each scene::

    python -m endogsim.synth.evaluate_flow --scenes tiny press pull two_tissues stomach gallbladder --work /tmp/bench
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from endogsim.evaluate.flow_metrics import epe
from endogsim.priors.flow import FlowConfig, flow_estimator

__all__ = ["read_scene_flow", "estimator_epe", "iter_dis_epe", "dis_epe_table"]


def read_scene_flow(folder: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """frames [T, H, W, 3] float in [0, 1], gt flow [T-1, H, W, 2] (pixels), valid [T-1, H, W] of a synth folder."""
    import cv2

    folder = Path(folder)
    imgs = sorted((folder / "images").glob("frame-*.color.png"))
    frames = np.stack([cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB) for p in imgs]).astype(np.float32) / 255
    flows = np.stack([np.load(folder / "flow" / f"frame-{t:06d}.flow.npy") for t in range(len(imgs) - 1)])
    valid = np.stack([cv2.imread(str(folder / "flow" / f"frame-{t:06d}.valid.png"), cv2.IMREAD_GRAYSCALE) > 0
                      for t in range(len(imgs) - 1)])
    return frames, flows, valid


MOVING_PX = 0.5  # ground-truth flow (pixels per frame) above which a tissue pixel counts as moving


def estimator_epe(folder: Path, estimator: str = "dis", weights: str | None = None) -> dict:
    """EPE (pixels) of ``estimator`` against a scene folder's ground-truth flow over all consecutive pairs.

    Returns ``epe`` over valid pixels (rendered alpha > 0.95), ``epe_tissue`` over valid non-tool pixels,
    ``epe_moving`` over tissue pixels whose ground truth moves more than :data:`MOVING_PX`, the zero-flow
    baseline ``zero_epe`` (valid pixels), the mean ground-truth magnitude on valid / tissue / moving pixels
    (``mean_gt_px``, ``mean_gt_tissue_px``, ``mean_gt_moving_px``), the tissue's peak (99.9th percentile)
    ``peak_gt_tissue_px``, the fraction of tissue pixels that move and the number of ``pairs``.
    """
    import cv2

    frames, gt, valid = read_scene_flow(folder)
    est = flow_estimator(FlowConfig(estimator, weights))
    pred = est.estimate_sequence(frames)
    tool = np.stack([cv2.imread(str(Path(folder) / "masks" / f"frame-{t:06d}.mask.png"), cv2.IMREAD_GRAYSCALE) > 127
                     for t in range(len(gt))])
    mag = np.linalg.norm(gt, axis=-1)
    tissue = valid & ~tool
    moving = tissue & (mag > MOVING_PX)

    def mean(m):
        return float(mag[m].mean()) if m.any() else float("nan")

    return {"epe": epe(pred, gt, valid), "epe_tissue": epe(pred, gt, tissue), "epe_moving": epe(pred, gt, moving),
            "zero_epe": epe(np.zeros_like(gt), gt, valid),
            "mean_gt_px": mean(valid), "mean_gt_tissue_px": mean(tissue), "mean_gt_moving_px": mean(moving),
            "peak_gt_tissue_px": float(np.percentile(mag[tissue], 99.9)) if tissue.any() else float("nan"),
            "moving_fraction": float(moving.sum() / max(tissue.sum(), 1)), "pairs": len(gt)}


def iter_dis_epe(scenes: list[str], work: Path, seed: int = 0, frames: int | None = None,
                 scale: float | None = None, estimator: str = "dis") -> Iterator[dict]:
    """Synthesize each scene into ``work``/NAME (reusing an existing folder; ``gen_s`` is then None) and
    yield the EPE of a registered flow estimator (:func:`estimator_epe`) scene by scene."""
    from endogsim.synth.generate import synthesize

    for name in scenes:
        folder = Path(work) / name
        gen_s = None
        if not (folder / "scene.json").exists():
            t0 = time.perf_counter()
            synthesize(name, folder, seed=seed, frames=frames, scale=scale)
            gen_s = time.perf_counter() - t0
        yield {"scene": name, "gen_s": gen_s, **estimator_epe(folder, estimator)}


def dis_epe_table(*args, **kwargs) -> list[dict]:
    """All rows of :func:`iter_dis_epe`."""
    return list(iter_dis_epe(*args, **kwargs))


def main() -> None:  # pragma: no cover - script
    from endogsim.synth.suite import suite_scene_names

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", nargs="*", default=suite_scene_names())
    ap.add_argument("--work", type=Path, default=Path("bench_synth"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--estimator", default="dis", help="a registered flow estimator (dis, dis_fine, raft)")
    a = ap.parse_args()
    print("| scene | gen (s) | DIS EPE all | DIS EPE tissue | DIS EPE moving | zero-flow EPE all | "
          "mean GT all / tissue / moving | peak GT tissue | moving % | pairs |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in iter_dis_epe(a.scenes, a.work, a.seed, a.frames, estimator=a.estimator):
        gen = "reused" if r["gen_s"] is None else f"{r['gen_s']:.0f}"
        print(f"| {r['scene']} | {gen} | {r['epe']:.3f} | {r['epe_tissue']:.3f} | {r['epe_moving']:.3f} | "
              f"{r['zero_epe']:.3f} | {r['mean_gt_px']:.2f} / {r['mean_gt_tissue_px']:.2f} / {r['mean_gt_moving_px']:.2f} | "
              f"{r['peak_gt_tissue_px']:.2f} | {100 * r['moving_fraction']:.0f} | {r['pairs']} |", flush=True)


if __name__ == "__main__":  # pragma: no cover
    main()
