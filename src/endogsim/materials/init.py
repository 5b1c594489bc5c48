"""One entry point for every way to initialise a material field: manual, prior, mllm, replay."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from endogsim.errors import DataError, MaterialError
from endogsim.io.scene import ObjectLabel, Scene
from endogsim.materials.field import MaterialField, MaterialRecord
from endogsim.materials.mllm import (
    MLLMConfig,
    ObjectQuery,
    make_client,
    object_images,
    query_object,
)
from endogsim.materials.prior import REGIMES, load_prior_table, prior_record

Backend = Literal["manual", "prior", "mllm", "replay"]
BACKENDS = ("manual", "prior", "mllm", "replay")


@dataclass
class ManualMaterial:
    """The paper's manual baseline: one generic value for every deformable object (E in Pa, rho in kg/m^3)."""

    E: float = 1e4
    nu: float = 0.45
    density: float = 1000.0
    model: Literal["fixed_corotated", "neo_hookean"] = "fixed_corotated"


@dataclass
class MaterialInitConfig:
    """Options of :func:`initialise_materials`."""

    backend: Backend = "prior"
    regime: Literal["in_vivo", "ex_vivo_tensile"] = "in_vivo"
    manual: ManualMaterial = field(default_factory=ManualMaterial)
    mllm: MLLMConfig = field(default_factory=MLLMConfig)


def _best_frame(masks: np.ndarray, object_id: int) -> int | None:
    """Index of the frame where the object covers the most pixels (None if it never appears)."""
    areas = (masks == object_id).reshape(masks.shape[0], -1).sum(axis=1)
    return int(np.argmax(areas)) if areas.max() > 0 else None


def initialise_materials(
    labels: dict[int, ObjectLabel], config: MaterialInitConfig | None = None, scene: Scene | None = None
) -> MaterialField:
    """A material field with one record per label.

    Args:
        labels: id -> ObjectLabel (name, is_tool, klass), e.g. ``scene.labels``.
        config: backend and its options.
        scene: needed by ``mllm``/``replay`` (frames [T,H,W,3] and object_masks [T,H,W] give each object's images).
    Returns:
        The field; ``meta`` records backend, regime, prior version and (mllm) model and endpoint.
    """
    cfg = config or MaterialInitConfig()
    if cfg.backend not in BACKENDS:
        raise MaterialError(f"unknown materials backend {cfg.backend!r}; choose one of {BACKENDS}")
    if cfg.regime not in REGIMES:
        raise MaterialError(f"unknown regime {cfg.regime!r}; choose one of {REGIMES}")
    # The field-of-view border (CholecSeg8K class 50) is a label, not an object with a material.
    labels = {oid: lab for oid, lab in labels.items() if lab.klass != "background"}
    if not labels:
        raise DataError("no objects: the label table is empty")
    meta: dict = {"backend": cfg.backend, "regime": cfg.regime, "prior_version": load_prior_table()["version"]}
    records: list[MaterialRecord] = []
    if cfg.backend in ("manual", "prior"):
        for oid, lab in sorted(labels.items()):
            rec = prior_record(oid, lab.name, lab.klass, lab.is_tool, cfg.regime, source=cfg.backend)
            if cfg.backend == "manual" and not rec.rigid:
                m = cfg.manual
                rec = MaterialRecord(name=lab.name, object_id=oid, klass=lab.klass, model=m.model, rigid=False,
                                     E=m.E, nu=m.nu, density=m.density, source="manual", regime=cfg.regime)
            records.append(rec)
        return MaterialField(records, meta=meta)

    if scene is None or scene.object_masks is None:
        raise DataError(f"the {cfg.backend} backend needs frames and object masks (a data folder), "
                        "not only a label table")
    replay = cfg.backend == "replay"
    meta.update({"model": cfg.mllm.model, "base_url": cfg.mllm.base_url})
    from endogsim.materials.mllm import PROMPT_VERSION

    meta["prompt_version"] = PROMPT_VERSION
    client = None if replay else make_client(cfg.mllm)[0]
    for oid, lab in sorted(labels.items()):
        t = _best_frame(scene.object_masks, oid)
        if t is None:
            # Not visible anywhere: nothing to show the model; the prior is the honest answer.
            records.append(prior_record(oid, lab.name, lab.klass, lab.is_tool, cfg.regime,
                                        source="prior (not visible in any frame)"))
            continue
        images = object_images(scene.frames[t], scene.object_masks[t] == oid)
        q = ObjectQuery(oid, lab.name, lab.klass, lab.is_tool, images)
        records.append(query_object(q, cfg.mllm, cfg.regime, client=client, replay=replay))
    return MaterialField(records, meta=meta)


def load_labels_json(path: str | Path) -> dict[int, ObjectLabel]:
    """Read a run folder's ``labels.json``: ``{"<id>": {"name": str, "is_tool": bool, "klass": str}, ...}``.

    ``klass`` may be omitted (defaults to the name); ``is_tool`` defaults to false.
    """
    path = Path(path)
    try:
        obj = json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"{path}: labels file not found") from None
    except json.JSONDecodeError as exc:
        raise DataError(f"{path}: not valid JSON ({exc})") from None
    if isinstance(obj, dict) and "labels" in obj and isinstance(obj["labels"], dict):
        obj = obj["labels"]  # scene.json style: the label table under "labels"
    if not isinstance(obj, dict):
        raise DataError(f"{path}: expected an object {{id: {{name, is_tool, klass}}}}")
    out: dict[int, ObjectLabel] = {}
    for k, v in obj.items():
        try:
            oid = int(k)
            name = str(v["name"])
            out[oid] = ObjectLabel(oid, name, bool(v.get("is_tool", False)), str(v.get("klass") or name))
        except (ValueError, TypeError, KeyError, AttributeError):
            raise DataError(f"{path}: entry {k!r} must be {{'name': str, 'is_tool': bool, 'klass': str}} "
                            f"under an integer id, got {v!r}") from None
    return out


def load_objects(path: str | Path, need_images: bool = False, downscale: float | None = None
                 ) -> tuple[dict[int, ObjectLabel], Scene | None]:
    """Labels (and, for a data folder, the Scene) from a data folder, a run folder or a labels.json file.

    Run folders: ``labels.json`` (see :func:`load_labels_json`) or ``scene.json`` with a ``labels`` table.
    Anything else is read with ``endogsim.io.load_scene``.
    """
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    for cand in ([path] if path.is_file() else [path / "labels.json", path / "scene.json"]):
        if cand.is_file() and cand.suffix == ".json":
            labels = load_labels_json(cand)
            if need_images:
                raise DataError(f"{cand}: a label table has no images; the mllm/replay backends need a data folder")
            return labels, None
    try:
        from endogsim.io import load_scene  # type: ignore[attr-defined]
    except ImportError:
        raise DataError(f"{path}: no labels.json here and this build cannot read data folders "
                        "(endogsim.io.load_scene missing)") from None
    kwargs = {} if downscale is None else {"downscale": downscale}
    scene = load_scene(path, **kwargs)
    return dict(scene.labels), scene
