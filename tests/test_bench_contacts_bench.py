"""`tensortouch bench contacts` runs on the demo unit's tables; the rule adds the light touch only."""
import argparse
import json

from tensortouch.tools.bench.contacts_bench import add_arguments, run


def test_bench_contacts_reports_both_configs_and_the_light_touch(capsys):
    p = argparse.ArgumentParser()
    add_arguments(p)
    # the fifth configuration: the teacher's settings (split_dip 0.5 parts the two joined presses below; the
    # default student's 0.6, chosen on the same validation units, does not)
    assert run(p.parse_args(["--frames", "2", "--model", "hiera-qup-128", "--json"])) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rows = {(r["field"], r["config"]): r for r in out["rows"]}
    assert len(rows) == 7 * 6 and all(r["ms"] > 0 for r in rows.values())
    assert set(out["mean_ms"]) == {"strong only", "with rule", "rule+merge", "rule+merge+split", "package",
                                   "package, low core"}
    # a network's rest-frame rim: single pixels above the core threshold, no contact under any setting
    assert all(rows[("rim noise", c)]["clusters_n"] == [] for c in out["mean_ms"])
    assert [round(f) for f in rows[("press + rim noise", "package, low core")]["clusters_n"]] == [2]
    assert out["package"] == "hiera-qup-128"
    assert len(rows[("one touch + light touch", "strong only")]["clusters_n"]) == 1
    light = sorted(rows[("one touch + light touch", "with rule")]["clusters_n"])
    assert len(light) == 2 and 0.25 < light[0] <= 0.31
    assert rows[("one touch", "with rule")]["clusters_n"] == rows[("one touch", "strong only")]["clusters_n"]
    # merging keeps two real contacts apart and publishes the split sliding contact once, with its whole force
    assert sorted(rows[("one touch + light touch", "rule+merge")]["clusters_n"]) == light
    split = rows[("split sliding contact", "with rule")]["clusters_n"]
    merged = rows[("split sliding contact", "rule+merge")]["clusters_n"]
    assert len(split) == 2 and len(merged) == 1 and merged[0] > max(split)
    # the teacher's light-touch rule sees the light touch, and its splitting (chosen on validation
    # units, where no single contact was split) parts the two joined presses
    assert len(rows[("one touch + light touch", "package")]["clusters_n"]) == 2
    assert len(rows[("two presses joined", "package")]["clusters_n"]) == 2
    # splitting keeps the merged sliding contact whole and parts two heavy presses joined above the threshold
    assert rows[("split sliding contact", "rule+merge+split")]["clusters_n"] == merged
    joined = rows[("two presses joined", "rule+merge")]["clusters_n"]
    parts = sorted(rows[("two presses joined", "rule+merge+split")]["clusters_n"])
    assert len(joined) == 1 and len(parts) == 2 and 2.8 < parts[0] < 3.2 and 3.7 < parts[1] < 4.1
    assert abs(sum(parts) - joined[0]) < 0.01
