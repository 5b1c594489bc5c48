"""One entry point for every way to initialise a material field: manual, prior, mllm, replay."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from endogsim.errors import DataError, MaterialError
from endogsim.io.labels import label_table
from endogsim.io.runfolder import PROVENANCE
from endogsim.io.scene import ObjectLabel, Scene
from endogsim.materials.field import MaterialField, MaterialRecord
from endogsim.materials.mllm import (
    MLLMBudget,
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
    budget = MLLMBudget(cfg.mllm.total_timeout_s)
    for oid, lab in sorted(labels.items()):
        t = _best_frame(scene.object_masks, oid)
        if t is None:
            # Not visible anywhere: nothing to show the model; the prior is the honest answer.
            records.append(prior_record(oid, lab.name, lab.klass, lab.is_tool, cfg.regime,
                                        source="prior (not visible in any frame)"))
            continue
        images = object_images(scene.frames[t], scene.object_masks[t] == oid)
        q = ObjectQuery(oid, lab.name, lab.klass, lab.is_tool, images)
        records.append(query_object(q, cfg.mllm, cfg.regime, client=client, replay=replay, budget=budget))
    # The backend asked for is not always the one that answered: count the records' real sources.
    from_prior = [r.name for r in records if r.source.startswith("prior")]
    meta["sources"] = {cfg.backend: len(records) - len(from_prior), "prior": len(from_prior)}
    if from_prior:
        meta["note"] = (f"{len(from_prior)} of {len(records)} objects took the prior instead of an MLLM answer "
                        f"({', '.join(from_prior)}); each record's source says why")
    return MaterialField(records, meta=meta)


def load_labels_json(path: str | Path) -> dict[int, ObjectLabel]:
    """Read a label table from a JSON file: a ``labels.json`` (``{"<id>": {"name": str, "is_tool": bool,
    "klass": str}, ...}``), a reconstruction's ``objects.json`` or a scene folder's ``scene.json``
    (:func:`endogsim.io.labels.label_table`)."""
    path = Path(path)
    try:
        obj = json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"{path}: labels file not found") from None
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: not valid JSON ({exc})") from None
    return label_table(obj, str(path))


#: Files that hold a folder's label table, in the order they are looked for: a label file, a reconstruction
#: run folder, a scene folder (``endogsim synth``), an ``endogsim run`` folder (its scene, its reconstruction).
LABEL_FILES = ("labels.json", "objects.json", "scene.json", "scene/scene.json", "recon/objects.json")


def _is_dataset(path: Path) -> bool:
    """Whether a registered dataset format reads ``path``."""
    from endogsim.io.formats import detect_format

    try:
        detect_format(path)
    except DataError:
        return False
    return True


def load_objects(path: str | Path, need_images: bool = False, downscale: float | None = None
                 ) -> tuple[dict[int, ObjectLabel], Scene | None]:
    """Labels (and, when ``need_images``, the Scene) of a data folder, a run folder or a label JSON file.

    Without ``need_images`` a folder's label table comes from the first of :data:`LABEL_FILES` it holds,
    else from reading it as a dataset (``endogsim.io.load_scene``). With ``need_images`` (the mllm and
    replay backends show the model each object) the path must be a dataset: a data folder, a video or a
    scene folder.
    """
    from endogsim.io import load_scene  # type: ignore[attr-defined]

    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    if path.is_file() and path.suffix == ".json":
        if need_images:
            raise DataError(f"{path}: a label table has no images; the mllm/replay backends need a data folder")
        return load_labels_json(path), None
    label_file = next((path / n for n in LABEL_FILES if (path / n).is_file()), None) if path.is_dir() else None
    if label_file is not None and not need_images:
        return load_labels_json(label_file), None
    if label_file is not None and not _is_dataset(path):
        made_from = json.loads((path / PROVENANCE).read_text()).get("data") if (path / PROVENANCE).is_file() else None
        raise DataError(f"{label_file}: a label table has no images; the mllm/replay backends need a data folder"
                        + (f" (this run was made from {made_from})" if made_from else ""))
    kwargs = {} if downscale is None else {"downscale": downscale}
    scene = load_scene(path, **kwargs)
    return dict(scene.labels), scene
