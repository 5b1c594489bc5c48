"""The scene layer: a scene folder's schema, loading it for simulation, and simulate-then-render.

Shared by the benchmark generator (:mod:`endogsim.synth`, which writes scene folders), identification
(:mod:`endogsim.identify`) and the pipeline (:mod:`endogsim.pipeline`), which read them.

* :mod:`~endogsim.scene.schema`: ``scene.json`` as typed records (:class:`SceneSpec`, :func:`load_scene_spec`).
* :mod:`~endogsim.scene.folder`: :func:`load_sim_scene` -> :class:`SimScene` (observations, Gaussians,
  particles, scenario, numerics, binding).
* :mod:`~endogsim.scene.forward`: simulate with given materials and render (RGB, Gaussian flow).
* :mod:`~endogsim.scene.motion`: keyframed tool motion.
"""

from importlib import import_module

_EXPORTS = {
    "SceneSpec": "schema", "SceneObject": "schema", "ToolCapsule": "schema", "ScenarioSpec": "schema",
    "CameraSpec": "schema", "SimSettings": "schema", "load_scene_spec": "schema",
    "SimScene": "folder", "load_sim_scene": "folder", "read_observations": "folder",
    "Rendered": "forward", "simulate_materials": "forward", "same_materials": "forward", "Simulations": "forward",
    "frame_gaussians": "forward", "render_sequence": "forward",
    "tool_offsets": "motion", "translations": "motion", "tool_capsule": "motion", "tool_speed": "motion",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(f"endogsim.scene.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'endogsim.scene' has no attribute {name!r}")
