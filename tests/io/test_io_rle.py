"""Run-length encoding: exact round trips (labels, masks, floats with NaN), the run count against a
plain-Python count, the jit capacity path and its truncation flag, the file form, and refusals."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.io import RunLength, read_rle, rle_decode, rle_encode


def _labels():
    lab = np.zeros((64, 64, 64), np.int32)
    lab[5:20, 10:40, 3:60] = 1
    lab[30:50, 30:35, 20:30] = 2
    lab[40:60, 2:62, 40:44] = 7
    return lab


def _python_runs(flat):
    runs = []
    for v in flat.tolist():
        if runs and runs[-1][0] == v:
            runs[-1][1] += 1
        else:
            runs.append([v, 1])
    return runs


def test_label_volume_round_trip_and_compression(tmp_path):
    lab = _labels()
    lv = fsjax.LabelVolume(jnp.asarray(lab))
    r = rle_encode(lv)
    ref = _python_runs(lab.ravel())
    assert int(r.count) == len(ref) == r.values.shape[0]
    assert [[int(a), int(b)] for a, b in zip(r.values, r.lengths)] == ref
    out = rle_decode(r)
    assert out.dtype == jnp.int32 and out.shape == lab.shape
    np.testing.assert_array_equal(np.asarray(out), lab)
    print(f"64^3 labels: {lab.size} voxels in {int(r.count)} runs")
    assert int(r.count) < lab.size / 30
    # the file form
    r.to_npz(tmp_path / "lab.npz")
    back = read_rle(tmp_path / "lab.npz")
    np.testing.assert_array_equal(np.asarray(rle_decode(back)), lab)


def test_masks_and_floats_with_nan_round_trip_bit_for_bit():
    mask = _labels() > 0
    r = rle_encode(jnp.asarray(mask))
    out = rle_decode(r)
    assert out.dtype == jnp.uint8
    np.testing.assert_array_equal(np.asarray(out), mask.astype(np.uint8))
    x = np.round(np.random.default_rng(0).random((7, 9, 11)) * 3) / 3
    x[2, 3, 4:7] = np.nan
    x[6, 8, 10] = -0.0
    r = rle_encode(fsjax.Volume(jnp.asarray(x)))
    y = np.asarray(rle_decode(r))
    np.testing.assert_array_equal(np.isnan(y), np.isnan(x))
    ok = ~np.isnan(x)
    assert np.array_equal(y[ok].view(np.int64), x[ok].view(np.int64))     # bit for bit, -0.0 included
    assert int(r.count) == len(_python_runs(np.where(np.isnan(x), np.arange(x.size).reshape(x.shape) + 10.0, x).ravel()))


def test_jit_capacity_and_truncation_fail_closed():
    lab = _labels()
    n = int(rle_encode(jnp.asarray(lab)).count)
    enc = jax.jit(lambda a: rle_encode(a, capacity=n + 5))
    r = enc(jnp.asarray(lab))
    assert not bool(r.truncated) and int(r.count) == n
    np.testing.assert_array_equal(np.asarray(jax.jit(rle_decode)(r)), lab)
    small = jax.jit(lambda a: rle_encode(a, capacity=n // 2))(jnp.asarray(lab))
    assert bool(small.truncated) and int(small.count) == n
    with pytest.raises(ValueError, match="rle_decode.*truncated"):
        rle_decode(small)
    with pytest.raises(ValueError, match="truncated"):
        small.to_npz("never_written.npz")
    lost = np.asarray(jax.jit(rle_decode)(small))          # under jit: the lost tail is -1, not a label
    kept = int(np.sum(np.asarray(small.lengths)))
    np.testing.assert_array_equal(lost.ravel()[:kept], lab.ravel()[:kept])
    assert np.all(lost.ravel()[kept:] == -1) and kept < lab.size
    xf = jax.jit(lambda a: rle_decode(rle_encode(a, capacity=3)))(jnp.asarray(np.arange(10.0)))
    assert np.isnan(np.asarray(xf)[3:]).all() and np.asarray(xf)[:3].tolist() == [0.0, 1.0, 2.0]


def test_refusals(tmp_path):
    with pytest.raises(ValueError, match="rle_encode.*empty"):
        rle_encode(jnp.zeros((0, 3)))
    with pytest.raises(ValueError, match="rle_encode.*capacity"):
        rle_encode(jnp.zeros(4), capacity=0)
    with pytest.raises(TypeError, match="rle_encode.*capacity.*jit"):
        jax.jit(lambda a: rle_encode(a))(jnp.zeros(4))
    with pytest.raises(TypeError, match="rle_decode.*RunLength"):
        rle_decode(np.zeros(3))
    np.savez(tmp_path / "bad.npz", values=np.array([1, 2]), lengths=np.array([3, 3]), shape=np.array([2, 2]))
    with pytest.raises(ValueError, match="read_rle.*sum to 6"):
        read_rle(tmp_path / "bad.npz")
    assert isinstance(rle_encode(jnp.ones(3)), RunLength)
