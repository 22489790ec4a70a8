"""Physical effects, model side: plugin API, the eight library effects, registry, enabled chain.

See runtime/stages/effects/base.py for the plugin contract and docs/effects-model.md for the equations.
"""
from .base import COVARIATES, STAGES, Effect, EffectError, MissingCovariate, Param, need, scale_rows
from .builtin import BUILTIN, CANONICAL
from .chain import EffectChain, EnabledEffect
from .registry import ENTRY_POINT_GROUP, Registry

__all__ = ["COVARIATES", "STAGES", "Effect", "EffectError", "MissingCovariate", "Param", "need", "scale_rows", "BUILTIN", "CANONICAL",
           "EffectChain", "EnabledEffect", "ENTRY_POINT_GROUP", "Registry"]
