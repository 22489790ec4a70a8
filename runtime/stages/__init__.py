"""The frame loop's stages, in the order they run: preprocess → baseline → model → contacts →
effects → correction (geometry and temperature are their lookups). Pure cores; the pipeline
(runtime/pipeline.py) chains them.
"""
