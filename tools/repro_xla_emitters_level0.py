"""XLA:CPU's older loop emitters at backend optimisation level 0 give a wrong answer.

``fsjax.ops.measure_pos`` (eager) on a profile with three edges finds three under XLA's
defaults, under ``--xla_backend_optimization_level=0`` alone and under
``--xla_cpu_use_fusion_emitters=false`` alone, and five (two duplicated) under both flags
(jaxlib 0.10, measured 2026-12-04). Run it under each setting::

    for f in "" "--xla_backend_optimization_level=0" "--xla_cpu_use_fusion_emitters=false" \\
             "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"; do
        XLA_FLAGS="$f" python tools/repro_xla_emitters_level0.py; done

Not reduced to a pure-JAX program yet. Hence: the test suite sets level 0 only, the tour the
older emitters only (and not when XLA_FLAGS sets a level), and the fits' per-program option
(``fsjax._linalg.FAST_COMPILE``) pins level 2.
"""

import os

import jax
import jax.numpy as jnp
import numpy as np

import fsjax

jax.config.update("jax_enable_x64", True)
prof = np.full(60, 0.1)
prof[15:] = 0.6
prof[25:] = 0.95
prof[40:] = 0.1
img = fsjax.Image(jnp.asarray(np.tile(prof, (5, 1))))
e = fsjax.ops.measure_pos(img, row=2, col=29.5, length=59, sigma=1.0, threshold=0.05)
v = np.asarray(e.valid)
print(f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}: {int(v.sum())} edges (3 expected) at {np.asarray(e.pos)[v]}")
