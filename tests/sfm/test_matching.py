"""Blocked mutual-NN + ratio matching against a brute-force numpy reference."""

import jax.numpy as jnp
import numpy as np
import pytest

from fsjax.sfm.matching import match_descriptors, match_pairs


def _brute(a, b, ratio):
    sim = a @ b.T
    j1 = sim.argmax(1)
    s = np.sort(sim, 1)
    d1, d2 = np.sqrt(np.maximum(2 - 2 * s[:, -1], 0)), np.sqrt(np.maximum(2 - 2 * s[:, -2], 0))
    ok = (sim.argmax(0)[j1] == np.arange(len(a))) & (d1 < ratio * d2)
    return np.where(ok, j1, -1)


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def test_blocked_matches_equal_brute_force():
    rng = np.random.default_rng(1)
    b = _unit(rng.normal(size=(150, 32)))
    a = _unit(b[rng.permutation(150)[:100]] + 0.15 * rng.normal(size=(100, 32)))  # 100 true, noisy
    a = np.concatenate([a, _unit(rng.normal(size=(30, 32)))])  # 30 with no partner
    ref = _brute(a, b, 0.8)
    for block in (7, 64, 512):  # the block size changes memory, not the answer
        m, d = match_descriptors(jnp.asarray(a), jnp.ones(130, bool), jnp.asarray(b), jnp.ones(150, bool),
                                 block=block)
        np.testing.assert_array_equal(np.asarray(m), ref)
    assert (ref[:100] >= 0).sum() > 80 and (ref[100:] >= 0).sum() < 5  # the test data is meaningful


def test_invalid_descriptors_never_match_and_pairs_agree():
    rng = np.random.default_rng(2)
    d = _unit(rng.normal(size=(3, 40, 16)))
    d[1] = _unit(d[0] + 0.05 * rng.normal(size=(40, 16)))
    valid = np.ones((3, 40), bool)
    valid[1, :10] = False
    mp = np.asarray(match_pairs(jnp.asarray(d), jnp.asarray(valid), np.array([[0, 1], [1, 0], [0, 2]]), block=16))
    m01, _ = match_descriptors(jnp.asarray(d[0]), jnp.asarray(valid[0]), jnp.asarray(d[1]), jnp.asarray(valid[1]))
    np.testing.assert_array_equal(mp[0], np.asarray(m01))
    assert np.all((mp[0] < 0) | (mp[0] >= 10))  # B's invalid rows are never chosen
    assert np.all(mp[1][:10] == -1)  # A's invalid rows match nothing
    np.testing.assert_array_equal(mp[0][10:], np.arange(10, 40))  # the rest find their partner
    with pytest.raises(ValueError, match="match_descriptors: argument 'ratio'"):
        match_descriptors(jnp.asarray(d[0]), valid[0], jnp.asarray(d[1]), valid[1], ratio=1.5)
