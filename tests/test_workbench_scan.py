"""The covariate scan (tools/workbench/scan.py): a depth-dependent gain is found, noise is not."""
import numpy as np
from tensortouch.tools.workbench.scan import covariate_score


def test_covariate_scan_finds_a_gain_that_depends_on_depth():
    rng = np.random.default_rng(0)
    n = 2000
    depth = rng.uniform(0, 2, n)
    pred = np.column_stack([np.zeros(n), np.zeros(n), depth ** 1.5])
    resid = pred * (0.2 * depth ** 2)[:, None] + rng.normal(0, 0.01, (n, 3))
    blocks = np.repeat(np.arange(10), n // 10)
    good = covariate_score(depth, resid, pred, blocks)
    noise = covariate_score(rng.uniform(0, 1, n), resid, pred, blocks)
    assert good["score"] > 0.9 and good["form"] == "multiplicative"
    assert noise["score"] < 0.05
