"""All registered ops, re-exported here: ``fsjax.ops.<name>`` is the one public path.

Op families live in private modules grouped by domain: :mod:`.image` (filters,
morphology, thresholds, edges, frequency, colour, pixel-wise maps, geometry, distance,
skeleton, binary, features), :mod:`.measure2d` (labels, segmentation, region
measurement, contours, calipers, 2-D fits), :mod:`.matching` (correlation and shape
matching), :mod:`.points` (point clouds, curvature, neighbour search, segmentation),
:mod:`.measure3d` (photometric stereo, structured light, tomography, camera, rendering),
:mod:`.mesh` (area, enclosed volume, topology, smoothing, decimation, subdivision of a ``Mesh``) and
:mod:`.volume` (3-D filters, morphology, labels, distance, projections, iso-surfaces of a ``Volume``).
Each family module lists its public names in ``__all__`` (the one export list); the
domain packages export nothing themselves. Importing this package registers every op.
Shared op-only helpers are in :mod:`._common`; argument checks in :mod:`fsjax._checks`.
"""

# Sorts that op modules defined before they moved home to fsjax.types (same objects; the
# canonical path is fsjax.types.<Sort>).
from ..types import FringeStack as FringeStack
from ..types import GrayStack as GrayStack
from ..types import LightStack as LightStack
from ..types import NormalMap as NormalMap
from ..types import PointLabels as PointLabels
from ..types import PointValues as PointValues
from ..types import StructuredLightRig as StructuredLightRig
from .image._binary import *  # noqa: F403
from .image._color import *  # noqa: F403
from .image._distance import *  # noqa: F403
from .image._edges import *  # noqa: F403
from .image._edges_canny import *  # noqa: F403
from .image._features import *  # noqa: F403
from .image._filters import *  # noqa: F403
from .image._frequency import *  # noqa: F403
from .image._geometry import *  # noqa: F403
from .image._morphology import *  # noqa: F403
from .image._pixelwise import *  # noqa: F403
from .image._skeleton import *  # noqa: F403
from .image._threshold import *  # noqa: F403
from .image._threshold_local import *  # noqa: F403
from .match3d._chamfer3d import *  # noqa: F403
from .match3d._depth_tsdf import *  # noqa: F403
from .match3d._fft3d import *  # noqa: F403
from .match3d._fmellin3d import *  # noqa: F403
from .match3d._gaussvox import *  # noqa: F403
from .match3d._ghough3d import *  # noqa: F403
from .match3d._ghoughrot3d import *  # noqa: F403
from .match3d._hough3d import *  # noqa: F403
from .match3d._pose3d import *  # noqa: F403
from .match3d._pyramid3d import *  # noqa: F403
from .match3d._refine3d import *  # noqa: F403
from .match3d._shape3d import *  # noqa: F403
from .match3d._shapeindex3d import *  # noqa: F403
from .match3d._shaperot3d import *  # noqa: F403
from .match3d._shdesc import *  # noqa: F403
from .match3d._sirot3d import *  # noqa: F403
from .match3d._transforms import *  # noqa: F403
from .matching._correlation import *  # noqa: F403
from .matching._shape import *  # noqa: F403
from .measure2d._caliper import *  # noqa: F403
from .measure2d._contours import *  # noqa: F403
from .measure2d._fit2d import *  # noqa: F403
from .measure2d._label import *  # noqa: F403
from .measure2d._measure import *  # noqa: F403
from .measure2d._segment import *  # noqa: F403
from .measure3d._camera import *  # noqa: F403
from .measure3d._photometric import *  # noqa: F403
from .measure3d._render import *  # noqa: F403
from .measure3d._structured_light import *  # noqa: F403
from .measure3d._tomography import *  # noqa: F403
from .mesh._decimate import *  # noqa: F403
from .mesh._mesh import *  # noqa: F403
from .mesh._subdivide import *  # noqa: F403
from .mesh._voxelize import *  # noqa: F403
from .points._cloud import *  # noqa: F403
from .points._curvature import *  # noqa: F403
from .points._harris3d import *  # noqa: F403
from .points._search import *  # noqa: F403
from .points._segment import *  # noqa: F403
from .volume._distance3d import *  # noqa: F403
from .volume._filters3d import *  # noqa: F403
from .volume._hessian3d import *  # noqa: F403
from .volume._isosurface import *  # noqa: F403
from .volume._label3d import *  # noqa: F403
from .volume._morphology3d import *  # noqa: F403
from .volume._project3d import *  # noqa: F403
from .volume._resample3d import *  # noqa: F403
from .volume._sdf import *  # noqa: F403
from .volume._tsdf import *  # noqa: F403
from .volume._watershed3d import *  # noqa: F403
