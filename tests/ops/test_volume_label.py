"""label3d / regionprops3d / distance_transform3d / project3d: conformance with
scipy.ndimage and skimage.measure on small random and structured volumes, capacity
overflow, float32, jit/vmap, bad input. One volume shape throughout."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi
from skimage import measure

from fsjax import LabelVolume, Volume
from fsjax.ops import distance_transform3d, label3d, project3d, regionprops3d

SHAPE = (16, 18, 20)
SP = (2.0, 1.0, 0.5)
STRUCT = {6: ndi.generate_binary_structure(3, 1), 18: ndi.generate_binary_structure(3, 2),
          26: np.ones((3, 3, 3), bool)}


def _masks():
    rng = np.random.default_rng(3)
    smooth = ndi.gaussian_filter(rng.random(SHAPE), 1.0) > 0.5
    speckle = rng.random(SHAPE) < 0.25          # many small components, diagonal contacts
    z, y, x = np.mgrid[0:SHAPE[0], 0:SHAPE[1], 0:SHAPE[2]]
    # a helix-like tube: one long thin component that needs many union-find rounds
    t = np.linspace(0, 4 * np.pi, 400)
    tube = np.zeros(SHAPE, bool)
    tube[np.clip((t / (4 * np.pi) * 15).astype(int), 0, 15), (9 + 7 * np.sin(t)).astype(int),
         (10 + 8 * np.cos(t)).astype(int)] = True
    shell = ((z - 8) ** 2 + (y - 9) ** 2 + (x - 10) ** 2 <= 49) & ((z - 8) ** 2 + (y - 9) ** 2 + (x - 10) ** 2 >= 25)
    return {"smooth": smooth, "speckle": speckle, "tube": tube, "shell": shell | speckle & (z < 3)}


MASKS = _masks()


@pytest.mark.parametrize("name", list(MASKS))
def test_label_equals_scipy(name):
    m = MASKS[name]
    v = Volume(jnp.asarray(m, jnp.float64))
    for conn in (6, 18, 26):
        lab = label3d(v, connectivity=conn)
        ref, n = ndi.label(m, STRUCT[conn])
        assert int(lab.count) == n and not bool(lab.truncated), (name, conn)
        assert np.array_equal(np.asarray(lab.data), ref), (name, conn)
    # skimage numbers the same way for the full connectivity
    sk = measure.label(m, connectivity=3)
    assert np.array_equal(np.asarray(label3d(v).data), sk)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_label_random_odd_shape_equals_scipy(seed):
    """Random masks at an odd shape (every axis padded to whole blocks) and densities around the
    percolation threshold, each connectivity, single and batched: the same array as SciPy."""
    rng = np.random.default_rng(100 + seed)
    shape = (13, 17, 11)
    ms = [rng.random(shape) < p for p in (0.15, 0.3, 0.45)] + [ndi.gaussian_filter(rng.random(shape), 1.0) > 0.5]
    for conn in (6, 18, 26):
        fn = jax.jit(lambda d, c=conn: label3d(Volume(d), connectivity=c).data)
        batched = np.asarray(jax.jit(jax.vmap(fn))(jnp.asarray(np.stack(ms), jnp.float32)))
        counts = []
        for i, m in enumerate(ms):
            ref, n = ndi.label(m, STRUCT[conn])
            counts.append(n)
            assert np.array_equal(np.asarray(fn(jnp.asarray(m, jnp.float32))), ref), (seed, conn, i)
            assert np.array_equal(batched[i], ref), (seed, conn, i)
        assert max(counts) > 5, counts     # not only one big component


def test_label_nested_vmap_uses_the_batching_rule():
    rng = np.random.default_rng(1)
    ms = rng.random((2, 3, 6, 7, 8)) < 0.3
    out = jax.jit(jax.vmap(jax.vmap(lambda d: label3d(Volume(d)).data)))(jnp.asarray(ms, jnp.float32))
    for i in range(2):
        for j in range(3):
            assert np.array_equal(np.asarray(out[i, j]), ndi.label(ms[i, j], STRUCT[26])[0])


def test_label_capacity_fails_closed():
    m = MASKS["speckle"]
    ref, n = ndi.label(m, STRUCT[6])
    assert n > 20
    lab = label3d(Volume(jnp.asarray(m, jnp.float64)), connectivity=6, capacity=20)
    assert int(lab.count) == 20 and bool(lab.truncated)
    assert np.array_equal(np.asarray(lab.data), np.where(ref <= 20, ref, 0))
    props = regionprops3d(lab, capacity=32)
    assert bool(props.truncated)  # the labelling lost components: the table says so


def test_label_float32_level_vmap():
    m1, m2 = MASKS["smooth"], MASKS["tube"]
    prob = jnp.asarray(np.stack([m1 * 0.8 + 0.1, m2 * 0.8 + 0.1]), jnp.float32)
    out = jax.jit(jax.vmap(lambda d: label3d(Volume(d, spacing=SP), level=0.5).data))(prob)
    for i, m in enumerate((m1, m2)):
        assert np.array_equal(np.asarray(out[i]), ndi.label(m, STRUCT[26])[0])


def test_regionprops_equal_skimage():
    ref, n = ndi.label(MASKS["speckle"], STRUCT[6])
    assert n > 3
    p = regionprops3d(LabelVolume(jnp.asarray(ref, jnp.int32), spacing=SP), capacity=n + 3)
    rp = measure.regionprops(ref)
    assert np.asarray(p.valid).tolist() == [True] * n + [False] * 3
    assert not bool(p.truncated)
    tab = {c: np.asarray(p[c]) for c in p.names}  # one transfer, then plain numpy
    for i, r in enumerate(rp):
        assert tab["voxels"][i] == r.area
        assert abs(tab["volume"][i] - r.area * np.prod(SP)) < 1e-12
        for k, ax in enumerate("zyx"):
            assert abs(tab[f"centroid_{ax}"][i] - r.centroid[k] * SP[k]) < 1e-12
        assert tuple(int(tab[c][i]) for c in ("bbox_z0", "bbox_y0", "bbox_x0", "bbox_z1", "bbox_y1", "bbox_x1")) \
            == r.bbox
    small = regionprops3d(LabelVolume(jnp.asarray(ref, jnp.int32), spacing=SP), capacity=2)
    assert bool(small.truncated)


def test_regionprops_inertia_equals_skimage():
    """Inertia-tensor eigenvalues equal skimage's (with spacing) on every component; the long axis
    of an ellipsoid is the eigenvector of the smallest eigenvalue."""
    ref, n = ndi.label(MASKS["speckle"], STRUCT[18])
    assert n >= 5
    p = regionprops3d(LabelVolume(jnp.asarray(ref, jnp.int32), spacing=SP), capacity=n)
    tab = {c: np.asarray(p[c]) for c in p.names}
    for i, r in enumerate(measure.regionprops(ref, spacing=SP)):
        mine = [tab[f"inertia_{k}"][i] for k in range(3)]
        assert np.allclose(mine, r.inertia_tensor_eigvals, rtol=1e-10, atol=1e-10), (i, mine)
    z, y, x = np.mgrid[0:SHAPE[0], 0:SHAPE[1], 0:SHAPE[2]]
    # semi-axes z 3, y 4, x 9 voxels: physically (spacing 2, 1, 0.5) 6, 4, 4.5 mm, so z is the long axis
    ell = ((z - 7.5) / 3) ** 2 + ((y - 8.5) / 4) ** 2 + ((x - 9.5) / 9) ** 2 < 1
    q = regionprops3d(LabelVolume(jnp.asarray(ell, jnp.int32), spacing=SP), capacity=1)
    axis = [float(q[c][0]) for c in ("axis_z", "axis_y", "axis_x")]
    assert np.allclose(axis, [1.0, 0.0, 0.0], atol=1e-9), axis
    q2 = regionprops3d(LabelVolume(jnp.asarray(ell, jnp.int32)), capacity=1)  # in voxels x (9) is the longest
    assert np.allclose([float(q2[c][0]) for c in ("axis_z", "axis_y", "axis_x")], [0.0, 0.0, 1.0], atol=1e-9)


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), SP])
def test_regionprops_surface_area_of_a_ball(spacing):
    """Crofton surface area of a digitised ball of radius 9 mm: within 3 % of 4 pi r^2, where the
    null (exposed voxel faces times face area) is ~50 % too large, and skimage's marching cubes
    on the same mask ~8 % too large."""
    r = 9.0
    shape = tuple(int(2 * r / s) + 5 for s in spacing)
    g = np.meshgrid(*[(np.arange(n) - (n - 1) / 2) * s for n, s in zip(shape, spacing)], indexing="ij")
    ball = g[0] ** 2 + g[1] ** 2 + g[2] ** 2 <= r * r
    two = np.where(ball, 1, 0)
    two[:2, :2, :2] = 2  # a second label in a corner: a 2x2x2 cube touching the border
    p = regionprops3d(LabelVolume(jnp.asarray(two, jnp.int32), spacing=spacing), capacity=2)
    true = 4 * np.pi * r * r
    area = float(p["surface_area"][0])
    dz, dy, dx = spacing
    face_area = (dy * dx, dz * dx, dz * dy)
    null = sum(np.sum(np.diff(np.pad(ball, 1).astype(int), axis=a) != 0) * face_area[a] for a in range(3))
    verts, faces, _, _ = measure.marching_cubes(np.pad(ball, 1).astype(float), 0.5, spacing=spacing)
    mc = measure.mesh_surface_area(verts, faces)
    err, err_null, err_mc = abs(area / true - 1), abs(null / true - 1), abs(mc / true - 1)
    print(f"surface area of a r=9 mm ball, spacing {spacing}: Crofton {err:.2%}, faces {err_null:.1%}, "
          f"marching cubes {err_mc:.1%}")
    assert err < 0.03 and err_null > 0.3 and err < err_mc
    # the corner cube (touches the volume border: outside is background): 6 faces of 2x2 voxels
    cube = 2 * 4 * (dy * dx + dz * dx + dz * dy)
    assert abs(float(p["surface_area"][1]) / cube - 1) < 0.35, float(p["surface_area"][1])


@pytest.mark.parametrize("sampling", [(1.0, 1.0, 1.0), SP])
def test_edt_equals_scipy(sampling):
    for name in ("smooth", "speckle", "shell"):
        fg = ~MASKS[name] if name == "speckle" else MASKS[name]  # speckle inverted: mostly foreground
        d = distance_transform3d(Volume(jnp.asarray(fg, jnp.float64), spacing=sampling))
        ref = ndi.distance_transform_edt(fg, sampling=sampling)
        err = float(np.abs(np.asarray(d.data) - ref).max())
        if sampling == (1.0, 1.0, 1.0):
            assert err == 0.0, name
        else:
            assert err < 1e-12, name


def test_edt_single_background_voxel_and_no_background():
    fg = np.ones(SHAPE, bool)
    fg[3, 15, 2] = False
    d = distance_transform3d(Volume(jnp.asarray(fg, jnp.float64), spacing=SP))
    assert float(np.abs(np.asarray(d.data) - ndi.distance_transform_edt(fg, sampling=SP)).max()) < 1e-12
    allfg = distance_transform3d(Volume(jnp.ones((4, 5, 6))))
    assert bool(jnp.all(jnp.isinf(allfg.data)))


def test_edt_vmap_float32():
    fgs = jnp.asarray(np.stack([MASKS["smooth"], MASKS["shell"]]), jnp.float32)
    out = jax.jit(jax.vmap(lambda d: distance_transform3d(Volume(d, spacing=SP)).data))(fgs)
    assert out.dtype == jnp.float32
    for i, name in enumerate(("smooth", "shell")):
        ref = ndi.distance_transform_edt(MASKS[name], sampling=SP)
        assert float(np.abs(np.asarray(out[i], np.float64) - ref).max()) < 1e-5 * max(1.0, ref.max())


def test_projections():
    rng = np.random.default_rng(5)
    x = rng.random(SHAPE)
    v = Volume(jnp.asarray(x), spacing=SP)
    for axis in (0, 1, 2):
        assert np.array_equal(np.asarray(project3d(v, axis=axis).data), x.max(axis))
        assert np.array_equal(np.asarray(project3d(v, axis=axis, kind="min").data), x.min(axis))
        assert float(np.abs(np.asarray(project3d(v, axis=axis, kind="mean").data) - x.mean(axis)).max()) < 1e-14
        s = project3d(v, axis=axis, kind="sum").data
        assert float(np.abs(np.asarray(s) - x.sum(axis) * SP[axis]).max()) < 1e-12
    b = jax.jit(jax.vmap(lambda d: project3d(Volume(d), axis=1).data))(jnp.stack([jnp.asarray(x)] * 2))
    assert b.shape == (2, SHAPE[0], SHAPE[2])
    x32 = project3d(Volume(jnp.asarray(x, jnp.float32)), kind="mean").data
    assert x32.dtype == jnp.float32 and float(np.abs(np.asarray(x32) - x.mean(0)).max()) < 1e-6


def test_bad_input_names_op_and_argument():
    v = Volume(jnp.zeros((4, 4, 4)))
    with pytest.raises(ValueError, match="label3d: argument 'connectivity'"):
        label3d(v, connectivity=8)
    with pytest.raises(ValueError, match="label3d: argument 'capacity'"):
        label3d(v, capacity=0)
    with pytest.raises(ValueError, match="project3d: argument 'axis'"):
        project3d(v, axis=3)
    with pytest.raises(ValueError, match="project3d: argument 'kind'"):
        project3d(v, kind="median")
    with pytest.raises(ValueError, match="distance_transform3d: argument 'level'"):
        distance_transform3d(v, level=float("nan"))
    with pytest.raises(TypeError, match="regionprops3d"):
        regionprops3d(v)
