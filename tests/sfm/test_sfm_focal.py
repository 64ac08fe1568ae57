"""Focal-length self-calibration (``fsjax.sfm.focal``, issue 14 "unknown focal length")."""
import numpy as np
import pytest

from fsjax.sfm.focal import estimate_focal, focal_cost, fundamental_8point


def _rot(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    t = np.deg2rad(deg)
    A = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(t) * A + (1 - np.cos(t)) * A @ A


def _scene(f, w=768, h=512, n_views=5, noise_px=0.3, seed=0, dtype=np.float64):
    """Random points in front of cameras on an arc (like a photographed facade), pixel matches of all pairs."""
    rng = np.random.default_rng(seed)
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    X = rng.uniform([-3, -2, 6], [3, 2, 10], (400, 3))
    uv = []
    for k in range(n_views):
        R = _rot([0.1, 1, 0.05], -20 + 40 * k / (n_views - 1))  # camera_from_world
        C = np.array([8 * np.sin(np.deg2rad(-20 + 40 * k / (n_views - 1))), 0.2 * k, 0.0])
        x = (X - C) @ R.T @ K.T
        uv.append((x[:, :2] / x[:, 2:] + rng.normal(0, noise_px, (len(X), 2))).astype(dtype))
    return K, [(uv[i], uv[j]) for i in range(n_views) for j in range(i + 1, n_views)]


@pytest.mark.parametrize("f", [450.0, 690.0, 1100.0])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_focal_recovered_within_1_percent(f, dtype):
    K, pairs = _scene(f, dtype=dtype)
    est = estimate_focal(pairs, (768, 512))
    guess = 1.2 * 768
    assert abs(guess - f) / f > 0.02  # the old guess-only behaviour would fail this case
    assert not est["at_bound"]
    assert abs(est["focal_px"] - f) / f < 0.01, est
    assert est["n_pairs"] == len(pairs)


def test_fundamental_satisfies_epipolar_constraint():
    _, pairs = _scene(690.0, noise_px=0.0)
    uv1, uv2 = pairs[0]
    F = fundamental_8point(uv1, uv2)
    r = np.einsum("ni,ij,nj->n", np.c_[uv2, np.ones(len(uv2))], F, np.c_[uv1, np.ones(len(uv1))])
    assert np.abs(r).max() < 1e-6  # F has unit norm, pixels up to ~800
    assert abs(np.linalg.det(F)) < 1e-10


def test_cost_minimal_near_true_focal():
    _, pairs = _scene(690.0, noise_px=0.0)
    Fs = np.stack([fundamental_8point(a, b) for a, b in pairs])
    w = np.ones(len(Fs))
    c_true = focal_cost(690.0, Fs, w, 383.5, 255.5)
    assert c_true < 1e-4
    assert focal_cost(1.2 * 768, Fs, w, 383.5, 255.5) > 100 * c_true


def test_bad_input_named():
    with pytest.raises(ValueError, match="estimate_focal.*pairs_uv"):
        estimate_focal([(np.zeros((5, 2)), np.zeros((5, 2)))], (768, 512))
    with pytest.raises(ValueError, match="fundamental_8point.*uv1"):
        fundamental_8point(np.zeros((10, 2)), np.zeros((9, 2)))


def test_reconstruct_without_intrinsics_recovers_the_focal_length(tmp_path):
    # the bundled three-view fountain crop (384 x 256, real photographs): no K given
    from fsjax.sfm.export import write_report
    from fsjax.sfm.reconstruct import reconstruct

    from ._data import NAMES, cameras, grey

    K, _, _ = cameras()
    rec = reconstruct([grey(n) for n in NAMES], None, names=list(NAMES), n_max=2048, n_octaves=3)
    assert rec.registered.all()
    f = rec.K[0, 0]
    assert rec.K[1, 1] == f and rec.focal["guess_px"] == 1.2 * 384
    assert abs(f - K[0, 0]) / K[0, 0] < 0.02, (f, K[0, 0])  # the guess 460.8 is 34 % off
    write_report(rec, tmp_path)
    assert f"focal length **{f:.2f} px**" in (tmp_path / "report.md").read_text()
