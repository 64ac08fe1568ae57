"""Tone mapping: scene-referred linear radiance to display values in [0, 1].

Inputs are linear (scene-referred) values >= 0 of any shape; outputs are linear display
values in [0, 1] (apply an sRGB transfer curve afterwards if writing an 8-bit file).
"""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["aces_filmic"]


def aces_filmic(x, *, exposure: float = 1.0):
    """ACES filmic tone curve, K. Narkowicz's rational fit (2016) of the ACES RRT + ODT.

    ``y = clip(x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14), 0, 1)`` applied per channel to
    ``exposure * x``. The fit is of the sRGB-display ACES reference transform (Narkowicz,
    "ACES Filmic Tone Mapping Curve", blog post, 2016); it is monotone on ``x >= 0``, maps 0 to 0
    and saturates at 1 near ``x = 11``. It is a curve fit, not the full ACES colour pipeline
    (no AP0/AP1 matrices).

    Example:
        >>> from fsjax.render import aces_filmic
        >>> [round(float(v), 6) for v in aces_filmic(jnp.asarray([0.0, 0.18, 1.0, 100.0]))]
        [0.0, 0.266899, 0.803797, 1.0]
    """
    x = jnp.maximum(jnp.asarray(x) * exposure, 0.0)
    y = x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14)
    return jnp.clip(y, 0.0, 1.0)
