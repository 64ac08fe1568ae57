"""The LiDAR scene generator: deterministic, labels and centroids consistent, slope as asked."""

from __future__ import annotations

import numpy as np

from fsjax.synth import LIDAR_OBJECTS, lidar_scene


def test_lidar_scene_ground_truth():
    pts, info = lidar_scene(0)
    pts2, info2 = lidar_scene(0)
    assert np.array_equal(np.asarray(pts.xyz), np.asarray(pts2.xyz))
    assert not np.array_equal(np.asarray(pts.xyz), np.asarray(lidar_scene(1)[0].xyz))
    xyz, lab = np.asarray(pts.xyz), info["labels"]
    assert lab.shape == (xyz.shape[0],) and set(np.unique(lab)) == {0, 1, 2, 3, 4}
    assert info["names"] == LIDAR_OBJECTS
    # ground points lie on z = tan(5 deg) x within the noise
    g = xyz[lab == 0]
    a = np.linalg.lstsq(np.c_[g[:, :2], np.ones(len(g))], g[:, 2], rcond=None)[0]
    slope = np.degrees(np.arctan(a[0]))
    # object centroids (noise-free truth) agree with the noisy samples' means
    errs = [np.linalg.norm(xyz[lab == i + 1].mean(0) - info["centroids"][i]) for i in range(4)]
    # objects are above the ground and separated by more than a metre
    gap = min(np.linalg.norm(info["centroids"][i, :2] - info["centroids"][j, :2]) for i in range(4)
              for j in range(i))
    print(f"lidar scene: {xyz.shape[0]} points, fitted ground slope {slope:.3f} deg (truth 5), "
          f"centroid consistency {max(errs):.4f}, object separation {gap:.2f}")
    assert abs(slope - 5.0) < 0.05 and abs(a[1]) < 0.01 and max(errs) < 0.01 and gap > 3
    for i in range(1, 5):
        o = xyz[lab == i]
        assert np.all(o[:, 2] > np.tan(np.radians(5.0)) * o[:, 0] - 0.05)
