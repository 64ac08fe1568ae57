"""3-D matching: the transforms that bring any 3-D structure onto a voxel grid or a point set,
and the FFT-family methods (phase correlation, NCC, moments) with their sub-voxel refinements,
each returning a :class:`fsjax.Match3D`. The family modules export; this package exports
nothing itself (see :mod:`fsjax.ops`)."""
