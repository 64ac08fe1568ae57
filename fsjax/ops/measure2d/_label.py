"""Connected components of a ``Region``: exact labelling and component filters.

Conventions:

* Connectivity is static: ``8`` (default: the 3x3 square, ``skimage.measure.label``'s
  default and ``scipy.ndimage.label(x, structure=np.ones((3, 3)))``) or ``4`` (the
  3x3 cross, SciPy's default structure). Pixels outside the image are background.
* Labels are numbered exactly as SciPy and scikit-image number them: ``1, 2, ...``
  in raster order of each component's first pixel (row-major, the smallest flat
  index). ``label`` therefore returns the *same array* as ``scipy.ndimage.label``,
  not only the same partition.
* Capacity: ``label`` holds at most ``capacity`` labels (static). Components
  beyond it (in the numbering order) are set to 0, ``Labels.truncated`` is True
  and ``Labels.count`` is ``min(true count, capacity)``, the number of labels
  actually present. The filters (``count_obj``, ``remove_small``,
  ``clear_border``, ``largest_component``) have no capacity: they work on every
  component.
* Algorithm (exact, jittable, ``vmap``-able): the image is cut into blocks whose
  foreground is always connected, 2x2 blocks for 8-connectivity and 1x2 blocks
  for 4-connectivity; block adjacency follows from the pixel pattern. On the
  block graph a Shiloach-Vishkin style union-find runs inside ``lax.while_loop``
  (per round: hook every root to the smallest root among its neighbours with a
  scatter-min, then two pointer-jumping steps). Pointers only decrease, so the
  loop reaches its fixed point (every block points at the smallest key of its
  component) after finitely many rounds; there is no iteration cap to hit, and
  in practice it takes 4-8 rounds (8 on the test shapes, among them a 127x127
  spiral that is one path of ~8000 pixels, and combs; 6 on 1024x1024 blobs).
  Labels are then ranked by an exact cumulative sum. For 8-connectivity the
  pointers hold the flat index of a block's first foreground pixel, so each
  root is its component's first pixel.
* Batching is ``jax.vmap``; a batch runs as many rounds as its slowest member.
* Speed (2-core CPU, 1024x1024 blobs, 110 components): several times slower
  than ``scipy.ndimage.label`` (a sequential C two-pass); every round costs a
  few gathers and one scatter over the ``H W / 4`` (8-connectivity) or
  ``H W / 2`` (4-connectivity) blocks. The measured figures are in the
  benchmarks, not here.
* Nothing here is differentiable (bool in, integers out).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax import lax

from ..._checks import check_choice, check_range, check_static_int
from ...registry import LogKnob, register
from ...types import Feature, Labels, Region

__all__ = [
    "label",
    "count_obj",
    "remove_small",
    "clear_border",
    "largest_component",
    "labels_to_region",
]

_REFS = [
    "A. Rosenfeld, J. L. Pfaltz, Sequential operations in digital picture processing, J. ACM 13(4), 1966",
    "Y. Shiloach, U. Vishkin, An O(log n) parallel connectivity algorithm, J. Algorithms 3(1), 1982",
    "Y. Zhang, A. Azad, Z. Hu, FastSV: a distributed-memory connected component algorithm "
    "with fast convergence, SIAM PP 2020",
]

_INT_MAX = jnp.iinfo(jnp.int32).max


# ---------------------------------------------------------------------------
# exact integer helpers
# ---------------------------------------------------------------------------


def _take(x, idx):
    """``x[idx]`` for indices known to be in bounds (no clamping pass)."""
    return x.at[idx].get(mode="promise_in_bounds")


def cumsum_count(x, block: int = 64):
    """Exact inclusive cumulative sum of a flat 0/1 (or small non-negative int) array.

    XLA's CPU scan is slow for long axes; this uses float32 products with a
    ``block x block`` upper-triangular matrix, level by level (exact while the
    total stays below ``2**24``; longer arrays fall back to ``jnp.cumsum``).
    Returns int32.
    """
    n = x.shape[0]
    if n >= 2**24:
        return jnp.cumsum(x.astype(jnp.int32))
    xf = x.astype(jnp.float32)
    if n <= block:
        return jnp.cumsum(xf).astype(jnp.int32)
    m = -(-n // block) * block
    xr = jnp.pad(xf, (0, m - n)).reshape(-1, block)
    tri = jnp.triu(jnp.ones((block, block), jnp.float32))
    within = xr @ tri
    tot = within[:, -1]
    before = cumsum_count(tot, block).astype(jnp.float32) - tot
    return (within + before[:, None]).reshape(-1)[:n].astype(jnp.int32)


def _shift(x, di: int, dj: int, fill):
    """``y[i, j] = x[i + di, j + dj]``, ``fill`` outside."""
    h, w = x.shape
    p = jnp.pad(x, 1, constant_values=fill)
    return p[1 + di:1 + di + h, 1 + dj:1 + dj + w]


# ---------------------------------------------------------------------------
# block graph and union-find
# ---------------------------------------------------------------------------


def _union_find(forward, key, node_of):
    """Smallest key of each node's component.

    ``forward``: list of ``(di, dj, mask)``: node ``(i, j)`` is adjacent to node
    ``(i + di, j + dj)`` where ``mask`` is True (the reverse edges are derived).
    ``key``: ``(h, w)`` int32, distinct per node; pointers hold keys and
    ``node_of`` maps a key back to the flat node index. Returns the root key of
    every node ``(h * w,)`` and the number of rounds.
    """
    h, w = key.shape
    dirs, bits = [], jnp.zeros((h, w), jnp.uint8)
    for di, dj, m in forward:
        for s, mm in ((1, m), (-1, _shift(m, -di, -dj, False))):
            bits = bits | (mm.astype(jnp.uint8) << len(dirs))
            dirs.append((s * di, s * dj))

    def neighbour_min(g):
        p = jnp.pad(g, 1, constant_values=_INT_MAX)
        out = g
        for k, (di, dj) in enumerate(dirs):
            nb = p[1 + di:1 + di + h, 1 + dj:1 + dj + w]
            out = jnp.minimum(out, jnp.where((bits >> k) & 1, nb, _INT_MAX))
        return out.reshape(-1)

    def jump(f):
        return _take(f, node_of(f))

    def body(state):
        f, _, rounds = state
        g = jump(f).reshape(h, w)                      # grandparent keys
        hook = neighbour_min(g)                        # smallest key next door
        fn = f.at[node_of(f)].min(hook, mode="promise_in_bounds")
        fn = jump(jump(fn))
        return fn, jnp.any(fn != f), rounds + 1

    f0 = key.reshape(-1)
    f, _, rounds = lax.while_loop(lambda s: s[1], body, (f0, jnp.asarray(True), jnp.int32(0)))
    return f, rounds


@dataclasses.dataclass(frozen=True)
class _Components:
    """Connected components on the block graph (internal)."""

    shape: tuple[int, int]
    root: jax.Array        # (n,) flat node index of each node's root
    is_root: jax.Array     # (n,) bool: foreground node that is its component's root
    npix: jax.Array        # (n,) int32 foreground pixels in the node
    border: jax.Array      # (n,) bool: the node has a foreground pixel on the image edge
    key: jax.Array         # (n,) int32 first foreground pixel (flat index in the padded grid)
    rank: Callable         # () -> ((n,) int32 1-based rank of each root in raster order, total)
    to_pixels: Callable    # (n,) values -> (H, W), 0 on background pixels
    rounds: jax.Array

    @property
    def n(self) -> int:
        return int(self.root.shape[0])

    def per_root(self, values, reducer: str = "sum"):
        """Reduce node values onto their root nodes (other nodes get the identity)."""
        fn = {"sum": jax.ops.segment_sum, "max": jax.ops.segment_max, "min": jax.ops.segment_min}[reducer]
        return fn(values, self.root, num_segments=self.n)


def _components8(mask) -> _Components:
    H, W = mask.shape
    Hp, Wp = H + H % 2, W + W % 2
    m = jnp.pad(mask, ((0, Hp - H), (0, Wp - W)))
    a, b, c, d = m[0::2, 0::2], m[0::2, 1::2], m[1::2, 0::2], m[1::2, 1::2]
    h, w = a.shape
    # 8-adjacency between 2x2 blocks from the facing pixels
    right = (b | d) & _shift(a | c, 0, 1, False)
    down = (c | d) & _shift(a | b, 1, 0, False)
    down_right = d & _shift(a, 1, 1, False)
    down_left = c & _shift(b, 1, -1, False)
    ii = jnp.arange(h, dtype=jnp.int32)[:, None]
    jj = jnp.arange(w, dtype=jnp.int32)[None, :]
    ka = 2 * ii * Wp + 2 * jj
    key = jnp.where(a, ka, jnp.where(b, ka + 1, jnp.where(c, ka + Wp, jnp.where(d, ka + Wp + 1, ka))))

    def node_of(p):
        r = lax.div(p, jnp.int32(Wp))
        return (r >> 1) * w + ((p - r * Wp) >> 1)

    f, rounds = _union_find([(0, 1, right), (1, 0, down), (1, 1, down_right), (1, -1, down_left)],
                            key, node_of)
    fg = a | b | c | d
    top = a | b
    is_root = fg.reshape(-1) & (f == key.reshape(-1))
    u8 = jnp.uint8
    npix = (a.astype(u8) + b.astype(u8) + c.astype(u8) + d.astype(u8)).astype(jnp.int32)
    # image-edge pixels of each block (the padding row/column is never foreground)
    rows, cols = 2 * ii, 2 * jj
    border = ((a | b) & (rows == 0)) | ((c | d) & (rows + 1 == H - 1)) | ((a | c) & (cols == 0)) \
        | ((b | d) & (cols + 1 == W - 1)) | ((a | b) & (rows == H - 1)) | ((a | c) & (cols == W - 1))

    def rank():
        first = is_root.reshape(h, w)
        marks = jnp.stack([first & top, first & ~top], axis=1)      # (h, 2, w): raster order of pixels
        cs = cumsum_count(marks.reshape(-1)).reshape(h, 2, w)
        r = jnp.where(top, cs[:, 0, :], cs[:, 1, :]).reshape(-1)
        return jnp.where(is_root, r, 0), cs[-1, -1, -1]

    def to_pixels(v):
        v = v.reshape(h, w)
        z = jnp.zeros((), v.dtype)
        full = jnp.stack([jnp.stack([jnp.where(a, v, z), jnp.where(b, v, z)], -1),
                          jnp.stack([jnp.where(c, v, z), jnp.where(d, v, z)], -1)], 1)
        return full.reshape(Hp, Wp)[:H, :W]

    return _Components((H, W), node_of(f), is_root, npix.reshape(-1), border.reshape(-1),
                       key.reshape(-1), rank, to_pixels, rounds)


def _components4(mask) -> _Components:
    H, W = mask.shape
    Wp = W + W % 2
    m = jnp.pad(mask, ((0, 0), (0, Wp - W)))
    a, b = m[:, 0::2], m[:, 1::2]
    h, w = a.shape
    # 4-adjacency between 1x2 blocks
    right = b & _shift(a, 0, 1, False)
    down = (a & _shift(a, 1, 0, False)) | (b & _shift(b, 1, 0, False))
    node = jnp.arange(h * w, dtype=jnp.int32).reshape(h, w)
    # node order is raster order of the first pixels, so node indices serve as keys
    f, rounds = _union_find([(0, 1, right), (1, 0, down)], node, lambda p: p)
    fg = (a | b).reshape(-1)
    is_root = fg & (f == node.reshape(-1))
    npix = (a.astype(jnp.int32) + b.astype(jnp.int32)).reshape(-1)
    ii = jnp.arange(h, dtype=jnp.int32)[:, None]
    jj = jnp.arange(w, dtype=jnp.int32)[None, :]
    border = ((a | b) & ((ii == 0) | (ii == H - 1))) | (a & (jj == 0)) | (b & (2 * jj + 1 == W - 1)) \
        | (a & (2 * jj == W - 1))
    key = jnp.where(a, ii * Wp + 2 * jj, ii * Wp + 2 * jj + 1).reshape(-1)

    def rank():
        cs = cumsum_count(is_root)
        return jnp.where(is_root, cs, 0), cs[-1]

    def to_pixels(v):
        v = v.reshape(h, w)
        z = jnp.zeros((), v.dtype)
        return jnp.stack([jnp.where(a, v, z), jnp.where(b, v, z)], -1).reshape(H, Wp)[:, :W]

    return _Components((H, W), f, is_root, npix, border.reshape(-1), key, rank, to_pixels, rounds)


def components(mask, connectivity: int = 8) -> _Components:
    """Connected components of a bool mask ``(H, W)`` (internal building block)."""
    return _components8(mask) if connectivity == 8 else _components4(mask)


def _check_conn(op: str, connectivity) -> int:
    check_choice(op, "connectivity", connectivity, (4, 8))
    return int(connectivity)


@functools.partial(jax.jit, static_argnums=(1, 2))
def label_array(mask, connectivity: int = 8, capacity: int = 1024):
    """``(labels (H, W) int32, count, truncated, rounds)`` for a bool mask (internal)."""
    cc = components(mask, connectivity)
    rank, total = cc.rank()
    keep = rank <= capacity
    node_label = _take(jnp.where(keep, rank, 0), cc.root)
    lab = cc.to_pixels(node_label.astype(jnp.int32))
    return lab, jnp.minimum(total, capacity), total > capacity, cc.rounds


# ---------------------------------------------------------------------------
# ops
# ---------------------------------------------------------------------------


@register(family="label", takes=Region, gives=Labels, differentiable=False, refs=_REFS)
def label(region: Region, /, *, connectivity: int = 8, capacity: int = 1024) -> Labels:
    """Connected-component labelling: one label per connected foreground component.

    Two foreground pixels share a label when a path of foreground pixels joins
    them, each step to one of the ``connectivity`` neighbours. Labels count
    ``1, 2, ...`` in raster order of each component's first pixel; background is 0.

    Args:
      region: foreground mask ``(H, W)``.
      connectivity: 8 (default; the 3x3 square) or 4 (the 3x3 cross); static.
      capacity: most labels kept (static int >= 1, default 1024). Components past
        it in the numbering order become background; ``truncated`` is then True.

    Returns:
      ``Labels`` with ``count = min(number of components, capacity)`` and
      ``truncated = number of components > capacity``.

    Matches ``scipy.ndimage.label(x, structure)`` (``np.ones((3, 3))`` for 8, the
    cross for 4) and ``skimage.measure.label(x, connectivity=2 or 1)``
    array-for-array, labels included (tested on thresholded coins, blobs,
    spirals, combs, checkerboards).

    Example:
      Two squares and a diagonal pair: 8-connectivity joins the pair, 4 does not:

      >>> import jax.numpy as jnp, fsjax
      >>> x = jnp.zeros((6, 8), bool).at[0:2, 0:2].set(True).at[1:3, 5:7].set(True)
      >>> x = x.at[4, 1].set(True).at[5, 2].set(True)
      >>> lab = fsjax.ops.label(fsjax.Region(x))
      >>> int(lab.count), [int(v) for v in lab.data[:, 1]], int(lab.data[5, 2])
      (3, [1, 1, 0, 0, 3, 0], 3)
      >>> int(fsjax.ops.label(fsjax.Region(x), connectivity=4).count)
      4
    """
    conn = _check_conn("label", connectivity)
    cap = check_static_int("label", "capacity", capacity, lo=1)
    lab, count, truncated, _ = label_array(region.data, conn, cap)
    return Labels(lab, count=count, truncated=truncated)


@register(family="label", takes=Region, gives=Feature, differentiable=False, refs=_REFS)
def count_obj(region: Region, /, *, connectivity: int = 8) -> Feature:
    """Number of connected components of a region (no capacity limit).

    Args:
      region: foreground mask ``(H, W)``.
      connectivity: 8 (default) or 4; static.

    Returns:
      ``Feature`` (unit ``"objects"``): the component count, exact.

    Equals the count returned by ``scipy.ndimage.label`` with the matching
    structure.

    Example:
      A 3 x 4 grid of separate dots:

      >>> import jax.numpy as jnp, fsjax
      >>> x = jnp.zeros((9, 12), bool).at[1::3, 1::3].set(True)
      >>> float(fsjax.ops.count_obj(fsjax.Region(x)).value)
      12.0
    """
    conn = _check_conn("count_obj", connectivity)
    return Feature(_count_core(region.data, conn), unit="objects")


@functools.partial(jax.jit, static_argnums=1)
def _count_core(mask, conn: int):
    return jnp.sum(components(mask, conn).is_root).astype(jnp.result_type(float))


@register(family="label", takes=Region, gives=Region, knobs={"min_area": LogKnob(1.0, 4096.0, unit="px")},
          differentiable=False, refs=_REFS)
def remove_small(region: Region, /, *, min_area: float = 64.0, connectivity: int = 8) -> Region:
    """Remove the connected components with fewer than ``min_area`` pixels.

    Keeps component ``C`` when ``|C| >= min_area``.

    Args:
      region: foreground mask ``(H, W)``.
      min_area: smallest kept area in pixels (knob ``a``, log-mapped to
        [1, 4096]); may be traced. Default 64.
      connectivity: 8 (default) or 4; static.

    Returns:
      The filtered ``Region``.

    Matches ``skimage.morphology.remove_small_objects(x, max_size=min_area - 1,
    connectivity=2 or 1)`` (scikit-image >= 0.26; ``min_size=min_area`` before)
    for integer ``min_area`` exactly (noisy thresholded coins).

    Example:
      A 4x4 square (16 px) survives ``min_area=10``, a 3x3 one (9 px) does not:

      >>> import jax.numpy as jnp, fsjax
      >>> x = jnp.zeros((10, 12), bool).at[1:5, 1:5].set(True).at[2:5, 8:11].set(True)
      >>> int(fsjax.ops.remove_small(fsjax.Region(x), min_area=10).data.sum())
      16
    """
    check_range("remove_small", "min_area", min_area, 0.0)
    conn = _check_conn("remove_small", connectivity)
    return Region(_remove_small_core(region.data, min_area, conn))


@functools.partial(jax.jit, static_argnums=2)
def _remove_small_core(mask, min_area, conn: int):
    cc = components(mask, conn)
    area = cc.per_root(cc.npix)
    return cc.to_pixels(_take(area, cc.root).astype(jnp.result_type(float)) >= min_area)


@register(family="label", takes=Region, gives=Region, differentiable=False, refs=_REFS)
def clear_border(region: Region, /, *, connectivity: int = 8) -> Region:
    """Remove the connected components that touch the image border.

    Args:
      region: foreground mask ``(H, W)``.
      connectivity: 8 (default) or 4; static.

    Returns:
      The ``Region`` without border-touching components.

    Matches ``skimage.segmentation.clear_border(skimage.measure.label(x,
    connectivity=...)) > 0`` exactly (``buffer_size=0``).

    Example:
      A square in the middle stays, one on the left edge goes:

      >>> import jax.numpy as jnp, fsjax
      >>> x = jnp.zeros((10, 10), bool).at[3:6, 0:2].set(True).at[3:6, 5:8].set(True)
      >>> out = fsjax.ops.clear_border(fsjax.Region(x))
      >>> int(out.data.sum()), bool(out.data[4, 6])
      (9, True)
    """
    conn = _check_conn("clear_border", connectivity)
    return Region(_clear_border_core(region.data, conn))


@functools.partial(jax.jit, static_argnums=1)
def _clear_border_core(mask, conn: int):
    cc = components(mask, conn)
    touch = cc.per_root(cc.border.astype(jnp.int32), "max")
    return cc.to_pixels(_take(touch, cc.root) <= 0)


@register(family="label", takes=Region, gives=Region, differentiable=False, refs=_REFS)
def largest_component(region: Region, /, *, connectivity: int = 8) -> Region:
    """Keep only the connected component with the most pixels.

    Ties go to the component whose first pixel comes first in raster order (the
    lower label of :func:`label`). An empty region stays empty.

    Args:
      region: foreground mask ``(H, W)``.
      connectivity: 8 (default) or 4; static.

    Returns:
      The ``Region`` of the largest component.

    Equals ``lab == argmax(bincount(lab)[1:]) + 1`` with ``lab`` from
    ``scipy.ndimage.label`` (NumPy's argmax also takes the first maximum).

    Example:
      A 3x3 square beats a 2x4 bar:

      >>> import jax.numpy as jnp, fsjax
      >>> x = jnp.zeros((8, 10), bool).at[0:2, 0:4].set(True).at[4:7, 5:8].set(True)
      >>> out = fsjax.ops.largest_component(fsjax.Region(x))
      >>> int(out.data.sum()), bool(out.data[5, 6])
      (9, True)
    """
    conn = _check_conn("largest_component", connectivity)
    return Region(_largest_core(region.data, conn))


@functools.partial(jax.jit, static_argnums=1)
def _largest_core(mask, conn: int):
    cc = components(mask, conn)
    area = jnp.where(cc.is_root, cc.per_root(cc.npix), -1)
    best_area = jnp.max(area)
    best_key = jnp.min(jnp.where(cc.is_root & (area == best_area), cc.key, _INT_MAX))
    winner = cc.is_root & (cc.key == best_key)
    return cc.to_pixels(_take(winner, cc.root))


@register(family="label", takes=Labels, gives=Region, differentiable=False, refs=_REFS)
def labels_to_region(labels: Labels, /) -> Region:
    """The union of all labels: the region of non-zero label pixels.

    Args:
      labels: label image ``(H, W)``.

    Returns:
      ``Region`` ``labels != 0``.

    Example:
      >>> import jax.numpy as jnp, fsjax
      >>> lab = fsjax.Labels(jnp.array([[0, 1, 1], [2, 0, 3]], jnp.int32))
      >>> int(fsjax.ops.labels_to_region(lab).data.sum())
      4
    """
    return Region(labels.data != 0)
