"""Image ops: raster in, raster (or a feature) out.

Families and their private modules: ``filters`` (_filters), ``morphology``
(_morphology), ``threshold`` (_threshold, _threshold_local), ``edges`` (_edges,
_edges_canny), ``frequency`` (_frequency), ``color`` (_color), ``point``
(_pixelwise: pixel-wise maps), ``geometry`` (_geometry), ``distance`` (_distance),
``skeleton`` (_skeleton), ``binary`` (_binary), ``features`` (_features).

The public path of every op is ``fsjax.ops.<name>``; this package exports nothing
of its own.
"""
