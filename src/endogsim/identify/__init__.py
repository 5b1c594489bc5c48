"""Material identification through the differentiable simulator (render + optical-flow loss).

Typical use::

    from endogsim.identify import IdentifyConfig, identify, run_identify
    from endogsim.scene import load_sim_scene

    metrics = run_identify("scenes/press", "runs/press", init="prior", config=IdentifyConfig(iters=30))

    # or step by step
    problem = load_sim_scene("scenes/press")
    result = identify(problem, init_field, IdentifyConfig(loss="joint", grad_mode="frame"), run_dir="runs/press")
    result.field.save("materials_identified.json")

Modules: :mod:`~endogsim.identify.config` (options), :mod:`~endogsim.identify.loss` (the paper's loss),
:mod:`~endogsim.identify.optimize` (the optimisation loop, checkpoints), :mod:`~endogsim.identify.report` (metrics,
plots, video), :mod:`~endogsim.identify.run`.
The scene it identifies, and simulate-then-render, come from :mod:`endogsim.scene`.
"""

from importlib import import_module

# Names load lazily (PEP 562): the CLI imports the light ``config`` module at start-up without pulling in
# the simulator and renderer.
_EXPORTS = {
    "GRAD_MODES": "config", "LOSSES": "config", "IdentifyConfig": "config",
    "IdentifyResult": "optimize", "check_stable": "optimize", "identify": "optimize",
    "INIT_CHOICES": "run", "initial_field": "run", "run_identify": "run",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(f"endogsim.identify.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'endogsim.identify' has no attribute {name!r}")
