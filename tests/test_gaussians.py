"""Gaussian model: PLY round trip, shape validation, rotations and covariances."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from endogsim.errors import ModelError
from endogsim.gaussians.model import Gaussians, quat_to_rotmat, rotmat_to_quat, sh_coeff_count
from endogsim.gaussians.ply import read_ply, write_ply


def random_gaussians(n=50, degree=0, seed=0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3,
        opacity_logits=torch.randn(n, generator=g),
        sh=torch.randn(n, sh_coeff_count(degree), 3, generator=g),
        object_ids=torch.randint(0, 40, (n,), generator=g),
    )


@pytest.mark.parametrize("degree", [0, 3])
def test_ply_round_trip(tmp_path, degree):
    g = random_gaussians(degree=degree)
    path = write_ply(g, tmp_path / "g.ply")
    back = read_ply(path)
    assert back.sh_degree == degree
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(back, name).numpy(), getattr(g, name).float().numpy())
    assert torch.equal(back.object_ids, g.object_ids)
    names = [p.name for p in PlyData.read(str(path))["vertex"].properties]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[-1] == "object_id"


def test_ply_without_object_id_reads_zero(tmp_path):
    g = random_gaussians(n=7)
    cols = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"]
    data = np.zeros(7, dtype=[(c, "f4") for c in cols])
    data["x"] = g.means[:, 0].numpy()
    data["rot_0"] = 1
    PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp_path / "plain.ply"))
    back = read_ply(tmp_path / "plain.ply")
    assert torch.equal(back.object_ids, torch.zeros(7, dtype=torch.int64))
    np.testing.assert_array_equal(back.means[:, 0].numpy(), g.means[:, 0].numpy())


def test_corrupt_ply(tmp_path):
    path = write_ply(random_gaussians(), tmp_path / "g.ply")
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 3])
    with pytest.raises(ModelError, match="g.ply"):
        read_ply(path)
    (tmp_path / "junk.ply").write_bytes(b"hello world")
    with pytest.raises(ModelError, match="junk.ply"):
        read_ply(tmp_path / "junk.ply")
    with pytest.raises(ModelError, match="missing.ply"):
        read_ply(tmp_path / "missing.ply")


def test_shape_validation():
    g = random_gaussians(n=5)
    with pytest.raises(ModelError, match="quats"):
        g.with_(quats=torch.zeros(5, 3))
    with pytest.raises(ModelError, match="object_ids"):
        g.with_(object_ids=torch.zeros(4, dtype=torch.int64))
    with pytest.raises(ModelError):
        g.with_(sh=torch.zeros(5, 5, 3))  # 5 is not (d+1)^2


def test_quaternion_rotation_round_trip():
    q = torch.nn.functional.normalize(torch.randn(200, 4, dtype=torch.float64), dim=-1)
    R = quat_to_rotmat(q)
    eye = torch.eye(3, dtype=torch.float64).expand(200, 3, 3)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(200, dtype=torch.float64))
    q2 = rotmat_to_quat(R)
    # q and -q are the same rotation
    err = torch.minimum((q2 - q).abs().amax(-1), (q2 + q).abs().amax(-1))
    assert err.max() < 1e-9
    # unnormalised quaternions give the same rotation
    torch.testing.assert_close(quat_to_rotmat(3.0 * q), R)


def test_covariance_spd():
    g = random_gaussians(n=100)
    C = g.covariances().double()
    torch.testing.assert_close(C, C.transpose(-1, -2))
    evals = torch.linalg.eigvalsh(C)
    assert (evals > 0).all()
    # eigenvalues are the squared scales
    torch.testing.assert_close(evals.sort(-1).values, (g.scales.double() ** 2).sort(-1).values, rtol=1e-4, atol=1e-12)
