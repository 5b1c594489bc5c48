"""Where does an identification loss put E at identification's discretisation and at refinements of it?

Identification fits E at the scene's identification discretisation (1x). The suite's ground truth is simulated at
2x (grid x 2, particle spacing / 2, substeps x 2). This evaluates identification's own loss -- the same observed
video, the same particles rebuilt from the frame-0 Gaussians, the same camera and loss terms, substeps planned
once at the prior as identification plans them -- at a few E and nu, at several refinement factors, forward only.
Where the 1x optimum and the 2x optimum differ, the 1x estimate is a property of the discretisation; where a
coarser level (identification's 0.7x walk, the intervals' discretisation part) errs the same way as 1x, the
grid convergence index taken from it cannot see that.

usage (from an identify run folder of `endogsim bench suite` or `endogsim identify`, whose metrics.json names the
scene and the configuration; its observed-flow cache is reused):

    OMP_NUM_THREADS=1 python docs/experiments/loss_along_E_at_levels.py RUN_DIR 1,1.5,2 1112,2200,3500,5000,8000 \
        0.42,0.356

prints one line per (level, nu, E), with the paired z of its per-frame loss against the first E's at that level and
nu (:func:`endogsim.identify.uncertainty.paired_z`, the comparison the intervals make: below minus the printed
threshold the loss is significantly lower), and writes RUN_DIR/loss_along_E_at_levels.json {"level|nu|E": loss}.
"""

import json
import sys
import time
from pathlib import Path

import torch

from endogsim.identify.config import IdentifyConfig
from endogsim.identify.optimize import evaluate_loss, planned_for, prepare_observations
from endogsim.identify.run import initial_field
from endogsim.identify.uncertainty import paired_z, significant_z
from endogsim.materials.field import nu_to_raw
from endogsim.scene.folder import load_sim_scene


def main(run: Path, levels: list[float], Es: list[float], nus: list[float]) -> dict[str, float]:
    m = json.loads((run / "metrics.json").read_text())
    cfg = IdentifyConfig.from_json(m["config"])
    losses = {}
    for level in levels:
        pb = load_sim_scene(m["folder"], frames=cfg.frames, device="cpu", refine=level)
        prior, _ = initial_field(pb, "prior")
        pb = planned_for(pb, prior, cfg)  # as identification plans every level it simulates
        obs, cam = prepare_observations(pb, cfg, run)
        for nu in nus:
            first = None  # the first E's per-frame loss: every other E is compared with it, as the intervals do
            for E in Es:
                p = prior.to_params(global_material=cfg.global_material, nu_bounds=cfg.nu_bounds)
                with torch.no_grad():
                    p.log10_E.fill_(float(torch.log10(torch.tensor(E, dtype=torch.float64))))
                    p.nu_raw.fill_(nu_to_raw(nu, *cfg.nu_bounds))
                t0 = time.perf_counter()
                value, _ = evaluate_loss(pb, prior, p, obs, cam, cfg, grad=False)
                loss = float(value.total.detach())
                first = value.per_frame if first is None else first
                _, _, z = paired_z(value.per_frame, first)
                print(f"level {level:g} grid {pb.mpm.grid_res} particles {len(pb.particles)} substeps "
                      f"{pb.mpm.substeps_per_frame} nu {nu:.3f} E {E:8.1f} Pa loss {loss:.6f} paired z against "
                      f"E {Es[0]:g} Pa {z:+.2f} (significant beyond {significant_z(len(first)):.2f}) "
                      f"({time.perf_counter() - t0:.1f} s)", flush=True)
                losses[f"{level:g}|{nu:g}|{E:g}"] = loss
    (run / "loss_along_E_at_levels.json").write_text(json.dumps(losses, indent=1))
    return losses


if __name__ == "__main__":
    if len(sys.argv) != 5:
        sys.exit(__doc__)
    floats = lambda text: [float(v) for v in text.split(",")]  # noqa: E731
    main(Path(sys.argv[1]), floats(sys.argv[2]), floats(sys.argv[3]), floats(sys.argv[4]))
