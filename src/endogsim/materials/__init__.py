"""Object-wise material field and its initialisers (manual, prior table, MLLM, cache replay)."""

from endogsim.materials.field import (
    MaterialField,
    MaterialParams,
    MaterialRecord,
    nu_to_raw,
)
from endogsim.materials.init import (
    BACKENDS,
    ManualMaterial,
    MaterialInitConfig,
    initialise_materials,
    load_labels_json,
    load_objects,
)
from endogsim.materials.mllm import MLLMConfig, MLLMFallbackWarning
from endogsim.materials.prior import (
    CHOLECSEG8K_CLASSES,
    load_prior_table,
    prior_record,
    resolve_class,
)

__all__ = [
    "BACKENDS", "CHOLECSEG8K_CLASSES", "MLLMConfig", "MLLMFallbackWarning", "ManualMaterial", "MaterialField",
    "MaterialInitConfig", "MaterialParams", "MaterialRecord", "initialise_materials", "load_labels_json",
    "load_objects", "load_prior_table", "nu_to_raw", "prior_record", "resolve_class",
]
