"""Frechet Inception Distance (FID) between two frame sets, from a LOCAL Inception-v3 weights file.

FID = |mu_1 - mu_2|^2 + tr(S_1 + S_2 - 2 (S_1 S_2)^(1/2)) over the 2048-d pool features of Inception-v3
(Heusel et al. 2017; the same formula and singular-product fix as pytorch-fid).

Weights are never downloaded. Give one of:
  * torchvision's ``inception_v3_google-*.pth`` (1000 classes), or
  * pytorch-fid's ``pt_inception-2015-12-05-*.pth`` (1008 classes, the reference FID network).
The network is defined here (:class:`InceptionV3`, torchvision's parameter names) because the PyPI
torchvision / pytorch-fid wheels need a CUDA build of torch and do not import with the CPU one.
With few frames (N < 2048) the covariances are rank-deficient and FID is biased upwards; compare FIDs
only between runs with the same frame counts.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from endogsim.errors import ModelError

__all__ = ["InceptionV3", "frechet_distance", "feature_statistics", "load_inception", "inception_features", "fid", "FID_WEIGHTS_ENV"]

FID_WEIGHTS_ENV = "ENDOGSIM_FID_WEIGHTS"


def feature_statistics(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean [D] and covariance [D, D] (unbiased, rows = samples) of features [N, D], float64."""
    f = np.asarray(features, dtype=np.float64)
    if f.ndim != 2 or f.shape[0] < 2:
        raise ModelError(f"FID needs at least 2 feature vectors [N, D], got shape {f.shape}")
    return f.mean(0), np.cov(f, rowvar=False)


def frechet_distance(mu1: np.ndarray, sigma1: np.ndarray, mu2: np.ndarray, sigma2: np.ndarray, eps: float = 1e-6) -> float:
    """Frechet distance between N(mu1, sigma1) and N(mu2, sigma2).

    A singular product S_1 S_2 (few samples) gets ``eps`` added to both diagonals, as in pytorch-fid;
    the tiny imaginary part sqrtm returns from round-off is dropped.
    """
    from scipy import linalg

    mu1, mu2 = np.atleast_1d(mu1).astype(np.float64), np.atleast_1d(mu2).astype(np.float64)
    s1, s2 = np.atleast_2d(sigma1).astype(np.float64), np.atleast_2d(sigma2).astype(np.float64)
    if mu1.shape != mu2.shape or s1.shape != s2.shape or s1.shape != (mu1.size, mu1.size):
        raise ModelError(f"FID statistics do not match: mu {mu1.shape} vs {mu2.shape}, sigma {s1.shape} vs {s2.shape}")
    diff = mu1 - mu2
    with warnings.catch_warnings():  # a singular product warns; it is handled just below
        warnings.simplefilter("ignore")
        covmean = linalg.sqrtm(s1 @ s2)
        if not np.isfinite(covmean).all():
            offset = np.eye(s1.shape[0]) * eps
            covmean = linalg.sqrtm((s1 + offset) @ (s2 + offset))
    if np.iscomplexobj(covmean):
        covmean = covmean.real
    return float(diff @ diff + np.trace(s1) + np.trace(s2) - 2.0 * np.trace(covmean))


def _weights_path(weights: str | os.PathLike | None) -> Path:
    hint = ("FID needs a local Inception-v3 weights file (nothing is downloaded): pass --fid-weights FILE or set "
            f"${FID_WEIGHTS_ENV}; use torchvision's inception_v3_google-*.pth or pytorch-fid's pt_inception-2015-12-05-*.pth")
    if weights is None:
        weights = os.environ.get(FID_WEIGHTS_ENV) or None
    if weights is None:
        raise ModelError(hint)
    p = Path(weights)
    if not p.is_file():
        raise ModelError(f"{p}: Inception weights file not found. {hint}")
    return p


class _Conv(torch.nn.Module):
    """Conv (no bias) + batch norm (eps 1e-3) + ReLU: torchvision's ``BasicConv2d`` (same parameter names)."""

    def __init__(self, cin: int, cout: int, kernel, stride=1, padding=0):
        super().__init__()
        self.conv = torch.nn.Conv2d(cin, cout, kernel, stride=stride, padding=padding, bias=False)
        self.bn = torch.nn.BatchNorm2d(cout, eps=0.001)

    def forward(self, x):
        return torch.relu(self.bn(self.conv(x)))


def _avg3(x, fid: bool):
    # The TF graph behind FID's weights averages over valid pixels only (count_include_pad=False).
    return F.avg_pool2d(x, 3, stride=1, padding=1, count_include_pad=not fid)


class _A(torch.nn.Module):
    def __init__(self, cin: int, pool: int, fid: bool):
        super().__init__()
        self.fid = fid
        self.branch1x1 = _Conv(cin, 64, 1)
        self.branch5x5_1, self.branch5x5_2 = _Conv(cin, 48, 1), _Conv(48, 64, 5, padding=2)
        self.branch3x3dbl_1, self.branch3x3dbl_2 = _Conv(cin, 64, 1), _Conv(64, 96, 3, padding=1)
        self.branch3x3dbl_3 = _Conv(96, 96, 3, padding=1)
        self.branch_pool = _Conv(cin, pool, 1)

    def forward(self, x):
        return torch.cat([self.branch1x1(x), self.branch5x5_2(self.branch5x5_1(x)),
                          self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x))),
                          self.branch_pool(_avg3(x, self.fid))], 1)


class _B(torch.nn.Module):
    def __init__(self, cin: int):
        super().__init__()
        self.branch3x3 = _Conv(cin, 384, 3, stride=2)
        self.branch3x3dbl_1, self.branch3x3dbl_2 = _Conv(cin, 64, 1), _Conv(64, 96, 3, padding=1)
        self.branch3x3dbl_3 = _Conv(96, 96, 3, stride=2)

    def forward(self, x):
        return torch.cat([self.branch3x3(x), self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x))),
                          F.max_pool2d(x, 3, stride=2)], 1)


class _C(torch.nn.Module):
    def __init__(self, cin: int, c7: int, fid: bool):
        super().__init__()
        self.fid = fid
        row, col = dict(kernel=(1, 7), padding=(0, 3)), dict(kernel=(7, 1), padding=(3, 0))
        self.branch1x1 = _Conv(cin, 192, 1)
        self.branch7x7_1, self.branch7x7_2, self.branch7x7_3 = _Conv(cin, c7, 1), _Conv(c7, c7, **row), _Conv(c7, 192, **col)
        self.branch7x7dbl_1, self.branch7x7dbl_2 = _Conv(cin, c7, 1), _Conv(c7, c7, **col)
        self.branch7x7dbl_3, self.branch7x7dbl_4 = _Conv(c7, c7, **row), _Conv(c7, c7, **col)
        self.branch7x7dbl_5 = _Conv(c7, 192, **row)
        self.branch_pool = _Conv(cin, 192, 1)

    def forward(self, x):
        d = x
        for m in (self.branch7x7dbl_1, self.branch7x7dbl_2, self.branch7x7dbl_3, self.branch7x7dbl_4, self.branch7x7dbl_5):
            d = m(d)
        return torch.cat([self.branch1x1(x), self.branch7x7_3(self.branch7x7_2(self.branch7x7_1(x))), d,
                          self.branch_pool(_avg3(x, self.fid))], 1)


class _D(torch.nn.Module):
    def __init__(self, cin: int):
        super().__init__()
        self.branch3x3_1, self.branch3x3_2 = _Conv(cin, 192, 1), _Conv(192, 320, 3, stride=2)
        self.branch7x7x3_1 = _Conv(cin, 192, 1)
        self.branch7x7x3_2 = _Conv(192, 192, (1, 7), padding=(0, 3))
        self.branch7x7x3_3 = _Conv(192, 192, (7, 1), padding=(3, 0))
        self.branch7x7x3_4 = _Conv(192, 192, 3, stride=2)

    def forward(self, x):
        b = self.branch7x7x3_4(self.branch7x7x3_3(self.branch7x7x3_2(self.branch7x7x3_1(x))))
        return torch.cat([self.branch3x3_2(self.branch3x3_1(x)), b, F.max_pool2d(x, 3, stride=2)], 1)


class _E(torch.nn.Module):
    def __init__(self, cin: int, pool: str):
        super().__init__()
        self.pool = pool  # "avg" (torchvision), "avg_valid" (FID Mixed_7b) or "max" (FID Mixed_7c)
        self.branch1x1 = _Conv(cin, 320, 1)
        self.branch3x3_1 = _Conv(cin, 384, 1)
        self.branch3x3_2a = _Conv(384, 384, (1, 3), padding=(0, 1))
        self.branch3x3_2b = _Conv(384, 384, (3, 1), padding=(1, 0))
        self.branch3x3dbl_1, self.branch3x3dbl_2 = _Conv(cin, 448, 1), _Conv(448, 384, 3, padding=1)
        self.branch3x3dbl_3a = _Conv(384, 384, (1, 3), padding=(0, 1))
        self.branch3x3dbl_3b = _Conv(384, 384, (3, 1), padding=(1, 0))
        self.branch_pool = _Conv(cin, 192, 1)

    def forward(self, x):
        a = self.branch3x3_1(x)
        d = self.branch3x3dbl_2(self.branch3x3dbl_1(x))
        p = F.max_pool2d(x, 3, stride=1, padding=1) if self.pool == "max" else _avg3(x, self.pool == "avg_valid")
        return torch.cat([self.branch1x1(x), self.branch3x3_2a(a), self.branch3x3_2b(a),
                          self.branch3x3dbl_3a(d), self.branch3x3dbl_3b(d), self.branch_pool(p)], 1)


class InceptionV3(torch.nn.Module):
    """Inception-v3 up to the 2048-d average pool, with torchvision's parameter names, so its
    ``inception_v3_google`` state dict and pytorch-fid's ``pt_inception`` one both load into it.

    ``fid=True`` switches to the FID network's pooling (pytorch-fid's FIDInception blocks: average pools
    over valid pixels, max pool in the last block). Input: [B, 3, 299, 299] in [-1, 1]; output [B, 2048].
    """

    def __init__(self, fid: bool = False, num_classes: int = 1000):
        super().__init__()
        self.Conv2d_1a_3x3 = _Conv(3, 32, 3, stride=2)
        self.Conv2d_2a_3x3 = _Conv(32, 32, 3)
        self.Conv2d_2b_3x3 = _Conv(32, 64, 3, padding=1)
        self.Conv2d_3b_1x1 = _Conv(64, 80, 1)
        self.Conv2d_4a_3x3 = _Conv(80, 192, 3)
        self.Mixed_5b, self.Mixed_5c, self.Mixed_5d = _A(192, 32, fid), _A(256, 64, fid), _A(288, 64, fid)
        self.Mixed_6a = _B(288)
        self.Mixed_6b = _C(768, 128, fid)
        self.Mixed_6c, self.Mixed_6d = _C(768, 160, fid), _C(768, 160, fid)
        self.Mixed_6e = _C(768, 192, fid)
        self.Mixed_7a = _D(768)
        self.Mixed_7b = _E(1280, "avg_valid" if fid else "avg")
        self.Mixed_7c = _E(2048, "max" if fid else "avg")
        self.fc = torch.nn.Linear(2048, num_classes)  # kept so the state dict loads; not used for features

    def forward(self, x):
        x = self.Conv2d_2b_3x3(self.Conv2d_2a_3x3(self.Conv2d_1a_3x3(x)))
        x = F.max_pool2d(x, 3, stride=2)
        x = F.max_pool2d(self.Conv2d_4a_3x3(self.Conv2d_3b_1x1(x)), 3, stride=2)
        for name in ("5b", "5c", "5d", "6a", "6b", "6c", "6d", "6e", "7a", "7b", "7c"):
            x = getattr(self, f"Mixed_{name}")(x)
        return F.adaptive_avg_pool2d(x, 1).flatten(1)


def load_inception(weights: str | os.PathLike | None = None) -> InceptionV3:
    """Inception-v3 feature network (eval mode) from a local weights file; nothing is downloaded.

    The file is torchvision's ``inception_v3_google-*.pth`` (1000 classes) or pytorch-fid's
    ``pt_inception-2015-12-05-*.pth`` (1008 classes: the reference FID network, selected automatically).
    Raises:
        ModelError: no weights file given / found, or a file that is not an Inception-v3 state dict.
    """
    p = _weights_path(weights)
    try:
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - corrupt file, pickle, ...
        raise ModelError(f"{p}: not a readable PyTorch weights file ({exc})") from None
    if isinstance(state, dict) and "state_dict" in state:
        state = state["state_dict"]
    if not isinstance(state, dict) or "fc.weight" not in state or "Mixed_7c.branch_pool.conv.weight" not in state:
        raise ModelError(f"{p}: not an Inception-v3 state dict (no fc / Mixed_7c weights)")
    n_classes = int(state["fc.weight"].shape[0])
    net = InceptionV3(fid=n_classes == 1008, num_classes=n_classes)
    state = {k: v for k, v in state.items() if not k.startswith("AuxLogits.")}  # the training-only head
    try:
        net.load_state_dict(state)
    except RuntimeError as exc:
        raise ModelError(f"{p}: weights do not fit Inception-v3 ({str(exc)[:300]})") from None
    return net.eval()


@torch.no_grad()
def inception_features(net: torch.nn.Module, frames, batch: int = 8) -> np.ndarray:
    """Pool features [T, 2048] of frames [T, H, W, 3] (float in [0, 1] or uint8), resized to 299 x 299."""
    x = torch.as_tensor(np.asarray(frames))
    if x.dtype == torch.uint8:
        x = x.float() / 255.0
    if x.ndim != 4 or x.shape[-1] != 3:
        raise ModelError(f"FID frames must be [T, H, W, 3], got {tuple(x.shape)}")
    out = []
    for i in range(0, x.shape[0], batch):
        b = x[i:i + batch].float().permute(0, 3, 1, 2).clamp(0, 1)
        b = torch.nn.functional.interpolate(b, size=(299, 299), mode="bilinear", align_corners=False)
        out.append(net(2.0 * b - 1.0).double().numpy())
    return np.concatenate(out)


def fid(frames_a, frames_b, weights: str | os.PathLike | None = None, net: torch.nn.Module | None = None) -> float:
    """FID between two frame sets [T, H, W, 3] (each T >= 2) with the Inception weights file ``weights``."""
    net = net if net is not None else load_inception(weights)
    mu1, s1 = feature_statistics(inception_features(net, frames_a))
    mu2, s2 = feature_statistics(inception_features(net, frames_b))
    return frechet_distance(mu1, s1, mu2, s2)
