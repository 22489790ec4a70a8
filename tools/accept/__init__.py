"""Acceptance harnesses: the workbench and recalibration loops run end to end on twin sessions
(`tensortouch accept …`). The measured alterations (alter.py) are written apart from the effect library."""
