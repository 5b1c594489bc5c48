"""Exceptions that carry a message meant for the user.

Every error the package raises on bad input is an :class:`EndoGSimError`; the CLI prints its
message without a traceback. Subclasses say which stage refused the input. Input that is read with an
assumption or a repair gives a :class:`DataWarning` instead (and the outputs record it).
"""


class EndoGSimError(Exception):
    """Base class: the message names the file or value and what is wrong with it."""


class DataError(EndoGSimError):
    """A dataset folder, frame, mask, depth map or poses file is missing or malformed."""


class ModelError(EndoGSimError):
    """A Gaussian model or PLY file is malformed, or a model-backed prior lacks its weights."""


class MaterialError(EndoGSimError):
    """A material value is impossible (E <= 0, nu outside (-1, 0.5), density <= 0, ...)."""


class SimulationError(EndoGSimError):
    """The simulation was refused (unstable time step) or diverged (NaN/inf)."""


class GroundTruthRefused(SimulationError):
    """A synthesized scene's ground truth fails the generator's own checks (it has not settled by frame 0, or a
    grasper's bite tears out or the tissue parts: numerical fracture by an amount the grid sets), so the scene
    would be no fair test of identification; the benchmarks leave such a scene out and name it."""


class IdentificationError(EndoGSimError):
    """Identification cannot go on: a loss term or a gradient is NaN/inf (the message names the frame and
    the quantity)."""


class DataWarning(UserWarning):
    """A dataset was read with an assumption or a repair (default intrinsics, saturated depth, a truncated
    video); ``Scene.notes`` records it too."""
