"""Frame selection by rotation: thresholds, gaps, sign invariance, refusal of stuck telemetry."""

import doctest

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.fit import frames as F


def _yaw_stream(deg_per_frame):
    a = np.radians(np.cumsum(np.concatenate([[0.0], deg_per_frame]))) / 2
    return np.stack([np.cos(a), 0 * a, 0 * a, np.sin(a)], 1)


def test_module_examples():
    res = doctest.testmod(F, extraglobs={"fsjax": fsjax, "jnp": jnp, "np": np, "jax": jax})
    assert res.attempted >= 4 and res.failed == 0


def test_threshold_and_gaps():
    q = _yaw_stream(np.full(40, 3.0))  # 3 degrees per frame
    sel = F.select_frames_by_rotation(q, threshold_deg=10.0)
    assert sel.indices.tolist() == list(range(0, 41, 4))  # 12 degrees at every 4th frame
    # max gap forces a frame on a slow pan
    slow = _yaw_stream(np.full(30, 0.5))
    s2 = F.select_frames_by_rotation(slow, threshold_deg=10.0, max_gap=8)
    assert s2.indices.tolist() == [0, 8, 16, 24] and set(s2.why_kept[s2.keep][1:]) == {2}
    # min gap stops a fast turn from keeping every frame
    fast = _yaw_stream(np.full(20, 30.0))
    s3 = F.select_frames_by_rotation(fast, threshold_deg=10.0, min_gap=3)
    assert np.all(np.diff(s3.indices) == 3)
    # the null (every k-th frame) ignores rotation: a burst of turning after a still section
    burst = _yaw_stream(np.concatenate([np.zeros(20), np.full(10, 5.0)]))
    s4 = F.select_frames_by_rotation(burst, threshold_deg=10.0, max_gap=100)
    print(f"frame selection on still-then-turning stream: kept {s4.indices.tolist()}")
    assert s4.indices.tolist() == [0, 22, 24, 26, 28, 30]


def test_sign_invariance_and_accumulation():
    q = _yaw_stream(np.full(12, 4.0))
    flipped = q * np.where(np.arange(len(q)) % 2 == 0, 1.0, -1.0)[:, None]
    a = F.select_frames_by_rotation(q, threshold_deg=10.0).indices
    b = F.select_frames_by_rotation(flipped, threshold_deg=10.0).indices
    assert a.tolist() == b.tolist()
    # back-and-forth wobble accumulates path length, not net rotation
    wob = _yaw_stream(np.tile([4.0, -4.0], 6))
    s = F.select_frames_by_rotation(wob, threshold_deg=10.0, max_gap=100)
    assert s.indices.tolist() == [0, 3, 6, 9, 12]
    assert np.allclose(s.step_deg[1:], 4.0)


def test_refuses_identical_stream_and_zero_quaternion():
    q = np.tile([[0.9, 0.1, -0.3, 0.2]], (50, 1))
    with pytest.raises(ValueError, match="select_frames_by_rotation.*same rotation"):
        F.select_frames_by_rotation(q)
    with pytest.raises(ValueError, match="same rotation"):
        F.select_frames_by_rotation(q * np.where(np.arange(50) % 2, -1.0, 1.0)[:, None])
    z = _yaw_stream(np.full(5, 3.0))
    z[2] = 0.0
    with pytest.raises(ValueError, match="zero-length quaternion at frame\\(s\\) \\[2\\]"):
        F.select_frames_by_rotation(z)
    z[2] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        F.select_frames_by_rotation(z)


def test_bad_parameters():
    q = _yaw_stream(np.full(5, 3.0))
    with pytest.raises(ValueError, match="threshold_deg"):
        F.select_frames_by_rotation(q, threshold_deg=0.0)
    with pytest.raises(ValueError, match="min_gap"):
        F.select_frames_by_rotation(q, min_gap=0)
    with pytest.raises(ValueError, match="max_gap"):
        F.select_frames_by_rotation(q, min_gap=3, max_gap=2)
    with pytest.raises(ValueError, match="\\(N, 4\\)"):
        F.select_frames_by_rotation(q[:, :3])
