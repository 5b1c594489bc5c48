"""Material identification through the differentiable simulator (render + optical-flow loss).

Typical use::

    from endogsim.identify import IdentifyConfig, load_problem, identify, run_identify

    metrics = run_identify("scenes/press", "runs/press", init="prior", config=IdentifyConfig(iters=30))

    # or step by step
    problem = load_problem("scenes/press")
    result = identify(problem, init_field, IdentifyConfig(loss="joint", grad_mode="frame"), run_dir="runs/press")
    result.field.save("materials_identified.json")

Modules: :mod:`~endogsim.identify.config` (options), :mod:`~endogsim.identify.problem` (scene folder ->
simulator and renderer inputs), :mod:`~endogsim.identify.forward` (simulate + render),
:mod:`~endogsim.identify.loss` (the paper's loss), :mod:`~endogsim.identify.optimize` (the Adam loop,
checkpoints), :mod:`~endogsim.identify.report` (metrics, plots, video), :mod:`~endogsim.identify.run`.
"""

from endogsim.identify.config import GRAD_MODES, LOSSES, IdentifyConfig
from endogsim.identify.optimize import IdentifyResult, check_stable, identify
from endogsim.identify.problem import IdentifyProblem, load_problem
from endogsim.identify.run import INIT_CHOICES, initial_field, run_identify

__all__ = ["GRAD_MODES", "INIT_CHOICES", "LOSSES", "IdentifyConfig", "IdentifyProblem", "IdentifyResult",
           "check_stable", "identify", "initial_field", "load_problem", "run_identify"]
