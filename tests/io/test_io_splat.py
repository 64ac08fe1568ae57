"""PLY and .splat round trips with their stated quantisation bounds."""

import doctest

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax
from fsjax import Gaussians
from fsjax.io import splat as IO
from fsjax.render.splat import SH_C0


def _g(n=300, k=4, seed=0):
    rng = np.random.default_rng(seed)
    valid = np.ones(n, bool)
    valid[5] = False
    return Gaussians(rng.normal(0, 2, (n, 3)), rng.normal(-3, 1, (n, 3)), rng.normal(size=(n, 4)),
                     rng.normal(0, 3, n), rng.normal(0, 1, (n, k, 3)), valid=valid)


def test_module_examples():
    res = doctest.testmod(IO, extraglobs={"fsjax": fsjax, "jnp": jnp, "np": np, "jax": jax})
    assert res.attempted >= 4 and res.failed == 0


@pytest.mark.parametrize("k", [1, 4, 16])
def test_ply_round_trip(tmp_path, k):
    g = _g(k=k)
    p = tmp_path / "g.ply"
    assert IO.write_ply_gaussians(p, g) == 299
    h = IO.read_ply_gaussians(p)
    v = np.asarray(g.valid)
    worst = 0.0
    for f in ("means", "log_scales", "quats", "opacity_logits", "colors"):
        a, b = np.asarray(getattr(g, f))[v], np.asarray(getattr(h, f))
        worst = max(worst, float(np.max(np.abs(a - b) / np.maximum(np.abs(a), 1e-30))))
        assert np.array_equal(b, a.astype(np.float32).astype(np.float64)), f
    print(f"PLY round trip (K={k}): max relative error {worst:.1e} (bound 2^-24 = {2.0**-24:.1e})")
    assert worst <= 2.0**-24
    from plyfile import PlyData
    names = PlyData.read(str(p))["vertex"].data.dtype.names
    assert names[:9] == ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
    assert names[-8:] == ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
    assert len(names) == 17 + 3 * (k - 1)


def test_splat_round_trip_bounds(tmp_path):
    g = _g(k=4)
    p = tmp_path / "g.splat"
    assert IO.write_splat(p, g) == 299
    assert p.stat().st_size == 299 * 32
    h = IO.read_splat(p)
    v = np.asarray(g.valid)
    m = np.asarray(g.means)[v]
    assert np.array_equal(np.asarray(h.means), m.astype(np.float32).astype(np.float64))
    sc = np.exp(np.asarray(g.log_scales)[v])
    assert np.max(np.abs(np.exp(np.asarray(h.log_scales)) - sc) / sc) <= 2.0**-23
    rgb = np.clip(0.5 + SH_C0 * np.asarray(g.colors)[v][:, 0, :], 0, 1)
    rgb2 = 0.5 + SH_C0 * np.asarray(h.colors)[:, 0, :]
    e_rgb = float(np.max(np.abs(rgb - rgb2)))
    al = 1 / (1 + np.exp(-np.asarray(g.opacity_logits)[v]))
    al2 = 1 / (1 + np.exp(-np.asarray(h.opacity_logits)))
    e_al = float(np.max(np.abs(al - al2)))
    q = np.asarray(g.quats)[v]
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    q2 = np.asarray(h.quats)
    ang = np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(q * q2, 1)), 0, 1)))
    print(f".splat round trip: colour {e_rgb * 255:.3f}/255 (bound 0.5/255), opacity {e_al * 255:.3f}/255 "
          f"(bound 0.5/255 + end clamp), rotation max {ang.max():.2f} deg (bound 1.79 deg)")
    assert e_rgb <= 0.5 / 255 + 1e-12
    assert e_al <= 0.5 / 255 + 1e-12
    assert ang.max() <= 1.79
    assert h.colors.shape == (299, 1, 3)


def test_bad_files(tmp_path):
    p = tmp_path / "bad.splat"
    p.write_bytes(b"\0" * 33)
    with pytest.raises(ValueError, match="multiple of 32"):
        IO.read_splat(p)
    rec = np.zeros(1, IO.SPLAT_DTYPE)
    rec["scale"] = 1.0
    rec["rot"] = 128
    p.write_bytes(rec.tobytes())
    with pytest.raises(ValueError, match="zero-length"):
        IO.read_splat(p)
    with pytest.raises(TypeError, match="write_splat|splat_bytes"):
        IO.write_splat(tmp_path / "x.splat", np.zeros((3, 3)))
