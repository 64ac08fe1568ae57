"""fsjax: typed, pure, jit-compiled vision operators in JAX.

The public API: the sorts (typed pytrees), the op registry, the uniform call
:func:`apply`, and compiled, type-checked pipelines. Ops live in
:mod:`fsjax.ops` (``fsjax.ops.gaussian(img, sigma=2.0)``).
"""

from . import data as data
from . import fit as fit
from . import ops as ops
from . import render as render
from ._cache import compile_cache_dir as compile_cache_dir
from ._cache import enable_compile_cache as enable_compile_cache
from .pipeline import Pipeline as Pipeline
from .pipeline import PipelineTypeError as PipelineTypeError
from .pipeline import apply as apply
from .pipeline import pipeline as pipeline
from .pipeline import run_pipeline as run_pipeline
from .registry import IntKnob as IntKnob
from .registry import LinKnob as LinKnob
from .registry import LogKnob as LogKnob
from .registry import OpSpec as OpSpec
from .registry import UnknownOpError as UnknownOpError
from .registry import compiled_calls as compiled_calls
from .registry import families as families
from .registry import get_op as get_op
from .registry import list_ops as list_ops
from .registry import register as register
from .types import HSV as HSV
from .types import Camera as Camera
from .types import Color as Color
from .types import Contour as Contour
from .types import Depth as Depth
from .types import Edges1D as Edges1D
from .types import Feature as Feature
from .types import Fit as Fit
from .types import Gaussians as Gaussians
from .types import Image as Image
from .types import Lab as Lab
from .types import Labels as Labels
from .types import Match as Match
from .types import Mesh as Mesh
from .types import Points as Points
from .types import Region as Region
from .types import RegionProps as RegionProps
from .types import Signal as Signal
from .types import Sort as Sort
from .types import Volume as Volume

__version__ = "0.1.0"
