"""register_cross (issue 17, cross-structure registration): a CAD mesh against a partial point scan."""

from __future__ import annotations

import doctest

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax.fit import register_cross, rotation_error_deg
from fsjax.synth import cad_scan_pair

REF_DEG = 0.15  # the reference toolkit: CAD mesh vs partial point scan at 50 deg via FPFH


def run_docstring_example(fn) -> dict:
    """Run ``fn``'s docstring example (as tests/test_api_examples.py does: float64, ELLIPSIS and
    NORMALIZE_WHITESPACE); assert it holds and return the names it defined."""
    globs = {"fsjax": fsjax, "jnp": jnp, "np": np, "jax": jax}
    (test,) = doctest.DocTestFinder().find(fn, globs=globs)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    runner.run(test, clear_globs=False)
    res = runner.summarize(verbose=False)
    assert res.attempted > 0 and res.failed == 0, f"{test.name}: {res.failed} of {res.attempted} examples failed"
    return test.globs


@pytest.mark.slow
def test_cad_mesh_against_partial_scan_50deg_and_wrong_object():
    # register_cross's docstring example is this test's first call (fandisk vs its scan turned 50 deg,
    # voxel 2 % of the size, overlap 0.5): it runs here, not in tests/test_api_examples.py (its
    # RUN_ELSEWHERE), so the suite registers the pair once (the two copies cost ~18 s of CPU each,
    # mostly compilation); the checks below go further on the example's own result
    ex = run_docstring_example(register_cross)
    pair, res = ex["pair"], ex["res"]
    same = cad_scan_pair("fandisk", angle_deg=50.0, seed=0)  # the pair the figures below are quoted for
    assert np.array_equal(pair["scan"], same["scan"]) and np.array_equal(pair["R"], same["R"])
    R = jnp.asarray(pair["R"])
    err = float(rotation_error_deg(res.refined.R, R))
    coarse = float(rotation_error_deg(res.coarse.R, R))
    t_err = float(np.linalg.norm(np.asarray(res.refined.t) - pair["t"]) / pair["diag"])
    print(f"fandisk mesh (20,000 samples) vs a one-sided scan ({len(pair['scan'])} points, noise 0.1 % of the "
          f"size) turned 50 deg: FPFH + RANSAC {coarse:.3f} deg ({int(res.coarse.n_inliers)} inliers), + trimmed "
          f"ICP {err:.4f} deg, translation {t_err:.1e} of the size (reference {REF_DEG} deg; null 50 deg)")
    assert bool(res.converged) and err <= REF_DEG and coarse <= 1.0 and t_err <= 1e-3
    # a scan of another object (the bunny, scaled to the part's size): no consistent hypothesis
    # n_dense chosen so the bunny's scan (21,709 points) pads to the fandisk scan's bucket (21,774 -> 24,576
    # slots, fsjax.fit.cross._BUCKET): the second call reuses the first call's compiled programs (with the
    # default 60,000 samples, 19,390 points padded to 20,480: 14 programs, 15.4 s of compile, 22 -> 4.3 s CPU)
    b = cad_scan_pair("bunny", angle_deg=50.0, seed=0, n_dense=68000)
    other = fsjax.Points(jnp.asarray(b["scan"] * (pair["diag"] / b["diag"])))
    bad = register_cross(pair["mesh"], other, voxel=0.02 * pair["diag"], overlap=0.5)
    print(f"against a bunny scan: converged {bool(bad.converged)}, reason {int(bad.reason)} ({bad.refined.message})")
    assert not bool(bad.converged) and not bool(bad.coarse.converged)
    assert bool(jnp.all(jnp.isnan(bad.coarse.R)))


def test_partial_scan_and_arguments():
    pair = cad_scan_pair("fandisk", angle_deg=0.0, n_dense=8000, seed=0)
    v = np.asarray(pair["mesh"].vertices)
    d = np.array([0.3, -0.5, 1.0]) / np.linalg.norm([0.3, -0.5, 1.0])
    # the scan sees one side: its points face the viewer (lie on the near part along the view direction)
    assert 0.2 * 8000 < len(pair["scan"]) < 0.7 * 8000
    assert np.median(pair["scan"] @ d) < np.median(v @ d)
    with pytest.raises(TypeError, match="register_cross: argument 'target'"):
        register_cross(pair["mesh"], pair["scan"], voxel=0.1)
    with pytest.raises(ValueError, match="register_cross: argument 'method'"):
        register_cross(pair["mesh"], fsjax.Points(jnp.asarray(pair["scan"])), voxel=0.1, method="sift")
    with pytest.raises(ValueError, match="register_cross: argument 'voxel'"):
        register_cross(pair["mesh"], fsjax.Points(jnp.asarray(pair["scan"])), voxel=1e-4, n=5000)


def test_explicit_kinds_are_checked_against_the_sorts():
    """The issue's string kinds, as keywords: a kind naming the argument's sort passes (the call goes
    on to the next check, here the voxel's), one naming another sort raises TypeError naming the op,
    the argument and both kinds, an unknown kind raises ValueError listing the kinds."""
    mesh = fsjax.Mesh(jnp.asarray([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]),
                      jnp.asarray([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], jnp.int32))
    pts = fsjax.Points(jnp.asarray(np.random.default_rng(0).uniform(size=(64, 3))))
    with pytest.raises(ValueError, match="register_cross: argument 'voxel'"):  # the kinds passed
        register_cross(mesh, pts, voxel=0.0, source_kind="mesh", target_kind="points")
    with pytest.raises(TypeError, match="register_cross: argument 'source_kind' is 'points' .* 'source' is Mesh"):
        register_cross(mesh, pts, voxel=0.1, source_kind="points")
    with pytest.raises(TypeError, match="register_cross: argument 'target_kind' is 'voxel' .* 'target' is Points"):
        register_cross(mesh, pts, voxel=0.1, target_kind="voxel")
    with pytest.raises(ValueError, match="register_cross: argument 'target_kind'"):
        register_cross(mesh, pts, voxel=0.1, target_kind="cloud")
