"""fsjax: typed, pure, jit-compiled vision operators in JAX.

The public API: the sorts (typed pytrees), the op registry, the uniform call
:func:`apply`, and compiled, type-checked pipelines. Ops live in
:mod:`fsjax.ops` (``fsjax.ops.gaussian(img, sigma=2.0)``).

Names and subpackages are loaded on first use (PEP 562): ``import fsjax`` is
cheap and does not import JAX, so the ``fsjax`` command answers ``--help`` at
once; ``fsjax.ops``, ``fsjax.io``, ``fsjax.Image``, ``from fsjax import apply``
... all work as attributes of an eagerly imported package would.
"""

from __future__ import annotations

import importlib as _importlib
import sys as _sys
import types as _types
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

# Modules whose import registers ops; the registry imports them on first lookup
# (fsjax.registry names no op module: it sits below the ops in the layering).
OP_PROVIDERS = ("fsjax.ops",)

# subpackages / modules reachable as attributes
_SUBMODULES = ("data", "fit", "ops", "render", "io", "synth", "evolve", "fuzz", "types", "registry", "pipeline")
# former module paths, still reachable as attributes (importing them warns: DeprecationWarning)
_DEPRECATED_SUBMODULES = ("io3d", "io_splat")

# public name -> module that defines it
_NAMES = {
    **{n: ".pipeline" for n in ("Pipeline", "PipelineTypeError", "apply", "pipeline", "run_pipeline")},
    **{n: "._cache" for n in ("compile_cache_dir", "enable_compile_cache")},
    **{n: ".registry" for n in ("IntKnob", "LinKnob", "LogKnob", "OpSpec", "UnknownOpError", "compiled_calls",
                                "families", "get_op", "list_ops", "register")},
    **{n: ".types" for n in ("HSV", "Camera", "Color", "Contour", "Depth", "Edges1D", "Feature", "Fit",
                             "Gaussians", "Image", "Lab", "Labels", "Match", "Match3D", "Mesh", "Points", "Region",
                             "RegionProps", "Signal", "Sort", "Volume", "LabelVolume", "LightStack", "NormalMap",
                             "FringeStack", "GrayStack", "PointValues", "PointLabels", "StructuredLightRig",
                             "MeshTopology", "DepthStack")},
}

__all__ = sorted(_NAMES) + list(_SUBMODULES)


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        value = getattr(_importlib.import_module(_NAMES[name], __name__), name)
    elif name in _SUBMODULES or name in _DEPRECATED_SUBMODULES:
        value = _importlib.import_module(f".{name}", __name__)
    else:
        raise AttributeError(f"module 'fsjax' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


class _Package(_types.ModuleType):
    """``fsjax.pipeline`` is the function, as with an eager ``from .pipeline import pipeline``:
    when the import system binds the submodule ``fsjax.pipeline`` on the package (after
    loading it), the function it defines is bound instead."""

    def __setattr__(self, name: str, value: Any) -> None:
        if name == "pipeline" and isinstance(value, _types.ModuleType):
            value = value.pipeline
        super().__setattr__(name, value)


_sys.modules[__name__].__class__ = _Package


if TYPE_CHECKING:  # static analysers see the eager imports
    from . import data as data
    from . import fit as fit
    from . import io as io
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
    from .types import DepthStack as DepthStack
    from .types import Edges1D as Edges1D
    from .types import Feature as Feature
    from .types import Fit as Fit
    from .types import Gaussians as Gaussians
    from .types import Image as Image
    from .types import Lab as Lab
    from .types import Labels as Labels
    from .types import LabelVolume as LabelVolume
    from .types import Match as Match
    from .types import Match3D as Match3D
    from .types import Mesh as Mesh
    from .types import MeshTopology as MeshTopology
    from .types import Points as Points
    from .types import Region as Region
    from .types import RegionProps as RegionProps
    from .types import Signal as Signal
    from .types import Sort as Sort
    from .types import Volume as Volume
    from .types import FringeStack as FringeStack
    from .types import GrayStack as GrayStack
    from .types import LightStack as LightStack
    from .types import NormalMap as NormalMap
    from .types import PointLabels as PointLabels
    from .types import PointValues as PointValues
    from .types import StructuredLightRig as StructuredLightRig
