"""Chessboard inner-corner detection: saddle response, grid ordering, sub-pixel refinement.

Conventions:

* Images are greyscale ``(H, W)`` floats in [0, 1]; corner positions are returned as pixel
  coordinates ``uv = (u, v) = (column, row)`` with pixel centres on integers (the
  convention of :mod:`fsjax.render.camera` and of ``cv2.cornerSubPix``).
* A pattern ``(nx, ny)`` counts *inner* corners (OpenCV's ``patternSize``); corners are
  returned row-major, ``nx`` along a row, and the board coordinates of corner ``k`` are
  ``(k % nx, k // nx, 0)`` in square units (:func:`board_points`). The ordering is always
  right-handed in the image (board x to board y turns like image u to image v), so the
  board is seen from its front and a proper rotation maps it into the camera; the
  remaining 180-degree ambiguity of a non-square board is resolved by putting corner 0
  in the image half-plane nearest the origin along the board's x axis.

Method (three stages; the first and last are jit-compiled JAX, the middle is eager NumPy
because it is a data-dependent graph search):

1. **Saddle response.** ``S = Ixy^2 - Ixx Iyy`` (minus the Hessian determinant) of the
   image smoothed with a Gaussian of ``sigma`` px. An X-junction of two dark and two light
   quadrants is a saddle of the intensity surface, so ``S > 0`` there; at an ideal saddle
   of contrast ``c`` it is 4x larger than at the L-shaped corners of the board's border,
   and edges/blobs give ``S <= 0``. Local maxima (``(2 nms + 1)^2`` window) above
   ``rel_threshold`` times the strongest response are the candidates.
2. **Grid ordering.** From each of the strongest candidates (seeds) the lattice is grown
   breadth-first: a node predicts its four neighbours by linear extrapolation through the
   opposite neighbour when known (which follows perspective) or by the local lattice
   vectors, and accepts the nearest unused candidate within ``0.3`` of the local spacing.
   The grown lattice must contain a fully populated ``nx x ny`` window that is a whole board:
   its ``(nx + 1) x (ny + 1)`` squares alternate light/dark and the squares one step outside
   it do not continue the checker (:func:`_board_check`). A miscounted pattern therefore fails
   like ``cv2.findChessboardCorners`` does: a window inside a larger board, or one that takes
   in the L-shaped corners of the board's border, is refused. Of several whole-board windows
   the one with the largest total response wins. Nothing found gives ``converged=False`` with a
   reason and NaN corners: never a partial grid.
3. **Sub-pixel refinement** by the gradient-orthogonality condition (Forstner and
   Gulch 1987; the criterion of OpenCV's ``cornerSubPix``): for the true corner ``q`` and
   every pixel ``p`` near it, the image gradient ``g_p`` is orthogonal to ``p - q`` (either
   ``g_p = 0`` in a flat patch or ``p - q`` runs along an edge through ``q``). Minimising
   ``sum_p w_p (g_p . (q - p))^2`` gives ``q = (sum w g g^T)^-1 sum w g g^T p``; the window
   (half-size ``win``, Gaussian weights of sigma ``win / 2``) is resampled bilinearly at
   the current ``q`` and the step repeated until it moves less than ``1e-4`` px (at most 50
   times; the count is reported).

References: Forstner, W. and Gulch, E. (1987) "A fast operator for detection and precise
location of distinct points, corners and centres of circular features", ISPRS
Intercommission Workshop, Interlaken; Bennett, S. and Lasenby, J. (2014) "ChESS - Quick and
robust detection of chess-board features", CVIU 118; Zhang, Z. (2000) (see
:mod:`fsjax.fit.calibrate`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._checks import check_positive, check_static_int
from ..ops.measure2d._caliper import bilinear
from ..types.results import FitResult, reason_code, reason_message, renamed

__all__ = ["ChessboardCorners", "saddle_response", "refine_corners", "find_chessboard", "board_points"]


class ChessboardCorners(FitResult):
    """Result of :func:`find_chessboard`.

    A fit result (base fields ``converged``, ``reason``, ``iterations``) without a residual:
    the detector measures corners, it does not minimise one error over the board (the
    per-corner sub-pixel ``shift`` is reported instead; ``residual_name`` is ``None``).

    Attributes:
        corners: ``(nx * ny, 2)`` sub-pixel ``(u, v)`` corners, row-major (NaN when not found).
        converged: the full grid was found (was ``found``).
        reason: code of :data:`fsjax.types.RESULTS`: ``ok``, ``not_found`` (no saddle response,
          too few candidates, no complete grid), ``pattern_mismatch`` or ``refinement_failed``.
        detail: ``""`` when found, else the specific why-not text (static; was the string
          ``reason``: ``"too few saddle candidates (40 < 54)"``...).
        n_candidates: saddle candidates after non-maximum suppression.
        iterations: ``(nx * ny,)`` sub-pixel iterations used per corner.
        shift: ``(nx * ny,)`` distance (px) the sub-pixel stage moved each corner from
          its integer response peak.
    """

    corners: Float[Array, "n 2"]
    converged: Bool[Array, ""]
    reason: Int[Array, ""]
    detail: str = eqx.field(static=True)
    n_candidates: int = eqx.field(static=True)
    iterations: Int[Array, " n"]
    shift: Float[Array, " n"]

    found = renamed("converged")

    @property
    def message(self) -> str:
        """The reason's text, then the specific ``detail`` (``"ok"`` when found)."""
        base = reason_message(self.reason)
        return f"{base}: {self.detail}" if self.detail else base


def board_points(pattern=(9, 6), square: float = 1.0) -> np.ndarray:
    """Board coordinates ``(nx * ny, 3)`` of the inner corners, row-major, ``z = 0``, in ``square`` units.

    Example:
        >>> from fsjax.fit.chessboard import board_points
        >>> board_points((3, 2))[4].tolist()
        [1.0, 1.0, 0.0]
    """
    nx, ny = int(pattern[0]), int(pattern[1])
    j, i = np.mgrid[0:ny, 0:nx]
    return np.stack([i.ravel(), j.ravel(), np.zeros(nx * ny)], axis=1).astype(np.float64) * float(square)


def _gauss_smooth(x, sigma: float):
    r = int(4.0 * sigma + 0.5)
    k = jnp.arange(-r, r + 1, dtype=x.dtype)
    g = jnp.exp(-0.5 * (k / sigma) ** 2)
    g = g / jnp.sum(g)
    xp = jnp.pad(x, ((r, r), (0, 0)), mode="symmetric")
    x = sum(g[i] * xp[i:i + x.shape[0]] for i in range(2 * r + 1))
    xp = jnp.pad(x, ((0, 0), (r, r)), mode="symmetric")
    return sum(g[i] * xp[:, i:i + x.shape[1]] for i in range(2 * r + 1))


def saddle_response(img, *, sigma: float = 1.5):
    """Saddle response ``Ixy^2 - Ixx Iyy`` (scale-normalised by ``sigma^4``) of a greyscale image.

    Positive at X-junctions (chessboard inner corners), about 4x weaker at L-corners, zero or
    negative on edges and blobs. Second derivatives are central differences of the image
    smoothed with a Gaussian of ``sigma`` px (symmetric boundary).

    Example:
        >>> from fsjax.fit.chessboard import saddle_response
        >>> yy, xx = np.mgrid[0:31, 0:31]
        >>> img = 0.5 + 0.4 * np.sign((xx - 15.0) * (yy - 15.0))
        >>> s = np.asarray(saddle_response(img, sigma=2.0))
        >>> [int(i) for i in np.unravel_index(np.argmax(s), s.shape)]
        [15, 15]
    """
    x = jnp.asarray(img, dtype=jnp.result_type(float))
    if x.ndim != 2:
        raise ValueError(f"saddle_response: argument 'img' must be a 2-D image, got shape {x.shape}")
    check_positive("saddle_response", "sigma", sigma)
    return _saddle_jit(x, float(sigma))


@jax.jit
def _second_derivs(s):
    sp = jnp.pad(s, 1, mode="edge")
    ixx = sp[1:-1, 2:] - 2 * s + sp[1:-1, :-2]
    iyy = sp[2:, 1:-1] - 2 * s + sp[:-2, 1:-1]
    ixy = 0.25 * (sp[2:, 2:] - sp[2:, :-2] - sp[:-2, 2:] + sp[:-2, :-2])
    return ixx, iyy, ixy


def _saddle(x, sigma):
    s = _gauss_smooth(x, sigma)
    ixx, iyy, ixy = _second_derivs(s)
    return (ixy * ixy - ixx * iyy) * sigma ** 4


_saddle_jit = jax.jit(_saddle, static_argnums=1)


# ---------------------------------------------------------------------------
# sub-pixel refinement (gradient orthogonality)
# ---------------------------------------------------------------------------


def _refine_one(x, q0, win: int, max_iter: int, tol):
    d = jnp.arange(-win - 1, win + 2, dtype=x.dtype)
    dy, dx = jnp.meshgrid(d, d, indexing="ij")
    inner = (slice(1, -1), slice(1, -1))
    sw = jnp.exp(-0.5 * (dx[inner] ** 2 + dy[inner] ** 2) / (0.5 * win) ** 2)

    def step(q):
        patch = bilinear(x, q[1] + dy, q[0] + dx, mode="nearest")
        gx = 0.5 * (patch[1:-1, 2:] - patch[1:-1, :-2])
        gy = 0.5 * (patch[2:, 1:-1] - patch[:-2, 1:-1])
        px, py = q[0] + dx[inner], q[1] + dy[inner]
        a = jnp.sum(sw * gx * gx)
        b = jnp.sum(sw * gx * gy)
        c = jnp.sum(sw * gy * gy)
        bx = jnp.sum(sw * (gx * gx * px + gx * gy * py))
        by = jnp.sum(sw * (gx * gy * px + gy * gy * py))
        det = a * c - b * b
        ok = det > 1e-12 * (a + c) ** 2
        dets = jnp.where(ok, det, 1.0)
        qn = jnp.stack([(c * bx - b * by) / dets, (a * by - b * bx) / dets])
        return jnp.where(ok, qn, jnp.nan)

    def cond(s):
        q, moved, i = s
        return (moved > tol) & (i < max_iter) & jnp.all(jnp.isfinite(q))

    def body(s):
        q, _, i = s
        qn = step(q)
        return qn, jnp.linalg.norm(qn - q), i + 1

    q, moved, it = jax.lax.while_loop(cond, body, (q0, jnp.asarray(jnp.inf, x.dtype), jnp.asarray(0)))
    # a corner that wanders more than the window has locked onto something else: fail closed
    far = jnp.linalg.norm(q - q0) > win
    return jnp.where(far | ~(moved <= tol), jnp.nan, q), it


_refine_jit = jax.jit(jax.vmap(_refine_one, in_axes=(None, 0, None, None, None)), static_argnums=(2, 3))


def refine_corners(img, corners_uv, *, win: int = 5, max_iter: int = 50, tol: float = 1e-4):
    """Sub-pixel corners by the Forstner gradient-orthogonality iteration (``cornerSubPix``'s criterion).

    Args:
      img: ``(H, W)`` greyscale image.
      corners_uv: ``(N, 2)`` initial ``(u, v)`` corners (within about ``win / 2`` px).
      win: static half-size of the window in px (window ``2 win + 1`` square, Gaussian
        weights of sigma ``win / 2``).
      max_iter: iteration cap; ``tol``: stop when a step moves less than this (px).

    Returns:
      ``(corners (N, 2), iterations (N,))``; a corner that did not converge within the cap,
      whose normal matrix is singular (flat patch, single edge), or that moved further than
      ``win`` is NaN.

    Example:
        >>> from fsjax.fit.chessboard import refine_corners
        >>> yy, xx = np.mgrid[0:41, 0:41].astype(float)
        >>> img = 0.5 + 0.4 * np.tanh(0.5 * (xx - 20.3)) * np.tanh(0.5 * (yy - 19.6))
        >>> q, _ = refine_corners(img, np.array([[20.0, 20.0]]))
        >>> float(np.abs(np.asarray(q[0]) - [20.3, 19.6]).max()) < 0.02  # bilinear resampling bias ~0.01 px
        True
    """
    x = jnp.asarray(img, dtype=jnp.result_type(float))
    if x.ndim != 2:
        raise ValueError(f"refine_corners: argument 'img' must be a 2-D image, got shape {x.shape}")
    win = check_static_int("refine_corners", "win", win, lo=2)
    q0 = jnp.asarray(corners_uv, dtype=x.dtype).reshape(-1, 2)
    return _refine_jit(x, q0, int(win), int(max_iter), jnp.asarray(tol, x.dtype))


# ---------------------------------------------------------------------------
# candidates and grid ordering (eager NumPy: a data-dependent graph search)
# ---------------------------------------------------------------------------


def _candidates(resp: np.ndarray, nms: int, rel_threshold: float, capacity: int):
    from scipy import ndimage as ndi

    mx = ndi.maximum_filter(resp, size=2 * nms + 1, mode="nearest")
    top = float(resp.max())
    peak = (resp == mx) & (resp > rel_threshold * top) & (resp > 0)
    r, c = np.nonzero(peak)
    s = resp[r, c]
    order = np.argsort(-s)[:capacity]
    return np.stack([c[order], r[order]], axis=1).astype(np.float64), s[order]


def _grow(p: np.ndarray, s: np.ndarray, seed: int, tol: float):
    d = np.linalg.norm(p - p[seed], axis=1)
    d[seed] = np.inf
    near = np.argsort(d)[:8]
    v1 = p[near[0]] - p[seed]
    n1 = np.linalg.norm(v1)
    if not np.isfinite(n1) or n1 == 0:
        return None
    v2 = None
    for k in near[1:]:
        w = p[k] - p[seed]
        cosang = abs(np.dot(w, v1)) / (np.linalg.norm(w) * n1)
        if cosang < 0.5 and 0.5 < np.linalg.norm(w) / n1 < 2.0:
            v2 = w
            break
    if v2 is None:
        return None
    grid = {(0, 0): seed}
    vec = {(0, 0): (v1, v2)}
    used = {seed}
    queue = [(0, 0)]
    while queue:
        node = queue.pop(0)
        pn = p[grid[node]]
        va, vb = vec[node]
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            nb = (node[0] + di, node[1] + dj)
            if nb in grid:
                continue
            opp = (node[0] - di, node[1] - dj)
            if opp in grid:
                pred = 2 * pn - p[grid[opp]]
            else:
                pred = pn + di * va + dj * vb
            step = pred - pn
            spacing = np.linalg.norm(step)
            dd = np.linalg.norm(p - pred, axis=1)
            for u in used:
                dd[u] = np.inf
            k = int(np.argmin(dd))
            if dd[k] < tol * spacing:
                grid[nb] = k
                used.add(k)
                w = p[k] - pn
                vec[nb] = (di * w, vb) if di else (va, dj * w)
                queue.append(nb)
    return grid


def _windows(grid: dict, s: np.ndarray, nx: int, ny: int) -> list:
    """Every fully populated ``nx x ny`` window of the grown lattice, largest total response first."""
    ii = np.array([k[0] for k in grid])
    jj = np.array([k[1] for k in grid])
    out = []
    for (wi, wj, swap) in ((nx, ny, False), (ny, nx, True)):
        for i0 in range(ii.min(), ii.max() - wi + 2):
            for j0 in range(jj.min(), jj.max() - wj + 2):
                idx = [[grid.get((i0 + a, j0 + b)) for a in range(wi)] for b in range(wj)]
                if any(v is None for row in idx for v in row):
                    continue
                idx = np.array(idx)  # (wj, wi): rows along j
                out.append((float(s[idx].sum()), idx, swap))
    out.sort(key=lambda w: -w[0])
    return out


def _homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """DLT homography ``src -> dst`` (both ``(N, 2)``, N >= 4), Hartley-normalised."""
    def norm(x):
        c = x.mean(0)
        sc = np.sqrt(2.0) / max(float(np.linalg.norm(x - c, axis=1).mean()), 1e-300)
        return np.array([[sc, 0, -sc * c[0]], [0, sc, -sc * c[1]], [0, 0, 1.0]])

    ts, td = norm(src), norm(dst)
    a = np.c_[src, np.ones(len(src))] @ ts.T
    b = np.c_[dst, np.ones(len(dst))] @ td.T
    z = np.zeros((len(a), 3))
    rows = np.concatenate([np.c_[a, z, -b[:, :1] * a], np.c_[z, a, -b[:, 1:2] * a]])
    h = np.linalg.svd(rows)[2][-1].reshape(3, 3)
    return np.linalg.inv(td) @ h @ ts


# Board-size check. A pattern counts inner corners, so a board of nx x ny inner corners is a
# checker of (nx + 1) x (ny + 1) alternating squares, and the squares one step further out do
# not continue it (margin, background). A lattice window is accepted only when both hold, so a
# miscounted pattern fails as it does in ``cv2.findChessboardCorners``: a window inside a larger
# board fails the second test, a window that takes in the L-shaped corners of the board's border
# fails the first. Square intensities are sampled at the centres predicted by a homography fitted
# to the window's corners (mean of 5 bilinear samples per square; NaN off the image); the tests
# compare adjacent squares relative to the window's own median contrast, so they do not depend
# on the lighting level or the image's value scale.
_CELL_SAMPLES = np.array([[0.0, 0.0], [0.2, 0.2], [-0.2, 0.2], [0.2, -0.2], [-0.2, -0.2]])
_PAIR_MARGIN = 0.3  # adjacent light/dark squares must differ by this fraction of the median contrast
_CONTINUE_FRAC = 0.75  # an outer strip alternating in this fraction of its pairs continues the board


def _board_check(a: np.ndarray, corners: np.ndarray, nx: int, ny: int) -> str:
    """``""`` when the ordered coarse ``(nx * ny, 2)`` corners bound a whole board, else why not."""
    from scipy import ndimage as ndi

    H = _homography(board_points((nx, ny))[:, :2], corners)
    jj, ii = np.mgrid[-2:ny + 1, -2:nx + 1]  # square (i, j) has centre (i + 0.5, j + 0.5)
    b = np.stack([ii, jj], -1)[..., None, :] + 0.5 + _CELL_SAMPLES
    p = np.c_[b.reshape(-1, 2), np.ones(b.size // 2)] @ H.T
    val = ndi.map_coordinates(a, [p[:, 1] / p[:, 2], p[:, 0] / p[:, 2]], order=1, mode="constant", cval=np.nan)
    c = val.reshape(b.shape[:-1]).mean(-1)  # (ny + 3, nx + 3): the window's squares and one ring
    par = np.where((ii + jj) % 2 == 0, 1.0, -1.0)
    eh = (c[:, :-1] - c[:, 1:]) * par[:, :-1]  # > 0 where the even-parity square is the lighter
    ev = (c[:-1, :] - c[1:, :]) * par[:-1, :]
    inside = np.r_[eh[1:ny + 2, 1:nx + 1].ravel(), ev[1:ny + 1, 1:nx + 2].ravel()]
    orient = np.sign(np.nanmedian(inside))
    contrast = float(np.nanmedian(inside * orient)) if np.isfinite(orient) else np.nan
    if not contrast > 0:
        return f"no checker contrast inside the {nx}x{ny} window"
    thr = _PAIR_MARGIN * contrast
    bad = int(np.sum(~(inside * orient > thr)))
    if bad:
        return (f"the {nx}x{ny} window is not a checker of {nx + 1}x{ny + 1} alternating squares "
                f"({bad} of {inside.size} adjacent pairs do not alternate): pattern larger than the board?")
    strips = {
        "left": np.r_[eh[1:ny + 2, 0], ev[1:ny + 1, 0]],
        "right": np.r_[eh[1:ny + 2, nx + 1], ev[1:ny + 1, nx + 2]],
        "top": np.r_[ev[0, 1:nx + 2], eh[0, 1:nx + 1]],
        "bottom": np.r_[ev[ny + 1, 1:nx + 2], eh[ny + 2, 1:nx + 1]],
    }
    more = [k for k, e in strips.items() if np.mean(e * orient > thr) >= _CONTINUE_FRAC]
    if more:
        return (f"the board continues beyond the {nx}x{ny} window ({', '.join(more)} side): "
                "pattern smaller than the board")
    return ""


def _order(idx: np.ndarray, swap: bool, p: np.ndarray, nx: int, ny: int) -> np.ndarray:
    if swap:  # the long side runs along j: make it the row direction
        idx = idx.T
    pts = p[idx]  # (ny, nx, 2)
    di = pts[0, -1] - pts[0, 0]
    dj = pts[-1, 0] - pts[0, 0]
    if di[0] * dj[1] - di[1] * dj[0] < 0:  # left-handed in the image: flip the rows
        pts = pts[::-1]
        di = pts[0, -1] - pts[0, 0]
    # 180-degree ambiguity: board x axis pointing to +u (or +v when vertical)
    ax = 0 if abs(di[0]) >= abs(di[1]) else 1
    if di[ax] < 0:
        pts = pts[::-1, ::-1]
    return pts.reshape(nx * ny, 2)


def find_chessboard(img, pattern=(9, 6), *, sigma: float = 2.0, nms: int = 4, rel_threshold: float = 0.1,
                    capacity: int = 400, win: int = 11, max_seeds: int = 40, tol: float = 0.3) -> ChessboardCorners:
    """Find and order the inner corners of a chessboard, refined to sub-pixel accuracy.

    Args:
      img: ``(H, W)`` greyscale image in [0, 1] (uint8 is divided by 255).
      pattern: inner corners ``(nx, ny)`` (OpenCV ``patternSize``), e.g. ``(9, 6)``.
      sigma: Gaussian scale (px) of the saddle response; 2 suits squares of 12-80 px.
      nms: half-size of the non-maximum suppression window (px).
      rel_threshold: candidates need a response above this fraction of the image maximum.
      capacity: at most this many candidates (strongest first) enter the grid search.
      win: half-size of the sub-pixel window (px), see :func:`refine_corners`; 11 is OpenCV's
        ``winSize=(11, 11)`` (a 23 px window).
      max_seeds: number of strongest candidates tried as seeds for the grid growth.
      tol: a predicted neighbour accepts a candidate within ``tol`` times the local spacing.

    Returns:
      :class:`ChessboardCorners`; ``converged=False`` with a ``reason`` and NaN corners when no
      complete grid is found, when ``pattern`` does not match the board (a board with more
      or fewer inner corners than ``pattern``, as OpenCV refuses it), or a corner fails to
      refine. ``pattern`` and its transpose are the same board (the ordering follows the
      image, see the module notes).

    Matches ``cv2.findChessboardCorners`` + ``cv2.cornerSubPix`` (winSize 11) on the bundled
    photographs to a median of about 0.02 px (``tests/fit/test_chessboard.py``).

    Example:
        >>> from fsjax.fit.chessboard import find_chessboard
        >>> yy, xx = np.mgrid[0:120, 0:150].astype(float)
        >>> sq = ((np.floor((xx - 10.5) / 16) + np.floor((yy - 12.5) / 16)) % 2) * 0.8 + 0.1
        >>> inside = (xx > 10.5) & (xx < 10.5 + 16 * 8) & (yy > 12.5) & (yy < 12.5 + 16 * 6)
        >>> img = np.where(inside, sq, 0.9)
        >>> res = find_chessboard(img, (7, 5), win=5)
        >>> bool(res.converged), [round(float(v), 2) for v in res.corners[0]]
        (True, [26.5, 28.5])
    """
    nx, ny = int(pattern[0]), int(pattern[1])
    if nx < 2 or ny < 2:
        raise ValueError(f"find_chessboard: argument 'pattern' must have at least 2 x 2 inner corners, got {pattern}")
    a = np.asarray(img)
    if a.ndim != 2:
        raise ValueError(f"find_chessboard: argument 'img' must be a 2-D greyscale image, got shape {a.shape}")
    if a.dtype == np.uint8:
        a = a.astype(np.float64) / 255.0
    n = nx * ny
    dt = jnp.result_type(float)

    def fail(detail, ncand, why="not_found"):
        return ChessboardCorners(jnp.full((n, 2), jnp.nan, dt), jnp.asarray(False), jnp.int32(reason_code(why)),
                                 detail, ncand, jnp.zeros((n,), jnp.int32), jnp.full((n,), jnp.nan, dt))

    resp = np.asarray(saddle_response(a, sigma=sigma))
    if not np.all(np.isfinite(resp)) or resp.max() <= 0:
        return fail("no saddle response (flat or non-finite image)", 0)
    p, s = _candidates(resp, int(nms), float(rel_threshold), int(capacity))
    if len(p) < n:
        return fail(f"too few saddle candidates ({len(p)} < {n})", len(p))
    windows, why = None, ""
    for seed in range(min(int(max_seeds), len(p))):
        grid = _grow(p, s, seed, float(tol))
        if grid is None or len(grid) < n:
            continue
        windows = _windows(grid, s, nx, ny)
        if windows:
            break
    if not windows:
        return fail(f"no complete {nx}x{ny} grid among {len(p)} candidates", len(p))
    coarse = None
    for w in windows:
        c = _order(w[1], w[2], p, nx, ny)
        bad = _board_check(a, c, nx, ny)
        if not bad:
            coarse = c
            break
        why = why or bad  # the reason of the strongest window
    if coarse is None:
        return fail(f"pattern {nx}x{ny} does not match the board: {why}", len(p), "pattern_mismatch")
    q, it = refine_corners(a, coarse, win=win)
    if not bool(jnp.all(jnp.isfinite(q))):
        return fail("sub-pixel refinement failed at some corner", len(p), "refinement_failed")
    shift = jnp.linalg.norm(q - jnp.asarray(coarse, q.dtype), axis=1)
    # a corner that slid onto a neighbour: refined corners must keep at least a third of the
    # smallest coarse lattice spacing between them
    grid_q = np.asarray(q).reshape(ny, nx, 2)
    gc = coarse.reshape(ny, nx, 2)
    spacing = min(np.linalg.norm(np.diff(gc, axis=0), axis=-1).min(), np.linalg.norm(np.diff(gc, axis=1), axis=-1).min())
    dq = np.linalg.norm(grid_q.reshape(-1, 1, 2) - grid_q.reshape(1, -1, 2), axis=-1) + np.eye(n) * 1e9
    if dq.min() < spacing / 3.0:
        return fail("sub-pixel refinement merged neighbouring corners", len(p), "refinement_failed")
    return ChessboardCorners(q, jnp.asarray(True), jnp.int32(reason_code("ok")), "", len(p), it.astype(jnp.int32),
                             shift)
