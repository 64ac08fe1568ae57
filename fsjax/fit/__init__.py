"""fsjax.fit: geometric fits and estimators that return one result vocabulary.

The fits, by module (every public name is re-exported here, ``fsjax.fit.<name>``):

* :mod:`.rigid` -- Kabsch/Umeyama with known correspondences (:class:`RigidFit`), SO(3)/SE(3)
  helpers, PCA canonical pose (:class:`CanonicalPose`);
* :mod:`.icp` -- point-to-point / point-to-plane / GICP ICP (:class:`ICPResult`), multi-start
  (:class:`MultiStartResult`);
* :mod:`.global_reg` -- FPFH, correspondence RANSAC (:class:`CorrespondenceRansacResult`),
  global registration (:class:`GlobalResult`);
* :mod:`.cross` -- registration across structures (mesh, scan, depth, volume, Gaussians):
  :func:`register_cross`;
* :mod:`.ransac3d` -- RANSAC plane / line / sphere / cylinder (:class:`RansacResult`);
* :mod:`.primitives3d` -- closed-form and LM 3-D primitives (:class:`Fit3D`), distances and
  angles, model selection (:class:`ModelSelection`);
* :mod:`.chessboard` -- chessboard corners (:class:`ChessboardCorners`);
* :mod:`.calibrate` -- Zhang + LM camera calibration (:class:`Calibration`);
* :mod:`.twoview` -- essential matrix RANSAC, relative pose (:class:`TwoViewResult`); homography
  RANSAC (:class:`HomographyResult`) and its decomposition;
* :mod:`.pnp` -- DLT + LM PnP, RANSAC (:class:`PnPResult`);
* :mod:`.bundle_adjust` -- sparse bundle adjustment (:class:`BundleResult`);
* :mod:`.splat_train` -- Gaussian-splat training (:class:`SplatTrainResult`);
* :mod:`.frames` -- key-frame selection by rotation (:class:`FrameSelection`, not a fit).

The result vocabulary (:mod:`fsjax.types.results`, ``docs/results.md``): every fit result has
``converged``, ``reason`` (an int32 code of the one :data:`fsjax.types.RESULTS` enumeration,
``message`` its text), ``iterations`` and a residual named with its unit (``rms_px``,
``rms_len``, ``sampson_rms_px``; ``residual_name`` says which). Records with named parameters
(:class:`Fit3D`, :class:`RansacResult`) read them as ``fit["r"]`` (:class:`fsjax.types.NamedParams`).

Deprecated names (one release, each warns naming its replacement): ``knn`` (use
:func:`fsjax.ops.knn`), ``estimate_normals`` (:func:`fsjax.ops.estimate_normals`), ``fit_line``
(:func:`fit_line3d`), ``REGISTRATION_REASONS``, ``PNP_REASONS``, ``TWOVIEW_REASONS``,
``REASONS``, ``BA_REASONS`` (:data:`fsjax.types.RESULTS`).
"""

from . import bundle_adjust as _bundle_adjust
from . import icp as _icp
from . import pnp as _pnp
from . import primitives3d as _primitives3d
from . import ransac3d as _ransac3d
from . import rigid as _rigid
from . import splat_train as _splat_train
from . import twoview as _twoview
from .bundle_adjust import *  # noqa: F403
from .calibrate import *  # noqa: F401,F403
from .chessboard import *  # noqa: F401,F403
from .cross import *  # noqa: F401,F403
from .frames import *  # noqa: F401,F403
from .global_reg import *  # noqa: F401,F403
from .icp import *  # noqa: F401,F403
from .pnp import *  # noqa: F401,F403
from .primitives3d import *  # noqa: F403
from .ransac3d import *  # noqa: F403
from .rigid import *  # noqa: F401,F403
from .splat_train import *  # noqa: F401,F403
from .twoview import *  # noqa: F401,F403

_TABLES = {"REGISTRATION_REASONS": _rigid, "PNP_REASONS": _pnp, "TWOVIEW_REASONS": _twoview, "REASONS": _ransac3d,
           "BA_REASONS": _bundle_adjust}


def __getattr__(name):
    if name in ("knn", "estimate_normals"):
        return _icp.__getattr__(name)
    if name == "fit_line":
        return _primitives3d.__getattr__("fit_line")
    if name == "psnr":
        return _splat_train.__getattr__("psnr")
    if name in _TABLES:
        return _TABLES[name].__getattr__(name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
