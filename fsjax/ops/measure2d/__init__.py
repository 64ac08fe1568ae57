"""2-D measurement ops: regions, labels, contours, calipers and 2-D fits.

Families and their private modules: ``label`` (_label), ``segment`` (_segment),
``measure`` (_measure), ``contours`` (_contours), ``caliper`` (_caliper),
``fit2d`` (_fit2d).

The public path of every op is ``fsjax.ops.<name>``; this package exports nothing
of its own.
"""
