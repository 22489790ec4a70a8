"""Pictures and the HTML report of a comparison (matplotlib, Agg; small PNGs).

residual_map.png   signed normal-force residual over the gel (θ/φ, polar view), contact samples
residual_vs.png    residual vs depth, loading rate, slip, temperature, time, load history,
                   brightness
timeline.png       measured vs predicted |F| and residual over the session
worst.jpg          the worst samples with their camera frames
position.png       contact position error (network path: cluster centroid − mocap tip, mm)
before_after.png   error per axis before/after (when a previous comparison is given)

From a diagnosis (`tensortouch diagnose --pictures DIR`):
covariates.png     every covariate ranked by the held-out partial R² of the residual on it
residual_top.png   the residual against the top covariate (along it, for a vector such as velocity)
shape.png          the verdict's fitted shape next to its family's other member (gain vs its covariate,
                   or the relaxation after a step)
"""
from __future__ import annotations

import html
import json
import logging
from pathlib import Path

import numpy as np

from ...contracts.files import atomic_write, atomic_write_json, atomic_write_text

log = logging.getLogger(__name__)

DPI = 72
MAX_POINTS = 2500
PANELS = (("depth", "depth (mm)"), ("rate", "loading rate (mm/s)"), ("slip", "slip (mm)"),
          ("temperature", "temperature (°C)"), ("time", "time (s)"), ("load_history", "max depth − depth (mm)"),
          ("brightness", "frame brightness (rel.)"), ("rim_distance", "distance to rim (mm)"))


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> str:
    """Lay the figure out, write it to `path` (a temporary file renamed into place) and close it; returns the file name."""
    fig.tight_layout()
    kw = {"pil_kwargs": {"quality": 80}} if path.suffix == ".jpg" else {}
    atomic_write(path, lambda fh: fig.savefig(fh, format=path.suffix[1:], dpi=DPI, **kw))
    _plt().close(fig)
    return path.name


def normal_residual(comp) -> np.ndarray:
    r = comp.table.meas - comp.pred
    n = comp.table.vec.get("normal")
    return np.sum(r * n, axis=1) if n is not None else np.linalg.norm(r, axis=1)


def residual_map(comp, path: Path) -> str:
    plt = _plt()
    c = comp.table.cols
    m = c["depth"] > 0
    rn = normal_residual(comp)
    fig, ax = plt.subplots(figsize=(4.6, 4.0))
    x, y = c["theta"][m] * np.cos(c["phi"][m]), c["theta"][m] * np.sin(c["phi"][m])
    lim = max(float(np.quantile(np.abs(rn[m]), 0.98)) if m.any() else 1e-3, 1e-3)
    sc = ax.scatter(x, y, c=rn[m], s=4, cmap="coolwarm", vmin=-lim, vmax=lim)
    fig.colorbar(sc, ax=ax, label="normal-force residual (N)")
    ax.set_aspect("equal")
    ax.set_xlabel("θ cos φ (rad)")
    ax.set_ylabel("θ sin φ (rad)")
    ax.set_title("residual over the gel (contact samples)")
    return _save(fig, path)


def residual_vs(comp, path: Path) -> str:
    plt = _plt()
    cov = comp.table.cov()
    rn = normal_residual(comp)
    contact = comp.table.cols["depth"] > 0
    panels = [(k, lab) for k, lab in PANELS if k in cov]
    fig, axes = plt.subplots(2, (len(panels) + 1) // 2, figsize=(3.0 * ((len(panels) + 1) // 2), 5.2), squeeze=False)
    for ax, (key, label) in zip(axes.ravel(), panels):
        v = np.asarray(cov[key], dtype=np.float64)
        if key == "brightness":
            ok = np.isfinite(v)
            g = comp.chain.image_gain(cov, len(v))
            ax.plot(cov["time"][ok], v[ok] - g[ok], ".", ms=2)
            ax.set_xlabel("time (s)")
            ax.set_ylabel("brightness residual")
            continue
        sel = contact if key not in ("time",) else np.ones_like(contact)
        show = np.flatnonzero(sel)
        if len(show) > MAX_POINTS:  # keep the PNG small: plot a fixed subsample, bin all points
            show = show[np.linspace(0, len(show) - 1, MAX_POINTS).astype(int)]
        ax.plot(v[show], rn[show], ".", ms=1.5, alpha=0.4)
        if sel.sum() > 20:
            edges = np.unique(np.quantile(v[sel], np.linspace(0, 1, 13)))
            idx = np.clip(np.searchsorted(edges, v[sel], side="right") - 1, 0, len(edges) - 2)
            med = [np.median(rn[sel][idx == i]) if np.any(idx == i) else np.nan for i in range(len(edges) - 1)]
            ax.plot(0.5 * (edges[1:] + edges[:-1]), med, "-", color="C3", lw=2)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(label)
        ax.set_ylabel("residual (N)")
    for ax in axes.ravel()[len(panels):]:
        ax.axis("off")
    fig.suptitle("normal-force residual vs covariates (red: binned median)")
    return _save(fig, path)


def timeline(comp, path: Path) -> str:
    plt = _plt()
    t = comp.table.cols["time"]
    s = comp.table.cols.get("indenter", comp.table.cols["series"])   # network tables: series = contact track
    fig, ax = plt.subplots(2, 1, figsize=(8, 4.2), sharex=True)
    for k in np.unique(s)[:2]:
        m = s == k
        ax[0].plot(t[m], np.linalg.norm(comp.table.meas[m], axis=1), lw=0.8, label=f"measured #{int(k)}")
        ax[0].plot(t[m], np.linalg.norm(comp.pred[m], axis=1), lw=0.8, ls="--", label=f"model #{int(k)}")
        ax[1].plot(t[m], np.linalg.norm(comp.table.meas[m] - comp.pred[m], axis=1), lw=0.6)
    ax[0].set_ylabel("|F| (N)")
    ax[0].legend(fontsize=7, ncol=4)
    ax[1].set_ylabel("|residual| (N)")
    ax[1].set_xlabel("time (s)")
    return _save(fig, path)


def _frame_at(session_path: Path, t: float):
    try:
        import cv2

        from ...contracts.session import load_session

        s = load_session(session_path, check_frames=False)
        fr = s.table("frames")
        i = int(np.argmin(np.abs(fr[:, 0] - t)))
        kind, src = s.image_source()
        if kind == "video":
            cap = cv2.VideoCapture(str(src))
            cap.set(cv2.CAP_PROP_POS_FRAMES, int(fr[i, 1]))
            ok, img = cap.read()
            cap.release()
            return img[:, :, ::-1] if ok else None
        img = cv2.imread(str(src / f"{int(fr[i, 1]):06d}.png"), cv2.IMREAD_COLOR)
        return None if img is None else img[:, :, ::-1]
    except Exception as exc:  # pictures are best effort; the numbers are in summary.json
        log.warning("frame at t=%.2f s unavailable: %s", t, exc)
        return None


def worst(comp, path: Path, session_path: Path | None, k: int = 6) -> tuple[str, list[dict]]:
    plt = _plt()
    err = np.linalg.norm(comp.table.meas - comp.pred, axis=1)
    order = np.argsort(-err)
    picked, times = [], []
    for i in order:  # one per second of the session, so the worst are not all one press
        t = comp.table.cols["time"][i]
        if all(abs(t - u) > 1.0 for u in times):
            picked.append(int(i))
            times.append(t)
        if len(picked) >= k:
            break
    fig, axes = plt.subplots(1, len(picked), figsize=(1.8 * max(len(picked), 1), 2.0), squeeze=False)
    rows = []
    for ax, i in zip(axes[0], picked):
        c = comp.table.cols
        img = _frame_at(session_path, float(c["t"][i])) if session_path else None
        if img is not None:
            h, w = img.shape[:2]
            r = min(h, w) // 2
            ax.imshow(img[h // 2 - r:h // 2 + r:2, w // 2 - r:w // 2 + r:2])
        ax.set_title(f"t={c['time'][i]:.1f}s |r|={err[i]:.2f}N", fontsize=7)
        ax.axis("off")
        rows.append({"time": float(c["time"][i]), "indenter": int(c.get("indenter", c["series"])[i]),
                     "error_n": float(err[i]),
                     "depth_mm": float(c["depth"][i]), "measured": comp.table.meas[i].tolist(),
                     "predicted": comp.pred[i].tolist()})
    return _save(fig, path), rows


def position_residuals(comp, path: Path) -> str | None:
    """Contact position error (cluster centroid − mocap tip, mm) per axis and over the gel."""
    pos = comp.table.vec.get("position_residual")
    if pos is None:
        return None
    c = comp.table.cols
    ok = np.all(np.isfinite(pos), axis=1) & (c.get("mocap_depth", c["depth"]) > 0)
    if not ok.any():
        return None
    plt = _plt()
    fig, ax = plt.subplots(1, 2, figsize=(8.4, 3.4))
    for j, axis in enumerate("xyz"):
        ax[0].hist(pos[ok, j], bins=40, histtype="step", label=f"{axis}: mean |e| {np.mean(np.abs(pos[ok, j])):.2f} mm")
    ax[0].set_xlabel("cluster centroid − mocap tip (mm)")
    ax[0].legend(fontsize=7)
    tip = comp.table.vec["tip"][ok]
    sc = ax[1].scatter(tip[:, 0], tip[:, 1], c=np.linalg.norm(pos[ok], axis=1), s=4, cmap="viridis")
    fig.colorbar(sc, ax=ax[1], label="position error (mm)")
    ax[1].set_aspect("equal")
    ax[1].set_xlabel("x (mm)")
    ax[1].set_ylabel("y (mm)")
    ax[1].set_title("contact position error over the gel")
    return _save(fig, path)


def before_after(prev: dict, cur: dict, path: Path) -> str:
    plt = _plt()
    keys = ["rms_x", "rms_y", "rms_z", "rms_vector", "mae_magnitude"]
    a = [prev["force_error"][k] for k in keys]
    b = [cur["force_error"][k] for k in keys]
    fig, ax = plt.subplots(figsize=(5.5, 3.0))
    x = np.arange(len(keys))
    ax.bar(x - 0.2, a, 0.4, label=f"before ({len(prev.get('effects', []))} effects)")
    ax.bar(x + 0.2, b, 0.4, label=f"after ({len(cur.get('effects', []))} effects)")
    ax.set_xticks(x, ["rms x", "rms y", "rms z", "rms |r|", "mean ||F|-|F'||"], fontsize=8)
    ax.set_ylabel("force error (N)")
    ax.legend(fontsize=8)
    return _save(fig, path)


def _table_html(err: dict) -> str:
    cells = "".join(f"<tr><td>{html.escape(k)}</td><td>{v:.4g}</td></tr>" for k, v in err.items()
                    if isinstance(v, float))
    return f"<table border=1 cellpadding=3>{cells}</table>"


def write_report(comp, out: Path, session_path: Path | None = None, previous: dict | None = None) -> Path:
    """summary.json, PNGs and report.html into `out`; returns the HTML path."""
    out.mkdir(parents=True, exist_ok=True)
    pics = [residual_map(comp, out / "residual_map.png"), residual_vs(comp, out / "residual_vs.png"),
            timeline(comp, out / "timeline.png")]
    pos = position_residuals(comp, out / "position.png")
    if pos:
        pics.append(pos)
    wname, wrows = worst(comp, out / "worst.jpg", session_path)
    pics.append(wname)
    comp.summary["worst_samples"] = wrows
    parts = [f"<h1>TensorTouch compare: {html.escape(str(comp.summary.get('session', '')))}</h1>",
             (f"<p>sensor {html.escape(str(comp.summary.get('sensor_id', '')))}, calibration "
             f"{html.escape(str(comp.summary.get('calibration_version', '')))}, model "
             f"{html.escape(json.dumps(comp.summary.get('model', {})))}</p>"),
             f"<p>enabled effects: {html.escape(', '.join(e['name'] for e in comp.summary['effects']) or 'none')}</p>",
             "<h2>Force error, all samples (N)</h2>", _table_html(comp.summary["force_error"]),
             "<h2>Force error, contact samples (N)</h2>", _table_html(comp.summary["force_error_contact"])]
    if comp.summary.get("position_error"):
        parts += ["<h2>Contact position error (mm)</h2>", _table_html(comp.summary["position_error"])]
    if previous is not None:
        comp.summary["before"] = {"effects": previous.get("effects", []), "force_error": previous["force_error"]}
        pics.append(before_after(previous, comp.summary, out / "before_after.png"))
        rows = "".join(f"<tr><td>{k}</td><td>{previous['force_error'][k]:.4g}</td><td>{v:.4g}</td>"
                       f"<td>{100 * (v / previous['force_error'][k] - 1):+.0f} %</td></tr>"
                       for k, v in comp.summary["force_error"].items()
                       if isinstance(v, float) and previous["force_error"].get(k))
        parts += [("<h2>Before / after</h2><table border=1 cellpadding=3><tr><th>error</th><th>before</th>"
                  f"<th>after</th><th>change</th></tr>{rows}</table>")]
    parts += [f'<h2>{html.escape(p.rsplit(".", 1)[0].replace("_", " "))}</h2><img src="{p}">' for p in pics]
    page = "<!doctype html><meta charset=utf-8><title>compare</title>" + "\n".join(parts)
    atomic_write_text(out / "report.html", page)
    atomic_write_json(out / "summary.json", comp.summary, indent=2, default=float)
    return out / "report.html"


def covariate_ranking(diag, path: Path, top: int = 12) -> str:
    """Horizontal bars: held-out partial R² per covariate (what remains after the verdict)."""
    plt = _plt()
    rows = diag.scan[:top][::-1]
    fig, ax = plt.subplots(figsize=(4.6, 0.25 * len(rows) + 1.0))
    ax.barh([r["covariate"] for r in rows], [max(r["score"], 0.0) for r in rows],
            color=["C3" if r.get("p_adjusted", 1.0) <= 0.05 else "C0" for r in rows])
    ax.set_xlabel("held-out partial R² of the residual")
    u = diag.unexplained
    ax.set_title(f"top: {u.get('covariate')} (p = {u.get('p_adjusted', 1.0):.2g}); red: p ≤ 0.05", fontsize=9)
    return _save(fig, path)


def residual_vs_covariate(table, diag, path: Path, name: str | None = None) -> str:
    """The residual that remains against one covariate (default: the top one); for a vector
    covariate the residual component along it against its magnitude. Red: binned median."""
    from .table import SCAN_VECTORS

    plt = _plt()
    name = name or diag.unexplained.get("covariate")
    cov = table.cov()
    r = np.asarray(diag.residual)
    if name in SCAN_VECTORS:
        v = np.column_stack([np.asarray(cov[k], dtype=np.float64) for k in SCAN_VECTORS[name][0]])
        x = np.linalg.norm(v, axis=1)
        y = np.sum(r * v, axis=1) / np.maximum(x, 1e-12)
        xl, yl = f"|{name}| ({SCAN_VECTORS[name][1]})", f"residual along {name} (N)"
    else:
        x = np.asarray(cov[name], dtype=np.float64)
        n = table.vec.get("normal")
        y = np.sum(r * n, axis=1) if n is not None else np.linalg.norm(r, axis=1)
        xl, yl = name, "normal-force residual (N)"
    ok = np.flatnonzero(np.isfinite(x))
    show = ok if len(ok) <= MAX_POINTS else ok[np.linspace(0, len(ok) - 1, MAX_POINTS).astype(int)]
    fig, ax = plt.subplots(figsize=(4.2, 3.0))
    ax.plot(x[show], y[show], ".", ms=1.5, alpha=0.4)
    edges = np.unique(np.quantile(x[ok], np.linspace(0, 1, 13)))
    if len(edges) > 2:
        idx = np.clip(np.searchsorted(edges, x[ok], side="right") - 1, 0, len(edges) - 2)
        med = [np.median(y[ok][idx == i]) if np.any(idx == i) else np.nan for i in range(len(edges) - 1)]
        ax.plot(0.5 * (edges[1:] + edges[:-1]), med, "-", color="C3", lw=2)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel(xl)
    ax.set_ylabel(yl)
    return _save(fig, path)


def _gain_curve(effect, params: dict, table, n: int = 120):
    """(x, gain, label) of a gain-type effect over the range of the covariate it reads."""
    cov = table.cov()
    fam = effect.family or effect.name
    if fam == "strain_stiffening":
        x = np.linspace(0.0, float(np.max(cov["depth"])), n)
        sub = {"depth": x, "gel_height": np.full(n, float(np.median(cov["gel_height"])))}
        label = "depth (mm)"
    elif fam == "mullins_softening":
        x = np.linspace(0.0, float(np.max(cov["max_depth"])), n)
        sub = {"depth": np.zeros(n), "max_depth": x}
        label = "max depth − depth (mm)"
    else:
        key = next((c for c in effect.covariates if c in cov and np.ndim(cov[c]) == 1), None)
        if key is None:
            return None
        v = np.asarray(cov[key], dtype=np.float64)
        x = np.linspace(float(np.nanmin(v)), float(np.nanmax(v)), n)
        sub = {k: np.full(n, float(np.nanmedian(np.asarray(c, dtype=np.float64))))
               for k, c in cov.items() if np.ndim(c) == 1 and len(c) == len(v) and np.issubdtype(np.asarray(c).dtype, np.number)}
        sub[key] = x
        label = key
    unit = np.tile([0.0, 0.0, 1.0], (n, 1))
    sub.update({"normal": unit, "series": np.zeros(n), "time": sub.get("time", np.zeros(n))})
    g = effect.forward(unit, sub, params)[:, 2]
    return x, g, label


def effect_shape(score, table, path: Path) -> str:
    """The fitted shape of a verdict and of its family's other member(s): the force gain against the
    covariate the effect reads, or for a relaxation the force after a 1 N step held 20 s."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(4.2, 3.0))
    members = [(score, "-")] + [(a, "--") for a in getattr(score, "alternatives", [])]
    for s, style in members:
        e = s.effect
        tag = f"{e.name} (held-out {s.after:.3g} {s.unit})"
        if e.sequential:
            t = np.linspace(0.0, 20.0, 400)
            x = np.tile([0.0, 0.0, 1.0], (len(t), 1))
            y = e.forward(x, {"time": t}, s.params)[:, 2]
            ax.plot(t, y, style, label=tag)
            ax.set_xlabel("time after a 1 N step (s)")
            ax.set_ylabel("force (N)")
            continue
        curve = _gain_curve(e, s.params, table)
        if curve is None:
            continue
        x, g, label = curve
        ax.plot(x, g, style, label=tag)
        ax.set_xlabel(label)
        ax.set_ylabel("force gain")
    ax.legend(fontsize=7)
    ax.set_title(f"fitted shape: {score.effect.family or score.effect.name}", fontsize=9)
    return _save(fig, path)
