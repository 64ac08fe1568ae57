"""The CT part road: a part volume with internal voids of known volume -> segmentation ->
labels -> the part's volume and every void with its volume (issue 16)."""

import jax.numpy as jnp
import numpy as np

import fsjax
from fsjax import ops as O

SP = (0.5, 0.4, 0.4)            # mm: anisotropic voxels (dz, dy, dx)
SHAPE = (40, 50, 50)
VOIDS = [((8.0, 6.0, 6.5), 1.2), ((10.0, 13.0, 9.0), 1.6), ((12.0, 9.5, 14.0), 0.9), ((7.0, 13.0, 13.5), 1.0)]
BOX = ((4.0, 16.0), (3.5, 16.5), (4.5, 15.5))   # z, y, x extent of the part, mm


def _phantom(ss=4):
    """Material fraction per voxel (supersampled ss^3): a box with spherical voids; exact volumes."""
    D, H, W = SHAPE
    o = (np.arange(ss) + 0.5) / ss - 0.5
    z = (np.arange(D)[:, None] + o[None, :]).reshape(-1) * SP[0]
    y = (np.arange(H)[:, None] + o[None, :]).reshape(-1) * SP[1]
    x = (np.arange(W)[:, None] + o[None, :]).reshape(-1) * SP[2]
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    m = (Z > BOX[0][0]) & (Z < BOX[0][1]) & (Y > BOX[1][0]) & (Y < BOX[1][1]) & (X > BOX[2][0]) & (X < BOX[2][1])
    for (cz, cy, cx), r in VOIDS:
        m &= (Z - cz) ** 2 + (Y - cy) ** 2 + (X - cx) ** 2 > r * r
    frac = m.reshape(D, ss, H, ss, W, ss).mean(axis=(1, 3, 5))
    box = np.prod([b - a for a, b in BOX])
    return frac, box - sum(4 / 3 * np.pi * r**3 for _, r in VOIDS), [4 / 3 * np.pi * r**3 for _, r in VOIDS]


def test_ct_part_road_part_volume_and_every_void():
    frac, part_true, voids_true = _phantom()
    rng = np.random.default_rng(0)
    ct = fsjax.Volume(jnp.asarray(0.1 + 0.8 * frac + 0.02 * rng.standard_normal(frac.shape)), spacing=SP)
    vvox = SP[0] * SP[1] * SP[2]
    # segmentation: smooth the noise, threshold half-way between air (0.1) and material (0.9)
    sm = O.gaussian3d(ct, sigma=0.4)
    solid = O.fill_holes3d(sm, level=0.5)                          # part with its voids filled
    voids = fsjax.Volume(((solid.data > 0.5) & ~(sm.data > 0.5)).astype(ct.data.dtype), spacing=SP)
    lab = O.label3d(voids, level=0.5, connectivity=6)
    props = O.regionprops3d(lab)
    n_found = int(lab.count)
    # sub-voxel volumes from the grey values (partial-volume integration): material fraction
    # (ct - air) / (material - air), summed over the filled part grown by one voxel;
    f = (np.asarray(ct.data) - 0.1) / 0.8          # not clipped: clipping the noise would bias the sums
    grown = np.asarray(O.dilation3d(solid, radius=1.0, shape="cube").data) > 0.5
    part = float(f[grown].sum() * vvox)
    # each void: the missing material within its label grown by one voxel
    L = np.asarray(lab.data)
    found = []
    for k in range(1, n_found + 1):
        near = np.asarray(O.dilation3d(fsjax.Volume(jnp.asarray((L == k).astype(float)), spacing=SP),
                                       radius=1.0, shape="cube").data) > 0.5
        found.append(float((1.0 - f[near]).sum() * vvox))
    order = np.argsort(found)
    want = np.sort(voids_true)
    part_err = part / part_true - 1
    voxel_count = float(np.asarray(props["volume"])[np.asarray(props.valid)].sum())
    print(f"CT part road: part {part:.2f} mm^3 (true {part_true:.2f}, error {part_err:+.4%}); voids found "
          f"{n_found}/{len(VOIDS)}: " + ", ".join(f"{found[i]:.3f} (true {w:.3f})" for i, w in zip(order, want))
          + f"; voxel-count void volume (the null) {voxel_count:.2f} vs {sum(voids_true):.2f}")
    assert n_found == len(VOIDS) and not bool(lab.truncated)
    assert abs(part_err) < 0.005
    rel = np.abs(np.asarray(found)[order] / want - 1)
    assert np.all(rel < 0.1)
    # the null (voxel counting of the thresholded voids) is further from the truth in total
    assert abs(sum(found) - sum(voids_true)) < abs(voxel_count - sum(voids_true))
