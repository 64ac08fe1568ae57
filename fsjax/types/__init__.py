"""The sorts: typed pytrees that flow between fsjax ops.

A sort is an :class:`equinox.Module` subclass; the *class itself* is the static
type tag. Pipelines are type-checked from classes before anything is traced, so
the check costs nothing at run time. Array fields hold data; metadata that fixes
shapes or meaning is a static field.

Every sort lives in this package, grouped by what it holds:

* :mod:`fsjax.types.raster`: images, colour spaces, regions, labels, signals,
  volumes and the image stacks of photometric stereo and structured light;
* :mod:`fsjax.types.geometry`: contours, points (and per-point values/labels),
  meshes, Gaussians, cameras, depth maps, structured-light rigs;
* :mod:`fsjax.types.records`: measured numbers and records (features, matches,
  region properties, 2-D fits, 1-D edges);
* :mod:`fsjax.types.results`: the result vocabulary every fit shares.

The canonical public path of a sort is ``fsjax.<Sort>`` (also ``fsjax.types.<Sort>``);
the conventions (pixel centres, value ranges, camera frame, batching) are stated
once in :mod:`fsjax.types._base`. ``fsjax.types`` imports nothing else of fsjax.
"""

from ._base import Sort as Sort
from ._base import is_concrete as is_concrete
from .geometry import *  # noqa: F403
from .geometry import __all__ as _geometry_all
from .raster import *  # noqa: F403
from .raster import __all__ as _raster_all
from .records import *  # noqa: F403
from .records import __all__ as _records_all
from .results import RESULTS as RESULTS
from .results import FitResult as FitResult
from .results import reason_code as reason_code
from .results import reason_message as reason_message

__all__ = ["Sort", "is_concrete", *_raster_all, *_geometry_all, *_records_all, "RESULTS", "FitResult",
           "reason_code", "reason_message"]
