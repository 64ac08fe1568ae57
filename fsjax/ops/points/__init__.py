"""Point-cloud ops.

Families and their private modules: ``points`` (_cloud: filters, normals,
down-sampling; _curvature; _segment: plane and cluster segmentation),
``points_search`` and ``mesh`` (_search: k-nearest neighbours, radius search,
surface sampling).

The public path of every op is ``fsjax.ops.<name>``; this package exports nothing
of its own.
"""
