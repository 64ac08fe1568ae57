"""fsjax.render: the camera model, renderers and shading.

Submodules add their public names here with one ``from .<module> import *`` line each.
"""

from .camera import *  # noqa: F403
from .splat import *  # noqa: F403
from .volume import *  # noqa: F403
from .raster import *  # noqa: F403
from .sdf import *  # noqa: F403
from .tonemap import *  # noqa: F403
from .raycast import *  # noqa: F403
from .shading import *  # noqa: F403
from .materials import *  # noqa: F403
