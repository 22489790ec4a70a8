"""The minimum-detectable-effect check on synthetic sessions (fast path, no network):

    python -m tests.workbench_mdecheck [--draws 10] [--effect strain_stiffening]

Per draw (its own plan and noise, a floor correlated within presses like a real model's): the MDE
of the effect on the unaltered session (its own shape), then the same session with a hidden effect of 2× and of 0.5× that size
(rms of the effect's own contribution, N). Found = the verdict names the effect; claimed = any
significant verdict. The hidden forms come from tests/workbench_synth.py (independent of the library).
"""
from __future__ import annotations

import argparse
import json

import numpy as np
from tensortouch.runtime.stages.effects import Registry
from tensortouch.tools.workbench.diagnose import diagnose
from tensortouch.tools.workbench.table import SampleTable

from tests.workbench_synth import alter, synth_table

UNIT = {"strain_stiffening": ("k", {}), "temperature_softening": ("alpha", {"t_ref": 22.0}),
        "rim_stiffening": ("a", {"w": 3.0})}


def press_floor(table: SampleTable, seed: int, rel: float = 0.05) -> SampleTable:
    """The measurement plus a per-press random gain error of the model (a floor correlated within
    presses, as a trained model's is)."""
    rng = np.random.default_rng(500 + seed)
    on = table.cols["depth"] > 0
    press = np.cumsum(np.r_[on[0], np.diff(on.astype(int)) == 1])
    g = rng.normal(0.0, rel, press.max() + 1)[press]
    meas = table.meas + table.model * g[:, None]
    return SampleTable(table.cols, meas, table.model, table.vec, table.meta)


def rms(x):
    return float(np.sqrt(np.mean(np.sum(np.asarray(x) ** 2, axis=1))))


def with_effect(null: SampleTable, name: str, size: float) -> SampleTable:
    """`null` with the hidden effect scaled so its own contribution has rms `size` N."""
    key, fixed = UNIT[name]
    cov = dict(null.cols, normal=null.vec["normal"])
    unit = rms(alter(null.model, cov, [(name, {key: 1.0, **fixed})])[0] - null.model)
    f, _ = alter(null.model, cov, [(name, {key: size / unit, **fixed})])
    return SampleTable(null.cols, null.meas + (f - null.model), null.model, null.vec, null.meta)


def draw(seed: int, name: str, registry, n_pokes: int = 30) -> dict:
    null = press_floor(synth_table(seed, n_pokes=n_pokes, rate=25.0, noise=0.01), seed)
    m = diagnose(null, registry).mde
    mde = m["per_effect"][name]
    row = {"seed": seed, "mde": mde, "floor": m["floor"], "session_mde": m["mde"]}
    for mult in (2.0, 0.5):
        d = diagnose(with_effect(null, name, mult * mde), registry)
        v = d.verdict
        row[f"x{mult:g}"] = v.effect.name if v else None
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.workbench_mdecheck")
    p.add_argument("--draws", type=int, default=10)
    p.add_argument("--effect", default="strain_stiffening", choices=sorted(UNIT))
    p.add_argument("--first-seed", type=int, default=200)
    a = p.parse_args(argv)
    reg = Registry.default(entry_points=False)
    rows = []
    for s in range(a.draws):
        rows.append(draw(a.first_seed + s, a.effect, reg))
        print(json.dumps(rows[-1]), flush=True)
    found = np.mean([r["x2"] == a.effect for r in rows])
    claimed = np.mean([r["x0.5"] is not None for r in rows])
    print(json.dumps({"effect": a.effect, "draws": len(rows), "found_at_2x": found, "claimed_at_0.5x": claimed}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
