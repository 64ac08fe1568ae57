"""Template matching ops (family ``matching``).

Private modules: _correlation (NCC maps and peaks, phase correlation), _shape
(gradient-orientation shape matching).

The public path of every op is ``fsjax.ops.<name>``; this package exports nothing
of its own.
"""
