"""3-D marker-controlled watershed: against scikit-image on touching balls (exact and quantised),
against the null of labelling the union (no split), connectivities, jit/vmap, refusals."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage as ndi
from skimage.segmentation import watershed as sk_watershed

import fsjax

_CENTRES = [(14, 16, 14), (14, 16, 27), (25, 22, 20)]
_R = 8.0


@pytest.fixture(scope="module")
def balls():
    z, y, x = np.mgrid[:40, :38, :42]
    fg = np.zeros(z.shape, bool)
    truth = np.zeros(z.shape, np.int32)
    dist = np.full(z.shape, np.inf)
    for k, (cz, cy, cx) in enumerate(_CENTRES, 1):
        d = np.sqrt((z - cz) ** 2 + (y - cy) ** 2 + (x - cx) ** 2)
        fg |= d <= _R
        closer = d < dist
        truth[closer] = k
        dist = np.minimum(dist, d)
    truth[~fg] = 0
    edt = ndi.distance_transform_edt(fg)
    markers = np.zeros(z.shape, np.int32)
    for k, (cz, cy, cx) in enumerate(_CENTRES, 1):
        markers[cz - 1:cz + 2, cy - 1:cy + 2, cx - 1:cx + 2] = k
    return fg, truth, -edt, markers


@pytest.mark.parametrize("conn, sk_conn", [(6, 1), (26, 3)])
def test_equals_scikit_image_on_touching_balls(balls, conn, sk_conn):
    fg, truth, land, markers = balls
    ref = sk_watershed(land, markers, connectivity=sk_conn)
    m = fsjax.LabelVolume(jnp.asarray(markers), count=3)
    exact = np.asarray(fsjax.ops.watershed3d(fsjax.Volume(jnp.asarray(land)), m, connectivity=conn, levels=0).data)
    quant = np.asarray(fsjax.ops.watershed3d(fsjax.Volume(jnp.asarray(land)), m, connectivity=conn).data)
    agree_exact = float(np.mean(exact[fg] == ref[fg]))
    agree_quant = float(np.mean(quant[fg] == ref[fg]))
    # against the geometric truth (nearest centre), and the null: labelling the union (one object)
    truth_exact = float(np.mean(exact[fg] == truth[fg]))
    truth_sk = float(np.mean(ref[fg] == truth[fg]))
    union = ndi.label(fg)[0]
    truth_null = float(np.mean(union[fg] == truth[fg]))
    print(f"conn {conn}: vs skimage exact {agree_exact:.5f}, levels=256 {agree_quant:.5f}; "
          f"vs nearest-centre truth {truth_exact:.4f} (skimage {truth_sk:.4f}, union null {truth_null:.4f})")
    # the two floods differ only among voxels of equal value (ties on the distance map's
    # plateaus and on the crest between balls): the agreement is high but not total, and the
    # agreement with the geometric truth is as good as scikit-image's
    assert agree_exact >= 0.99 and agree_quant >= 0.99
    assert truth_exact >= truth_sk - 0.003
    assert truth_exact > 0.97 and truth_null < 0.5
    # every disagreement sits on the border of two basins: the label given here is one that
    # scikit-image gives to a neighbouring voxel (a different order of equal-value arrivals)
    diff = np.argwhere(fg & (exact != ref))
    assert len(diff) > 0
    for z, y, x in diff:
        nb = ref[max(z - 1, 0):z + 2, max(y - 1, 0):y + 2, max(x - 1, 0):x + 2]
        assert exact[z, y, x] in nb
    assert set(np.unique(exact)) == {1, 2, 3}


def test_flat_landscape_floods_breadth_first_and_a_wall_floods_last():
    # a constant landscape floods breadth-first: each voxel goes to the marker it is fewest
    # steps from (6-connectivity: city-block distance), ties to the smaller label
    v = np.zeros((5, 5, 11))
    m = np.zeros(v.shape, np.int32)
    m[2, 2, 0] = 1
    m[2, 2, 10] = 2
    lm = fsjax.LabelVolume(jnp.asarray(m), count=2)
    lab = np.asarray(fsjax.ops.watershed3d(fsjax.Volume(jnp.asarray(v)), lm, levels=0).data)
    assert lab[2, 2].tolist() == [1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2]
    assert lab[0, 0].tolist() == [1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2]
    # a high wall at x = 8 is flooded last: marker 1 takes the whole low side first
    v[:, :, 8] = 5.0
    lab = np.asarray(fsjax.ops.watershed3d(fsjax.Volume(jnp.asarray(v)), lm, levels=0).data)
    assert np.all(lab[:, :, :8] == 1) and np.all(lab[:, :, 9:] == 2)
    with pytest.raises(ValueError, match="watershed3d.*NaN"):
        fsjax.ops.watershed3d(fsjax.Volume(jnp.asarray(np.where(v > 1, np.nan, v))), lm)


def test_jit_vmap_and_refusals(balls):
    _, _, land, markers = balls
    v = fsjax.Volume(jnp.asarray(land[:20, :20, :20]))
    m = fsjax.LabelVolume(jnp.asarray(markers[:20, :20, :20]))
    one = fsjax.ops.watershed3d(v, m)
    two = jax.jit(jax.vmap(lambda a, b: fsjax.ops.watershed3d(fsjax.Volume(a), fsjax.LabelVolume(b, count=3)).data))(
        jnp.stack([v.data, v.data[:, :, ::-1]]), jnp.stack([m.data, m.data[:, :, ::-1]]))
    np.testing.assert_array_equal(np.asarray(two[0]), np.asarray(one.data))
    np.testing.assert_array_equal(np.asarray(two[1]), np.asarray(one.data)[:, :, ::-1])
    with pytest.raises(ValueError, match="watershed3d.*same shape"):
        fsjax.ops.watershed3d(fsjax.Volume(jnp.zeros((4, 4, 4))), fsjax.LabelVolume(jnp.zeros((4, 4, 5), jnp.int32)))
    with pytest.raises(ValueError, match="watershed3d.*connectivity"):
        fsjax.ops.watershed3d(v, m, connectivity=8)
    with pytest.raises((TypeError, ValueError), match="watershed3d.*levels"):
        fsjax.ops.watershed3d(v, m, levels=-1)
