"""Export and import of :class:`fsjax.Gaussians`: the 3DGS PLY layout and the 32-byte ``.splat`` layout.

**PLY** (the layout of the reference 3DGS implementation, read by most viewers), one
``vertex`` element, binary little-endian, every property ``float32``::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3(K-1)-1} opacity
    scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3

``f_dc_c`` is the degree-0 SH coefficient of channel ``c``; ``f_rest`` is channel-major
(``f_rest[c * (K-1) + k - 1]`` is coefficient ``k`` of channel ``c``); ``opacity`` is the
logit, ``scale_i`` the log-scale, ``rot`` the quaternion ``(w, x, y, z)`` as stored (not
normalised); normals are written as zeros. Only valid splats are written. Round trip: exact
up to float32 rounding (relative error <= 2^-24 per value; tested).

**.splat** (the compact layout of the widely used WebGL viewers), 32 bytes per splat,
little-endian, no header::

    3 x float32 position | 3 x float32 scale (linear, exp(log_scale)) |
    4 x uint8 RGBA | 4 x uint8 quaternion (w, x, y, z)

RGB is the degree-0 colour ``0.5 + C0 f_dc`` clamped to [0, 1] and rounded to 1/255 (higher
SH degrees are dropped); A is ``sigmoid(opacity_logit)`` rounded to 1/255; the normalised
quaternion ``q`` is stored as ``clip(round(128 q + 128), 0, 255)``. Stated bounds (tested):
position and scale exact to float32; colour and opacity within 0.5/255 (colour after
clamping to [0, 1]); each quaternion component within 1/128 before renormalisation, so
the rotation is within 2 asin(||dq||) <= 2 asin(1/64) = 1.79 degrees (measured worst case is
reported by the test). On reading, opacity bytes 0 and 255 map to alpha 0.5/255 and
1 - 0.5/255 (finite logits). Splats are written in the given order (viewers sort at run time).
"""

from __future__ import annotations

import os

import jax.numpy as jnp
import numpy as np

from ..render.splat import SH_C0
from ..types import Gaussians

__all__ = ["write_ply_gaussians", "read_ply_gaussians", "write_splat", "read_splat", "splat_bytes",
           "SPLAT_DTYPE"]

SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
assert SPLAT_DTYPE.itemsize == 32


def _valid_arrays(g: Gaussians, fn: str):
    if not isinstance(g, Gaussians):
        raise TypeError(f"{fn}(gaussians=...): expected Gaussians, got {type(g).__name__}")
    if g.batch_shape:
        raise ValueError(f"{fn}(gaussians=...): expected one set of splats, got batch shape {g.batch_shape}")
    v = np.asarray(g.valid)
    a = {k: np.asarray(getattr(g, k), dtype=np.float64)[v] for k in
         ("means", "log_scales", "quats", "opacity_logits", "colors")}
    qn = np.linalg.norm(a["quats"], axis=1)
    if np.any(qn == 0):
        raise ValueError(f"{fn}(gaussians=...): a valid splat has a zero-length quaternion")
    return a


def write_ply_gaussians(path: str | os.PathLike, gaussians: Gaussians) -> int:
    """Write valid splats to ``path`` in the 3DGS PLY layout; returns the number written.

    Example:
        >>> import tempfile, os
        >>> g = fsjax.Gaussians(jnp.zeros((2, 3)), jnp.zeros((2, 3)), jnp.asarray([[1.0, 0, 0, 0]] * 2),
        ...                     jnp.zeros(2), jnp.zeros((2, 4, 3)))
        >>> p = os.path.join(tempfile.mkdtemp(), "g.ply")
        >>> fsjax.io.write_ply_gaussians(p, g), fsjax.io.read_ply_gaussians(p).colors.shape
        (2, (2, 4, 3))
    """
    from plyfile import PlyData, PlyElement

    a = _valid_arrays(gaussians, "write_ply_gaussians")
    n, K = a["colors"].shape[0], a["colors"].shape[1]
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (K - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    rest = np.transpose(a["colors"][:, 1:, :], (0, 2, 1)).reshape(n, -1)  # channel-major
    cols = np.concatenate([a["means"], np.zeros((n, 3)), a["colors"][:, 0, :], rest, a["opacity_logits"][:, None],
                           a["log_scales"], a["quats"]], axis=1).astype("<f4")
    rec = np.empty(n, dtype=[(nm, "<f4") for nm in names])
    for i, nm in enumerate(names):
        rec[nm] = cols[:, i]
    PlyData([PlyElement.describe(rec, "vertex")], text=False, byte_order="<").write(str(path))
    return n


def read_ply_gaussians(path: str | os.PathLike, dtype=None) -> Gaussians:
    """Read a 3DGS PLY file (layout in the module docstring) into :class:`fsjax.Gaussians`."""
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    if "vertex" not in ply:
        raise ValueError(f"read_ply_gaussians({path!r}): no 'vertex' element")
    v = ply["vertex"].data
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [k for k in need if k not in v.dtype.names]
    if missing:
        raise ValueError(f"read_ply_gaussians({path!r}): missing properties {missing}")
    n_rest = len([k for k in v.dtype.names if k.startswith("f_rest_")])
    if n_rest % 3:
        raise ValueError(f"read_ply_gaussians({path!r}): {n_rest} f_rest properties is not a multiple of 3")
    K = 1 + n_rest // 3
    if K not in (1, 4, 9, 16):
        raise ValueError(f"read_ply_gaussians({path!r}): {K} SH coefficients per channel (expected 1/4/9/16)")
    col = lambda names: np.stack([np.asarray(v[k], np.float64) for k in names], 1)  # noqa: E731
    n = len(v)
    colors = np.zeros((n, K, 3))
    colors[:, 0, :] = col(["f_dc_0", "f_dc_1", "f_dc_2"])
    if K > 1:
        rest = col([f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, K - 1)
        colors[:, 1:, :] = np.transpose(rest, (0, 2, 1))
    dt = jnp.result_type(float) if dtype is None else dtype
    arr = lambda x: jnp.asarray(x, dtype=dt)  # noqa: E731
    return Gaussians(arr(col(["x", "y", "z"])), arr(col(["scale_0", "scale_1", "scale_2"])),
                     arr(col(["rot_0", "rot_1", "rot_2", "rot_3"])), arr(np.asarray(v["opacity"], np.float64)),
                     arr(colors))


def splat_bytes(gaussians: Gaussians) -> bytes:
    """The ``.splat`` encoding (32 bytes per valid splat) as bytes."""
    a = _valid_arrays(gaussians, "splat_bytes")
    n = a["means"].shape[0]
    rec = np.zeros(n, dtype=SPLAT_DTYPE)
    rec["position"] = a["means"]
    rec["scale"] = np.exp(a["log_scales"])
    rgb = np.clip(0.5 + SH_C0 * a["colors"][:, 0, :], 0.0, 1.0)
    alpha = 1.0 / (1.0 + np.exp(-a["opacity_logits"]))
    rec["rgba"] = np.round(np.concatenate([rgb, alpha[:, None]], 1) * 255.0).astype(np.uint8)
    q = a["quats"] / np.linalg.norm(a["quats"], axis=1, keepdims=True)
    rec["rot"] = np.clip(np.round(q * 128.0 + 128.0), 0, 255).astype(np.uint8)
    return rec.tobytes()


def write_splat(path: str | os.PathLike, gaussians: Gaussians) -> int:
    """Write valid splats to ``path`` in the 32-byte ``.splat`` layout; returns the count.

    Example:
        >>> import tempfile, os
        >>> g = fsjax.Gaussians(jnp.zeros((3, 3)), jnp.zeros((3, 3)), jnp.asarray([[1.0, 0, 0, 0]] * 3),
        ...                     jnp.zeros(3), jnp.zeros((3, 1, 3)))
        >>> p = os.path.join(tempfile.mkdtemp(), "g.splat")
        >>> fsjax.io.write_splat(p, g), os.path.getsize(p)
        (3, 96)
    """
    data = splat_bytes(gaussians)
    with open(path, "wb") as f:
        f.write(data)
    return len(data) // 32


def read_splat(path: str | os.PathLike, dtype=None) -> Gaussians:
    """Read a ``.splat`` file into :class:`fsjax.Gaussians` (``K = 1``: plain colours)."""
    with open(path, "rb") as f:
        raw = f.read()
    if len(raw) % 32:
        raise ValueError(f"read_splat({path!r}): size {len(raw)} bytes is not a multiple of 32")
    rec = np.frombuffer(raw, dtype=SPLAT_DTYPE)
    rgba = rec["rgba"].astype(np.float64) / 255.0
    alpha = np.clip(rgba[:, 3], 0.5 / 255.0, 1.0 - 0.5 / 255.0)
    q = (rec["rot"].astype(np.float64) - 128.0) / 128.0
    qn = np.linalg.norm(q, axis=1, keepdims=True)
    if np.any(qn == 0):
        raise ValueError(f"read_splat({path!r}): a splat has an all-128 (zero-length) quaternion")
    scale = rec["scale"].astype(np.float64)
    if np.any(scale <= 0):
        raise ValueError(f"read_splat({path!r}): non-positive scale")
    dt = jnp.result_type(float) if dtype is None else dtype
    arr = lambda x: jnp.asarray(x, dtype=dt)  # noqa: E731
    return Gaussians(arr(rec["position"].astype(np.float64)), arr(np.log(scale)), arr(q / qn),
                     arr(np.log(alpha / (1.0 - alpha))), arr(((rgba[:, :3] - 0.5) / SH_C0)[:, None, :]))
