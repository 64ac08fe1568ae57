"""Ground-truth scenes for sub-pixel metrology (edges, discs, shafts, bar codes).

Every scene is rendered *exactly*: the ideal scene (a step, a disc, rectangles)
is blurred by a continuous Gaussian of standard deviation ``blur`` pixels (the
optics) and then integrated over each pixel's unit square (the sensor's fill
factor 1), so a pixel value is

    I[i, j] = lo + (hi - lo) * integral over [j - 1/2, j + 1/2] x [i - 1/2, i + 1/2]
              of (indicator * G_blur)(x, y) dx dy.

Pixel centres sit on integer indices; arrays are ``(row, col)``; positions in
the returned ground truth are in pixels in that frame. Axis-aligned shapes
(steps, rectangles, bars) have closed forms; the disc and tilted edges are
integrated over one axis in closed form and over the other by Gauss-Legendre
quadrature (error < 1e-12 in grey value). No noise is added: add your own.

Each generator returns ``(image, truth)``: a float64 numpy array and a dict of
the exact geometry. Only numpy and the standard library are used.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "step_edge",
    "edge_sweep",
    "tilted_edge",
    "blurred_disc",
    "shaft",
    "bar_code",
]

_erfc = np.frompyfunc(math.erfc, 1, 1)


def _ndtr(z):
    """Standard normal CDF, float64, accurate in both tails (``math.erfc``)."""
    z = np.asarray(z, dtype=float)
    return (0.5 * _erfc(-z / math.sqrt(2.0))).astype(float)


def _npdf(z):
    return np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)


def _kernel_cdf(u, blur: float):
    """Integral from -inf to ``u`` of the pixel kernel ``k = box(1) * G_blur``.

    ``k(u) = Phi((u + 1/2) / s) - Phi((u - 1/2) / s)``; its antiderivative is
    ``s [F((u + 1/2) / s) - F((u - 1/2) / s)]`` with ``F(z) = z Phi(z) + phi(z)``.
    ``blur = 0`` is the pure box (area sampling without optics).
    """
    u = np.asarray(u, dtype=float)
    if blur == 0:
        return np.clip(u + 0.5, 0.0, 1.0)
    s = float(blur)

    def big_f(z):
        return z * _ndtr(z) + _npdf(z)

    return s * (big_f((u + 0.5) / s) - big_f((u - 0.5) / s))


def _kernel_pdf(u, blur: float):
    u = np.asarray(u, dtype=float)
    s = float(blur)
    return _ndtr((u + 0.5) / s) - _ndtr((u - 0.5) / s)


def _interval(centres, a, b, blur: float):
    """Kernel mass of ``[a, b]`` seen by pixels at ``centres`` (1-D, exact)."""
    return _kernel_cdf(b - centres, blur) - _kernel_cdf(a - centres, blur)


def _check_blur(name: str, blur: float, lo: float = 0.0) -> float:
    blur = float(blur)
    if not (np.isfinite(blur) and blur >= lo):
        raise ValueError(f"{name}: argument 'blur' must be >= {lo:g}, got {blur}")
    return blur


def step_edge(edge_col: float = 23.37, *, shape: tuple[int, int] = (9, 48), lo: float = 0.2,
              hi: float = 0.8, blur: float = 0.7):
    """A vertical straight edge at a sub-pixel column, dark (``lo``) left, bright (``hi``) right.

    Args:
      edge_col: column of the edge in pixels (pixel centres on integers).
      shape: ``(H, W)``.
      lo, hi: grey values left and right of the edge.
      blur: Gaussian blur (pixels) of the optics before area integration; 0
        gives pure area sampling.

    Returns:
      ``(image, truth)`` with ``truth = {"edge_col": edge_col, "lo": lo, "hi": hi}``.
      Every row is the same exact profile ``lo + (hi - lo) * mass([edge_col, inf))``.
    """
    blur = _check_blur("step_edge", blur)
    h, w = shape
    cols = np.arange(w, dtype=float)
    frac = 1.0 - _kernel_cdf(edge_col - cols, blur)
    img = np.broadcast_to(lo + (hi - lo) * frac, (h, w)).copy()
    return img, {"edge_col": float(edge_col), "lo": lo, "hi": hi}


def edge_sweep(*, start: float = 23.0, step: float = 0.05, n: int = 21, **kw):
    """``n`` :func:`step_edge` images with the edge moved by ``step`` pixels each.

    The default moves the edge across one whole pixel (23.00 to 24.00 in 0.05 px
    steps). Returns ``(images (n, H, W), edge_cols (n,))``.
    """
    edges = start + step * np.arange(n)
    imgs = np.stack([step_edge(e, **kw)[0] for e in edges])
    return imgs, edges


def _gauss_legendre(a, b, n: int):
    x, w = np.polynomial.legendre.leggauss(n)
    a = np.asarray(a, dtype=float)[..., None]
    b = np.asarray(b, dtype=float)[..., None]
    return 0.5 * (b - a) * x + 0.5 * (b + a), 0.5 * (b - a) * w


def tilted_edge(point: tuple[float, float] = (20.3, 24.6), angle_deg: float = 20.0, *,
                shape: tuple[int, int] = (40, 48), lo: float = 0.2, hi: float = 0.8, blur: float = 0.7,
                nodes: int = 64):
    """A straight edge through ``point`` (row, col), bright on the side its normal points to.

    The edge line's normal makes ``angle_deg`` with the +col axis, counter-clockwise
    on screen (towards -row): unit normal ``n = (-sin a, cos a)`` in ``(row, col)``;
    the bright half-plane is ``n . (p - point) > 0``. ``angle_deg = 0`` is a
    vertical edge, bright to the right, like :func:`step_edge`.

    Returns ``(image, truth)`` with ``truth = {"point", "normal", "angle_deg"}``;
    the signed distance of a point ``p`` to the edge is ``normal . (p - point)``.
    """
    blur = _check_blur("tilted_edge", blur, lo=0.2)
    h, w = shape
    a = math.radians(angle_deg)
    nr, nc = -math.sin(a), math.cos(a)
    rows, cols = np.mgrid[0:h, 0:w].astype(float)
    # integrate over the axis along which the normal is larger in closed form
    if abs(nc) >= abs(nr):
        # bright where nc * (x - c0) > -nr * (y - r0): x > c0 - nr/nc (y - r0)   (if nc > 0)
        half = 0.5 + 8.0 * blur
        ys, wy = _gauss_legendre(rows - half, rows + half, nodes)
        xb = point[1] - nr / nc * (ys - point[0])
        mass_x = 1.0 - _kernel_cdf(xb - cols[..., None], blur)
        if nc < 0:
            mass_x = 1.0 - mass_x
        val = np.sum(wy * _kernel_pdf(ys - rows[..., None], blur) * mass_x, axis=-1)
    else:
        half = 0.5 + 8.0 * blur
        xs, wx = _gauss_legendre(cols - half, cols + half, nodes)
        yb = point[0] - nc / nr * (xs - point[1])
        mass_y = 1.0 - _kernel_cdf(yb - rows[..., None], blur)
        if nr < 0:
            mass_y = 1.0 - mass_y
        val = np.sum(wx * _kernel_pdf(xs - cols[..., None], blur) * mass_y, axis=-1)
    img = lo + (hi - lo) * val
    return img, {"point": tuple(map(float, point)), "normal": (nr, nc), "angle_deg": float(angle_deg)}


def blurred_disc(centre: tuple[float, float] = (31.37, 32.81), radius: float = 20.25, *,
                 shape: tuple[int, int] = (64, 64), lo: float = 0.2, hi: float = 0.8, blur: float = 0.6,
                 nodes: int = 96):
    """A bright disc of known radius and sub-pixel centre on a dark background.

    The column integral of the blurred, pixel-integrated disc is done in closed
    form for every chord; the row integral by Gauss-Legendre quadrature in the
    angle ``t`` of ``y = cy + R sin t`` (smooth at the poles).

    Returns ``(image, truth)`` with ``truth = {"centre": (row, col), "radius": R}``.
    """
    blur = _check_blur("blurred_disc", blur, lo=0.2)
    h, w = shape
    cy, cx = map(float, centre)
    r = float(radius)
    rows, cols = np.mgrid[0:h, 0:w].astype(float)
    dist = np.hypot(rows - cy, cols - cx)
    margin = 12.0 * blur + 1.0
    img = np.where(dist < r - margin, 1.0, 0.0)
    band = np.abs(dist - r) <= margin
    pr, pc = rows[band], cols[band]
    # rows of the disc that the pixel kernel sees: y in [pr - half, pr + half] within [cy - R, cy + R]
    half = 0.5 + 9.0 * blur
    y0 = np.clip(pr - half - cy, -r, r) / r
    y1 = np.clip(pr + half - cy, -r, r) / r
    t0, t1 = np.arcsin(y0), np.arcsin(y1)
    ts, wt = _gauss_legendre(t0, t1, nodes)
    ys = cy + r * np.sin(ts)
    half_chord = r * np.cos(ts)
    dy = r * np.cos(ts)  # dy/dt
    mass_x = _interval(pc[:, None], cx - half_chord, cx + half_chord, blur)
    img[band] = np.sum(wt * dy * _kernel_pdf(ys - pr[:, None], blur) * mass_x, axis=-1)
    return lo + (hi - lo) * img, {"centre": (cy, cx), "radius": r}


def _rects(shape, rects, blur):
    """Coverage of a union of disjoint axis-aligned rectangles ``(r0, r1, c0, c1)`` (closed form)."""
    h, w = shape
    rows = np.arange(h, dtype=float)[:, None]
    cols = np.arange(w, dtype=float)[None, :]
    cov = np.zeros(shape)
    for r0, r1, c0, c1 in rects:
        cov += _interval(rows, r0, r1, blur) * _interval(cols, c0, c1, blur)
    return cov


def shaft(diameters: tuple[float, ...] = (18.35, 30.7, 24.15), *, shape: tuple[int, int] = (56, 150),
          axis_row: float = 27.6, starts: tuple[float, ...] = (10.3, 55.6, 100.2), section_length: float = 40.0,
          lo: float = 0.15, hi: float = 0.85, blur: float = 0.6):
    """A back-lit turned shaft of stepped diameters: a dark silhouette on a bright background.

    The shaft's axis is the row ``axis_row``; section ``i`` spans columns
    ``[starts[i], starts[i] + section_length]`` and rows
    ``axis_row -+ diameters[i] / 2``. Sections must not overlap.

    Returns ``(image, truth)`` with ``truth`` holding ``"diameters"``,
    ``"top"``/``"bottom"`` (edge rows of each section), ``"centre_cols"`` (the
    middle column of each section, where to put a vertical caliper) and
    ``"axis_row"``.
    """
    blur = _check_blur("shaft", blur)
    d = np.asarray(diameters, dtype=float)
    s = np.asarray(starts, dtype=float)
    if d.shape != s.shape:
        raise ValueError("shaft: 'diameters' and 'starts' need the same length")
    if np.any(np.diff(s) < section_length):
        raise ValueError("shaft: sections overlap; increase the spacing of 'starts'")
    top, bottom = axis_row - d / 2, axis_row + d / 2
    cov = _rects(shape, [(t, b, c, c + section_length) for t, b, c in zip(top, bottom, s, strict=True)], blur)
    img = hi - (hi - lo) * cov
    return img, {"diameters": d, "top": top, "bottom": bottom, "centre_cols": s + section_length / 2,
                 "axis_row": float(axis_row)}


def bar_code(n_bars: int = 45, *, seed: int = 7, height: int = 15, first: float = 12.4,
             bar_range: tuple[float, float] = (2.0, 6.0), gap_range: tuple[float, float] = (2.0, 6.0),
             lo: float = 0.1, hi: float = 0.9, blur: float = 0.5):
    """``n_bars`` dark vertical bars of random sub-pixel widths and gaps on a bright ground.

    Bar and gap widths are drawn uniformly from ``bar_range``/``gap_range``
    (pixels) with a fixed ``seed``; the first bar starts at column ``first``.
    Bars span the full height (a 1-D scene seen along any row).

    Returns ``(image, truth)`` with ``truth = {"edges": (2 n_bars,) sorted edge
    columns, "bars": (n_bars, 2) start/end columns, "row": centre row}``.
    The image width leaves ``first`` pixels of margin after the last bar.
    """
    blur = _check_blur("bar_code", blur)
    rng = np.random.default_rng(seed)
    widths = rng.uniform(*bar_range, size=n_bars)
    gaps = rng.uniform(*gap_range, size=n_bars)
    starts = first + np.concatenate([[0.0], np.cumsum(widths + gaps)[:-1]])
    ends = starts + widths
    w = int(math.ceil(ends[-1] + first))
    cols = np.arange(w, dtype=float)
    cov = np.zeros(w)
    for a, b in zip(starts, ends, strict=True):
        cov += _interval(cols, a, b, blur)
    img = np.broadcast_to(hi - (hi - lo) * cov, (height, w)).copy()
    bars = np.stack([starts, ends], axis=1)
    return img, {"edges": np.sort(bars.ravel()), "bars": bars, "row": (height - 1) / 2}
