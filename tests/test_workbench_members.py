"""Choosing between a family's named form and its flexible member (diagnose.pick_members)."""
from tensortouch.runtime.stages.effects import Registry
from tensortouch.tools.workbench.diagnose import DiagnoseConfig, EffectScore, pick_members


def _score(reg, name, after, significant):
    return EffectScore(reg.get(name), "force", {}, before=0.031, after=after, p_value=0.001,
                       significant=significant)


def test_named_form_kept_within_the_margin_unless_only_the_flexible_member_is_significant():
    reg = Registry.default(entry_points=False)
    cfg = DiagnoseConfig()
    # both significant, within 2 %: the named form is reported
    got = pick_members([_score(reg, "strain_stiffening", 0.0297, True),
                        _score(reg, "strain_stiffening_spline", 0.02936, True)], cfg)
    assert [s.effect.name for s in got] == ["strain_stiffening"]
    assert got[0].alternatives[0].effect.name == "strain_stiffening_spline"
    # within 2 % but only the flexible member passes the bars: the family is not lost
    got = pick_members([_score(reg, "strain_stiffening", 0.0297, False),
                        _score(reg, "strain_stiffening_spline", 0.02936, True)], cfg)
    assert [s.effect.name for s in got] == ["strain_stiffening_spline"]
    # neither significant: parsimony
    got = pick_members([_score(reg, "strain_stiffening", 0.0297, False),
                        _score(reg, "strain_stiffening_spline", 0.02936, False)], cfg)
    assert [s.effect.name for s in got] == ["strain_stiffening"]
    # beyond the margin the flexible member wins anyway
    got = pick_members([_score(reg, "strain_stiffening", 0.0297, True),
                        _score(reg, "strain_stiffening_spline", 0.0280, True)], cfg)
    assert [s.effect.name for s in got] == ["strain_stiffening_spline"]
