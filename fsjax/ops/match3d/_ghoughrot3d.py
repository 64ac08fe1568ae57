"""Generalised Hough transform in 3-D with a rotation about z: :func:`fsjax.ops.generalised_hough3d`'s
R-table turned per angle, one accumulator per angle (a 4-D accumulator over (angle, k, i, j)).

Choice: a search over a fixed set of angles with the R-table turned per angle, not a 4-D vote
per R-table entry and angle in one buffer, and not a rotation found first. The model points
(offsets ``u`` and gradient directions) are taken once from the unturned template; for angle
``a`` each is turned exactly about z through the template box's centre ``c`` (``c + Rz(a) (u - c)``,
rounded to the nearest voxel; its direction turned by ``Rz(a)`` and re-binned), and the scene's
edge voxels (found, binned and sorted once) vote through that angle's R-table into that angle's
accumulator (:func:`generalised_hough3d`'s voting, its static vote capacity per angle). The
angles are mapped one after another (``lax.map``): memory stays one angle's votes, the time is
the number of angles times one translation-only vote. Instances are the local maxima of the
4-D accumulator (smoothed by ``[1, 2, 1] / 4`` along each axis, the angle axis circular), best
first, each suppressing the peaks within ``min_distance`` of its position at every angle; the
position by the 3x3x3 Newton peak of its angle's slice, the angle by a parabola through the
three angles around the peak, then ``2 n_fine + 1`` angles spaced ``1 / n_fine`` of the coarse
step around each instance's angle voted again, the votes within 1.5 voxels of its placement
summed per angle, and the vertex of the least-squares parabola through those sums taken (on the
grid's turned bunny: mean 0.43 degree over voxel, points and Gaussians rows, seeds 0-2, where the
best fine angle's three-point parabola on the peak votes gave 1.31).

The rotation does not resample the template (no interpolation of its intensities): the turned
R-table is the unturned one carried by ``Rz(a)``, so every angle counts the same model points.

Cost: one translation-only vote per angle, ``n_angles`` of them, and ``2 n_fine + 1`` more per
instance found (an empty slot casts none, except under ``vmap``, where both branches run). On the
grid's 48^3 voxel scene with a 24^3 template (one instance): 0.26 s per call where
:func:`generalised_hough3d` takes 0.026 s (the coarse angles alone, ``n_fine=0``, 0.23 s; before the
votes were cast in chunks as many as there are votes, not over the whole capacity: 0.91, 0.05 and
0.73 s); compile 3.4 s of CPU against 2.9 s (2 cores, load 2.4-2.6, 2026-12-05;
``python benchmarks/bench_hough_rotation.py``). Memory: one angle's votes at a time and the
``(n_angles, placements)`` accumulator (36 x 25^3 values there). The alternative, all angles'
votes in one buffer of ``n_angles`` times the capacity, would cast the same votes in one scatter
at ``n_angles`` times the memory.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ..._checks import check_static_int
from ...registry import LinKnob, register
from ...types import Match3D, Volume
from ._ghough3d import (
    _MIN_MODEL_POINTS,
    _REF_BALLARD,
    _REF_NW,
    _bins,
    _hough_args,
    _hough_match,
    _model_points,
    _rtable,
    _scene_edges,
    _smooth121,
    _vote,
)
from ._shared3d import neighbourhood3, newton_peak3, turned_pose

__all__ = ["generalised_hough_rotation_z3d"]


def _turn(u, dirm, a, c):
    """Model points ``u (P, 3)`` (k, i, j) and directions ``dirm (P, 3)`` ((z, y, x)) turned about z by ``a``
    through ``c`` (k, i, j): counter-clockwise from +x (j) towards +y (i); the points rounded to voxels."""
    ca, sa = jnp.cos(a), jnp.sin(a)
    q = u.astype(c.dtype) - c
    x, y = q[:, 2], q[:, 1]
    ut = jnp.stack([q[:, 0], sa * x + ca * y, ca * x - sa * y], -1) + c
    dx, dy = dirm[:, 2], dirm[:, 1]
    dt = jnp.stack([dirm[:, 0], sa * dx + ca * dy, ca * dx - sa * dy], -1)
    return jnp.round(ut).astype(jnp.int32), dt


def _parabola(m, c, p):
    """Offset in ``[-0.5, 0.5]`` of the vertex of the parabola through ``(-1, m), (0, c), (1, p)`` (0 where it
    is not a maximum)."""
    den = m - 2 * c + p
    ok = den < 0
    return jnp.where(ok, jnp.clip(0.5 * (m - p) / jnp.where(ok, den, -1.0), -0.5, 0.5), 0.0)


@functools.partial(jax.jit, static_argnames=("sigma", "spacing", "n_dirs", "max_points", "max_votes",
                                             "max_instances", "n_angles", "n_fine"))
def _ghoughrot_core(x, t, model_contrast, edge_contrast, cos_tol, min_votes, min_dist, *, sigma: float, spacing,
                    n_dirs: int, max_points: int, max_votes: int, max_instances: int, n_angles: int, n_fine: int):
    dt = x.dtype
    dirs = _bins(n_dirs)
    u, dirm, pv, n_model = _model_points(t, sigma, spacing, model_contrast, max_points)
    edges = _scene_edges(x, sigma, spacing, edge_contrast, dirs.shape[0])
    c = (jnp.asarray(t.shape, dt) - 1) / 2
    nm = jnp.maximum(n_model, 1).astype(dt)

    def acc(a):
        ut, dtn = _turn(u, dirm, a, c)
        eb, eu, ev = _rtable(ut, dtn, pv, cos_tol, dirs)
        A, total = _vote(edges, eb, eu, ev, x.shape, t.shape, max_votes, dt)
        return A / nm, total

    step = 2 * jnp.pi / n_angles
    angles = -jnp.pi + step * jnp.arange(n_angles, dtype=dt)
    score, totals = jax.lax.map(acc, angles)  # (n_angles, P0, P1, P2)
    As = jax.vmap(_smooth121)(score)
    As = 0.25 * jnp.roll(As, 1, 0) + 0.5 * As + 0.25 * jnp.roll(As, -1, 0)
    m3 = jax.vmap(lambda a: jax.lax.reduce_window(a, -jnp.inf, jax.lax.max, (3, 3, 3), (1, 1, 1), "SAME"))(As)
    m4 = jnp.maximum(m3, jnp.maximum(jnp.roll(m3, 1, 0), jnp.roll(m3, -1, 0)))
    cand = jnp.where((As >= m4) & (score >= min_votes), As, -jnp.inf)
    shp = score.shape[1:]
    grid = jnp.stack(jnp.meshgrid(*(jnp.arange(n, dtype=dt) for n in shp), indexing="ij"), -1)
    md2 = jnp.asarray(min_dist, dt) ** 2

    def pick(cand, _):
        i = jnp.argmax(cand)
        ok = cand.reshape(-1)[i] > -jnp.inf
        ia, *pos = jnp.unravel_index(i, cand.shape)
        idx = jnp.asarray(pos)
        v, okn = neighbourhood3(As[ia], idx)
        off = idx.astype(dt) + newton_peak3(v, okn)
        la = As[(ia - 1) % n_angles, idx[0], idx[1], idx[2]]
        ra = As[(ia + 1) % n_angles, idx[0], idx[1], idx[2]]
        a = angles[ia] + step * _parabola(la, As[ia, idx[0], idx[1], idx[2]], ra)
        d2 = jnp.sum((grid - idx.astype(dt)) ** 2, -1)
        cand = jnp.where(ok & (d2 <= md2)[None], -jnp.inf, cand)
        return cand, (a, off, score[ia, idx[0], idx[1], idx[2]], ok)

    _, (a, off, sc, ok) = jax.lax.scan(pick, cand, None, length=max_instances)
    over = jnp.max(totals) > max_votes
    if n_fine:
        # each instance: 2 n_fine + 1 angles around its angle, voted again; the votes within 1.5 voxels of its
        # placement count (their sum: smoother over angles than the peak, whose rounded offsets jitter), and the
        # vertex of the least-squares parabola through all of them is the angle
        fstep = step / n_fine
        r = jnp.arange(-n_fine, n_fine + 1, dtype=dt)
        near = jnp.sum((grid[None] - off[:, None, None, None, :]) ** 2, -1) <= 2.25  # (k, P0, P1, P2)

        def acc_found(args):  # an empty slot casts no votes (one branch runs; under vmap both, selected)
            a_k, ok_k = args
            return jax.lax.cond(ok_k, acc, lambda _: (jnp.zeros(shp, dt), jnp.zeros((), totals.dtype)), a_k)

        Sf, tf = jax.lax.map(acc_found, ((a[:, None] + fstep * r[None, :]).reshape(-1), jnp.repeat(ok, r.shape[0])))
        v = jnp.sum(jnp.where(near[:, None], Sf.reshape((max_instances, r.shape[0]) + shp), 0.0), axis=(2, 3, 4))
        q = r * r - jnp.mean(r * r)  # orthogonal basis 1, r, r^2 - mean
        c1 = jnp.sum(v * r, 1) / jnp.sum(r * r)
        c2 = jnp.sum(v * q, 1) / jnp.sum(q * q)
        okp = c2 < 0
        a = a + fstep * jnp.where(okp, jnp.clip(-c1 / (2 * jnp.where(okp, c2, -1.0)), -n_fine, n_fine), 0.0)
        over = over | (jnp.max(tf) > max_votes)
    return a, off, sc, ok, n_model >= _MIN_MODEL_POINTS, over


@register(family="match3d", takes=(Volume, Volume), gives=Match3D, differentiable=False,
          knobs={"min_votes": LinKnob(0.1, 0.8)}, refs=[_REF_BALLARD, _REF_NW])
def generalised_hough_rotation_z3d(scene: Volume, template: Volume, /, *, min_votes: float = 0.4,
                                   max_instances: int = 4, min_distance: float | None = None, n_angles: int = 36,
                                   n_fine: int = 4, n_dirs: int = 64, angle_tol_deg: float = 15.0,
                                   sigma: float = 1.0, model_contrast: float = 0.3, edge_contrast: float = 0.2,
                                   max_points: int = 512, max_votes: int = 2 ** 20) -> Match3D:
    """Find instances of a template turned by any angle about z by the generalised Hough transform in 3-D.

    :func:`generalised_hough3d`'s R-table (offsets of the template's edge voxels to its reference
    point, keyed by their quantised gradient direction) turned about the z axis (the volume's first
    axis) through the template box's centre by each of ``n_angles`` angles over the full turn: the
    model points and their directions are turned exactly and rounded to voxels (the template is not
    resampled), the scene's edge voxels vote through each angle's R-table into that angle's
    accumulator (a 4-D accumulator over angle and placement). Instances are its local maxima, best
    first, by non-maximum suppression over positions (an instance suppresses every angle near its
    position); the position by the Newton peak of its angle's accumulator, the angle by a parabola
    over the neighbouring angles, then ``2 n_fine + 1`` angles around it voted again (the votes
    within 1.5 voxels of the instance summed per angle) and the vertex of the least-squares parabola
    through them. Occlusion only removes votes; a contrast reversal changes no direction bin.

    Args:
      scene: the scene ``(D, H, W)``, ``dx == dy`` (a turn about z).
      template: the template ``(d, h, w)``, no larger than the scene, same spacing, >= 3 voxels per
        axis.
      min_votes: an instance needs at least this fraction of the model points' votes (knob ``a``,
        linear on [0.1, 0.8]; default 0.4, above :func:`generalised_hough3d`'s 0.22: over 36 turned
        R-tables the clutter finds a better fit, on the grid's turned-bunny scenes without the bunny
        up to 0.29, the bunny 0.63-0.81, seeds 0-2 of the voxel, points, mesh and Gaussians rows;
        the depth row's views 0.69-0.81 and at most 0.20; docs/matching_grid.md).
      max_instances: instances reported (static int in [1, 64]), best first.
      min_distance: two instances are at least this far apart (voxels; default half the
        template's smallest side).
      n_angles: coarse angles over the full turn (static int, 4 to 720; default 36: every 10 degrees).
      n_fine: angles each side of an instance's coarse angle voted again, per coarse step (static
        int, 0 to 32; 0 = the coarse angles and their parabola only).
      n_dirs, angle_tol_deg, sigma, model_contrast, edge_contrast, max_points: as
        :func:`generalised_hough3d`.
      max_votes: vote capacity per angle (static int); more votes than this at any angle
        invalidate the result (``capacity_exceeded``).

    Returns:
      ``Match3D`` of batch shape ``(max_instances,)``, best first: ``R = Rz(a)`` (counter-clockwise
      from +x towards +y, as :func:`shape_rotation_z3d`), ``t`` such that a template point ``p``
      (physical, template frame) lands at ``R p + t``, ``scale = 1``, ``score`` = votes at the
      integer peak of its coarse angle / model points (0 for an empty slot). Slots beyond the
      instances found are ``valid`` False (``not_found``); all are invalid with ``invalid_input``
      (fewer than 8 model points) or ``capacity_exceeded`` (vote overflow at some angle).

    Example:
      The shell of an anisotropic blob (an ellipsoid with a knob) turned by -117.3 degrees about z
      and moved: found with the angle within 1 degree and the centre within 0.2 voxel (measured in
      float32: 0.40 degree, 0.06 voxel; the coarse angles' parabola alone, ``n_fine=0``, 0.26); the
      translation-only :func:`generalised_hough3d` (the null) finds no instance:

      >>> import numpy as np, fsjax
      >>> from fsjax.synth import turned_shell  # an anisotropic blob's shell, turned about z
      >>> scene = fsjax.Volume(turned_shell((14.3, 15.2, 13.6), -117.3, dtype=np.float32))
      >>> tpl = fsjax.Volume(turned_shell((10.0, 10.0, 10.0), 0.0, dtype=np.float32)[:21, :21, :21])
      >>> m = fsjax.ops.generalised_hough_rotation_z3d(scene, tpl, max_instances=2)
      >>> a = np.degrees(np.arctan2(float(m.R[0, 1, 0]), float(m.R[0, 0, 0])))
      >>> c = np.asarray(m.R[0]) @ np.full(3, 10.0) + np.asarray(m.t[0])  # the template's box centre in the scene
      >>> m.valid.tolist(), bool(abs(a + 117.3) < 1.0), float(np.abs(c - [13.6, 15.2, 14.3]).max()) < 0.2
      ([True, False], True, True)
      >>> bool(fsjax.ops.generalised_hough3d(scene, tpl).valid[0])
      False
    """
    op = "generalised_hough_rotation_z3d"
    if isinstance(scene, Volume) and scene.spacing[1] != scene.spacing[2]:
        raise ValueError(f"{op}: argument 'scene' has spacing {scene.spacing}; a rotation about z needs dy == dx")
    T, dt, arrays, static = _hough_args(op, scene, template, min_votes, max_instances, min_distance, n_dirs,
                                        angle_tol_deg, sigma, model_contrast, edge_contrast, max_points, max_votes)
    na = check_static_int(op, "n_angles", n_angles, lo=4, hi=720)
    nf = check_static_int(op, "n_fine", n_fine, lo=0, hi=32)
    a, off, sc, found, ok, over = _ghoughrot_core(*arrays, **static, n_angles=na, n_fine=nf)
    return _hough_match(*turned_pose(a, off, T, scene.spacing, dt), sc, found, ok, over, dt)
