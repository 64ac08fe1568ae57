"""Ground-truth scene and data generators, and the standard input pool.

The pool (:func:`standard_input`) gives every sort a small deterministic
instance; the contract tests, the docs and the evolutionary search feed ops
from it. A family that introduces a sort registers its builder with
:func:`register_pool`.
"""

from ._pool import register_pool as register_pool
from ._pool import standard_input as standard_input
from ._pool import standard_scene as standard_scene
