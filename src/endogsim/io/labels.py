"""Object-id label tables, one per dataset format.

Every pixel of a scene's ``object_masks`` and every Gaussian / particle carries an integer object id;
the scene's ``labels`` map that id to an :class:`~endogsim.io.scene.ObjectLabel` (name, tool or
tissue, and ``klass``, the key of the material prior; lowercase snake_case).

EndoNeRF (``masks/``: 255 = tool, 0 = tissue)

=====  ========  =======  ================
id     name      is_tool  klass
=====  ========  =======  ================
0      tissue    no       unknown_tissue
1      tool      yes      instrument
=====  ========  =======  ================

Without ``masks/`` every pixel is tissue (id 0) and the table holds only id 0.

CholecSeg8K (watershed mask grey value = class id; Hong et al. 2020)

=====  =============================  =======  ======================
id     name                           is_tool  klass
=====  =============================  =======  ======================
5      liver ligament                 no       liver_ligament
11     abdominal wall                 no       abdominal_wall
12     fat                            no       fat
13     gastrointestinal tract         no       gastrointestinal_tract
21     liver                          no       liver
22     gallbladder                    no       gallbladder
23     connective tissue              no       connective_tissue
24     blood                          no       blood
25     cystic duct                    no       cystic_duct
31     grasper                        yes      grasper
32     L-hook electrocautery          yes      l_hook
33     hepatic vein                   no       hepatic_vein
50     background                     --       (not an object; kept as id 50, klass "background")
255    unlabelled                     --       stored as -1 in ``object_masks``; not in the table
=====  =============================  =======  ======================

Plain videos without masks: everything is tissue id 0, as for EndoNeRF.

These tables give one id per tool *class*. Reconstruction splits each into one object per instrument
(:mod:`endogsim.priors.instances`): the first instrument of a class keeps the class's id, further ones get
new ids and numbered names ("tool_1", "tool_2", "grasper_2") with the class's ``klass``.
"""

from __future__ import annotations

from typing import Any

from endogsim.errors import DataError
from endogsim.io.scene import ObjectLabel

#: The id stored in ``object_masks`` for pixels that carry no label.
UNLABELLED = -1

ENDONERF_TISSUE = ObjectLabel(0, "tissue", False, "unknown_tissue")
ENDONERF_TOOL = ObjectLabel(1, "tool", True, "instrument")


def endonerf_labels(has_masks: bool) -> dict[int, ObjectLabel]:
    """EndoNeRF table: tissue id 0, plus tool id 1 when tool masks exist."""
    return {0: ENDONERF_TISSUE, 1: ENDONERF_TOOL} if has_masks else {0: ENDONERF_TISSUE}


#: CholecSeg8K class id -> label (255 "unlabelled" is mapped to -1 and left out).
CHOLECSEG8K_LABELS: dict[int, ObjectLabel] = {
    lab.id: lab
    for lab in [
        ObjectLabel(5, "liver ligament", False, "liver_ligament"),
        ObjectLabel(11, "abdominal wall", False, "abdominal_wall"),
        ObjectLabel(12, "fat", False, "fat"),
        ObjectLabel(13, "gastrointestinal tract", False, "gastrointestinal_tract"),
        ObjectLabel(21, "liver", False, "liver"),
        ObjectLabel(22, "gallbladder", False, "gallbladder"),
        ObjectLabel(23, "connective tissue", False, "connective_tissue"),
        ObjectLabel(24, "blood", False, "blood"),
        ObjectLabel(25, "cystic duct", False, "cystic_duct"),
        ObjectLabel(31, "grasper", True, "grasper"),
        ObjectLabel(32, "L-hook electrocautery", True, "l_hook"),
        ObjectLabel(33, "hepatic vein", False, "hepatic_vein"),
        ObjectLabel(50, "background", False, "background"),
    ]
}

#: CholecSeg8K ids that are not physical objects (the black border outside the field of view).
CHOLECSEG8K_NON_OBJECTS = frozenset({50})
CHOLECSEG8K_UNLABELLED_VALUE = 255


def label_table(obj: Any, where: str) -> dict[int, ObjectLabel]:
    """A label table from any JSON layout the package writes (``where`` names its file in errors).

    - ``{"<id>": {"name": str, "is_tool": bool, "klass" or "class": str}, ...}``: a ``labels.json``, a
      reconstruction's ``objects.json``; ``klass`` defaults to the name, ``is_tool`` to false;
    - the same under a ``"labels"`` key;
    - a scene folder's ``scene.json``: ``{"objects": [{"id", "name", "rigid", "class"}, ...]}``; ``class``
      defaults to "unknown_tissue", ``rigid`` (a tool) to false.
    """
    if isinstance(obj, dict) and isinstance(obj.get("objects"), list):
        out = {}
        for i, o in enumerate(obj["objects"]):
            try:
                out[int(o["id"])] = ObjectLabel(int(o["id"]), str(o["name"]), bool(o.get("rigid", False)),
                                                str(o.get("class", "unknown_tissue")))
            except (KeyError, TypeError, ValueError, AttributeError):
                raise DataError(f"{where}: objects[{i}] must be {{'id': int, 'name': str, 'rigid': bool, "
                                f"'class': str}}, got {o!r}") from None
        return out
    if isinstance(obj, dict) and isinstance(obj.get("labels"), dict):
        obj = obj["labels"]
    if not isinstance(obj, dict):
        raise DataError(f"{where}: expected a label table {{id: {{name, is_tool, klass}}}} or a scene.json "
                        "with an 'objects' list")
    out = {}
    for k, v in obj.items():
        try:
            oid, name = int(k), str(v["name"])
            out[oid] = ObjectLabel(oid, name, bool(v.get("is_tool", False)), str(v.get("klass") or v.get("class") or name))
        except (ValueError, TypeError, KeyError, AttributeError):
            raise DataError(f"{where}: entry {k!r} must be {{'name': str, 'is_tool': bool, 'klass': str}} "
                            f"under an integer id, got {v!r}") from None
    return out
