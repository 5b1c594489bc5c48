"""The shipped, versioned, cited prior table (``endogsim/data/tissue_prior.json``) and class look-up."""

from __future__ import annotations

import functools
import json
import re
from importlib import resources

from endogsim.errors import MaterialError
from endogsim.materials.field import MaterialRecord

REGIMES = ("in_vivo", "ex_vivo_tensile")

# CholecSeg8K: (colour-mask id, class index, name). Every entry must resolve to a prior class.
CHOLECSEG8K_CLASSES = [
    (50, 0, "black background"), (11, 1, "abdominal wall"), (21, 2, "liver"), (13, 3, "gastrointestinal tract"),
    (12, 4, "fat"), (31, 5, "grasper"), (23, 6, "connective tissue"), (24, 7, "blood"), (25, 8, "cystic duct"),
    (32, 9, "l-hook electrocautery"), (22, 10, "gallbladder"), (33, 11, "hepatic vein"), (5, 12, "liver ligament"),
]


@functools.lru_cache(maxsize=1)
def load_prior_table() -> dict:
    """The prior table as a dict: ``version``, ``classes`` {key: {model, rigid, nu, density, aliases, sources,
    in_vivo: {E, E_min, E_max}, ex_vivo_tensile: {...}}}, ``references``. E in Pa, density in kg/m^3."""
    text = resources.files("endogsim").joinpath("data", "tissue_prior.json").read_text()
    return json.loads(text)


def _norm(s: str) -> str:
    return re.sub(r"[\s_\-]+", " ", s.strip().lower())


@functools.lru_cache(maxsize=1)
def _alias_index() -> dict[str, str]:
    idx: dict[str, str] = {}
    for key, entry in load_prior_table()["classes"].items():
        idx[_norm(key)] = key
        for a in entry.get("aliases", []):
            idx[_norm(a)] = key
    return idx


def resolve_class(name: str) -> str | None:
    """Prior class key for a class key, dataset name or alias ("Gall bladder", "cholecseg8k:22"); None if unknown."""
    return _alias_index().get(_norm(str(name)))


def prior_entry(klass: str, is_tool: bool = False) -> tuple[str, dict]:
    """(resolved key, table entry). Unknown classes fall back to ``instrument`` / ``unknown_tissue``."""
    key = resolve_class(klass) or ("instrument" if is_tool else "unknown_tissue")
    return key, load_prior_table()["classes"][key]


def prior_record(
    object_id: int, name: str, klass: str, is_tool: bool = False, regime: str = "in_vivo", source: str = "prior"
) -> MaterialRecord:
    """The prior's material for one object in the chosen ``regime`` ("in_vivo" or "ex_vivo_tensile")."""
    if regime not in REGIMES:
        raise MaterialError(f"regime {regime!r} is not one of {REGIMES}")
    key, e = prior_entry(klass, is_tool)
    col = e[regime]
    rigid = bool(e["rigid"]) or is_tool
    return MaterialRecord(
        name=name, object_id=object_id, klass=klass, model="rigid" if rigid else e["model"], rigid=rigid,
        E=col["E"], nu=e["nu"], density=e["density"], E_min=col["E_min"], E_max=col["E_max"],
        source=source, confidence=None, regime=regime,  # type: ignore[arg-type]
    )
