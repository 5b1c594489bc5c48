"""EndoGSim: physics-aware 4D endoscopic scenes from video.

Gaussian splats per object, a per-object material field (E, nu, density, rigid or deformable)
and a differentiable MLS-MPM simulator, identified from video through rendering and optical flow.
"""

__version__ = "0.1.0"

from endogsim.errors import DataError, EndoGSimError, MaterialError, ModelError, SimulationError

__all__ = ["DataError", "EndoGSimError", "MaterialError", "ModelError", "SimulationError", "__version__"]
