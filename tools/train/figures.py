"""Figures of a build's evaluation (seed Fig. 10 and Fig. 11 styles) → PNGs under docs/.

- `docs/train_eval_fig11.png`: a held-out twin session through the runtime: predicted vs measured
  force (x, y, z, magnitude) over time, and predicted cluster position vs mocap tip (x, y, z);
- `docs/train_fields_fig10.png`: the 15 predicted channels (physical units) of the held-out frame
  with the largest measured force, beside the camera image and the FE ground truth is not shown
  (the runtime has none) — per-channel colour scale symmetric about 0.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def _docs() -> Path:
    from ...contracts.paths import ROOT

    return ROOT / "docs"


def fig11(eval_doc: dict, title: str, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tr = eval_doc["trace"]
    t = np.array([r["t"] for r in tr])
    meas = np.array([r["meas"] for r in tr])
    pred = np.array([r["pred"] for r in tr])
    rows = eval_doc["rows"]
    fig, ax = plt.subplots(4, 2, figsize=(11, 8.5))
    names = ["$F_x$", "$F_y$", "$F_z$", "$|F|$"]
    for i in range(4):
        m = meas[:, i] if i < 3 else np.linalg.norm(meas, axis=1)
        p = pred[:, i] if i < 3 else np.linalg.norm(pred, axis=1)
        ax[i, 0].plot(t, m, "k-", lw=1.2, label="measured (F/T)")
        ax[i, 0].plot(t, p, "C3-", lw=1.0, label="predicted (runtime, int8)")
        ax[i, 0].set_ylabel(f"{names[i]} (N)")
    ax[0, 0].legend(fontsize=8, loc="upper right")
    hit = [r for r in rows if not r["miss"]]
    if hit:
        th = np.array([r["t"] for r in hit])
        tip = np.array([r["tip"] for r in hit])
        pp = np.array([r["pred_pos"] for r in hit])
        for i, a in enumerate("xyz"):
            ax[i, 1].plot(th, tip[:, i], "k.", ms=3, label="mocap tip")
            ax[i, 1].plot(th, pp[:, i], "C0.", ms=3, label="cluster centroid")
            ax[i, 1].set_ylabel(f"{a} (mm)")
        ax[0, 1].legend(fontsize=8, loc="upper right")
        mf = np.linalg.norm([r["meas_force"] for r in rows], axis=1)
        pf = np.linalg.norm([r["pred_force"] for r in rows], axis=1)
        ax[3, 1].plot(mf, pf, "C3.", ms=3)
        lim = max(1.0, float(mf.max()), float(pf.max()))
        ax[3, 1].plot([0, lim], [0, lim], "k--", lw=0.8)
        ax[3, 1].set_xlabel("measured |F| (N)   [contact frames: predicted vs measured]")
        ax[3, 1].set_ylabel("predicted |F| (N)")
    for a in list(ax[:, 0]) + list(ax[:3, 1]):
        a.grid(alpha=0.3)
        a.set_xlim(float(t.min()), float(t.max()))
    ax[2, 1].set_xlabel("t (s)")
    ax[3, 0].set_xlabel("t (s)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def fig10(fields: np.ndarray, image: np.ndarray, title: str, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ...contracts.fields import CHANNEL_UNITS, CHANNELS

    fig, ax = plt.subplots(3, 6, figsize=(14, 7))
    ax[0, 0].imshow(image)
    ax[0, 0].set_title("camera frame", fontsize=8)
    for a in ax[1:, 0]:
        a.axis("off")
    for c in range(15):
        mod, comp = divmod(c, 3)
        a = ax[comp, mod + 1]
        v = float(np.abs(fields[c]).max()) or 1.0
        im = a.imshow(fields[c], cmap="RdBu_r", vmin=-v, vmax=v)
        a.set_title(f"{CHANNELS[c]} ({CHANNEL_UNITS[c]})", fontsize=8)
        fig.colorbar(im, ax=a, fraction=0.046, pad=0.02).ax.tick_params(labelsize=6)
    for a in ax.ravel():
        a.set_xticks([])
        a.set_yticks([])
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out


def write_figures(b, package, docs: Path | None = None) -> list[Path]:
    """Fig. 11 and Fig. 10 for the build's first held-out session."""
    from .build import unit_calibration
    from .evaluate import evaluate_session

    docs = docs or _docs()
    spec = b.cfg.heldout[0]
    doc = json.loads((b.root / "eval" / f"{spec.name}.json").read_text())
    title = f"{package.name} on held-out twin session {spec.name} (unit {spec.serial}, not in training)"
    paths = [fig11(doc, title, docs / "train_eval_fig11.png")]
    rows = doc["rows"]
    if rows:
        best = max(rows, key=lambda r: np.linalg.norm(r["meas_force"]))
        r = evaluate_session(b.session(spec), package, unit_calibration(b, spec.serial), keep_fields_at=best["frame"])
        if r["kept"] is not None:
            f = np.linalg.norm(best["meas_force"])
            paths.append(fig10(r["kept"]["fields"], r["kept"]["image"],
                               f"{package.name}: 15 predicted channels, {spec.name} frame {best['frame']} "
                               f"(measured |F| = {f:.2f} N)", docs / "train_fields_fig10.png"))
    log.info("figures: %s", [str(p) for p in paths])
    return paths
