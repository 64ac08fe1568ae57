"""Camera calibration from planar targets: Zhang's closed form, then joint Levenberg-Marquardt.

Conventions:

* The camera model is :mod:`fsjax.render.camera` (pinhole, OpenCV frame, Brown-Conrady
  ``(k1, k2, p1, p2, k3)``); projections here go through :func:`fsjax.render.project`.
* Per-view board poses are ``camera_from_board`` (OpenCV's ``rvec, tvec``): a board point
  ``X`` is ``R X + t`` in the camera frame; rotation vectors are axis times angle (rad).
  :meth:`Calibration.camera` converts a view to the ``world_from_camera`` :class:`Camera`
  with the board as the world.
* Image points are ``(u, v) = (column, row)`` pixels, centres on integers. Board points are
  ``(X, Y, 0)`` in any unit (square units for the bundled chessboard).
* RMS reprojection error is OpenCV's: ``sqrt(sum |uv_obs - uv_proj|^2 / n_points)`` (squared
  distances summed over both coordinates, divided by the number of points).

Method:

1. Per view, a normalised-DLT homography board -> image (Hartley 1997 normalisation).
2. Zhang's closed form (Zhang 2000, section 3.1): each homography gives two linear
   constraints on ``B = K^-T K^-1``; a zero-skew row is added; the smallest right singular
   vector gives ``B``, from which ``fx, fy, cx, cy`` follow in closed form, and each view's
   ``R, t`` from ``K^-1 H`` (orthonormalised by SVD). Distortion starts at zero.
3. Joint refinement of ``fx, fy, cx, cy, k1, k2, p1, p2, k3`` and all ``6 N`` pose parameters
   with ``optimistix.LevenbergMarquardt`` (``throw=False``, ``converged`` reported). The
   intrinsics are optimised in units of the image width so that all unknowns are O(1).
4. Standard deviations from the Jacobian at the solution:
   ``cov = (J^T J)^-1 sigma^2``, ``sigma^2 = SSR / (2 n_points - n_params)``.

References: Zhang, Z. (2000) "A flexible new technique for camera calibration", IEEE TPAMI
22(11):1330-1334; Hartley, R. (1997) "In defense of the eight-point algorithm", IEEE TPAMI
19(6); Brown, D. C. (1966) "Decentering distortion of lenses", Photogrammetric Engineering.
Reference implementation: ``cv2.calibrateCamera`` (default flags: same 9 intrinsic
parameters); on the bundled photographs the two agree to < 0.1 % in fx, fy, cx, cy
(``tests/fit/test_calibrate.py``).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from .._linalg import filter_jit_fast_compile, levenberg_marquardt
from ..render.camera import project
from ..types import Camera
from ..types.results import FitResult, reason_code, renamed

__all__ = [
    "Calibration",
    "calibrate_camera",
    "homography_dlt",
    "zhang_init",
    "rodrigues",
    "rotvec_from_matrix",
    "project_board",
    "PARAM_NAMES",
]

PARAM_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


# ---------------------------------------------------------------------------
# rotations (rotation vector <-> matrix), NaN-free at 0
# ---------------------------------------------------------------------------


def rodrigues(w):
    """Rotation matrix ``(..., 3, 3)`` of rotation vectors ``(..., 3)`` (Rodrigues, Taylor branch at 0)."""
    w = jnp.asarray(w)
    th2 = jnp.sum(w * w, -1)
    small = th2 < 1e-8
    t2 = jnp.where(small, 1.0, th2)
    t = jnp.sqrt(t2)
    a = jnp.where(small, 1.0 - th2 / 6.0, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - th2 / 24.0, (1.0 - jnp.cos(t)) / t2)
    z = jnp.zeros_like(w[..., 0])
    k = jnp.stack([jnp.stack([z, -w[..., 2], w[..., 1]], -1),
                   jnp.stack([w[..., 2], z, -w[..., 0]], -1),
                   jnp.stack([-w[..., 1], w[..., 0], z], -1)], -2)
    eye = jnp.eye(3, dtype=w.dtype)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def rotvec_from_matrix(R) -> np.ndarray:
    """Rotation vector of a rotation matrix (NumPy, eager; angle in [0, pi])."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_rotvec()


# ---------------------------------------------------------------------------
# closed-form initialisation (NumPy, eager)
# ---------------------------------------------------------------------------


def _norm_T(p: np.ndarray) -> np.ndarray:
    c = p.mean(0)
    s = np.sqrt(2.0) / np.mean(np.linalg.norm(p - c, axis=1))
    return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])


def homography_dlt(src_xy, dst_uv) -> np.ndarray:
    """Homography ``H`` with ``dst ~ H [src, 1]`` by the normalised DLT (>= 4 points, NumPy).

    Example:
        >>> from fsjax.fit.calibrate import homography_dlt
        >>> H0 = np.array([[2.0, 0.1, 5.0], [0.2, 1.5, -3.0], [1e-3, 2e-3, 1.0]])
        >>> s = np.random.default_rng(0).uniform(0, 10, (8, 2))
        >>> d = (np.c_[s, np.ones(8)] @ H0.T); d = d[:, :2] / d[:, 2:]
        >>> H = homography_dlt(s, d); bool(np.allclose(H / H[2, 2], H0, atol=1e-9))
        True
    """
    s = np.asarray(src_xy, np.float64)
    d = np.asarray(dst_uv, np.float64)
    if s.shape[0] < 4 or s.shape != d.shape or s.shape[1] != 2:
        raise ValueError(f"homography_dlt: arguments 'src', 'dst' must be (N >= 4, 2) point pairs, got {s.shape} and {d.shape}")
    Ts, Td = _norm_T(s), _norm_T(d)
    sh = np.c_[s, np.ones(len(s))] @ Ts.T
    dh = np.c_[d, np.ones(len(d))] @ Td.T
    n = len(s)
    A = np.zeros((2 * n, 9))
    A[0::2, 0:3] = sh
    A[0::2, 6:9] = -dh[:, :1] * sh
    A[1::2, 3:6] = sh
    A[1::2, 6:9] = -dh[:, 1:2] * sh
    h = np.linalg.svd(A)[2][-1].reshape(3, 3)
    H = np.linalg.inv(Td) @ h @ Ts
    return H / H[2, 2]


def _vij(H, i, j):
    h = H.T  # h[i] is column i of H
    return np.array([h[i][0] * h[j][0], h[i][0] * h[j][1] + h[i][1] * h[j][0], h[i][1] * h[j][1],
                     h[i][2] * h[j][0] + h[i][0] * h[j][2], h[i][2] * h[j][1] + h[i][1] * h[j][2],
                     h[i][2] * h[j][2]])


def zhang_init(board_xy, image_uv, image_size) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zhang's closed-form ``K`` (zero skew) and per-view ``(rvecs (N, 3), tvecs (N, 3))``.

    ``board_xy`` ``(P, 2)`` planar board coordinates shared by all views; ``image_uv``
    ``(N, P, 2)``; ``image_size = (width, height)``. Pixel coordinates are pre-scaled to
    O(1) (centre, divide by the width) for conditioning. Needs >= 3 views in general
    position (2 with the zero-skew constraint); a degenerate set (parallel boards) gives a
    non-positive-definite ``B`` and raises ``ValueError``.
    """
    W, Hh = float(image_size[0]), float(image_size[1])
    S = np.array([[1 / W, 0, -0.5], [0, 1 / W, -0.5 * Hh / W], [0, 0, 1.0]])
    uv = np.asarray(image_uv, np.float64)
    bx = np.asarray(board_xy, np.float64)
    Hs = []
    rows = []
    for v in range(uv.shape[0]):
        un = uv[v] @ S[:2, :2].T + S[:2, 2]
        H = homography_dlt(bx, un)
        H = H / np.linalg.norm(H[:, :2])
        Hs.append(H)
        rows += [_vij(H, 0, 1), _vij(H, 0, 0) - _vij(H, 1, 1)]
    V = np.array(rows)
    V = np.vstack([V, np.array([0, 1.0, 0, 0, 0, 0]) * np.linalg.norm(V)])
    b = np.linalg.svd(V)[2][-1]
    B11, B12, B22, B13, B23, B33 = b
    # a degenerate set can give B11 = 0 or den = 0 exactly (parallel boards; whether the SVD
    # returns an exact zero depends on the LAPACK build): the NaN / inf it yields fails the
    # positivity test below, which raises the clear error, not a numpy warning
    with np.errstate(divide="ignore", invalid="ignore"):
        den = B11 * B22 - B12 ** 2
        v0 = (B12 * B13 - B11 * B23) / den
        lam = B33 - (B13 ** 2 + v0 * (B12 * B13 - B11 * B23)) / B11
        determined = bool(lam / B11 > 0 and lam * B11 / den > 0)
    if not determined:
        raise ValueError("zhang_init: argument 'image_uv' must hold views that determine the intrinsics; the "
                         "homographies are degenerate")
    al = np.sqrt(lam / B11)
    be = np.sqrt(lam * B11 / den)
    u0 = -B13 * al ** 2 / lam
    Kn = np.array([[al, 0, u0], [0, be, v0], [0, 0, 1.0]])
    K = np.linalg.inv(S) @ Kn
    K[0, 1] = 0.0
    Ki = np.linalg.inv(Kn)
    rv, tv = [], []
    for H in Hs:
        r1, r2, t = (Ki @ H).T
        s = 1.0 / np.linalg.norm(r1)
        if (s * t)[2] < 0:
            s = -s
        r1, r2, t = s * r1, s * r2, s * t
        R = np.stack([r1, r2, np.cross(r1, r2)], 1)
        U, _, Vt = np.linalg.svd(R)
        R = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
        rv.append(rotvec_from_matrix(R))
        tv.append(t)
    return K, np.array(rv), np.array(tv)


# ---------------------------------------------------------------------------
# projection and the joint refinement
# ---------------------------------------------------------------------------


def _camera(fx, fy, cx, cy, dist, rvec, tvec, width, height) -> Camera:
    """``world_from_camera`` Camera for a ``camera_from_board`` pose (board = world)."""
    R = rodrigues(rvec)
    z, o = jnp.zeros_like(fx), jnp.ones_like(fx)
    K = jnp.stack([jnp.stack([fx, z, cx]), jnp.stack([z, fy, cy]), jnp.stack([z, z, o])])
    return Camera(K, width=width, height=height, dist=dist, R=R.T, t=-(R.T @ tvec))


def project_board(intr, rvec, tvec, board_xyz, width: int = 1, height: int = 1):
    """Pixels ``(P, 2)`` of board points under intrinsics ``intr = (fx, fy, cx, cy, k1, k2, p1, p2, k3)``."""
    return _project_board(intr, rvec, tvec, board_xyz, width=width, height=height)


@functools.partial(jax.jit, static_argnames=("width", "height"))  # one program, not ~40 eager ones
def _project_board(intr, rvec, tvec, board_xyz, width: int, height: int):
    intr = jnp.asarray(intr)
    cam = _camera(intr[0], intr[1], intr[2], intr[3], intr[4:9], jnp.asarray(rvec), jnp.asarray(tvec),
                  width, height)
    return project(cam, jnp.asarray(board_xyz))[0]


def _unpack(y, scale, n_views):
    intr = y[:9] * scale
    poses = y[9:].reshape(n_views, 6)
    return intr, poses[:, :3], poses[:, 3:]


def _residuals(y, args):
    board, uv, scale, wh = args
    intr, rv, tv = _unpack(y, scale, uv.shape[0])
    pred = jax.vmap(lambda r, t: project_board(intr, r, t, board, *wh))(rv, tv)
    return (pred - uv).reshape(-1)


class Calibration(FitResult):
    """Result of :func:`calibrate_camera`.

    Attributes:
        K: ``(3, 3)`` intrinsics (zero skew). dist: ``(5,)`` ``(k1, k2, p1, p2, k3)``.
        rvecs, tvecs: ``(N, 3)`` per-view ``camera_from_board`` poses.
        rms_px: OpenCV-style RMS reprojection error (px) over all points (was ``rms``).
        per_view_rms_px: ``(N,)`` the same per view (was ``per_view_rms``).
        std: ``(9,)`` standard deviations of ``fx, fy, cx, cy, k1, k2, p1, p2, k3``
          (``(J^T J)^-1 sigma^2``; NaN if ``J^T J`` is singular; 0 for fixed parameters).
        pose_std: ``(N, 6)`` standard deviations of the pose parameters.
        init_K: ``(3, 3)`` Zhang's closed-form intrinsics (before refinement).
        iterations: LM steps. converged: optimistix reported success.
        reason: code of :data:`fsjax.types.RESULTS`: ``ok`` or ``max_iterations`` (bad input
          raises before the solve).
        width, height: image size (static).
    """

    K: Float[Array, "3 3"]
    dist: Float[Array, "5"]
    rvecs: Float[Array, "N 3"]
    tvecs: Float[Array, "N 3"]
    rms_px: Float[Array, ""]
    per_view_rms_px: Float[Array, " N"]
    std: Float[Array, "9"]
    pose_std: Float[Array, "N 6"]
    init_K: Float[Array, "3 3"]
    iterations: Int[Array, ""]
    converged: Bool[Array, ""]
    reason: Int[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    residual_name = "rms_px"

    rms = renamed("rms_px")
    per_view_rms = renamed("per_view_rms_px")

    @property
    def params(self) -> dict:
        """``{name: value}`` of the 9 intrinsic parameters."""
        vals = [self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2], *self.dist]
        return {n: float(v) for n, v in zip(PARAM_NAMES, vals)}

    def camera(self, view: int) -> Camera:
        """The calibrated :class:`Camera` of view ``view`` (``world_from_camera``, board = world)."""
        return _camera(self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2], self.dist, self.rvecs[view],
                       self.tvecs[view], self.width, self.height)


def calibrate_camera(board_xyz, image_uv, image_size, *, max_steps: int = 200, rtol: float = 1e-10,
                     atol: float = 1e-10, fix_distortion: bool = False, verbose: bool = False) -> Calibration:
    """Calibrate a camera from N views of a planar board (Zhang init + optimistix LM).

    Args:
      board_xyz: ``(P, 3)`` board points, ``z = 0`` (e.g. :func:`fsjax.fit.chessboard.board_points`).
      image_uv: ``(N, P, 2)`` observed ``(u, v)`` pixels of every board point in every view
        (complete views; drop views where the board was not found).
      image_size: ``(width, height)`` in pixels.
      max_steps: LM step cap (``converged=False`` if reached).
      rtol, atol: optimistix LM tolerances.
      fix_distortion: keep ``dist = 0`` (pinhole-only calibration).
      verbose: print what it is doing: the problem size, the closed-form (Zhang) start, one
        line per Levenberg-Marquardt step from inside the compiled solve, and the result.

    Returns:
      :class:`Calibration`.

    Example:
        >>> from fsjax.fit.calibrate import calibrate_camera, project_board
        >>> from fsjax.fit.chessboard import board_points
        >>> P = board_points((9, 6))
        >>> truth = jnp.asarray([500.0, 505.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        >>> rv = [[0.3, 0.1, 0.0], [-0.2, 0.35, 0.1], [0.1, -0.3, -0.2], [0.4, 0.3, 0.05]]
        >>> tv = [[-4.0, -2.5, 14.0], [-3.0, -3.0, 12.0], [-4.5, -2.0, 15.0], [-4.0, -3.5, 13.0]]
        >>> uv = np.stack([np.asarray(project_board(truth, jnp.asarray(r), jnp.asarray(t), P))
        ...                for r, t in zip(rv, tv)])
        >>> cal = calibrate_camera(P, uv, (640, 480), fix_distortion=True)
        >>> bool(cal.converged), round(float(cal.K[0, 0]), 6), float(cal.rms_px) < 1e-8
        (True, 500.0, True)
    """
    board = np.asarray(board_xyz, np.float64)
    uv = np.asarray(image_uv, np.float64)
    if board.ndim != 2 or board.shape[1] != 3:
        raise ValueError(f"calibrate_camera: argument 'board_xyz' must have shape (P, 3), got {board.shape}")
    if uv.ndim != 3 or uv.shape[1:] != (board.shape[0], 2):
        raise ValueError(f"calibrate_camera: argument 'image_uv' must have shape (N, {board.shape[0]}, 2), got {uv.shape}")
    if uv.shape[0] < 2:
        raise ValueError(f"calibrate_camera: argument 'image_uv' must hold at least 2 views, got {uv.shape[0]}")
    if not np.allclose(board[:, 2], 0.0):
        raise ValueError("calibrate_camera: argument 'board_xyz' must be planar with z = 0")
    if not np.all(np.isfinite(uv)):
        raise ValueError("calibrate_camera: argument 'image_uv' must be finite, got non-finite image points "
                         "(drop views that failed)")
    width, height = int(image_size[0]), int(image_size[1])
    n = uv.shape[0]
    if verbose:
        print(f"calibrate_camera: {n} views x {board.shape[0]} points; closed-form start (Zhang)", flush=True)
    K0, rv0, tv0 = zhang_init(board[:, :2], uv, (width, height))
    if verbose:
        print(f"calibrate_camera: start fx {K0[0, 0]:.2f} fy {K0[1, 1]:.2f} cx {K0[0, 2]:.2f} cy {K0[1, 2]:.2f}; "
              f"Levenberg-Marquardt over {9 + 6 * n} parameters (the first call compiles)", flush=True)
    s = float(width)
    scale = np.array([s, s, s, s, 1, 1, 1, 1, 1.0])
    y0 = np.concatenate([[K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2], 0, 0, 0, 0, 0] / scale,
                         np.concatenate([rv0, tv0], 1).ravel()])
    dt = jnp.result_type(float)
    dmask = np.ones(9)
    if fix_distortion:
        dmask[4:] = 0.0
    scale_j = jnp.asarray(scale * dmask, dt)
    args = (jnp.asarray(board, dt), jnp.asarray(uv, dt), scale_j, (width, height))
    keep = np.r_[dmask > 0, np.ones(6 * n, bool)]
    y, nsteps, ok, r, sd_full = _solve_and_std(jnp.asarray(y0, dt), args, max_steps, rtol, atol,
                                               tuple(np.nonzero(keep)[0].tolist()), bool(verbose))
    K, intr, rv, tv, fields = _finish(y, r, sd_full, jnp.asarray(scale, dt), scale_j, ok, n)
    if verbose:
        print(f"calibrate_camera: {int(nsteps)} steps, converged {bool(ok)}, "
              f"rms {float(fields['rms_px']):.4f} px", flush=True)
    return Calibration(
        K=K, dist=intr[4:9], rvecs=rv, tvecs=tv, **fields, init_K=jnp.asarray(K0, dt), iterations=nsteps,
        converged=ok, width=width, height=height)


@functools.partial(jax.jit, static_argnames=("n",))
def _finish(y, r, sd_full, scale, scale_j, ok, n):
    """The solution unpacked: ``K``, intrinsics, poses and the result fields (RMS, scaled std, reason; one
    program; eager, these few lines compiled ~30 small ones)."""
    sd_full = sd_full.at[:9].multiply(scale)
    intr, rv, tv = _unpack(y, scale_j, n)
    d2 = jnp.sum(r.reshape(n, -1, 2) ** 2, axis=-1)
    z, o = jnp.zeros_like(intr[0]), jnp.ones_like(intr[0])
    K = jnp.stack([jnp.stack([intr[0], z, intr[2]]), jnp.stack([z, intr[1], intr[3]]), jnp.stack([z, z, o])])
    fields = dict(rms_px=jnp.sqrt(jnp.mean(d2)), per_view_rms_px=jnp.sqrt(jnp.mean(d2, axis=1)), std=sd_full[:9],
                  pose_std=sd_full[9:].reshape(n, 6),
                  reason=jnp.where(ok, reason_code("ok"), reason_code("max_iterations")).astype(jnp.int32))
    return K, intr, rv, tv, fields


# compiled with fsjax._linalg.FAST_COMPILE (calibrate_camera is called eagerly: its start is NumPy)
@filter_jit_fast_compile
def _solve_and_std(y0, args, max_steps, rtol, atol, keep, verbose=False):
    sol = _solve(y0, args, max_steps, rtol, atol, verbose)
    y = sol.value
    r = _residuals(y, args)
    keep = jnp.asarray(keep)
    J = jax.jacfwd(_residuals)(y, args)[:, keep]
    m, p = r.shape[0], J.shape[1]
    sig2 = jnp.sum(r * r) / max(m - p, 1)
    cov = jnp.linalg.inv(J.T @ J) * sig2
    sd = jnp.zeros(y.shape, y.dtype).at[keep].set(jnp.sqrt(jnp.abs(jnp.diag(cov))))
    sd = jnp.where(jnp.isfinite(sd), sd, jnp.nan)
    return y, jnp.asarray(sol.stats["num_steps"]), sol.result == optx.RESULTS.successful, r, sd


@eqx.filter_jit
def _solve(y0, args, max_steps, rtol, atol, verbose=False):
    solver = levenberg_marquardt(rtol, atol, verbose=verbose)
    return optx.least_squares(_residuals, solver, y0, args, max_steps=max_steps, throw=False)
