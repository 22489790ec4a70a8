"""Pictures of a pose selection: the two heatmaps and the contact cloud with both axes (and the
matplotlib set-up and saving the grasp pictures share)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .mount import MountResult


def pyplot():
    """matplotlib.pyplot on the Agg backend (files only, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int) -> Path:
    """Write `fig` as `path` (its folder made) and close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return path


def heatmaps(result: MountResult, path: str | Path) -> Path:
    """Left: mean thumb manipulability per (z, pitch); right: best-axis inliers per (z, pitch)."""
    plt = pyplot()
    cfg = result.config
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    for ax, what, title, fmt in ((axes[0], "mean_w", "mean manipulability √det(JJᵀ) [1e-4]", "{:.2f}"),
                                 (axes[1], "inliers", "principal inliers (1 cm axis)", "{:.0f}")):
        g = result.grid(what)
        shown = g * 1e4 if what == "mean_w" else g
        im = ax.imshow(shown, origin="lower", cmap="viridis", aspect="auto")
        ax.set_xticks(range(len(cfg.pitch_deg)), [f"{p:g}" for p in cfg.pitch_deg])
        ax.set_yticks(range(len(cfg.z_cm)), [f"{z:g}" for z in cfg.z_cm])
        ax.set_xlabel("pitch (deg)")
        ax.set_ylabel("z-offset (cm)")
        ax.set_title(title, fontsize=9)
        for (r, c), v in np.ndenumerate(shown):
            if np.isfinite(v):
                ax.text(c, r, fmt.format(v), ha="center", va="center", fontsize=6, color="w")
        ci = list(cfg.z_cm).index(result.chosen.z_cm), list(cfg.pitch_deg).index(result.chosen.pitch_deg)
        ax.add_patch(plt.Rectangle((ci[1] - 0.5, ci[0] - 0.5), 1, 1, fill=False, ec="r", lw=2))
        fig.colorbar(im, ax=ax, fraction=0.046)
    fig.tight_layout()
    return save_figure(fig, path, dpi=90)


def contacts_3d(result: MountResult, path: str | Path) -> Path:
    """Contact points of the chosen variant (blue), PCA axis (red), best inlier axis (green), mm."""
    plt = pyplot()
    v = result.chosen
    P = v.workspace.contact_points * 1000
    fig = plt.figure(figsize=(5, 4.5))
    ax = fig.add_subplot(projection="3d")
    if len(P):
        inl = v.best.inliers if v.best is not None else np.zeros(len(P), bool)
        ax.scatter(*P[~inl].T, s=4, c="tab:blue", alpha=0.5, label="contacts")
        ax.scatter(*P[inl].T, s=6, c="navy", label=f"inliers ({inl.sum()})")
        half = 0.6 * float(np.ptp(P, axis=0).max())
        for axis, col, name in ((v.pca, "r", "principal axis (PCA)"), (v.best, "g", "best inlier axis")):
            if axis is None:
                continue
            c = axis.point * 1000
            seg = np.stack([c - half * axis.direction, c + half * axis.direction])
            ax.plot(*seg.T, c=col, lw=2, label=name)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_title(f"z = {v.z_cm:g} cm, pitch = {v.pitch_deg:g}°: {v.n_contacts} contacts", fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    return save_figure(fig, path, dpi=90)
