"""fsjax.fit (placeholder for later issues)."""
from .bundle_adjust import *  # noqa: F403
from .rigid import *  # noqa: F401,F403
from .icp import *  # noqa: F401,F403
from .global_reg import *  # noqa: F401,F403
from .ransac3d import *  # noqa: F403
from .primitives3d import *  # noqa: F403
from .frames import *  # noqa: F401,F403
from .chessboard import *  # noqa: F401,F403
from .calibrate import *  # noqa: F401,F403
from .twoview import *  # noqa: F401,F403
from .pnp import *  # noqa: F401,F403
from .splat_train import *  # noqa: F401,F403
