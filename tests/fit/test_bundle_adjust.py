"""Bundle adjustment (LM + Schur complement): SciPy conformance, robust losses, implicit gradient, bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fsjax.fit.bundle_adjust import bundle_adjust
from fsjax.fit.rigid import so3_exp
from fsjax.synth._ba_scipy import scipy_bundle_adjust
from fsjax.synth._multiview import bundle_scene
from fsjax.types import reason_code


def _args(s, uv=None):
    return (s["K"], s["init_rotvecs"], s["init_translations"], s["init_points"], s["cam_idx"], s["pt_idx"],
            s["uv"] if uv is None else uv)


def _point_error(pts, s):
    return float(np.sqrt(np.mean(np.sum((np.asarray(pts) - s["points"]) ** 2, axis=1))))


def test_matches_scipy_least_squares_and_beats_the_initial_guess():
    s = bundle_scene(8, 300, noise_px=1.0, seed=1)
    res = bundle_adjust(*_args(s))
    _, _, Xs, rmse_s, _ = scipy_bundle_adjust(*_args(s))
    rel = abs(float(res.rms_px) - rmse_s) / rmse_s
    print(f"BA 8 cams x 300 pts, 1 px noise: RMSE {float(res.rms_px_initial):.2f} -> {float(res.rms_px):.5f} px in "
          f"{int(res.iterations)} iterations; SciPy trf {rmse_s:.5f} px (rel diff {rel:.1e}); point error "
          f"{_point_error(res.points, s):.4f} vs initial {_point_error(s['init_points'], s):.4f}")
    assert bool(res.converged) and int(res.reason) == 0
    assert rel < 0.01
    assert float(res.rms_px) < 0.2 * float(res.rms_px_initial)
    assert _point_error(res.points, s) < 0.5 * _point_error(s["init_points"], s)
    # gauge: camera 0 is held at its initial pose
    np.testing.assert_array_equal(np.asarray(res.rotvecs[0]), s["init_rotvecs"][0])
    # the world_from_camera view of the same poses
    R = np.asarray(so3_exp(res.rotvecs))
    np.testing.assert_allclose(np.asarray(res.R_world_from_camera), np.swapaxes(R, 1, 2), atol=1e-14)


def test_robust_losses_resist_outliers():
    s = bundle_scene(6, 200, noise_px=0.5, seed=2)
    rng = np.random.default_rng(0)
    uv = s["uv"].copy()
    bad = rng.random(len(uv)) < 0.1
    uv[bad] += rng.normal(0.0, 40.0, (int(bad.sum()), 2))
    errs = {}
    for loss in ("linear", "huber", "cauchy"):
        r = bundle_adjust(*_args(s, uv), loss=loss, loss_scale=2.0)
        assert bool(r.converged), (loss, r.message)
        errs[loss] = _point_error(r.points, s)
    print("BA with 10 % outliers (40 px): point RMS error " + ", ".join(f"{k} {v:.4f}" for k, v in errs.items()))
    assert errs["cauchy"] < 0.5 * errs["linear"] and errs["huber"] < errs["linear"]


def test_gradient_wrt_observations_matches_finite_differences():
    s = bundle_scene(3, 15, noise_px=0.5, seed=3, focal=400.0, size=(640, 480))

    def f(uv):
        r = bundle_adjust(*_args(s, uv), tol=1e-15, max_iter=200)
        return jnp.sum(r.points[:, 0] * jnp.arange(15)) + jnp.sum(r.translations[2])

    uv0 = jnp.asarray(s["uv"])
    g = jax.grad(f)(uv0)
    rng = np.random.default_rng(1)
    d = jnp.asarray(rng.normal(size=uv0.shape))
    h = 1e-4
    fd = (f(uv0 + h * d) - f(uv0 - h * d)) / (2 * h)
    gd = float(jnp.sum(g * d))
    print(f"BA implicit gradient: directional {gd:.6e} vs FD {float(fd):.6e}")
    assert abs(gd) > 1e-4
    assert abs(gd - float(fd)) <= 1e-4 * max(1.0, abs(float(fd)))


def test_fails_closed():
    s = bundle_scene(3, 10, seed=4)
    uv = s["uv"].copy()
    uv[3, 0] = np.nan
    r = bundle_adjust(*_args(s, uv))
    assert not bool(r.converged) and int(r.reason) == reason_code("invalid_input") and bool(jnp.all(jnp.isnan(r.points)))
    ci = s["cam_idx"].copy()
    ci[0] = 7
    r = bundle_adjust(s["K"], s["init_rotvecs"], s["init_translations"], s["init_points"], ci, s["pt_idx"], s["uv"])
    assert int(r.reason) == reason_code("invalid_input") and bool(jnp.all(jnp.isnan(r.rotvecs)))
    r = bundle_adjust(*_args(s), max_iter=1)
    assert not bool(r.converged) and int(r.reason) == reason_code("max_iterations")


def test_bad_arguments_raise():
    s = bundle_scene(3, 10, seed=5)
    with pytest.raises(ValueError, match="bundle_adjust.*loss"):
        bundle_adjust(*_args(s), loss="tukey")
    with pytest.raises(ValueError, match="bundle_adjust.*points"):
        bundle_adjust(s["K"], s["init_rotvecs"], s["init_translations"], s["init_points"][:, :2], s["cam_idx"],
                      s["pt_idx"], s["uv"])
    with pytest.raises(ValueError, match="bundle_adjust.*lengths"):
        bundle_adjust(s["K"], s["init_rotvecs"], s["init_translations"], s["init_points"], s["cam_idx"][:-1],
                      s["pt_idx"], s["uv"])
