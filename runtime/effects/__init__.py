"""Physical effects, model side: plugin API, the eight library effects, registry, enabled chain.

See runtime/effects/base.py for the plugin contract and docs/effects-model.md for the equations.
"""
from runtime.effects.base import COVARIATES, STAGES, Effect, EffectError, MissingCovariate, Param, need, scale_rows
from runtime.effects.builtin import BUILTIN, CANONICAL
from runtime.effects.chain import EffectChain, EnabledEffect
from runtime.effects.registry import ENTRY_POINT_GROUP, Registry

__all__ = ["COVARIATES", "STAGES", "Effect", "EffectError", "MissingCovariate", "Param", "need", "scale_rows", "BUILTIN", "CANONICAL",
           "EffectChain", "EnabledEffect", "ENTRY_POINT_GROUP", "Registry"]
