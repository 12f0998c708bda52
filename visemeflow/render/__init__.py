"""Rendering: the numpy rasteriser (`raster`: Lambert-shaded meshes, used by the synthetic corpus, the previews and
the automatic markers) and the pinhole camera in torch (`camera`, the tracker's). Imports only `visemes`."""
