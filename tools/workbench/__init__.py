"""The physics workbench: compare the model with measurements, diagnose the missing physical
effect, add it, watch the error fall (DESIGN.md §7, docs/workbench.md)."""
