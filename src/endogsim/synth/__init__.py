"""Benchmark scenes with ground-truth materials (DESIGN.md section 8).

* :func:`synthesize` (``endogsim synth``): build, simulate and write one scene folder.
* :func:`load_scene_spec`: read its ``scene.json`` (objects, scenario, camera, seed) into typed records.
* :mod:`endogsim.synth.procedural`: reusable geometry / texture builders (tissue surfaces, tools).
* Ground-truth videos are simulated by :mod:`endogsim.physics` (the Warp MLS-MPM identification also uses)
  at the suite's ``ground_truth`` discretisation (by default identification's, as in the paper; it can be
  made finer); both are recorded in ``scene.json``.
* :func:`dis_epe_table`: EPE of an optical-flow estimator against the ground-truth flow of scene folders.
"""

from endogsim.scene.schema import SceneSpec, load_scene_spec
from endogsim.synth.suite import load_suite, scene_spec, suite_scene_names


def synthesize(*args, **kwargs):
    """See :func:`endogsim.synth.generate.synthesize` (imported lazily: it pulls in the renderer)."""
    from endogsim.synth.generate import synthesize as _synthesize

    return _synthesize(*args, **kwargs)


def dis_epe_table(*args, **kwargs):
    """See :func:`endogsim.synth.evaluate_flow.dis_epe_table`."""
    from endogsim.synth.evaluate_flow import dis_epe_table as _f

    return _f(*args, **kwargs)


__all__ = ["synthesize", "load_scene_spec", "SceneSpec", "load_suite", "scene_spec", "suite_scene_names",
           "dis_epe_table"]
