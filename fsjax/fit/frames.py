"""Frame selection by rotation: thin a video stream by how far the camera has turned.

From a stream of orientation quaternions ``(w, x, y, z)`` (one per frame, e.g. drone gimbal
or IMU telemetry), keep a frame when the rotation accumulated since the last kept frame
reaches ``threshold_deg``, subject to a minimum and a maximum gap in frames. The accumulated
rotation is the path length: the sum of the geodesic angles between consecutive frames,
``angle(q_a, q_b) = 2 atan2(|vec(q_a^* q_b)|, |scalar(q_a^* q_b)|)`` (sign-invariant, so
``q`` and ``-q`` are the same rotation).

Rules (frame 0 is always kept; ``last`` is the last kept index):

* frame ``i`` is kept when ``i - last >= max_gap`` (a slow pan still gets frames), or when
  ``i - last >= min_gap`` and the accumulated angle since ``last`` is ``>= threshold_deg``.

Failing closed: a zero-length or non-finite quaternion is an error (not the identity), and
a stream whose quaternions are all the same rotation is refused: on a moving platform that
is a silent telemetry failure, and selecting "by rotation" from it would return a plausible
but meaningless subset. This is eager NumPy data preparation (not traced).
"""

from __future__ import annotations

import equinox as eqx
import numpy as np

from .._checks import check_positive, check_static_int
from ..types.results import renamed

__all__ = ["FrameSelection", "select_frames_by_rotation", "quaternion_angle_deg"]


class FrameSelection(eqx.Module):
    """Kept frame ``indices`` (sorted), a ``keep`` mask ``(N,)``, the per-step angles
    ``step_deg (N,)`` (``step_deg[0] = 0``), and ``why_kept (N,)`` per frame: 0 first
    frame, 1 rotation threshold, 2 maximum gap, -1 not kept (was ``reason``).

    Not a fit result: a deterministic selection rule applied to a pose stream (NumPy,
    eager); nothing is estimated, nothing can fail to converge, so it has no ``converged``,
    ``reason`` or residual (bad input raises)."""

    indices: np.ndarray
    keep: np.ndarray
    step_deg: np.ndarray
    why_kept: np.ndarray

    reason = renamed("why_kept")


def _normalised(quats, fn):
    q = np.asarray(quats, dtype=float)
    if q.ndim != 2 or q.shape[1] != 4:
        raise ValueError(f"{fn}: argument 'quats' must have shape (N, 4) as (w, x, y, z), got {q.shape}")
    if not np.all(np.isfinite(q)):
        bad = np.flatnonzero(~np.all(np.isfinite(q), axis=1))
        raise ValueError(f"{fn}: argument 'quats' must be finite, got a non-finite quaternion at frame(s) "
                         f"{bad[:10].tolist()}")
    n = np.linalg.norm(q, axis=1)
    if np.any(n == 0):
        bad = np.flatnonzero(n == 0)
        raise ValueError(f"{fn}: argument 'quats' must be unit quaternions, got a zero-length quaternion at frame(s) {bad[:10].tolist()}; "
                         "it is not a rotation")
    return q / n[:, None]


def quaternion_angle_deg(qa, qb) -> np.ndarray:
    """Geodesic angle (degrees) between unit quaternions ``(..., 4)``, sign-invariant.

    Example:
        >>> from fsjax.fit import quaternion_angle_deg
        >>> c, s = np.cos(np.radians(15)), np.sin(np.radians(15))
        >>> round(float(quaternion_angle_deg([1.0, 0, 0, 0], [-c, 0, 0, -s])), 9)
        30.0
    """
    qa, qb = np.asarray(qa, float), np.asarray(qb, float)
    w = np.sum(qa * qb, axis=-1)
    # vector part of conj(qa) * qb
    aw, av = qa[..., :1], qa[..., 1:]
    bw, bv = qb[..., :1], qb[..., 1:]
    v = aw * bv - bw * av - np.cross(av, bv)
    return np.degrees(2.0 * np.arctan2(np.linalg.norm(v, axis=-1), np.abs(w)))


def select_frames_by_rotation(quats, *, threshold_deg: float = 10.0, min_gap: int = 1,
                              max_gap: int | None = None, identical_tol_deg: float = 1e-9) -> FrameSelection:
    """Select frames from an orientation stream by accumulated rotation.

    Args:
        quats: ``(N, 4)`` orientations ``(w, x, y, z)``, ``N >= 2`` (normalised here).
        threshold_deg: accumulated rotation (degrees, path length) that triggers a keep.
        min_gap: minimum frames between kept frames (>= 1).
        max_gap: maximum frames between kept frames (``None``: unlimited); ``>= min_gap``.
        identical_tol_deg: a stream whose every frame is within this angle of frame 0 is
            refused as "all identical".

    Returns:
        :class:`FrameSelection`.

    Raises:
        ValueError: zero-length/non-finite quaternions, all-identical stream, bad gaps.

    Example:
        >>> from fsjax.fit import select_frames_by_rotation
        >>> a = np.radians(np.arange(10) * 4.0) / 2  # 4 degrees per frame about z
        >>> q = np.stack([np.cos(a), 0 * a, 0 * a, np.sin(a)], 1)
        >>> select_frames_by_rotation(q, threshold_deg=10.0).indices.tolist()
        [0, 3, 6, 9]
    """
    fn = "select_frames_by_rotation"
    q = _normalised(quats, fn)
    n = q.shape[0]
    if n < 2:
        raise ValueError(f"{fn}: argument 'quats' must hold at least 2 frames, got {n}")
    check_positive(fn, "threshold_deg", threshold_deg)
    min_gap = check_static_int(fn, "min_gap", min_gap, lo=1)
    if max_gap is not None:
        max_gap = check_static_int(fn, "max_gap", max_gap, lo=min_gap)
    if np.all(quaternion_angle_deg(q[:1], q) <= identical_tol_deg):
        raise ValueError(f"{fn}: argument 'quats' must change orientation, got {n} quaternions of the same rotation; the orientation "
                         "telemetry is probably stuck (refusing to select frames by rotation)")
    step = np.concatenate([[0.0], quaternion_angle_deg(q[:-1], q[1:])])
    keep = np.zeros(n, bool)
    reason = np.full(n, -1, np.int32)
    keep[0], reason[0] = True, 0
    last, acc = 0, 0.0
    for i in range(1, n):
        acc += step[i]
        gap = i - last
        if max_gap is not None and gap >= max_gap:
            keep[i], reason[i] = True, 2
        elif gap >= min_gap and acc >= threshold_deg - 1e-9:
            keep[i], reason[i] = True, 1
        if keep[i]:
            last, acc = i, 0.0
    return FrameSelection(indices=np.flatnonzero(keep), keep=keep, step_deg=step, why_kept=reason)
