"""Bundle adjustment over observation lists: the Schur complement summed over the unordered pairs of
observations of one point (and their transposes) equals the dense camera x point coupling; the fit
recovers perturbed cameras."""

import jax
import jax.numpy as jnp
import numpy as np

from fsjax.fit.rigid import so3_exp
from fsjax.sfm.bundle import (
    _project,
    _residual_and_jacobian,
    bundle_adjust_masked,
    observation_pairs,
)


def _scene(seed=0, n_cam=5, n_pt=60):
    rng = np.random.default_rng(seed)
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    X = rng.uniform(-1, 1, (n_pt, 3)) + [0, 0, 6]
    R = np.stack([np.asarray(so3_exp(jnp.asarray(rng.normal(0, 0.05, 3)))) for _ in range(n_cam)])
    t = np.c_[np.linspace(-1, 1, n_cam), rng.normal(0, 0.1, (n_cam, 2))]
    ci, pi, uv = [], [], []
    for c in range(n_cam):
        for p in range(n_pt):
            if rng.random() < 0.7 or c < 2:
                x = R[c] @ X[p] + t[c]
                ci.append(c)
                pi.append(p)
                uv.append(K[:2, :2] @ (x[:2] / x[2]) + K[:2, 2] + rng.normal(0, 0.3, 2))
    return K, R, t, X, np.array(ci), np.array(pi), np.array(uv)


def test_observation_pairs_lists_every_pair_of_a_point():
    pi = np.array([3, 1, 3, 0, 3, 1])
    got = {tuple(p) for p in observation_pairs(pi)}
    want = {(a, b) for a in range(6) for b in range(a + 1, 6) if pi[a] == pi[b]}  # unordered, a < b
    assert got == want and len(observation_pairs(pi)) == len(want)
    padded = observation_pairs(pi, 20)
    assert padded.shape == (20, 2) and np.all(padded[len(want):] == -1)


def test_pair_schur_equals_dense_and_fits():
    K, R, t, X, ci, pi, uv = _scene()
    n, m, o = len(R), len(X), len(ci)
    rng = np.random.default_rng(1)
    # perturbed start; padded observations (weight 0) and a frozen camera / gauge as in reconstruct
    R0 = np.stack([np.asarray(so3_exp(jnp.asarray(rng.normal(0, 0.01, 3)))) @ r for r in R])
    t0 = t + rng.normal(0, 0.02, t.shape)
    X0 = X + rng.normal(0, 0.02, X.shape)
    R0[0], t0[0] = R[0], t[0]
    pad = 13
    ci_p, pi_p = np.pad(ci, (0, pad)), np.pad(pi, (0, pad))
    uv_p = np.pad(uv, ((0, pad), (0, 0)))
    w = np.r_[np.ones(o), np.zeros(pad)]
    w[5] = 0.0  # an observation not in the problem
    free = np.ones((n, 6))
    free[0] = 0
    free[1, 3] = 0
    args = [jnp.asarray(a) for a in (K, R0, t0, X0, ci_p, pi_p, uv_p, w, free, np.ones(m))]
    dense = bundle_adjust_masked(*args, max_iter=15)
    pairs = bundle_adjust_masked(*args, obs_pairs=jnp.asarray(observation_pairs(pi, 2048)), max_iter=15)
    for a, b in zip(dense[:4], pairs[:4]):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-7, atol=1e-9)
    assert int(dense[4]) == int(pairs[4])
    # the fit itself: reprojection RMS near the pixel noise (0.3 px per axis), far below the start's
    start = bundle_adjust_masked(*args, max_iter=0)
    assert float(pairs[3]) < 0.5 < float(start[3])


def test_analytic_jacobian_equals_autodiff():
    K, R, t, X, ci, pi, uv = _scene(seed=2)
    for k in (0, 7, 40):
        c, p = ci[k], pi[k]

        def f(d, c=c, p=p, k=k):
            return _project(jnp.asarray(K), so3_exp(d[:3]) @ jnp.asarray(R[c]), t[c] + d[3:6], X[p] + d[6:]) - uv[k]

        d0 = jnp.zeros(9)
        r, J = _residual_and_jacobian(jnp.asarray(K), jnp.asarray(uv[k]), jnp.asarray(R[c]), jnp.asarray(t[c]),
                                      jnp.asarray(X[p]))
        np.testing.assert_allclose(np.asarray(r), np.asarray(f(d0)), rtol=1e-12, atol=1e-9)
        J_ad = np.asarray(jax.jacfwd(f)(d0))
        assert np.abs(J_ad).min() < np.abs(J_ad).max() and np.abs(J_ad[:, :3]).max() > 1.0  # not a zero Jacobian
        np.testing.assert_allclose(np.asarray(J), J_ad, rtol=1e-10, atol=1e-8)
