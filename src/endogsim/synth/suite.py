"""The benchmark suite file (``endogsim/data/benchmark_suite.json``): scene specs with the suite defaults."""

from __future__ import annotations

import json
from importlib import resources
from typing import Any

from endogsim.errors import DataError

__all__ = ["DEMO_SCENE", "GENERATOR_REVISION", "SMALL_SCENES", "MAX_FRAMES", "MAX_IMAGE_SIDE", "MAX_PIXEL_FRAMES",
           "MAX_PARTICLES", "check_size", "load_suite", "suite_scene_names", "scene_spec"]

# Bump when the ground truth a seed produces changes (simulator physics, suite numerics): cached scenes
# with another revision are synthesized again (endogsim.bench.identify.ensure_scene).
GENERATOR_REVISION = 13  # 13: identification's discretisation is planned without the true materials (its substeps a
#                        floor, as a real video's; the ground truth is unchanged; stop 75);
#                        12: the real regime's scenes are identified with the real-video pipeline's quasi-static
#                        mass scaling (scene.json's scenario.mass_scaling 4; the ground truth is unchanged; stop 74);
#                        11: a ground truth whose tissue parts (scene.coverage.PARTED_LIMIT) is refused, so
#                        the grasper scenes lift straight towards the lens, no longer drawn sideways (stop 72); 10: the
#                        instrument's path moves with the seed's relief beneath its tip (every seed
#                        presses as deep; seed 0's scenes are unchanged; stop 68); 9: a ground truth whose
#                        grasper tears its bite out is refused (BITE_TEAR_CELLS),
#                        so `stomach` is lifted 8 mm, not 16 (stop 56); 8: a grasper's bite reaches 3 mm
#                        beyond its tip sphere, not 1 (GRASP_MARGIN: the 1-mm bite tore out of the sheet;
#                        stop 55); 7: tissue rests on a Coulomb support
#                        (support_friction 1), as on real video (stop 50); 6: settling reaches the
#                        equilibrium (8 frames at 200/s, checked); 5: organs that meet are not held there,
#                        one material per place (stop 32)

#: Small scenes for the tests and the demo (seconds on a CPU), left out of the suite's tables: `endogsim bench
#: suite` runs the others unless told otherwise (``--scenes``).
SMALL_SCENES = ("tiny", "tiny_lift")
#: The demo's scene: a grasper bites the patch and lifts it 7 mm. The lift's shape weighs the tissue's stiffness
#: against its weight, so its video determines E; ``tiny``'s probe, pressing the same patch, sets the motion nearly
#: whatever E is (docs/IDENTIFICATION.md section 5).
DEMO_SCENE = "tiny_lift"

# Limits of a synthesized scene, checked before the work that would exceed them. Rendering holds every
# frame in memory (about 40 bytes a pixel: RGB, depth, alpha, ids, flow), so MAX_PIXEL_FRAMES bounds it to
# about 2 GB; MAX_FRAMES is also the longest interaction (endogsim.pipeline.interaction).
MAX_FRAMES = 400
MAX_IMAGE_SIDE = 2048
MAX_PIXEL_FRAMES = 50_000_000
MAX_PARTICLES = 2_000_000


def check_size(frames: int | None = None, width: int | None = None, height: int | None = None,
               particles: int | None = None) -> None:
    """Refuse a scene larger than the limits above (DataError naming the limit); None skips a check."""
    if frames is not None and not 2 <= frames <= MAX_FRAMES:
        raise DataError(f"--frames {frames}: a synthesized scene has 2 to {MAX_FRAMES} frames")
    if width is not None and height is not None:
        if max(width, height) > MAX_IMAGE_SIDE:
            raise DataError(f"images of {width}x{height} px: the limit is {MAX_IMAGE_SIDE} px a side (lower --scale)")
        if frames is not None and frames * width * height > MAX_PIXEL_FRAMES:
            raise DataError(f"{frames} frames of {width}x{height} px are {frames * width * height / 1e6:.0f} M "
                            f"pixel-frames; the limit is {MAX_PIXEL_FRAMES / 1e6:.0f} M (about 2 GB while "
                            "rendering): lower --frames or --scale")
    if particles is not None and particles > MAX_PARTICLES:
        raise DataError(f"{particles} particles: the limit is {MAX_PARTICLES} (a smaller or coarser scene)")


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
