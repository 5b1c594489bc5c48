"""The benchmark suite file (``endogsim/data/benchmark_suite.json``): scene specs with the suite defaults."""

from __future__ import annotations

import json
from importlib import resources
from typing import Any

from endogsim.errors import DataError

__all__ = ["GENERATOR_REVISION", "load_suite", "suite_scene_names", "scene_spec"]

# Bump when the ground truth a seed produces changes (simulator physics, suite numerics): cached scenes
# with another revision are synthesized again (endogsim.bench.identify.ensure_scene).
GENERATOR_REVISION = 2


def load_suite() -> dict[str, Any]:
    """The packaged suite file ``endogsim/data/benchmark_suite.json`` as a dict."""
    text = resources.files("endogsim").joinpath("data/benchmark_suite.json").read_text()
    return json.loads(text)


def suite_scene_names() -> list[str]:
    return list(load_suite()["scenes"])


def scene_spec(name: str) -> dict[str, Any]:
    """The suite entry of scene ``name`` with the suite defaults filled in."""
    suite = load_suite()
    if name not in suite["scenes"]:
        raise DataError(f"unknown benchmark scene {name!r}; choose one of {', '.join(suite['scenes'])} "
                        "or use --from DATA_DIR")
    spec = dict(suite["defaults"])
    spec.update(suite["scenes"][name])
    spec["name"] = name
    return spec
