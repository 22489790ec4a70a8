"""A trial as a picture sequence (matplotlib sketch): per stage, the pinch seen from the side
(fingertip spheres, object sections) and both sensors' rendered frames with the contacts the
runtime published."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .figures import pyplot


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
            ax.annotate(f"{'pulled' if k == result.pulled else 'other'} {2000 * r:.1f} mm", p,
                        xytext=(0, 9 if k % 2 == 0 else -13), textcoords="offset points", ha="center", fontsize=7,
                        color=col_, bbox={"fc": "w", "ec": "none", "alpha": 0.8, "pad": 0.5})
        ax.set_xlim(-18, 18)
        ax.set_ylim(-26, 26)
        ax.set_aspect("equal")
        ax.set_title(f"{f['label']} (t = {f['t']:.2f} s)\ncores touching {f['touching'].astype(int).tolist()}", fontsize=8)
        ax.set_xlabel("across the pinch (mm)", fontsize=7)
        ax.tick_params(labelsize=6)
        for row, name in ((1, "thumb"), (2, "index")):
            ax = axes[row, col]
            ax.imshow(f["frames"][name])
            for j, (p_mm, F, *_) in enumerate(f["contacts"][name]):
                ax.text(3, 4 + 16 * j, f"contact {j + 1}: ({p_mm[0]:+.1f}, {p_mm[1]:+.1f}) mm, |F| {np.linalg.norm(F):.2f} N",
                        color="k", fontsize=7, va="top", bbox={"fc": "w", "ec": "none", "alpha": 0.85, "pad": 1.0})
            if not f["contacts"][name]:
                ax.text(3, 4, "no contact published", color="k", fontsize=7, va="top",
                        bbox={"fc": "w", "ec": "none", "alpha": 0.85, "pad": 1.0})
            ax.set_title(f"{name} sensor frame + published contacts", fontsize=7)
            ax.axis("off")
    gel = ""
    if result.gel_mm:
        g = np.round(np.asarray(result.gel_mm, float), 2).tolist()
        gel = f"\nat the end, gel indentation (mm; thumb, index × objects 0, 1) {g}"
    task = getattr(result, "task", None) or {}
    drawn = ""
    if getattr(result, "randomized", False) and task:
        drawn = (f"\nrandomized seed {result.seed}: shift {task['shift_mm'][0]:+.1f}/{task['shift_mm'][1]:+.1f} mm, "
                 f"yaw {task['yaw_deg']:+.0f}°, pull {task['pull_n']:.2f} N at {task['pull_tilt_deg']:+.0f}°, "
                 f"friction {task['friction']:.2f}, {task['contact']} contact")
    why = f" ({result.cause})" if result.cause else ""
    fig.suptitle(f"{result.pair}: pulled object {result.pulled} (red), judged {result.judged}: {result.outcome}{why}"
                 f"{gel}{drawn}", fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    return _save_small(fig, path, dpi=80)


def _save_small(fig, path: str | Path, dpi: int) -> Path:
    """The figure as a 256-colour PNG (the sensor frames make a full-colour one ~0.5 MB), written atomically."""
    import io

    from PIL import Image

    from ...contracts.files import atomic_write
    from .figures import pyplot

    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format="png")
    pyplot().close(fig)
    small = io.BytesIO()
    Image.open(buf).convert("RGB").quantize(256).save(small, format="PNG", optimize=True)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, small.getvalue())
    return path
