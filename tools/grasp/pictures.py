"""A trial as a picture sequence (matplotlib sketch): per stage, the pinch seen from the side
(fingertip spheres, object sections) and both sensors' rendered frames with the contacts the
runtime published."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .figures import pyplot, save_figure


def trial_sequence(frames: list[dict], result, path: str | Path) -> Path:
    plt = pyplot()
    stages = [f for f in frames if f["label"] in ("pinch", "pull", "final")]
    fig, axes = plt.subplots(3, len(stages), figsize=(3.2 * len(stages), 8.2), squeeze=False)
    for col, f in enumerate(stages):
        snap = f["model"]
        tips = [np.asarray(t) * 1000 for t in snap["tips"]]
        n = tips[0] - tips[1]
        n /= np.linalg.norm(n)
        e = np.asarray(snap["objects"][0][1])
        v = np.cross(e, n)                      # drawing plane: across the pinch (v) × normal (n)
        mid = 0.5 * (tips[0] + tips[1])
        ax = axes[0, col]
        for t, name in zip(tips, ("thumb", "index")):
            p = (t - mid) @ v, (t - mid) @ n
            ax.add_patch(plt.Circle(p, snap["tip_radius"] * 1000, fc="#f2c14e", ec="k", alpha=0.6))
            ax.add_patch(plt.Circle(p, 12.0, fill=False, ec="#888", ls="--", lw=0.8))
            ax.text(p[0], p[1], name, ha="center", va="center", fontsize=7)
        for k, ((c, _), r) in enumerate(zip(snap["objects"], snap["radii"])):
            p = (np.asarray(c) * 1000 - mid) @ v, (np.asarray(c) * 1000 - mid) @ n
            col_ = "tab:red" if k == result.pulled else "tab:blue"
            ax.add_patch(plt.Circle(p, r * 1000, fc=col_, ec="k"))
        ax.set_xlim(-18, 18)
        ax.set_ylim(-26, 26)
        ax.set_aspect("equal")
        ax.set_title(f"{f['label']} (t = {f['t']:.2f} s)\ncores touching {f['touching'].astype(int).tolist()}", fontsize=8)
        ax.set_xlabel("across the pinch (mm)", fontsize=7)
        ax.tick_params(labelsize=6)
        for row, name in ((1, "thumb"), (2, "index")):
            ax = axes[row, col]
            ax.imshow(f["frames"][name])
            for p_mm, F, *_ in f["contacts"][name]:
                ax.text(2, 12 + 14 * len(ax.texts), f"({p_mm[0]:+.1f},{p_mm[1]:+.1f}) mm |F| {np.linalg.norm(F):.2f} N",
                        color="w", fontsize=6)
            ax.set_title(f"{name} sensor frame + published contacts", fontsize=7)
            ax.axis("off")
    gel = f"; at the end, gel indentation (mm; thumb, index × objects 0, 1) {result.gel_mm}" if result.gel_mm else ""
    fig.suptitle(f"{result.pair}: pulled object {result.pulled} (red), judged {result.judged}: {result.outcome}{gel}",
                 fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path, dpi=80)
