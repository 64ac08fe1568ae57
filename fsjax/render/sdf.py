"""Signed-distance scenes and sphere tracing: the renderer as a measuring instrument.

A scene is a pytree (:class:`SDFScene`, an ``equinox.Module``) of primitives and CSG nodes,
so it passes through ``jax.jit``/``vmap``/``grad`` like any array. :func:`render_sdf` traces
one ray per pixel of a :class:`fsjax.Camera` (or any rays, :func:`trace_rays`) and returns
the *channels* as arrays (:class:`SDFRender`): depth along the optical axis, ray length,
world position, unit normals from the SDF gradient, ambient occlusion, soft-shadow
visibility of a disc light of given angular diameter, object id and albedo, hit/miss flags.

Conventions:

* World units are whatever the scene uses (metres, millimetres): nothing is inferred.
* Cameras follow :mod:`fsjax.render.camera` (OpenCV frame, ``world_from_camera`` pose).
  ``depth`` is the camera-frame z of the hit point; ``t`` the distance along the unit ray.
  :func:`orthographic_rays` gives parallel rays (a telecentric view) for methods whose
  theory is orthographic (normal integration); the pinhole model has no orthographic mode.
* A signed distance is negative inside. Primitives are exact distance bounds (the standard
  closed forms, e.g. Hart 1996; Quilez's catalogue), except that CSG intersection and
  difference give bounds (correct zero set and sign, distances under-estimated), which is
  all sphere tracing needs.
* Light direction ``light_dir`` points *from the surface towards the light* (world frame);
  a zero-length direction is refused eagerly and gives NaN shadows under ``jit``.
* Misses: ``hit`` is False and depth/position/normals are NaN; a ray that used up its step
  cap without reaching the surface or ``t_max`` is flagged in ``unconverged`` (counted in
  ``n_unconverged``), never reported as a miss silently.
* Gradients: the march runs without derivatives; one Newton step on the hit,
  ``t <- t - f(o + t d) / (grad f . d)``, carries the implicit-function gradient of the hit
  distance with respect to the scene parameters and the rays (as in the camera's undistort).

References: J. C. Hart, "Sphere tracing: a geometric method for the antialiased ray tracing
of implicit surfaces", The Visual Computer 12 (1996); I. Quilez, distance functions and
soft shadows (iquilezles.org articles, 2008-2020); A. Evans, "Fast approximations for
global illumination on dynamic scenes", SIGGRAPH 2006 course notes (SDF ambient occlusion).
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._checks import check_positive, check_range, check_static_int
from ..types import Camera, is_concrete
from .camera import pixel_rays

__all__ = [
    "SDF",
    "Sphere",
    "Box",
    "RoundBox",
    "Cylinder",
    "Capsule",
    "Torus",
    "Plane",
    "Cone",
    "Union",
    "Intersection",
    "Difference",
    "SmoothUnion",
    "smooth_min",
    "SDFScene",
    "SDFRender",
    "trace_rays",
    "render_sdf",
    "sdf_normal",
    "orthographic_rays",
    "disc_visible_fraction",
    "shadow_visibility",
]


def _safe_norm(v: jax.Array, axis: int = -1) -> jax.Array:
    """Euclidean norm with a finite gradient at 0 (double ``where``)."""
    sq = jnp.sum(v * v, axis=axis)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def _arr(x, dtype=None):
    return jnp.asarray(x, dtype=jnp.result_type(float) if dtype is None else dtype)


class SDF(eqx.Module):
    """Base class: a signed distance field ``f(p)`` for one point ``p (3,)`` (negative inside)."""

    def __call__(self, p: Float[Array, "3"]) -> Float[Array, ""]:  # pragma: no cover - abstract
        raise NotImplementedError


class _Posed(SDF):
    """A primitive with a centre and a ``world_from_local`` rotation (identity by default)."""

    center: Float[Array, "3"]
    rotation: Float[Array, "3 3"]

    def local(self, p):
        return (p - self.center) @ self.rotation


def _init_pose(obj, center, rotation):
    obj.center = _arr(center)
    obj.rotation = jnp.eye(3, dtype=obj.center.dtype) if rotation is None else _arr(rotation)


class Sphere(_Posed):
    """Sphere of ``radius`` at ``center``: ``|p - c| - r`` (exact)."""

    radius: Float[Array, ""]

    def __init__(self, center, radius, rotation=None):
        _init_pose(self, center, rotation)
        self.radius = _arr(radius)

    def __call__(self, p):
        return _safe_norm(self.local(p)) - self.radius


def _box_local(q, half):
    d = jnp.abs(q) - half
    return _safe_norm(jnp.maximum(d, 0.0)) + jnp.minimum(jnp.max(d), 0.0)


class Box(_Posed):
    """Box with half-extents ``half (3,)`` in its local frame (exact distance)."""

    half: Float[Array, "3"]

    def __init__(self, center, half, rotation=None):
        _init_pose(self, center, rotation)
        self.half = _arr(half)

    def __call__(self, p):
        return _box_local(self.local(p), self.half)


class RoundBox(_Posed):
    """Box of half-extents ``half`` whose edges are rounded with ``radius`` (outer size ``half``)."""

    half: Float[Array, "3"]
    radius: Float[Array, ""]

    def __init__(self, center, half, radius, rotation=None):
        _init_pose(self, center, rotation)
        self.half = _arr(half)
        self.radius = _arr(radius)

    def __call__(self, p):
        return _box_local(self.local(p), self.half - self.radius) - self.radius


class Cylinder(_Posed):
    """Capped cylinder along the local z axis: ``radius``, half-height ``half_height`` (exact)."""

    radius: Float[Array, ""]
    half_height: Float[Array, ""]

    def __init__(self, center, radius, half_height, rotation=None):
        _init_pose(self, center, rotation)
        self.radius = _arr(radius)
        self.half_height = _arr(half_height)

    def __call__(self, p):
        q = self.local(p)
        d = jnp.stack([_safe_norm(q[:2]) - self.radius, jnp.abs(q[2]) - self.half_height])
        return jnp.minimum(jnp.max(d), 0.0) + _safe_norm(jnp.maximum(d, 0.0))


class Capsule(SDF):
    """Capsule: points within ``radius`` of the segment ``a``-``b`` (exact)."""

    a: Float[Array, "3"]
    b: Float[Array, "3"]
    radius: Float[Array, ""]

    def __init__(self, a, b, radius):
        self.a = _arr(a)
        self.b = _arr(b)
        self.radius = _arr(radius)

    def __call__(self, p):
        ab = self.b - self.a
        ll = jnp.dot(ab, ab)
        h = jnp.clip(jnp.dot(p - self.a, ab) / jnp.where(ll > 0, ll, 1.0), 0.0, 1.0)
        return _safe_norm(p - self.a - h * ab) - self.radius


class Torus(_Posed):
    """Torus around the local z axis: ring radius ``major``, tube radius ``minor`` (exact)."""

    major: Float[Array, ""]
    minor: Float[Array, ""]

    def __init__(self, center, major, minor, rotation=None):
        _init_pose(self, center, rotation)
        self.major = _arr(major)
        self.minor = _arr(minor)

    def __call__(self, p):
        q = self.local(p)
        return _safe_norm(jnp.stack([_safe_norm(q[:2]) - self.major, q[2]])) - self.minor


class Plane(SDF):
    """Half-space ``n . p <= offset`` with unit normal ``normal`` (outward): ``n . p - offset``."""

    normal: Float[Array, "3"]
    offset: Float[Array, ""]

    def __init__(self, normal, offset=0.0):
        n = _arr(normal)
        nn = jnp.linalg.norm(n)
        if is_concrete(nn) and not float(nn) > 0:
            raise ValueError("Plane(normal=...): zero-length normal")
        self.normal = n / jnp.where(nn > 0, nn, jnp.nan)
        self.offset = _arr(offset)

    def __call__(self, p):
        return jnp.dot(self.normal, p) - self.offset


def _seg_dist2(p, a, b):
    ab = b - a
    h = jnp.clip(jnp.dot(p - a, ab) / jnp.dot(ab, ab), 0.0, 1.0)
    d = p - a - h * ab
    return jnp.dot(d, d)


class Cone(_Posed):
    """Solid cone along the local z axis: base disc of ``radius`` at z = 0, apex at z = ``height``.

    Exact: the solid of revolution's distance is the 2-D signed distance of ``(rho, z)`` to
    the isosceles triangle ``(-r, 0), (r, 0), (0, h)``.
    """

    radius: Float[Array, ""]
    height: Float[Array, ""]

    def __init__(self, center, radius, height, rotation=None):
        _init_pose(self, center, rotation)
        self.radius = _arr(radius)
        self.height = _arr(height)

    def __call__(self, p):
        q = self.local(p)
        rho, z = _safe_norm(q[:2]), q[2]
        x = jnp.stack([rho, z])
        zero = jnp.zeros((), x.dtype)
        base = _seg_dist2(x, jnp.stack([zero, zero]), jnp.stack([self.radius, zero]))
        side = _seg_dist2(x, jnp.stack([self.radius, zero]), jnp.stack([zero, self.height]))
        d2 = jnp.minimum(base, side)
        slant = jnp.sqrt(self.radius**2 + self.height**2)
        side_lin = (rho * self.height + z * self.radius - self.radius * self.height) / slant
        inside = (z >= 0) & (side_lin <= 0)
        # inside a convex section the distance is the largest signed edge-line distance (linear,
        # so the gradient is exact on the surface too); outside, the distance to the segments
        d_in = jnp.maximum(side_lin, -z)
        on = d2 <= 0  # exactly on the surface: the linear form has the right gradient
        d_out = jnp.where(on, d_in, jnp.sqrt(jnp.where(inside | on, 1.0, d2)))
        return jnp.where(inside, d_in, d_out)


class Union(SDF):
    """Union of two fields: ``min(a, b)``."""

    a: SDF
    b: SDF

    def __call__(self, p):
        return jnp.minimum(self.a(p), self.b(p))


class Intersection(SDF):
    """Intersection: ``max(a, b)`` (a distance bound)."""

    a: SDF
    b: SDF

    def __call__(self, p):
        return jnp.maximum(self.a(p), self.b(p))


class Difference(SDF):
    """``a`` minus ``b``: ``max(a, -b)`` (a distance bound)."""

    a: SDF
    b: SDF

    def __call__(self, p):
        return jnp.maximum(self.a(p), -self.b(p))


def smooth_min(a, b, k):
    """Quadratic smooth minimum ``min(a, b) - max(k - |a - b|, 0)^2 / (4 k)`` (Quilez).

    Equals ``min(a, b)`` when ``|a - b| >= k`` and blends within ``k``; finite on infinite
    inputs (``smooth_min(inf, 1, k) == 1``, ``smooth_min(inf, inf, k) == inf``): the blend term
    is computed from a safe difference, so no ``inf - inf`` ever reaches it (also in the
    gradient). ``k <= 0`` gives the plain minimum.

    Example:
        >>> from fsjax.render import smooth_min
        >>> float(smooth_min(jnp.inf, 1.0, 0.5)), round(float(smooth_min(0.0, 0.0, 0.4)), 12)
        (1.0, -0.1)
    """
    a, b = jnp.asarray(a), jnp.asarray(b)
    k = jnp.asarray(k, dtype=jnp.result_type(a, b, float))
    both = jnp.isfinite(a) & jnp.isfinite(b)
    diff = jnp.where(both, a - b, jnp.inf)
    kpos = k > 0
    ks = jnp.where(kpos, k, 1.0)
    h = jnp.maximum(ks - jnp.abs(diff), 0.0)
    # (a + b - |a - b|) / 2 is min(a, b) with the symmetric gradient (1/2, 1/2) at a tie
    a_s, b_s = jnp.where(both, a, 0.0), jnp.where(both, b, 0.0)
    m = jnp.where(both, 0.5 * (a_s + b_s - jnp.abs(diff)), jnp.minimum(a, b))
    return m - jnp.where(kpos, h * h / (4.0 * ks), 0.0)


class SmoothUnion(SDF):
    """Smooth union of two fields with blend radius ``k`` (:func:`smooth_min`)."""

    a: SDF
    b: SDF
    k: Float[Array, ""]

    def __init__(self, a, b, k):
        self.a, self.b, self.k = a, b, _arr(k)

    def __call__(self, p):
        return smooth_min(self.a(p), self.b(p), self.k)


class SDFScene(eqx.Module):
    """A scene: a tuple of objects (any :class:`SDF`, CSG trees included), each with an albedo.

    The scene's field is the union (minimum) of its objects; ``object_id`` of a point is the
    index of the nearest object. ``albedo`` ``(n_objects,)`` is the diffuse reflectance used by
    :func:`render_sdf` (the channel ``albedo``). Being an ``equinox.Module``, a scene is a
    pytree: its arrays can be traced, batched and differentiated.
    """

    objects: tuple
    albedo: Float[Array, " n"]

    def __init__(self, objects, albedo=None):
        objects = tuple(objects)
        if not objects:
            raise ValueError("SDFScene(objects=...): a scene needs at least one object")
        for o in objects:
            if not isinstance(o, SDF):
                raise TypeError(f"SDFScene(objects=...): expected SDF objects, got {type(o).__name__}")
        self.objects = objects
        self.albedo = jnp.ones(len(objects)) if albedo is None else _arr(albedo)
        if self.albedo.shape != (len(objects),):
            raise ValueError(f"SDFScene(albedo=...): expected shape ({len(objects)},), got {self.albedo.shape}")

    def distances(self, p):
        return jnp.stack([o(p) for o in self.objects])

    def __call__(self, p):
        return jnp.min(self.distances(p))

    def object_id(self, p):
        return jnp.argmin(self.distances(p)).astype(jnp.int32)


def sdf_normal(sdf, p):
    """Unit outward normal ``grad f / |grad f|`` at ``p (3,)`` from ``jax.grad`` of the field.

    Example:
        >>> from fsjax.render import Sphere, sdf_normal
        >>> n = sdf_normal(Sphere([0.0, 0.0, 0.0], 1.0), jnp.asarray([0.0, 3.0, 4.0]))
        >>> [round(float(v), 12) for v in n]
        [0.0, 0.6, 0.8]
    """
    g = jax.grad(lambda q: sdf(q))(p)
    gn = _safe_norm(g)
    return g / jnp.where(gn > 0, gn, jnp.nan)


class SDFRender(eqx.Module):
    """Channels of a sphere-traced image ``(H, W[, 3])`` (NaN where ``hit`` is False).

    ``depth``: camera-frame z (along the optical axis); ``t``: distance along the unit ray;
    ``position``/``normal``: world frame; ``ao`` in [0, 1] (1 = unoccluded); ``shadow``: the
    visible fraction of the light disc in [0, 1] (1 = fully lit; 0 also for surfaces facing
    away); ``object_id`` (-1 on a miss); ``albedo`` of the hit object; ``steps`` used;
    ``unconverged``: the step cap was reached before a hit or ``t_max``; ``n_unconverged``.
    """

    depth: Float[Array, "H W"]
    t: Float[Array, "H W"]
    position: Float[Array, "H W 3"]
    normal: Float[Array, "H W 3"]
    ao: Float[Array, "H W"]
    shadow: Float[Array, "H W"]
    object_id: Int[Array, "H W"]
    albedo: Float[Array, "H W"]
    hit: Bool[Array, "H W"]
    unconverged: Bool[Array, "H W"]
    steps: Int[Array, "H W"]
    n_unconverged: Int[Array, ""]


def _march(sdf, o, d, t_min, t_max, max_steps, tol):
    """Plain sphere tracing of one ray; returns ``(t, hit, unconverged, steps)`` (no gradient)."""

    def body(_, s):
        t, done, hit, n = s
        h = sdf(o + t * d)
        now_hit = jnp.abs(h) <= tol * (1.0 + t)
        escaped = t > t_max
        stop = done | now_hit | escaped
        t_new = jnp.where(stop, t, t + h)
        return t_new, stop, hit | (~done & now_hit & ~escaped), n + (~stop).astype(jnp.int32)

    dt = o.dtype
    s0 = (jnp.asarray(t_min, dt), jnp.asarray(False), jnp.asarray(False), jnp.asarray(0, jnp.int32))
    t, done, hit, n = jax.lax.fori_loop(0, max_steps, body, s0)
    # the last step may have landed on the surface without being tested
    h = sdf(o + t * d)
    last = ~done & (jnp.abs(h) <= tol * (1.0 + t)) & (t <= t_max)
    hit = hit | last
    done = done | last | (t > t_max)
    return t, hit, ~done, n


def _refine(sdf, o, d, t, hit, newton_steps):
    """Newton steps on ``f(o + t d) = 0`` (quadratic convergence); the last one carries gradients."""
    t = jax.lax.stop_gradient(t)

    def step(t, stop_grad_slope):
        p = o + t * d
        f = sdf(p)
        g = jax.grad(sdf)(p)
        slope = jnp.dot(g, d)
        if stop_grad_slope:
            slope = jax.lax.stop_gradient(slope)
        ok = hit & (slope < -1e-3)
        return t - jnp.where(ok, f / jnp.where(ok, slope, 1.0), 0.0)

    for _ in range(newton_steps):
        t = jax.lax.stop_gradient(step(t, True))
    return step(t, True)


def _ambient_occlusion(sdf, p, n, n_samples, spacing, strength):
    """SDF ambient occlusion (Evans 2006): ``1 - strength sum_i 2^-i (h_i - f(p + h_i n)) / h_i``.

    Sample ``i`` (1-based) is at height ``h_i = i spacing`` along the normal; for an unoccluded
    convex point every term is 0 (AO = 1). Normalised by ``sum 2^-i`` so the result is in [0, 1].
    """
    i = jnp.arange(1, n_samples + 1, dtype=p.dtype)
    h = i * spacing
    f = jax.vmap(lambda hh: sdf(p + hh * n))(h)
    w = 0.5 ** (i - 1)
    occ = jnp.sum(w * jnp.clip((h - f) / h, 0.0, 1.0)) / jnp.sum(w)
    return jnp.clip(1.0 - strength * occ, 0.0, 1.0)


def disc_visible_fraction(x):
    """Visible fraction of a uniform disc cut by a straight edge at signed offset ``x`` radii.

    ``x = 1``: the edge touches the far rim (disc fully visible); ``x = -1``: fully hidden;
    ``f(x) = 1/2 + (x sqrt(1 - x^2) + asin x) / pi`` (area of a circular segment).

    Example:
        >>> from fsjax.render import disc_visible_fraction
        >>> [round(float(disc_visible_fraction(v)), 6) for v in (-1.0, 0.0, 0.5, 1.0)]
        [0.0, 0.5, 0.804499, 1.0]
    """
    x = jnp.clip(jnp.asarray(x), -1.0, 1.0)
    # clipped to [0, 1]: at x = -1 the rounding of asin(-1) / pi against 1/2 may leave -1e-17 (it
    # did under XLA:CPU's older loop emitters at level 0), a fraction below 0
    return jnp.clip(0.5 + (x * jnp.sqrt(jnp.maximum(1.0 - x * x, 0.0)) + jnp.arcsin(x)) / math.pi, 0.0, 1.0)


def _soft_shadow(sdf, p, n, light, sin_rho, t_start, t_max, n_steps, min_step):
    """Visible fraction of a disc light of angular radius ``rho`` seen from ``p``.

    Marches towards the light, tracking the minimum of ``f / t`` (the sine of the angular
    clearance of the ray from the occluders: exact for a sphere, Quilez's soft-shadow idea),
    allowing negative values inside occluders (steps of at least ``min_step``), and maps the
    clearance in units of the disc radius to the visible fraction of a disc cut by a straight
    edge (:func:`disc_visible_fraction`). Points whose normal faces away get 0.
    """

    def body(_, s):
        t, m = s
        h = sdf(p + t * light)
        m = jnp.where(t <= t_max, jnp.minimum(m, h / t), m)
        return t + jnp.clip(h, min_step, 1e30), m

    dt = p.dtype
    t, m = jax.lax.fori_loop(0, n_steps, body, (jnp.asarray(t_start, dt), jnp.asarray(jnp.inf, dt)))
    vis = disc_visible_fraction(m / sin_rho)
    return jnp.where(jnp.dot(n, light) > 0, vis, 0.0)


def shadow_visibility(scene, points, normals, light_dir, *, light_angular_diameter_deg: float = 0.53,
                      t_max: float = 1e3, shadow_steps: int = 160, shadow_min_step: float | None = None,
                      offset: float | None = None):
    """Visible fraction of a disc light seen from surface ``points (..., 3)`` with ``normals (..., 3)``.

    The same soft-shadow march as :func:`trace_rays` (minimum of ``f / t`` towards the light,
    mapped to the visible fraction of the light disc), for points already found, e.g. to
    relight one traced frame under many lights (``jax.vmap`` over ``light_dir``). NaN points
    give NaN. ``offset`` (default ``t_max / 4e5``) lifts the start off the surface.

    Example:
        >>> from fsjax.render import Plane, Sphere, SDFScene, shadow_visibility
        >>> scene = SDFScene([Plane([0.0, 0.0, 1.0]), Sphere([0.0, 0.0, 2.0], 1.0)])
        >>> pts = jnp.asarray([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
        >>> nrm = jnp.asarray([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
        >>> [float(v) for v in shadow_visibility(scene, pts, nrm, [0.0, 0.0, 1.0], t_max=10.0)]
        [0.0, 1.0]
    """
    light = _check_light(light_dir, "shadow_visibility")
    pts = jnp.asarray(points)
    nrm = jnp.asarray(normals, pts.dtype)
    min_step = t_max / 400.0 if shadow_min_step is None else shadow_min_step
    off = t_max / 4e5 if offset is None else offset
    sin_rho = math.sin(math.radians(light_angular_diameter_deg) / 2.0)
    flat_p, flat_n = pts.reshape(-1, 3), nrm.reshape(-1, 3)
    return _shadow(scene, flat_p, flat_n, light, off, sin_rho, min_step, t_max,
                   shadow_steps=int(shadow_steps)).reshape(pts.shape[:-1])


@functools.partial(jax.jit, static_argnames=("shadow_steps",))
def _shadow(scene, flat_p, flat_n, light, off, sin_rho, min_step, t_max, *, shadow_steps):
    """The march of :func:`shadow_visibility` as one module-level program (see :func:`_trace`)."""

    def one(p, n):
        ok = jnp.all(jnp.isfinite(p)) & jnp.all(jnp.isfinite(n))
        p = jnp.where(ok, p, 0.0)
        n = jnp.where(ok, n, jnp.asarray([0.0, 0.0, 1.0], p.dtype))
        v = _soft_shadow(scene, p + off * n, n, light, sin_rho, min_step, t_max, shadow_steps, min_step)
        return jnp.where(ok, v, jnp.nan)

    return jax.vmap(one)(flat_p, flat_n)


def orthographic_rays(R, t, width: int, height: int, pixel_size: float):
    """Parallel rays of a telecentric view: ``(origins (H, W, 3), directions (H, W, 3))``.

    ``(R, t)`` is a ``world_from_camera`` pose in the OpenCV frame (:func:`look_at`); pixel
    ``(row, col)`` sits at camera-frame ``x = (col - (W-1)/2) s``, ``y = (row - (H-1)/2) s`` on
    the plane ``z = 0`` and looks along the camera z axis. The library's pinhole ``Camera`` has
    no orthographic mode; depth of these rays is the distance from that plane.

    Example:
        >>> from fsjax.render import orthographic_rays
        >>> o, d = orthographic_rays(jnp.eye(3), jnp.zeros(3), 4, 3, 0.5)
        >>> [float(v) for v in o[0, 0]], [float(v) for v in d[2, 3]]
        ([-0.75, -0.5, 0.0], [0.0, 0.0, 1.0])
    """
    R = _arr(R)
    t = _arr(t, R.dtype)
    check_positive("orthographic_rays", "pixel_size", pixel_size)
    r, c = jnp.meshgrid(jnp.arange(height, dtype=R.dtype), jnp.arange(width, dtype=R.dtype), indexing="ij")
    x = (c - (width - 1) / 2.0) * pixel_size
    y = (r - (height - 1) / 2.0) * pixel_size
    pc = jnp.stack([x, y, jnp.zeros_like(x)], axis=-1)
    o = pc @ R.T + t
    d = jnp.broadcast_to(R[:, 2], o.shape)
    return o, d


def _check_light(light_dir, fn):
    if light_dir is None:
        return None
    ld = _arr(light_dir)
    if ld.shape != (3,):
        raise ValueError(f"{fn}(light_dir=...): expected shape (3,), got {ld.shape}")
    nn = jnp.linalg.norm(ld)
    if is_concrete(nn) and not float(nn) > 0:
        raise ValueError(f"{fn}(light_dir=...): zero-length light direction")
    return ld / jnp.where(nn > 0, nn, jnp.nan)


def trace_rays(scene, origins, directions, *, axis=None, light_dir=None, light_angular_diameter_deg: float = 0.53,
               t_min: float = 0.0, t_max: float = 1e3, max_steps: int = 256, tol: float = 1e-7,
               newton_steps: int = 1, ao_samples: int = 5, ao_spacing: float | None = None,
               ao_strength: float = 1.0, shadow_steps: int = 160, shadow_min_step: float | None = None,
               shadow_t_max: float | None = None) -> SDFRender:
    """Sphere-trace rays ``origins, directions (H, W, 3)`` (unit directions) through ``scene``.

    Args:
        scene: an :class:`SDFScene` (or any :class:`SDF`, then albedo 1 and object 0).
        origins, directions: ray origins and unit directions, world frame, ``(H, W, 3)``.
        axis: ``(3,)`` optical axis for the ``depth`` channel (``depth = t d . axis``, plus
            ``o . axis`` offset for parallel rays is NOT added); default: ``depth = t``.
        light_dir: direction towards a distant light (unit or not; zero refused); ``None``
            gives ``shadow = 1`` everywhere.
        light_angular_diameter_deg: angular diameter of the light disc (the sun: 0.53 deg).
        t_min, t_max: ray interval in scene units (beyond ``t_max`` is a miss).
        max_steps: static step cap of the march; rays still marching at the cap are flagged
            ``unconverged``.
        tol: hit when ``|f| <= tol (1 + t)``; followed by ``newton_steps`` Newton steps.
        ao_samples, ao_spacing, ao_strength: ambient-occlusion samples along the normal
            (spacing default ``t_max / 200``).
        shadow_steps, shadow_min_step, shadow_t_max: soft-shadow march (defaults ``t_max/400``
            and ``t_max``).

    Returns:
        :class:`SDFRender` with all channels.
    """
    if not isinstance(scene, (SDFScene, SDF)):
        raise TypeError(f"trace_rays(scene=...): expected an SDFScene or SDF, got {type(scene).__name__}")
    max_steps = check_static_int("trace_rays", "max_steps", max_steps, lo=1)
    check_range("trace_rays", "light_angular_diameter_deg", light_angular_diameter_deg, 0.0, 180.0,
                lo_open=True, hi_open=True)
    light = _check_light(light_dir, "trace_rays")
    o = jnp.asarray(origins)
    d = jnp.asarray(directions, o.dtype)
    shape = o.shape[:-1]
    of, df = o.reshape(-1, 3), d.reshape(-1, 3)
    ao_spacing = t_max / 200.0 if ao_spacing is None else ao_spacing
    shadow_min_step = t_max / 400.0 if shadow_min_step is None else shadow_min_step
    shadow_t_max = t_max if shadow_t_max is None else shadow_t_max
    sin_rho = math.sin(math.radians(light_angular_diameter_deg) / 2.0)
    out = _trace(scene, of, df, axis, light, t_min, t_max, tol, ao_spacing, ao_strength, shadow_min_step,
                 shadow_t_max, sin_rho, max_steps=max_steps, newton_steps=int(newton_steps),
                 ao_samples=int(ao_samples), shadow_steps=int(shadow_steps))
    depth, t, p, nrm, ao, sh, oid, alb, hit, unconv, n = out
    r = lambda x, extra=(): x.reshape(shape + extra)  # noqa: E731
    return SDFRender(r(depth), r(t), r(p, (3,)), r(nrm, (3,)), r(ao), r(sh), r(oid), r(alb), r(hit), r(unconv),
                     r(n), jnp.sum(unconv).astype(jnp.int32))


@functools.partial(jax.jit, static_argnames=("max_steps", "newton_steps", "ao_samples", "shadow_steps"))
def _trace(field, of, df, axis, light, t_min, t_max, tol, ao_spacing, ao_strength, shadow_min_step, shadow_t_max,
           sin_rho, *, max_steps, newton_steps, ao_samples, shadow_steps):
    """The per-ray work of :func:`trace_rays`, one module-level program: called eagerly, its
    ``vmap`` of ``fori_loop`` marches over closures compiled again on every call."""

    def one(oo, dd):
        t, hit, unconv, n = _march(field, jax.lax.stop_gradient(oo), jax.lax.stop_gradient(dd), t_min, t_max,
                                   max_steps, tol)
        t = jax.lax.stop_gradient(t)
        t = _refine(field, oo, dd, t, hit, newton_steps)
        p = oo + t * dd
        nrm = sdf_normal(field, p)
        ao = _ambient_occlusion(field, p, nrm, ao_samples, ao_spacing, ao_strength)
        if light is None:
            sh = jnp.ones((), oo.dtype)
        else:
            # start a little off the surface so the start point does not count as an occluder
            p0 = p + nrm * (4.0 * tol * (1.0 + t) + 1e-3 * ao_spacing)
            sh = _soft_shadow(field, p0, nrm, light, sin_rho, shadow_min_step, shadow_t_max, shadow_steps,
                              shadow_min_step)
        if isinstance(field, SDFScene):
            oid = field.object_id(p)
            alb = field.albedo[oid]
        else:
            oid = jnp.asarray(0, jnp.int32)
            alb = jnp.ones((), oo.dtype)
        depth = t if axis is None else t * jnp.dot(dd, axis)
        nan = jnp.asarray(jnp.nan, oo.dtype)
        return (jnp.where(hit, depth, nan), jnp.where(hit, t, nan), jnp.where(hit, p, nan),
                jnp.where(hit, nrm, nan), jnp.where(hit, ao, nan), jnp.where(hit, sh, nan),
                jnp.where(hit, oid, -1), jnp.where(hit, alb, nan), hit, unconv, n)

    return jax.vmap(one)(of, df)


def render_sdf(scene, camera: Camera, *, undistort: bool = True, **kw) -> SDFRender:
    """Render the channels of ``scene`` seen by a pinhole ``camera`` (one ray per pixel centre).

    Rays come from :func:`fsjax.render.pixel_rays`; ``depth`` is the camera-frame z of the hit
    point. Keyword arguments are those of :func:`trace_rays`.

    Example:
        >>> from fsjax.render import Sphere, SDFScene, render_sdf
        >>> cam = fsjax.Camera.from_intrinsics(20.0, 20.0, 7.5, 5.5, width=16, height=12,
        ...                                    t=jnp.asarray([0.0, 0.0, -5.0]))
        >>> out = render_sdf(SDFScene([Sphere([0.0, 0.0, 0.0], 1.0)]), cam, t_max=20.0)
        >>> # closed form of the ray through pixel (5, 7) (half a pixel off the axis): depth 4.010102
        >>> bool(out.hit[5, 7]), round(float(out.depth[5, 7]), 6), int(out.n_unconverged)
        (True, 4.010102, 0)
    """
    if not isinstance(camera, Camera):
        raise TypeError(f"render_sdf(camera=...): expected a Camera, got {type(camera).__name__}")
    if undistort and is_concrete(camera.dist) and not np.any(np.asarray(camera.dist)):
        undistort = False  # no distortion: skip the (exact but costly to compile) Newton inverse
    o, d = pixel_rays(camera, undistort=undistort)
    return trace_rays(scene, o, d, axis=camera.R[:, 2], **kw)
