"""4D Gaussian reconstruction of endoscopic video (Endo-4DGS style), per object.

Tissue: canonical Gaussians deformed by a HexPlane + multi-head MLP field (:mod:`.deformation`).
Tools: their own Gaussians with a per-frame rigid transform (:mod:`.tools`), exported as trajectories
for the simulator's kinematic colliders. Entry points::

    from endogsim.recon import reconstruct, load_reconstruction, ReconConfig
    metrics = reconstruct("data/endonerf_pulling", "runs/pulling", ReconConfig(iters=3000))
    rec = load_reconstruction("runs/pulling")
    g0 = rec.gaussians_at(0)              # Gaussians of frame 0, object ids per Gaussian
    tracks = rec.tool_transforms()        # {object id: [T, 4, 4] world metres}
"""

from endogsim.recon.config import ReconConfig, default_config, load_config
from endogsim.recon.model import Reconstruction, compose_at, load_reconstruction
from endogsim.recon.train import reconstruct

__all__ = ["ReconConfig", "default_config", "load_config", "reconstruct", "Reconstruction", "load_reconstruction",
           "compose_at"]
