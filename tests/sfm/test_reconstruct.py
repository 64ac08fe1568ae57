"""Incremental SfM on three real views (bundled 384x256 fountain crop): registration, accuracy
against the ground truth beside a null, order independence, and failing honestly on an unrelated
photograph and a pure-rotation pair."""

import numpy as np
import pytest

from fsjax.sfm.reconstruct import align_to_ground_truth, reconstruct

from ._data import DATA, NAMES, cameras

cv2 = pytest.importorskip("cv2")
KW = dict(n_max=2048, n_octaves=3)  # the shapes of test_features.py: one compile for both


@pytest.fixture(scope="module")
def views():
    imgs = [cv2.imread(str(DATA / nm))[:, :, ::-1].copy() for nm in NAMES]
    return imgs, cameras()


@pytest.fixture(scope="module")
def rec(views):
    imgs, (K, _, _) = views
    return reconstruct(imgs, K, names=list(NAMES), **KW)


def _errors(rec, Rs, Cs, order=None):
    order = list(range(len(Rs))) if order is None else order
    # three centres on an arc fix the aligning rotation poorly: take it from the camera rotations
    return align_to_ground_truth(rec.centres, rec.R, np.array(Cs)[order], np.array(Rs)[order],
                                 rotation_from="rotations")


def test_three_views_registered_and_accurate(views, rec):
    _, (K, Rs, Cs) = views
    assert rec.registered.all() and rec.reasons == {}
    assert len(rec.points) > 100 and rec.rms_px < 1.0
    rot, cen = _errors(rec, Rs, Cs)
    baseline = np.linalg.norm(np.array(Cs)[0] - np.array(Cs)[2])
    assert rot.max() < 0.3 and cen.max() < 0.01 * baseline, (rot, cen, baseline)
    # null: every camera at the mean pose direction (identity rotation relative to the first)
    null_rot, _ = align_to_ground_truth(rec.centres, np.repeat(rec.R[:1], 3, 0), np.array(Cs), np.array(Rs),
                                        rotation_from="rotations")
    assert null_rot.max() > 10 * rot.max()
    # every point is seen by >= 2 registered views and lies in front of them
    for p, obs in zip(rec.points[:50], rec.point_obs[:50]):
        assert len(obs) >= 2
        for i, _ in obs:
            assert (rec.R[i] @ p + rec.t[i])[2] > 0
    flags = {(e["i"], e["j"]): e["flag"] for e in rec.view_graph}
    assert flags[(0, 1)] == flags[(1, 2)] == "ok"


def test_shuffled_order_gives_the_same_cameras(views, rec):
    imgs, (K, Rs, Cs) = views
    order = [2, 0, 1]
    rec2 = reconstruct([imgs[i] for i in order], K, **KW)
    assert rec2.registered.all()
    # rec2's cameras aligned onto rec's (same images): the same cameras up to RANSAC noise
    inv = np.argsort(order)
    rot, cen = align_to_ground_truth(rec2.centres[inv], rec2.R[inv], rec.centres,
                                     np.transpose(rec.R, (0, 2, 1)), rotation_from="rotations")
    baseline = np.linalg.norm(rec.centres[0] - rec.centres[2])
    assert rot.max() < 0.1 and cen.max() < 0.005 * baseline, (rot, cen / baseline)


def test_unrelated_photo_and_pure_rotation_fail_honestly(views):
    imgs, (K, _, _) = views
    board = cv2.imread(str(DATA.parents[2] / "fsjax" / "data" / "chessboard" / "left01.jpg"))[100:356, 100:484, ::-1]
    a = np.deg2rad(4.0)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    rotated = cv2.warpPerspective(imgs[1], K @ Ry @ np.linalg.inv(K), (384, 256))
    rec = reconstruct(list(imgs) + [board.copy(), rotated], K, **KW)
    assert not rec.registered[3] and "board" not in rec.reasons[3]  # a reason, stated
    assert len(rec.reasons[3]) > 10
    flags = {(e["i"], e["j"]): e["flag"] for e in rec.view_graph}
    assert flags[(1, 4)] == "pure_rotation"  # flagged, not triangulated
    assert all(flags[(i, 3)] in ("few_matches", "few_inliers") for i in range(3))
    assert rec.registered[:3].all()
