"""Acceptance on the digital twin (issue #7): 5–7 pokes cut the held-out force magnitude error by
>= 60 % on twin units with manufacturing variation the shipped model does not know.

Needs the twin recorder with FE physics and a TRAINED model package (tools/train); skips without one
(synthetic/untrained packages do not count). The twin acceptance benchmark
(tools/recalib/twin_bench.py, docs/recalibration.md "Twin acceptance") does the work: per unit the
store holds the NOMINAL calibration, a guided 7-press recalibration session and a separate 10-poke
held-out session are recorded (FE, cached under <cache>/recalib/twin and <cache>/twin/fe, so a
rerun only replays), the shipped int8 model runs through the runtime pipeline, the correction is
fitted from the first 5, 6 and 7 accepted pokes and the held-out error is measured again.

Status with hiera-qup-128 (docs/BENCHMARKS.md § Recalibration): on a unit WITHOUT variation the
pokes remove >= 60 % of the model's own (gain-like) error — asserted; on the varied units the
acceptance is NOT met (the centre shift under the nominal calibration makes the model's error
scatter per poke) — a strict xfail, so it turns into a failure to remove once it is met.
Run: pytest -m slow tests/test_recalib_twin.py   (cold: ~1 h of FE + rendering; warm: ~10 min)
"""
import os

import numpy as np
import pytest

pytestmark = pytest.mark.slow

PHYSICS = os.environ.get("TENSORTOUCH_RECALIB_TWIN_PHYSICS", "fe")


def trained_package():
    from runtime.errors import ModelPackageError
    from runtime.model import find_package

    try:
        pkg = find_package(os.environ.get("TENSORTOUCH_RECALIB_MODEL"))
    except ModelPackageError as exc:
        pytest.skip(f"no trained model package installed ({exc})")
    if pkg.manifest.get("synthetic"):
        pytest.skip(f"model package {pkg.name} is synthetic/untrained; the acceptance needs a trained model")
    return pkg


@pytest.fixture(scope="module")
def bench():
    from tools.recalib.twin_bench import NOMINAL, UNITS, TwinBenchConfig, markdown, run_bench

    pkg = trained_package()
    res = run_bench(TwinBenchConfig(units=UNITS[:5], nominal=NOMINAL, physics=PHYSICS, model=str(pkg.folder),
                                    variants=()), say=print)
    print(markdown(res, "probe"))
    return res


def _reductions(row):
    return {n: row["held_out"]["probe"]["after"].get(n, {}).get("reduction", 0.0) for n in ("5", "6", "7")}


def test_nominal_unit_pokes_remove_the_models_own_gain_error(bench):
    nominal = bench["units"][0]
    assert nominal["nominal"] and nominal["held_out"]["probe"]["pokes"] >= 6
    for n, red in _reductions(nominal).items():
        assert nominal["by_pokes"][n]["stored"], (n, nominal["by_pokes"][n])
        assert red >= 0.6, (n, red)
    varied = bench["units"][1]                       # the replayed correction is what the runtime computes
    check = varied["runtime_check"]
    assert check["pipeline_mae_n"] == pytest.approx(check["replayed_correction_mae_n"], rel=0.05, abs=0.01)


@pytest.mark.xfail(strict=True, reason="issue #7 acceptance not met with hiera-qup-128: centre-shifted units "
                                       "(docs/BENCHMARKS.md § Recalibration)")
def test_twin_units_five_to_seven_pokes_cut_held_out_error_60_percent(bench):
    units = [r for r in bench["units"] if not r["nominal"]]
    assert len(units) >= 5
    red = {n: [_reductions(r)[n] for r in units] for n in ("5", "6", "7")}
    print({n: [f"{v:.0%}" for v in vals] for n, vals in red.items()})
    for n, vals in red.items():
        assert np.median(vals) >= 0.6, (n, red)
