"""Euclidean clustering (vs SciPy connected components on the cKDTree radius graph),
capacities at overflow, ground removal, and the LiDAR scene of issue 4 (item 5)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

import fsjax
from fsjax.ops import cluster_centroids
from fsjax.types import PointLabels
from fsjax.synth import lidar_scene


def _scipy_clusters(xyz, radius, min_size):
    pairs = cKDTree(xyz).query_pairs(radius, output_type="ndarray")
    n = len(xyz)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    # relabel by lowest point index, drop small components
    out = np.zeros(n, int)
    k = 0
    for c in comp[np.sort(np.unique(comp, return_index=True)[1])]:
        m = comp == c
        if m.sum() >= min_size:
            k += 1
            out[m] = k
    return out


def test_clusters_equal_scipy_connected_components():
    rng = np.random.default_rng(0)
    centres = rng.uniform(-5, 5, (12, 3))
    xyz = np.concatenate([c + 0.3 * rng.normal(size=(rng.integers(3, 60), 3)) for c in centres])
    xyz = xyz[rng.permutation(len(xyz))]
    lab = jax.jit(lambda p: fsjax.ops.euclidean_cluster(p, radius=0.4, min_size=5, max_neighbors=64))(
        fsjax.Points(jnp.asarray(xyz)))
    ref = _scipy_clusters(xyz, 0.4, 5)
    assert isinstance(lab, PointLabels) and not bool(lab.truncated)
    print(f"euclidean_cluster vs scipy connected_components on the cKDTree radius graph: {int(lab.count)} clusters, "
          f"{int(np.sum(np.asarray(lab.labels) != ref))} of {len(xyz)} labels differ")
    assert np.array_equal(np.asarray(lab.labels), ref)


def test_capacities_at_overflow():
    rng = np.random.default_rng(1)
    blobs = np.concatenate([c + 0.05 * rng.normal(size=(20, 3)) for c in np.eye(3) * 10])
    lab = fsjax.ops.euclidean_cluster(fsjax.Points(jnp.asarray(blobs)), radius=0.5, min_size=2, capacity=2)
    assert bool(lab.truncated) and int(lab.count) == 2
    assert set(np.unique(np.asarray(lab.labels))) == {0, 1, 2}
    # neighbour-list overflow is flagged (each point has 19 neighbours, capacity 4)
    lab = fsjax.ops.euclidean_cluster(fsjax.Points(jnp.asarray(blobs)), radius=0.5, min_size=2, max_neighbors=4)
    assert bool(lab.truncated)
    with pytest.raises(ValueError, match="euclidean_cluster.*radius"):
        fsjax.ops.euclidean_cluster(fsjax.Points(jnp.asarray(blobs)), radius=0.0)
    with pytest.raises(TypeError, match="euclidean_cluster.*capacity"):
        fsjax.ops.euclidean_cluster(fsjax.Points(jnp.asarray(blobs)), capacity=2.5)
    with pytest.raises(ValueError, match="remove_ground.*max_slope_deg"):
        fsjax.ops.remove_ground(fsjax.Points(jnp.asarray(blobs)), max_slope_deg=120.0)


@jax.jit
def _pipeline(pts):
    ng = fsjax.ops.remove_ground(pts, threshold=0.1, max_slope_deg=15.0)
    lab = fsjax.ops.euclidean_cluster(ng, radius=0.3, min_size=20, max_neighbors=128, capacity=16)
    null = fsjax.ops.euclidean_cluster(pts, radius=0.3, min_size=20, max_neighbors=128, capacity=16)
    return ng, lab, cluster_centroids(ng, lab, 16), null


def lidar_result(seed=0):
    pts, info = lidar_scene(seed)
    ng, lab, (cen, size, ok), null = _pipeline(pts)
    truth = info["labels"]
    v = np.asarray(ng.valid)
    cen = np.asarray(cen)[np.asarray(ok)]
    err = np.array([np.min(np.linalg.norm(cen - c, axis=1)) for c in info["centroids"]]) if len(cen) else np.inf
    return {"count": int(lab.count), "truncated": bool(lab.truncated), "null_count": int(null.count),
            "ground_left": int(np.sum(v[truth == 0])), "objects_removed": int(np.sum(~v[truth > 0])),
            "n_objects": int(np.sum(truth > 0)), "centroid_errors": err}


def test_lidar_scene_four_clusters_after_ground_removal():
    r = lidar_result(0)
    print(f"LiDAR scene (sloped 5 deg): {r['count']} clusters after ground removal (truncated {r['truncated']}), "
          f"centroid errors {np.round(r['centroid_errors'], 3)}; ground points left {r['ground_left']}, "
          f"object points removed {r['objects_removed']}/{r['n_objects']}; "
          f"null without ground removal: {r['null_count']} cluster(s)")
    assert r["count"] == 4 and not r["truncated"]
    assert np.all(r["centroid_errors"] <= 0.13)
    assert r["ground_left"] == 0
    assert r["null_count"] == 1  # the ground links everything: one fused cluster


def test_remove_ground_flat_and_sloped():
    rng = np.random.default_rng(3)
    for slope in (0.0, 10.0):
        g = rng.uniform(-3, 3, (600, 2))
        z = np.tan(np.radians(slope)) * g[:, 0] + 0.01 * rng.normal(size=600)
        box = np.c_[rng.uniform(-0.5, 0.5, (100, 2)), rng.uniform(0.3, 1.0, 100)]
        box[:, 2] += np.tan(np.radians(slope)) * box[:, 0]
        out = fsjax.ops.remove_ground(fsjax.Points(jnp.asarray(np.r_[np.c_[g, z], box])), threshold=0.05)
        v = np.asarray(out.valid)
        assert not v[:600].any() and v[600:].all()
    # a steep wall only: no admissible ground, nothing removed
    wall = np.c_[np.zeros(200), rng.uniform(-1, 1, (200, 2))]
    out = fsjax.ops.remove_ground(fsjax.Points(jnp.asarray(wall)), threshold=0.05)
    assert bool(out.valid.all())
