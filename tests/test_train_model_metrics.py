"""Field metrics (tools/train/model/metrics.py) follow the seed's definitions."""
import numpy as np
import pytest
from tensortouch.contracts.fields import CHANNELS
from tensortouch.tools.train.model.metrics import evaluate, psnr_per_modality


def test_metrics_follow_the_seed_definitions():
    rng = np.random.default_rng(0)
    true = rng.uniform(0.2, 0.8, (2, 15, 32, 32))
    res = evaluate(true, true)
    assert res["mean"]["ssim"] == pytest.approx(1.0) and res["mean"]["auc_rel"] == pytest.approx(1.0)
    assert res["mean"]["fpr_rel"] == 0 and res["mean"]["mse"] == 0
    pred = true + 0.01
    res = evaluate(pred, true)
    assert res["mean"]["mse"] == pytest.approx(1e-4)
    assert res["mean"]["psnr"] == pytest.approx(40.0)
    assert set(res["per_modality"]) == {"displacement", "normal_stress", "shear_stress", "contact_normal",
                                        "contact_shear"}
    # relative error in physical units: truth 0 → predicted 0.1 is off by more than the truth (FPR)
    bounds = {c: [-1.0, 1.0] for c in CHANNELS}
    t = np.full((1, 15, 8, 8), 0.5)                # physical 0
    t[:, :, :4] = 0.75                             # physical 0.5
    p = t.copy(); p[:, :, 4:] = 0.55               # physical 0.1 where truth is 0
    r = evaluate(p, t, bounds)
    assert r["mean"]["fpr_rel"] == pytest.approx(0.5)
    # half the pixels exact (AUC contribution 0.5), half with rel error 0.1/(0+0.02) = 5 > 1 (0)
    assert r["mean"]["auc_rel"] == pytest.approx(0.5, abs=0.01)
    # sign matters: 2× the truth is off by exactly 100 % → not counted; 2.5× is
    p2 = t.copy(); p2[:, :, :4] = 0.5 + 0.25 * 2.5
    assert evaluate(p2, t, bounds)["mean"]["fpr_rel"] == pytest.approx(0.5)
    assert psnr_per_modality(pred, true)["displacement"] == pytest.approx(40.0)
