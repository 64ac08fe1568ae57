"""3-D measurement ops: shape from images and cameras.

Families and their private modules: ``photometric`` (_photometric),
``structured_light`` (_structured_light), ``tomography`` (_tomography),
``camera`` (_camera), ``render`` (_render).

The public path of every op is ``fsjax.ops.<name>``; this package exports nothing
of its own.
"""
