"""Mesh ops: a triangle ``Mesh`` in, measurements, a topology report or a smoothed mesh out.

Family ``mesh``: _mesh (area, enclosed volume, topology counts, Laplacian and Taubin
smoothing), _decimate (quadric decimation), _subdivide (Loop subdivision) and _voxelize (``Mesh -> Volume``: signed distance, occupancy, winding number). Iso-surfaces of volumes are in :mod:`fsjax.ops.volume` (``marching_cubes``);
surface sampling (``sample_surface``) is with the point-cloud ops. The public path of every
op is ``fsjax.ops.<name>``; this package exports nothing of its own.
"""
