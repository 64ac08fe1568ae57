"""All registered ops, one private module per family, re-exported here.

Each family module lists its public ops in ``__all__`` (the one export list);
importing this package registers every op.
"""

from ._binary import *  # noqa: F403
from ._caliper import *  # noqa: F403
from ._camera import *  # noqa: F403
from ._color import *  # noqa: F403
from ._contours import *  # noqa: F403
from ._distance import *  # noqa: F403
from ._edges import *  # noqa: F403
from ._edges_canny import *  # noqa: F403
from ._features import *  # noqa: F403
from ._filters import *  # noqa: F403
from ._fit2d import *  # noqa: F403
from ._frequency import *  # noqa: F403
from ._geometry import *  # noqa: F403
from ._label import *  # noqa: F403
from ._matching import *  # noqa: F403
from ._measure import *  # noqa: F403
from ._morphology import *  # noqa: F403
from ._photometric import *  # noqa: F403
from ._point import *  # noqa: F403
from ._points import *  # noqa: F403
from ._points_curvature import *  # noqa: F403
from ._points_segment import *  # noqa: F403
from ._points_search import *  # noqa: F403
from ._render import *  # noqa: F403
from ._segment import *  # noqa: F403
from ._skeleton import *  # noqa: F403
from ._structured_light import *  # noqa: F403
from ._threshold import *  # noqa: F403
from ._threshold_local import *  # noqa: F403
from ._tomography import *  # noqa: F403
