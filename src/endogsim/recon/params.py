"""Trainable Gaussians with their Adam optimiser, densification (clone / split) and pruning (3DGS).

:class:`GaussianParams` owns one ``nn.Parameter`` per attribute of a
:class:`~endogsim.gaussians.model.Gaussians` and one Adam param group per attribute, so that adding or
removing Gaussians can edit the optimiser's moment buffers in place (new Gaussians start with zero
moments, removed ones take theirs with them), exactly as the reference 3DGS implementation does.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn

from endogsim.gaussians.model import Gaussians, quat_to_rotmat

__all__ = ["GaussianParams", "ATTRS", "log_linear_lr"]

ATTRS = ("means", "quats", "log_scales", "opacity_logits", "sh")
#: Integer labels every Gaussian carries through densification (children inherit their parent's).
LABELS = ("object_ids", "track_ids")


def log_linear_lr(f: float, lr0: float, lr1: float) -> float:
    """Learning rate decayed log-linearly from lr0 at progress f = 0 to lr1 at f = 1 (clamped)."""
    f = min(max(f, 0.0), 1.0)
    return math.exp(math.log(lr0) * (1 - f) + math.log(lr1) * f)


class GaussianParams:
    """Gaussians as trainable parameters plus densification statistics.

    Args:
        g: initial Gaussians (copied).
        lrs: learning rate per attribute name in ``ATTRS``.
        track_ids: [N] int64 index of each Gaussian's point track (:mod:`endogsim.priors.tracks`), -1 for
            none; default: none.
    """

    def __init__(self, g: Gaussians, lrs: dict[str, float], track_ids: torch.Tensor | None = None) -> None:
        self.params = {a: nn.Parameter(getattr(g, a).detach().clone().float()) for a in ATTRS}
        self.object_ids = g.object_ids.detach().clone()
        self.track_ids = (torch.full_like(self.object_ids, -1) if track_ids is None
                          else torch.as_tensor(track_ids, dtype=torch.int64, device=self.object_ids.device).clone())
        self.optimizer = torch.optim.Adam(
            [{"params": [self.params[a]], "lr": lrs[a], "name": a} for a in ATTRS], lr=0.0, eps=1e-15)
        self.reset_stats()

    def __len__(self) -> int:
        return self.params["means"].shape[0]

    def gaussians(self) -> Gaussians:
        """The current Gaussians (the tensors are the parameters: gradients flow to them)."""
        return Gaussians(*(self.params[a] for a in ATTRS), self.object_ids)

    def set_lr(self, name: str, lr: float) -> None:
        for group in self.optimizer.param_groups:
            if group["name"] == name:
                group["lr"] = lr

    def step(self) -> None:
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    # ------------------------------------------------------------------ densification statistics
    def reset_stats(self) -> None:
        n, dev = len(self), self.params["means"].device
        self.grad_accum = torch.zeros(n, device=dev)
        self.grad_count = torch.zeros(n, device=dev)

    @torch.no_grad()
    def add_stats(self, means2d_grad: torch.Tensor, visible: torch.Tensor, width: int, height: int) -> None:
        """Accumulate the view-space positional gradient of one render.

        Args:
            means2d_grad: [N, 2] d loss / d projected centre (per pixel).
            visible: [N] bool, the Gaussian was drawn.
            width, height: image size; gradients are converted to NDC units (x W/2, x H/2) so the 3DGS
                threshold 2e-4 applies at any resolution.
        """
        g = means2d_grad * torch.tensor([width / 2, height / 2], device=means2d_grad.device)
        self.grad_accum[visible] += g[visible].norm(dim=-1)
        self.grad_count[visible] += 1

    # ------------------------------------------------------------------ editing the set
    def _edit(self, keep: torch.Tensor | None, extra: dict[str, torch.Tensor] | None,
              extra_labels: dict[str, torch.Tensor] | None) -> None:
        """Keep the rows ``keep`` (bool [N] or None = all) and append ``extra`` rows (with their ``LABELS``);
        optimiser moments follow (zeros for new rows)."""
        for group in self.optimizer.param_groups:
            name = group["name"]
            old = group["params"][0]
            state = self.optimizer.state.pop(old, None)
            data = old.data if keep is None else old.data[keep]
            if extra is not None:
                data = torch.cat([data, extra[name].to(data)])
            new = nn.Parameter(data)
            if state is not None:
                for key in ("exp_avg", "exp_avg_sq"):
                    buf = state[key] if keep is None else state[key][keep]
                    if extra is not None:
                        buf = torch.cat([buf, torch.zeros_like(extra[name]).to(buf)])
                    state[key] = buf
                self.optimizer.state[new] = state
            group["params"][0] = new
            self.params[name] = new
        for name in LABELS:
            ids = getattr(self, name) if keep is None else getattr(self, name)[keep]
            if extra_labels is not None:
                ids = torch.cat([ids, extra_labels[name]])
            setattr(self, name, ids)

    @torch.no_grad()
    def densify_and_prune(self, grad_threshold: float, percent_dense: float, extent: float, min_opacity: float,
                          max_gaussians: int, generator: torch.Generator | None = None) -> dict[str, int]:
        """Clone small Gaussians and split large ones whose mean view-space gradient exceeds
        ``grad_threshold``; then prune transparent (opacity < ``min_opacity``) and huge (> 0.2 extent)
        ones. At most ``max_gaussians`` remain: the highest-gradient candidates are densified first.

        Returns counts: cloned, split, pruned.
        """
        grads = self.grad_accum / self.grad_count.clamp_min(1)
        scales = self.params["log_scales"].exp()
        max_scale = scales.max(1).values
        cand = grads >= grad_threshold
        budget = max(0, max_gaussians - len(self))
        if int(cand.sum()) > budget:  # keep the strongest candidates only
            order = torch.argsort(torch.where(cand, grads, -1.0), descending=True)
            cand = torch.zeros_like(cand)
            cand[order[:budget]] = True
        clone = cand & (max_scale <= percent_dense * extent)
        split = cand & (max_scale > percent_dense * extent)
        p = self.params
        extra = {a: p[a][clone] for a in ATTRS}
        extra_labels = {n: getattr(self, n)[clone] for n in LABELS}
        if split.any():
            # two children per split Gaussian, sampled inside it, each 1.6x smaller (3DGS)
            s = scales[split].repeat(2, 1)
            noise = torch.randn(s.shape, generator=generator, device=s.device) * s
            R = quat_to_rotmat(p["quats"][split]).repeat(2, 1, 1)
            child = {
                "means": (R @ noise[..., None])[..., 0] + p["means"][split].repeat(2, 1),
                "quats": p["quats"][split].repeat(2, 1),
                "log_scales": (s / 1.6).log(),
                "opacity_logits": p["opacity_logits"][split].repeat(2),
                "sh": p["sh"][split].repeat(2, 1, 1),
            }
            extra = {a: torch.cat([extra[a], child[a]]) for a in ATTRS}
            extra_labels = {n: torch.cat([extra_labels[n], getattr(self, n)[split].repeat(2)]) for n in LABELS}
        n_old = len(self)
        self._edit(None, extra, extra_labels)
        keep = torch.ones(len(self), dtype=torch.bool, device=self.object_ids.device)
        keep[:n_old][split] = False
        opac = torch.sigmoid(self.params["opacity_logits"])
        big = self.params["log_scales"].exp().max(1).values > 0.2 * extent
        pruned = (~keep).clone()
        keep &= (opac >= min_opacity) & ~big
        self._edit(keep, None, None)
        self.reset_stats()
        return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int((~keep).sum() - pruned.sum())}

    # ------------------------------------------------------------------ checkpointing
    def state(self) -> dict:
        return {"params": {a: self.params[a].detach().clone() for a in ATTRS}, "object_ids": self.object_ids.clone(),
                "track_ids": self.track_ids.clone(), "optimizer": self.optimizer.state_dict(),
                "grad_accum": self.grad_accum.clone(), "grad_count": self.grad_count.clone()}

    @staticmethod
    def from_state(state: dict, lrs: dict[str, float]) -> "GaussianParams":
        g = Gaussians(*(state["params"][a] for a in ATTRS), state["object_ids"])
        gp = GaussianParams(g, lrs, state.get("track_ids"))
        gp.optimizer.load_state_dict(state["optimizer"])
        gp.grad_accum = state["grad_accum"].clone()
        gp.grad_count = state["grad_count"].clone()
        return gp

    def to(self, device: torch.device | str) -> "GaussianParams":
        """Move parameters, moments and statistics to ``device`` (rebuilds the optimiser)."""
        st = self.state()
        st = {**st, "params": {a: v.to(device) for a, v in st["params"].items()},
              "object_ids": st["object_ids"].to(device), "track_ids": st["track_ids"].to(device),
              "grad_accum": st["grad_accum"].to(device), "grad_count": st["grad_count"].to(device)}
        lrs = {g["name"]: g["lr"] for g in self.optimizer.param_groups}
        gp = GaussianParams.from_state(st, lrs)
        return gp
