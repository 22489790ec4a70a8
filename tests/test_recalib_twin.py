"""Acceptance on the digital twin (issue #7): 5–7 pokes cut the held-out force magnitude error by
>= 60 % on twin units with manufacturing variation the shipped model does not know.

Needs the twin recorder with FE physics and a TRAINED model package (tools/train); skips without one
(synthetic/untrained packages do not count). The twin acceptance benchmark
(tools/recalib/twin_bench.py, docs/recalibration.md "Twin acceptance") does the work: per unit the
store holds the NOMINAL calibration, a guided 7-press recalibration session and a separate 10-poke
held-out session are recorded (FE, cached under <cache>/recalib/twin and <cache>/twin/fe, so a
rerun only replays), the shipped int8 model runs through the runtime pipeline, the correction is
fitted from the first 5, 6 and 7 accepted pokes and the held-out error is measured again.

Status with hiera-qup-128 (docs/BENCHMARKS.md § Recalibration): units whose store holds their own
(factory) calibration, gel stiffness ×0.8–1.25 unknown: median >= 60 % — asserted; a unit WITHOUT
variation: the pokes remove >= 60 % of the model's own (gain-like) error — asserted; units whose
store holds the NOMINAL calibration (centre shift unknown too): NOT met — a strict xfail, so it
turns into a failure to remove once it is met.
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


def _run(calibration, nominal):
    from tools.recalib.twin_bench import NOMINAL, UNITS, TwinBenchConfig, markdown, run_bench

    pkg = trained_package()
    res = run_bench(TwinBenchConfig(units=UNITS[:5], nominal=NOMINAL if nominal else None, physics=PHYSICS,
                                    model=str(pkg.folder), variants=(), calibration=calibration), say=print)
    print(markdown(res, "probe"))
    return res


@pytest.fixture(scope="module")
def bench_factory():
    """Each unit's store holds its own (factory) calibration; the gel stiffness is unknown."""
    return _run("true", nominal=False)


@pytest.fixture(scope="module")
def bench_nominal():
    """Each unit's store holds the NOMINAL calibration (centre shift and gel both unknown)."""
    return _run("nominal", nominal=True)


def _reductions(row):
    return {n: row["held_out"]["probe"]["after"].get(n, {}).get("reduction", 0.0) for n in ("5", "6", "7")}


def _median_reductions(res):
    units = [r for r in res["units"] if not r.get("nominal")]
    assert len(units) >= 5
    red = {n: [_reductions(r)[n] for r in units] for n in ("5", "6", "7")}
    print({n: [f"{v:.0%}" for v in vals] for n, vals in red.items()})
    return red


def test_factory_calibrated_units_five_to_seven_pokes_cut_held_out_error_60_percent(bench_factory):
    for r in bench_factory["units"]:
        assert r["held_out"]["probe"]["pokes"] >= 6, r                        # the held-out session is real
        assert all(r["by_pokes"][n]["accepted"] >= 5 for n in ("5", "6", "7")), r["by_pokes"]
    for n, vals in _median_reductions(bench_factory).items():
        assert np.median(vals) >= 0.6, (n, vals)
    check = bench_factory["units"][0]["runtime_check"]   # the replayed correction is what the runtime computes
    assert check["pipeline_mae_n"] == pytest.approx(check["replayed_correction_mae_n"], rel=0.05, abs=0.01)


def test_nominal_unit_pokes_remove_the_models_own_gain_error(bench_nominal):
    nominal = bench_nominal["units"][0]
    assert nominal["nominal"] and nominal["held_out"]["probe"]["pokes"] >= 6
    for n, red in _reductions(nominal).items():
        assert nominal["by_pokes"][n]["stored"], (n, nominal["by_pokes"][n])
        assert red >= 0.6, (n, red)


@pytest.mark.xfail(strict=True, reason="not met with hiera-qup-128 when the store holds the NOMINAL calibration "
                                       "of a centre-shifted unit (docs/BENCHMARKS.md § Recalibration)")
def test_units_with_nominal_calibration_five_to_seven_pokes_cut_held_out_error_60_percent(bench_nominal):
    for n, vals in _median_reductions(bench_nominal).items():
        assert np.median(vals) >= 0.6, (n, vals)
