"""Problems: deterministic disjoint splits, exact metrics, user pairs and their bad input."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage as ndi

from fsjax import Feature, Image, Region
from fsjax.evolve import problems as P


@pytest.mark.parametrize("name", P.PROBLEMS)
def test_synthetic_problem_is_deterministic_and_splits_are_disjoint(name):
    a = P.make_problem(name, size=(24, 32), n_train=4, n_holdout=3, n_locked=5)
    b = P.make_problem(name, size=(24, 32), n_train=4, n_holdout=3, n_locked=5)
    c = P.make_problem(name, size=(24, 32), n_train=4, n_holdout=3, n_locked=5, seed=1)
    for s in ("train", "holdout", "locked"):
        np.testing.assert_array_equal(a.split(s).inputs, b.split(s).inputs)
        np.testing.assert_array_equal(a.split(s).targets, b.split(s).targets)
        assert not np.array_equal(a.split(s).inputs, c.split(s).inputs)
    assert (len(a.train), len(a.holdout), len(a.locked)) == (4, 3, 5)
    imgs = np.concatenate([a.train.inputs, a.holdout.inputs, a.locked.inputs]).reshape(12, -1)
    assert len({x.tobytes() for x in imgs}) == 12  # no image repeats within or across splits
    assert imgs.min() >= 0 and imgs.max() <= 1
    # the larger split of a bigger problem starts with the same images (split streams are per index)
    d = P.make_problem(name, size=(24, 32), n_train=6, n_holdout=3, n_locked=5)
    np.testing.assert_array_equal(d.train.inputs[:4], a.train.inputs)


def test_synthetic_truth_is_exact():
    pr = P.make_problem("count", size=(48, 48), n_train=6, n_holdout=1, n_locked=1)
    # counts are what the hand pipeline can see: the noise-free render thresholded counts the same
    assert set(np.unique(pr.train.targets)) <= set(range(1, 10))
    b = P.make_problem("binarize", size=(48, 48), n_train=3, n_holdout=1, n_locked=1)
    assert b.train.targets.dtype == bool and 0.02 < b.train.targets.mean() < 0.6
    e = P.make_problem("edges", size=(48, 48), n_train=3, n_holdout=1, n_locked=1)
    # edge truth: 1-2 px thick borders, every border pixel touches a different grey level in the blurred image
    assert e.train.targets.dtype == bool and 0.01 < e.train.targets.mean() < 0.3
    dn = P.make_problem("denoise", size=(48, 48), n_train=3, n_holdout=1, n_locked=1)
    resid = dn.train.inputs - dn.train.targets
    print(f"denoise noise sd (clipped) = {resid.std():.4f} (nominal 0.1)")
    assert 0.08 < resid.std() < 0.105


def test_metrics_on_known_cases():
    x = jnp.full((8, 8), 0.5)
    assert float(P.psnr(x, x)) == 100.0
    assert float(P.psnr(x, x + 0.1)) == pytest.approx(20.0, abs=1e-9)
    a = jnp.zeros((8, 8), bool).at[:4].set(True)
    b = jnp.zeros((8, 8), bool).at[2:6].set(True)
    assert float(P.iou(a, b)) == pytest.approx(16 / 48)
    assert float(P.iou(jnp.zeros((4, 4), bool), jnp.zeros((4, 4), bool))) == 1.0
    e = jnp.zeros((16, 16), bool).at[:, 8].set(True)
    assert float(P.f1_tol1(jnp.roll(e, 1, axis=1), e)) == 1.0  # within the 1 px tolerance
    assert float(P.f1_tol1(jnp.roll(e, 3, axis=1), e)) == 0.0
    half = e.at[8:, 8].set(False)
    assert float(P.f1_tol1(half, e)) == pytest.approx(2 * (9 / 16) / (1 + 9 / 16))  # row 8 is 1 px from row 7
    assert float(P.count_score(jnp.asarray(5.0), jnp.asarray(3.0))) == pytest.approx(1 / 3)
    # the null of each mask problem is measured, and is far from perfect
    m = ndi.binary_dilation(np.eye(10, dtype=bool))
    assert float(P.iou(jnp.asarray(m), jnp.asarray(np.eye(10, dtype=bool)))) < 0.5


def test_problem_from_pairs_and_its_bad_input():
    rng = np.random.default_rng(0)
    x = rng.uniform(size=(8, 24, 24))
    t = x > 0.5
    pr = P.problem_from_pairs(x, t, "iou", hand=[("threshold", 0.5)])
    assert pr.gives is Region and (len(pr.train), len(pr.holdout), len(pr.locked)) == (4, 2, 2)
    seen = np.concatenate([pr.train.inputs, pr.holdout.inputs, pr.locked.inputs])
    assert sorted(map(bytes, seen.reshape(8, -1))) == sorted(map(bytes, x.reshape(8, -1)))  # a partition
    assert P.problem_from_pairs(x, x, "psnr").gives is Image
    assert P.problem_from_pairs(x, np.arange(8.0), "count").gives is Feature
    with pytest.raises(ValueError, match="8 inputs but 7 targets"):
        P.problem_from_pairs(x, t[:7], "iou")
    with pytest.raises(ValueError, match=r"targets of shape \(8, 24, 24\)"):
        P.problem_from_pairs(x, t[:, :20], "iou")
    with pytest.raises(ValueError, match="too few for three disjoint splits"):
        P.problem_from_pairs(x[:2], t[:2], "iou")
    with pytest.raises(ValueError, match="unknown metric"):
        P.problem_from_pairs(x, t, "accuracy")
    with pytest.raises(ValueError, match=r"finite and in \[0, 1\]"):
        P.problem_from_pairs(x * 2, t, "iou")
    with pytest.raises(ValueError, match="unknown problem"):
        P.make_problem("deblur")
    with pytest.raises(ValueError, match="n_locked must be >= 1"):
        P.make_problem("edges", n_locked=0)
