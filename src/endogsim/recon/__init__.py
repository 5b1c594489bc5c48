"""4D Gaussian reconstruction of endoscopic video (Endo-4DGS style), per object.

Tissue: canonical Gaussians deformed by a HexPlane + multi-head MLP field (:mod:`.deformation`).
Tools: their own Gaussians with a per-frame rigid transform (:mod:`.tools`), exported as trajectories
for the simulator's kinematic colliders. Priors come from :mod:`endogsim.priors` (depth, segmentation,
point tracks from optical flow).

Python entry (what the end-to-end pipeline calls)::

    from endogsim.recon import reconstruct, default_config
    res = reconstruct("data/endonerf_pulling", "runs/pulling", default_config("cpu"))
    res.frame0_ply          # Gaussians of frame 0, PLY with an object_id per Gaussian
    res.tool_trajectories   # tool_trajectories.json (res.tool_trajectories_npz: the same arrays)
    res.metrics_path        # metrics.json; res["psnr_masked"], res.metrics
    rec = res.load()        # the full 4D model: rec.gaussians_at(t), rec.render(t), rec.tool_transforms()

``ReconResult.from_run(run_dir)`` gives the same object for a finished run folder.

How the identify stage consumes a reconstruction
------------------------------------------------
Identification simulates from frame 0 and compares with frames 1..T-1, so it needs exactly two things:

1. **Initial state** = ``frame0.ply``: every Gaussian at frame 0 with its ``object_id``. The ids index the
   label table (``objects.json``: id -> name, is_tool, class), the same ids as the dataset's masks (or the
   segmenter's). Tissue Gaussians (``is_tool`` false) become MPM particles (surface extruded along the
   viewing rays, DESIGN.md section 4) and get a material each; tool Gaussians (``is_tool`` true) become
   rigid kinematic colliders (e.g. a capsule fitted to them at frame 0).
2. **Tool motion** = ``tool_trajectories.json`` / ``.npz``: per tool id, ``M[t]`` [T, 4, 4], the rigid
   transform from the tool's *canonical* Gaussians (``canonical.ply``) to frame t, in world metres (camera
   frame of a fixed endoscope) at the frame times ``times`` (seconds). The collider's motion from frame 0
   to frame t is therefore ``M[t] @ inv(M[0])`` applied to its frame-0 geometry; its velocity between
   frames is the finite difference of that.

The tissue deformation field (``deformation.pt``) is *not* an input of the simulator: it is the
observation model of the reconstruction (and can render the reconstructed video with ``rec.render``).
:func:`endogsim.pipeline.scene_from_recon.scene_from_reconstruction` turns a run folder into the scene
folder ``endogsim identify`` reads.
"""

from endogsim.recon.config import ReconConfig, default_config, load_config
from endogsim.recon.model import ReconResult, Reconstruction, compose_at, load_reconstruction
from endogsim.recon.train import reconstruct

__all__ = ["ReconConfig", "default_config", "load_config", "reconstruct", "ReconResult", "Reconstruction",
           "load_reconstruction", "compose_at"]
