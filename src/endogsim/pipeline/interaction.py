"""New interactions: what acts on the tissue of a scene, as a validated JSON schema.

An *interaction* (JSON, validated by :class:`Interaction`) says what acts on the tissue, in up to three
sections that may be combined:

  ``tool``   a new trajectory of one of the scene's tool capsules: translation keyframes
             ``[[fraction of the clip, dx, dy, dz], ...]`` (metres, world; the camera looks along +z, so
             dz > 0 pushes into the tissue), optionally after moving the tool tip onto a surface point.
  ``force``  a body acceleration (m/s^2, world) on the particles within ``radius`` metres of a surface
             point, over the time window [t_start, t_end) seconds.
  ``grasp``  a sphere (radius metres) on a surface point that follows keyframes and holds the tissue
             within it (and ``GRASP_MARGIN``, 3 mm, beyond): grasp and pull; with ``with_tool`` the scene's
             tool tip goes to the grasp point and moves with it.

Surface points are given as ``at = [u, v]`` in [-1, 1]^2 over the (image-plane) bounding box of the
deformable particles (of ``object`` if named), and lie on the side facing the camera; or as a world
``point`` [x, y, z] in metres. Tools not driven by the interaction stay at their frame-0 pose
(``scene_tool = "static"``) or are removed (``"hidden"``: no collider, not rendered).

Built-in interactions live in ``endogsim/data/interactions/NAME.json`` (:func:`builtin_interactions`);
:mod:`endogsim.pipeline.simulate` simulates them.
"""

from __future__ import annotations

import json
import math
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from endogsim.errors import DataError

__all__ = ["Interaction", "Located", "ToolSpec", "ForceSpec", "GraspSpec", "builtin_interactions", "load_interaction"]


def _check_keyframes(kf: list) -> list:
    if len(kf) < 1 or kf[0][0] != 0.0:
        raise ValueError("keyframes must start with [0, dx, dy, dz]")
    fr = [k[0] for k in kf]
    if any(b <= a for a, b in zip(fr, fr[1:])) or fr[-1] > 1.0:
        raise ValueError(f"keyframe fractions {fr} must increase within [0, 1]")
    if any(not math.isfinite(v) or abs(v) > 0.1 for k in kf for v in k[1:]):
        raise ValueError("keyframe offsets must be finite and at most 0.1 m")
    return kf


# [[fraction of the clip in [0, 1], dx, dy, dz (metres, world)], ...], first fraction 0.
Keyframes = Annotated[list[tuple[float, float, float, float]], AfterValidator(_check_keyframes)]


class Located(BaseModel):
    """Where on the tissue: ``at`` (normalised [u, v]) or ``point`` (world metres), optionally on ``object``."""

    model_config = ConfigDict(extra="forbid")

    at: tuple[float, float] | None = None
    point: tuple[float, float, float] | None = None
    object: str | int | None = Field(None, description="deformable object (name or id) the point lies on")

    @field_validator("at")
    @classmethod
    def _at_range(cls, v):
        if v is not None and not all(-1.5 <= c <= 1.5 for c in v):
            raise ValueError(f"at = {list(v)} must lie in [-1.5, 1.5]^2 (normalised tissue coordinates)")
        return v


class ToolSpec(Located):
    """A new trajectory of a scene tool (``tool``: name or id; default the first tool). With ``at`` or
    ``point`` the tool is first translated so that its capsule touches that surface point from the camera side."""

    tool: str | int | None = None
    keyframes: Keyframes


class ForceSpec(Located):
    """Body acceleration ``acceleration`` (m/s^2, world) on particles within ``radius`` (m) of the point,
    for ``t_start <= t < t_end`` (s; ``t_end`` null: to the end of the clip)."""

    acceleration: tuple[float, float, float]
    radius: float = Field(0.01, gt=0, le=0.2)
    t_start: float = Field(0.0, ge=0)
    t_end: float | None = Field(None, gt=0)

    @model_validator(mode="after")
    def _window(self):
        if self.t_end is not None and not self.t_end > self.t_start:
            raise ValueError(f"force window [{self.t_start}, {self.t_end}) s is empty")
        if not all(math.isfinite(a) and abs(a) <= 1e4 for a in self.acceleration):
            raise ValueError(f"acceleration {list(self.acceleration)} must be finite and at most 1e4 m/s^2")
        return self


class GraspSpec(Located):
    """A sphere of ``radius`` (m) on the point following ``keyframes`` that holds the tissue it closes on
    (grasp and pull)."""

    radius: float = Field(0.003, gt=0, le=0.05)
    keyframes: Keyframes
    with_tool: bool = True


class Interaction(BaseModel):
    """A new interaction to simulate (see the module docstring). ``frames`` counts frame 0."""

    model_config = ConfigDict(extra="forbid")

    name: str = "interaction"
    description: str = ""
    frames: int = Field(16, ge=2, le=400)
    scene_tool: Literal["static", "hidden"] = "static"
    tool: ToolSpec | None = None
    force: ForceSpec | None = None
    grasp: GraspSpec | None = None

    @model_validator(mode="after")
    def _something(self):
        if self.tool is None and self.force is None and self.grasp is None:
            raise ValueError("an interaction needs at least one of 'tool', 'force', 'grasp'")
        return self


def _interaction_dir():
    return resources.files("endogsim").joinpath("data/interactions")


def builtin_interactions() -> list[str]:
    """Names of the packaged interactions (``endogsim/data/interactions/*.json``)."""
    return sorted(p.name[:-5] for p in _interaction_dir().iterdir() if p.name.endswith(".json"))


def load_interaction(spec: str | Path | dict | Interaction, where: str = "interaction") -> Interaction:
    """An :class:`Interaction` from a built-in name, a JSON file, a dict, or an Interaction.

    ``where`` names a dict's origin in error messages (files and built-ins name themselves).

    Raises:
        DataError: unknown name, unreadable file, or a schema violation (the message names the field).
    """
    if isinstance(spec, Interaction):
        return spec
    if isinstance(spec, dict):
        obj = spec
    else:
        p = Path(spec)
        if p.suffix == ".json" or p.is_file():
            if not p.is_file():
                raise DataError(f"{p}: interaction file not found")
            where = str(p)
            text = p.read_text()
        else:
            name = str(spec)
            if name not in builtin_interactions():
                raise DataError(f"unknown interaction {name!r}: give a JSON file or one of {', '.join(builtin_interactions())}")
            where = f"built-in interaction {name!r}"
            text = _interaction_dir().joinpath(f"{name}.json").read_text()
        try:
            obj = json.loads(text)
        except json.JSONDecodeError as exc:
            raise DataError(f"{where}: not valid JSON ({exc})") from None
    try:
        return Interaction.model_validate(obj)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(str(x) for x in e['loc']) or '(top)'}: {e['msg']}" for e in exc.errors())
        raise DataError(f"{where}: invalid interaction ({problems})") from None
