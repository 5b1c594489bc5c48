"""Atomic writes: a reader (or a resumed run) never sees half a file or half a folder.

Every writer goes through :func:`atomic_path`: the content is written to a temporary file in the same
folder, then renamed onto the destination (``os.replace`` is atomic on one file system); on any error the
temporary file is removed and the destination is left as it was. :func:`atomic_folder` does the same for a
whole folder (a temporary sibling renamed into place).

JSON files are always valid JSON: :func:`write_json_atomic` writes NaN and infinities as ``null`` and notes
them in the enclosing object under ``"non_finite"`` (key -> "nan", "inf" or "-inf").

    with atomic_path(out / "video.mp4") as tmp:      # tmp keeps the suffix, so encoders pick the format
        encode(tmp)
    write_json_atomic(out / "metrics.json", metrics)
    save_torch_atomic(state, out / "checkpoint.pt")
    save_npz_atomic(out / "flow.npz", flow=flow, key=np.array(key))
"""

from __future__ import annotations

import errno
import json
import math
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

__all__ = ["atomic_path", "atomic_folder", "write_json_atomic", "finite_json", "write_text_atomic",
           "save_torch_atomic", "save_npz_atomic"]


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """A temporary path beside ``path`` that becomes ``path`` when the block succeeds.

    The temporary file ends in ``suffix`` (default: ``path``'s own), so writers that pick the format from
    the name (encoders, image writers) do the right thing. The parent folder is created. On an exception
    the temporary file is removed and the exception re-raised. A ``path`` that is a folder, or a folder
    that cannot be written, raises an ``OSError`` naming it.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, "a folder, not a file to write", str(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix if suffix is None else suffix
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=f".tmp{suffix}")
    except OSError as exc:  # name the folder, not the temporary file
        raise type(exc)(exc.errno, exc.strerror, str(path.parent)) from None
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextmanager
def atomic_folder(path: str | os.PathLike, replace: bool = True) -> Iterator[Path]:
    """A temporary sibling folder that replaces ``path`` when the block succeeds.

    Args:
        path: destination folder.
        replace: remove an existing ``path`` before the rename (else the rename fails if it exists).
    Raises:
        OSError naming ``path`` when it is the working folder or holds it (``"."``, ``""``, ``".."``): replacing
        it would delete the folder the user is working in.
    """
    path = Path(path)
    here = Path.cwd().resolve()
    if path.resolve() in (here, *here.parents):
        raise OSError(errno.EINVAL, "the working folder or one that holds it, which would be replaced; name a new "
                                    "folder to write", str(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.tmp"))
    try:
        yield tmp
        if replace and path.exists():
            shutil.rmtree(path)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


#: The key under which :func:`write_json_atomic` notes the values it wrote as null.
NON_FINITE_KEY = "non_finite"


def finite_json(obj: Any) -> Any:
    """``obj`` with every NaN or infinite float replaced by None; each dict that held one gets a
    ``"non_finite"`` entry naming its keys (``"key"`` or ``"key[3]"`` inside a list) and what they were.

    A ``"non_finite"`` entry already present is kept for the keys that are still null (a file read back
    and written again keeps its notes).
    """

    def clean(v: Any, key: str, notes: dict[str, str]) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            notes[key] = str(v)
            return None
        if isinstance(v, dict):
            return clean_dict(v)
        if isinstance(v, (list, tuple)):
            return [clean(x, f"{key}[{i}]", notes) for i, x in enumerate(v)]
        return v

    def clean_dict(d: dict) -> dict:
        notes: dict[str, str] = {}
        out = {k: clean(v, str(k), notes) for k, v in d.items() if k != NON_FINITE_KEY}
        old = d.get(NON_FINITE_KEY)
        if isinstance(old, dict):
            notes = {k: v for k, v in old.items() if _value_at(out, k) is None} | notes
        if notes:
            out[NON_FINITE_KEY] = notes
        return out

    return clean(obj, "", {})


def _value_at(d: dict, key: str) -> Any:
    """``d["a"][1][2]`` for key "a[1][2]" (0 where there is no such value: "not null")."""
    name, *idx = key.replace("]", "").split("[")
    v = d.get(name, 0)
    for i in idx:
        v = v[int(i)] if isinstance(v, list) and i.isdigit() and int(i) < len(v) else 0
    return v


def write_json_atomic(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON to ``path`` atomically; NaN and infinities become null, noted
    (:func:`finite_json`)."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(finite_json(obj), f, indent=2, allow_nan=False)
    return Path(path)


def save_torch_atomic(obj: Any, path: str | os.PathLike) -> Path:
    """``torch.save(obj)`` to ``path`` atomically (no half-written checkpoints)."""
    import torch

    with atomic_path(path) as tmp:
        torch.save(obj, tmp)
    return Path(path)


def save_npz_atomic(path: str | os.PathLike, compressed: bool = False, **arrays: Any) -> Path:
    """``np.savez`` (or ``savez_compressed``) of ``arrays`` to ``path`` (``.npz``) atomically."""
    import numpy as np

    with atomic_path(path) as tmp, open(tmp, "wb") as f:  # a file object: numpy adds no ".npz" to the name
        (np.savez_compressed if compressed else np.savez)(f, **arrays)
    return Path(path)
