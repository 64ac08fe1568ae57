"""Volume ops: ``Volume`` ``(D, H, W)`` in, a volume, labels or measurements out.

Families and their private modules: ``filters3d`` (_filters3d: Gaussian, box, median,
Sobel gradient magnitude, Laplacian of Gaussian), ``hessian3d`` (_hessian3d: Frangi vesselness
and blobness), ``morphology3d`` (_morphology3d),
``label3d`` (_label3d: connected components and region properties), ``distance3d``
(_distance3d: exact anisotropic Euclidean distance transform), ``project3d``
(_project3d: maximum / mean projections along an axis), ``resample3d`` (_resample3d: crop,
pad, resample to a new spacing), ``watershed3d`` (_watershed3d: marker-controlled watershed), ``isosurface`` (_isosurface:
marching cubes, ``Volume -> Mesh``) and ``fusion`` (_tsdf: depth maps fused into a truncated
signed distance volume, ``DepthStack -> Volume``).

Axes are ``(z, y, x)``; ``Volume.spacing`` is ``(dz, dy, dx)`` in ``Volume.unit``.
The public path of every op is ``fsjax.ops.<name>``; this package exports nothing
of its own.
"""
