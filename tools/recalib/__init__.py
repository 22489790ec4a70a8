"""Field recalibration (issue #7, seed §III.I last paragraph, §III.G): 5–7 pokes → a zero-constrained
random-forest force correction (ONNX) and, optionally, refreshed θ/φ tables and gel centre.

Pure cores: `pokes` (acceptance rules, poke detection, position suggestions), `fit` (RF gain fit,
leave-one-out evaluation, ONNX export, store/refuse decision), `geometry` (GPR 2D–3D refresh).
Shells: `store_ops` (writing a version), `session` (the guided session), `cli` (`tensortouch recalibrate`).
See docs/recalibration.md.
"""
