"""Priors for reconstruction, each an extension point with registered back-ends and an offline default:
depth (:mod:`~endogsim.priors.depth`), segmentation (:mod:`~endogsim.priors.segmentation`), optical flow
(:mod:`~endogsim.priors.flow`), point tracks and camera rotations built on them."""

__all__ = ["resolve_auto"]


def resolve_auto(method: str, has_dataset: bool) -> str:
    """The back-end "auto" stands for: the dataset's own data when it has some, else the offline fallback
    (never a model: weights are never implied)."""
    if method != "auto":
        return method
    return "dataset" if has_dataset else "fallback"
