"""Synthetic talking-face corpus with ground truth: the rig driven by known curves, rendered by `render.raster`."""
