"""The model side of a comparison: something that predicts the contact force per sample.

`ForceModel` is pluggable: anything with `name`, `fingerprint()` and `predict(table) -> (N,3) N`.
Until the trained network is wired in, the default is `ContactLaw`, the nominal quasi-static
contact mechanics of each indenter fitted once on a calibration session (no effects in it):

    F = Fn(depth) * g(theta) * normal + c_t * sqrt(depth) * slip_vec,   |tangential| <= mu * Fn
    Fn = monotone piecewise-linear in depth (non-negative hat weights, Fn(0) = 0)
    g  = piecewise-linear positive gain over the contact angle θ (FE gels are stiffer near the rim)

per indenter name (Hertz/Mindlin-like, but the force-depth curve is learned, so an FE-made or a
real gel's curve fits too). `fit_sessions` fits it on several calibration sessions at once (their
rows pooled per indenter name), so sessions that each press with some of the indenters together
cover them all; a session pressing with an indenter no calibration session used is refused by
`predict` (one line naming the indenter and the sessions it was fitted on). Stored as JSON; the
workbench caches raw predictions by fingerprint.
"""
from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import lsq_linear

from ...contracts.errors import TensorTouchError
from ...contracts.files import atomic_write_json
from .scan import hat_basis
from .table import SampleTable

log = logging.getLogger(__name__)


@dataclass
class LawConfig:
    knots: int = 10
    theta_knots: int = 4          # smooth stiffness change over the gel (θ); 1 = none
    iterations: int = 4           # alternating fits of the depth curve and the θ gain
    mu: float = 2.2               # the model's friction coefficient (seed's mu)


@dataclass
class ContactLaw:
    """Per indenter name: depth knots, normal-force weights, tangential stiffness coefficient."""

    laws: dict = field(default_factory=dict)   # name -> {"knots": [...], "w": [...], "ct": float}
    mu: float = 2.2
    source: str = ""
    name: str = "contact-law"

    def fingerprint(self) -> str:
        return hashlib.sha256(json.dumps({"laws": self.laws, "mu": self.mu}, sort_keys=True).encode()).hexdigest()[:16]

    @staticmethod
    def _kinds(table: SampleTable) -> np.ndarray:
        names = table.meta.get("indenters", {})
        return np.array([names.get(str(int(s)), f"indenter{int(s)}") for s in table.cols["series"]])

    @classmethod
    def fit(cls, table: SampleTable, cfg: LawConfig | None = None, source: str = "") -> "ContactLaw":
        cfg = cfg or LawConfig()
        kinds = cls._kinds(table)
        d = table.cols["depth"]
        n = table.vec["normal"]
        sv = table.vec["slip_vec"]
        laws = {}
        for kind in np.unique(kinds):
            m = (kinds == kind) & (d > 0)
            if m.sum() < 3 * cfg.knots:
                log.warning("contact law: indenter %s has only %d contact samples; skipped", kind, m.sum())
                continue
            knots = np.concatenate([[0.0], np.quantile(d[m], np.linspace(0.1, 1.0, cfg.knots - 1))])
            knots = np.unique(knots)
            th = table.cols["theta"][m]
            tknots = np.unique(np.quantile(th, np.linspace(0.0, 1.0, cfg.theta_knots)))
            T = hat_basis(th, tknots) if len(tknots) > 1 else np.ones((len(th), 1))
            B = hat_basis(d[m], knots)[:, 1:]                       # Fn(0) = 0
            tang = np.sqrt(d[m])[:, None] * sv[m]
            y = table.meas[m].reshape(-1)
            gain = np.ones(len(th))
            for _ in range(cfg.iterations):  # alternate: force-depth curve, then gain over θ
                X = np.concatenate([(B * gain[:, None])[:, None, :] * n[m][:, :, None], tang[:, :, None]],
                                   axis=2).reshape(-1, B.shape[1] + 1)
                lo = np.r_[np.zeros(B.shape[1]), -np.inf]
                sol = lsq_linear(X, y, bounds=(lo, np.full(B.shape[1] + 1, np.inf)))
                w, ct = np.maximum.accumulate(sol.x[:-1]), float(sol.x[-1])  # monotone curve
                if T.shape[1] == 1:
                    break
                fn0 = B @ w
                Xg = (T * fn0[:, None])[:, None, :] * n[m][:, :, None]
                yg = (table.meas[m] - ct * tang).reshape(-1)
                v = lsq_linear(Xg.reshape(-1, T.shape[1]), yg, bounds=(0.0, np.inf)).x
                v = v / max(float(np.mean(T @ v)), 1e-12)           # gain averages 1 on the data
                gain = T @ v
            law = {"knots": knots.tolist(), "w": [0.0] + w.tolist(), "ct": ct}
            if T.shape[1] > 1:
                law.update({"theta_knots": tknots.tolist(), "theta_gain": v.tolist()})
            laws[str(kind)] = law
            log.info("contact law %s: Fn(%.2f mm) = %.3f N, ct = %.3f", kind, knots[-1], w[-1], ct)
        if not laws:
            raise TensorTouchError("contact law: no indenter has enough contact samples to fit")
        return cls(laws, cfg.mu, source)

    @classmethod
    def fit_sessions(cls, tables: list, sources: list, cfg: LawConfig | None = None) -> "ContactLaw":
        """One law per indenter name over the rows of several sessions' tables (pooled)."""
        if not tables:
            raise TensorTouchError("contact law: no calibration session given")
        return cls.fit(pool_tables(tables), cfg, source="fitted on " + ", ".join(str(s) for s in sources))

    def covers(self, table: SampleTable) -> list[str]:
        """The indenter names the table presses with that the law has no curve for."""
        kinds = self._kinds(table)
        pressed = np.unique(kinds[table.cols["depth"] > 0]) if len(kinds) else []
        return sorted(str(k) for k in pressed if str(k) not in self.laws)

    def predict(self, table: SampleTable) -> np.ndarray:
        kinds = self._kinds(table)
        d = table.cols["depth"]
        n = table.vec["normal"]
        sv = table.vec["slip_vec"]
        out = np.zeros((len(table), 3))
        for kind in map(str, np.unique(kinds)):
            if kind not in self.laws:
                raise TensorTouchError(f"contact law ({self.source}): the session presses with indenter {kind!r}, "
                                       f"which none of its calibration sessions used (it knows {sorted(self.laws)}); "
                                       f"add a calibration session with {kind} to --model-from")
            law = self.laws[kind]
            m = kinds == kind
            knots = np.asarray(law["knots"])
            dm = np.clip(d[m], 0.0, None)
            fn = np.interp(dm, knots, law["w"], right=np.nan)
            over = np.isnan(fn)  # beyond the calibrated range: extend the last slope
            if over.any():
                slope = (law["w"][-1] - law["w"][-2]) / max(knots[-1] - knots[-2], 1e-9)
                fn[over] = law["w"][-1] + slope * (dm[over] - knots[-1])
            if "theta_knots" in law:
                fn = fn * np.interp(table.cols["theta"][m], law["theta_knots"], law["theta_gain"])
            ft = law["ct"] * np.sqrt(dm)[:, None] * sv[m]
            ftm = np.linalg.norm(ft, axis=1)
            cap = self.mu * fn
            ft *= np.where(ftm > cap, cap / np.maximum(ftm, 1e-12), 1.0)[:, None]
            out[m] = fn[:, None] * n[m] + ft
        out[d <= 0] = 0.0
        return out

    def save(self, path: str | Path) -> None:
        atomic_write_json(path, {"schema": "tensortouch.contact_law", "mu": self.mu, "source": self.source,
                                 "laws": self.laws}, indent=2)

    @classmethod
    def load(cls, path: str | Path) -> "ContactLaw":
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise TensorTouchError(f"{path}: cannot read the contact-law model ({exc})") from None
        if data.get("schema") != "tensortouch.contact_law":
            raise TensorTouchError(f"{path}: schema {data.get('schema')!r}, expected 'tensortouch.contact_law'")
        return cls(data["laws"], float(data["mu"]), data.get("source", str(path)))


def pool_posts(posts: list, sizes: list[int]):
    """One correction for the rows of pooled tables (`pool_tables`): each table's `post` (None = none)
    on its own rows, in order. None when no table has one."""
    if all(p is None for p in posts):
        return None
    edges = np.cumsum(sizes)[:-1]

    def post(x):
        parts = np.split(np.asarray(x), edges)
        return np.concatenate([p(part) if p is not None else part for p, part in zip(posts, parts)])
    return post


def pool_tables(tables: list) -> SampleTable:
    """The rows of several sessions' tables as one table for the contact-law fit: the columns and
    vectors all of them have, series renumbered so each keeps its indenter name."""
    cols = set.intersection(*(set(t.cols) for t in tables))
    vecs = set.intersection(*(set(t.vec) for t in tables))
    names, series = {}, []
    for i, t in enumerate(tables):
        own = t.meta.get("indenters", {})
        s = np.asarray(t.cols["series"]).astype(int)
        new = 1000 * i + s
        for old in np.unique(s):
            names[str(int(1000 * i + old))] = own.get(str(int(old)), f"indenter{int(old)}")
        series.append(new)
    c = {k: np.concatenate([np.asarray(t.cols[k]) for t in tables]) for k in cols}
    c["series"] = np.concatenate(series)
    return SampleTable(c, np.concatenate([t.meas for t in tables]), np.concatenate([t.model for t in tables]),
                       {k: np.concatenate([t.vec[k] for t in tables]) for k in vecs}, {"indenters": names})
