"""`tensortouch bench hand` runs end to end (tiny sizes: checks the code path, not the numbers)."""
import argparse
import json

import pytest


@pytest.mark.slow
def test_hand_bench_small(capsys):
    from tools.bench import hand_bench

    p = argparse.ArgumentParser()
    hand_bench.add_arguments(p)
    args = p.parse_args(["--sensors", "2", "--size", "32", "--seconds", "1.5", "--warmup", "2",
                         "--soak", "3", "--log-every", "1", "--soak-fps", "10", "--json"])
    assert hand_bench.run(args) == 0
    out = capsys.readouterr().out
    summary = json.loads(out.strip().splitlines()[-1])
    assert set(summary["modes"]) == set(hand_bench.MODES)
    for r in summary["modes"].values():
        assert r["min_hz"] > 5 and len(r["fingers"]) == 2 and r["received_msgs_per_s"] > 0
    soak = summary["soak"]
    assert soak["windows"] >= 2 and soak["rss_last_mb"] > 0
