"""PLY files in the standard 3D Gaussian Splatting layout, plus an ``object_id`` property.

Layout (one vertex per Gaussian): x y z nx ny nz f_dc_0..2 f_rest_0..(3*(K-1)-1) opacity scale_0..2
rot_0..3 object_id. ``f_rest`` is channel-major (all R coefficients, then G, then B), opacity is the
logit, scales are logs and rot is (w, x, y, z), exactly as the reference implementation writes them,
so common splat viewers open the files; they ignore ``object_id``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from endogsim.errors import ModelError
from endogsim.gaussians.model import Gaussians, sh_degree_from_count
from endogsim.io.atomic import atomic_path


def write_ply(gaussians: Gaussians, path: str | os.PathLike) -> Path:
    """Write ``gaussians`` to ``path`` atomically (a temporary file renamed into place)."""
    path = Path(path)
    g = gaussians.detach().to("cpu")
    n, k = g.sh.shape[0], g.sh.shape[1]
    rest = g.sh[:, 1:].permute(0, 2, 1).reshape(n, 3 * (k - 1))  # channel-major, as 3DGS
    columns = {
        **{c: g.means[:, i] for i, c in enumerate("xyz")},
        **{c: torch.zeros(n) for c in ("nx", "ny", "nz")},
        **{f"f_dc_{i}": g.sh[:, 0, i] for i in range(3)},
        **{f"f_rest_{i}": rest[:, i] for i in range(rest.shape[1])},
        "opacity": g.opacity_logits,
        **{f"scale_{i}": g.log_scales[:, i] for i in range(3)},
        **{f"rot_{i}": g.quats[:, i] for i in range(4)},
    }
    dtype = [(name, "f4") for name in columns] + [("object_id", "i4")]
    data = np.empty(n, dtype=dtype)
    for name, col in columns.items():
        data[name] = col.float().numpy()
    data["object_id"] = g.object_ids.numpy().astype(np.int32)
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp))
    return path


def read_ply(path: str | os.PathLike) -> Gaussians:
    """Read a 3DGS-layout PLY; ``object_id`` defaults to 0 when the file has none."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: no such PLY file")
    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"].data
    except Exception as exc:  # plyfile raises many types on corrupt files
        raise ModelError(f"{path}: not a readable PLY file ({exc})") from None
    names = set(v.dtype.names)
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [c for c in required if c not in names]
    if missing:
        raise ModelError(f"{path}: not a Gaussian-splat PLY, missing properties {missing}")
    n = len(v)
    col = lambda c: torch.from_numpy(np.asarray(v[c], dtype=np.float32))  # noqa: E731
    n_rest = sum(1 for c in names if c.startswith("f_rest_"))
    if n_rest % 3:
        raise ModelError(f"{path}: {n_rest} f_rest properties is not a multiple of 3")
    sh_degree_from_count(1 + n_rest // 3)
    sh = torch.zeros(n, 1 + n_rest // 3, 3)
    sh[:, 0] = torch.stack([col(f"f_dc_{i}") for i in range(3)], -1)
    if n_rest:
        rest = torch.stack([col(f"f_rest_{i}") for i in range(n_rest)], -1)
        sh[:, 1:] = rest.reshape(n, 3, n_rest // 3).permute(0, 2, 1)
    ids = (torch.from_numpy(np.asarray(v["object_id"], dtype=np.int64)) if "object_id" in names
           else torch.zeros(n, dtype=torch.int64))
    g = Gaussians(
        means=torch.stack([col(c) for c in "xyz"], -1),
        quats=torch.stack([col(f"rot_{i}") for i in range(4)], -1),
        log_scales=torch.stack([col(f"scale_{i}") for i in range(3)], -1),
        opacity_logits=col("opacity"),
        sh=sh,
        object_ids=ids,
    )
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        if not torch.isfinite(getattr(g, name)).all():
            raise ModelError(f"{path}: non-finite values in {name}")
    return g
