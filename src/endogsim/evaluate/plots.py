"""Figures of an identification run (matplotlib, Agg backend: no display needed). PNGs written atomically."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from endogsim.io.atomic import atomic_path

__all__ = ["plot_loss", "plot_parameters"]


def _figure():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    return path


def plot_loss(history: Sequence[Mapping], path: str | os.PathLike, best_iteration: int | None = None,
              title: str = "identification loss") -> Path:
    """Total loss and each (unweighted) loss term per iteration, log scale.

    Args:
        history: one mapping per iteration with keys ``iteration``, ``loss`` (the total) and ``terms``
            ({term name: unweighted value}).
        path: PNG to write.
        best_iteration: marked with a vertical line.
    """
    plt = _figure()
    fig, ax = plt.subplots(figsize=(6, 3.6))
    it = [h["iteration"] for h in history]
    series = {"total": [h["loss"] for h in history]}
    for name in (history[0].get("terms", {}) if history else {}):
        series[name] = [h["terms"][name] for h in history]
    for label, vals in series.items():
        ax.plot(it, [max(float(v), 1e-30) for v in vals], marker=".", label=label)
    if best_iteration is not None and best_iteration >= 0:
        ax.axvline(best_iteration, color="k", ls=":", lw=1, label="kept iterate")
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_title(title)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    out = _save(fig, Path(path))
    plt.close(fig)
    return out


def plot_parameters(history: Sequence[Mapping], path: str | os.PathLike, names: Mapping[str, str] | None = None,
                    truth: Mapping[str, tuple[float, float]] | None = None) -> Path:
    """Trajectories of E (Pa, log scale) and nu per object, with ground truth as dashed lines.

    Args:
        history: per iteration ``E`` {object id (str): Pa} and ``nu`` {object id: value}.
        path: PNG to write.
        names: object id (str) -> display name.
        truth: object id (str) -> (E Pa, nu).
    """
    plt = _figure()
    fig, (ax_e, ax_n) = plt.subplots(1, 2, figsize=(9, 3.6))
    it = [h["iteration"] for h in history]
    ids = list(history[0]["E"]) if history else []
    names = names or {}
    for j, oid in enumerate(ids):
        c = f"C{j}"
        label = names.get(oid, f"object {oid}")
        ax_e.plot(it, [h["E"][oid] for h in history], color=c, marker=".", label=label)
        ax_n.plot(it, [h["nu"][oid] for h in history], color=c, marker=".", label=label)
        if truth and oid in truth:
            ax_e.axhline(truth[oid][0], color=c, ls="--", lw=1)
            ax_n.axhline(truth[oid][1], color=c, ls="--", lw=1)
    ax_e.set_yscale("log")
    ax_e.set_ylabel("Young's modulus E (Pa)")
    ax_n.set_ylabel("Poisson's ratio nu")
    for ax in (ax_e, ax_n):
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
    if ids:
        ax_e.legend(fontsize=7)
    fig.suptitle("material parameters (dashed: ground truth)")
    out = _save(fig, Path(path))
    plt.close(fig)
    return out
