"""Incremental structure from motion with known intrinsics: features -> matches -> verified view
graph -> tracks -> initial pair -> PnP registration + triangulation + bundle adjustment.

Choice: **incremental** (as COLMAP; Schonberger and Frahm 2016, "Structure-from-Motion Revisited",
CVPR), not global: with a few tens of images the incremental loop is simple, robust to wrong
view-graph edges (every registration is re-checked by PnP RANSAC) and needs no rotation /
translation averaging.

Stages (each timed; ``Reconstruction.times_s``):

1. **features**: :func:`fsjax.sfm.detect_and_describe` per image (one compile; fixed capacity).
2. **matching**: every pair by :func:`fsjax.sfm.match_pairs` (mutual NN + ratio 0.8, one call).
3. **verification**: :func:`fsjax.fit.twoview.relative_pose` per pair (normalised 8-point
   essential matrices: RANSAC hypotheses fitted and scored in one ``vmap``, inliers by Sampson
   distance, Levenberg-Marquardt refinement, parallax test). The 8-point solver rather than
   Nister's 5-point: fsjax has it, it is a linear least-squares fit that ``vmap``s and
   differentiates without a polynomial root finder, and the price (more samples for the same
   outlier rate: ~1,200 vs ~145 samples for 50 % outliers at 99 % confidence) is paid in one
   ``vmap`` of ``n_hypotheses`` samples. A pair is an edge of the view graph with its inlier
   count when it has >= ``min_inliers`` inliers; a pair without parallax is flagged
   ``pure_rotation`` and never used to initialise or triangulate alone.
   Beside E, a homography (:func:`fsjax.fit.twoview.homography_ransac`: 4-point normalised DLT
   hypotheses in one ``vmap``, half as many as E's, since a 4-point sample is outlier-free far
   more often than an 8-point one; weighted refits on the inliers) with the threshold
   ``1.25 threshold_px`` on its transfer distance (``sqrt(5.99 / 3.84)``: the 95 % quantiles of
   a codimension-2 and a codimension-1 model, Hartley and Zisserman 2004, table 4.1, so both
   count the same noise alike). **The rule**: a scene point on one plane, or any point when
   the camera only turns, maps by one homography (H&Z sections 13.1 and 8.4), and then the
   essential matrix adds nothing (H&Z 11.9: the 8-point system is rank-deficient for coplanar
   points). So when H's inliers are >= ``h_ratio`` (0.9) of E's, the pair is degenerate for E:
   ``pure_rotation`` when the H inliers have less than ``min_parallax_px`` of parallax (the best
   single rotation aligns their bearings, :func:`fsjax.fit.twoview.rotation_parallax`), else
   ``planar``. COLMAP's two-view geometry compares the same inlier ratio with 0.8; 0.9 here
   because herzjesu-P8's wide-baseline facade pairs measure 0.80-0.82 and are reconstructed
   accurately from E (their other 18-20 % of inliers, 100-160 points, fix it), while a plane
   measures 0.98-0.99 (tests). A planar pair's pose comes from the homography
   (:func:`fsjax.fit.twoview.decompose_homography`), the solution putting more H inliers in front
   of both cameras; its H inliers feed the tracks. The initial pair is chosen among general
   pairs first and from planar pairs only when no general pair has the angle.
4. **tracks**: union-find over the inlier matches; a track that holds two keypoints of one
   image (inconsistent matches) is dropped.
5. **reconstruction**: the initial pair maximises inliers among general (``ok``) edges whose median
   triangulation angle is >= ``init_angle_deg`` (``planar`` edges only when no general one qualifies); then repeatedly the unregistered image seeing the most
   triangulated tracks is registered by :func:`fsjax.fit.pnp.solve_pnp_ransac` (reprojection
   threshold ``max_reproj_px``), new tracks are triangulated (DLT over all registered views;
   kept when every kept view reprojects within ``max_reproj_px``, depth is positive and the
   largest ray angle >= ``min_tri_angle_deg``), and the model is refined by the robust (Cauchy)
   bundle adjustment of :mod:`fsjax.sfm.bundle`: globally (every registered camera and point) when
   the registered views or the points grew by ``global_ba_growth`` (1.1, COLMAP's ratio) since the
   last global one, otherwise locally (the new view, its ``local_ba_views - 1`` most covisible
   registered views and the points they see; other views observing those points stay fixed);
   observations beyond ``max_reproj_px`` are then dropped. A final global bundle adjustment runs
   to convergence (relative cost decrease < 1e-6). Each problem is compacted to what it holds and
   padded to a power-of-two level (observations, points half of them, observation pairs 1.5x
   them): one compile per level.

Every image left out carries a reason (``Reconstruction.reasons``).
Poses are ``camera_from_world`` (``R``, ``t``: ``x = R X + t``), OpenCV camera frame, pixels
``(u, v) = (column, row)`` with centres on integers; the world frame is the first camera of the
initial pair, the scale its baseline (unobservable from images alone).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from ..fit.pnp import solve_pnp_ransac
from ..fit.twoview import decompose_homography, homography_ransac, relative_pose, rotation_parallax
from ..types.results import reason_code
from .bundle import bundle_adjust_masked, observation_pairs
from .features import detect_and_describe
from .focal import estimate_focal
from .matching import match_pairs

__all__ = ["Reconstruction", "reconstruct", "grey_image"]


@dataclass
class Reconstruction:
    """Result of :func:`reconstruct` (numpy arrays; N images, T tracks)."""

    names: list[str]
    K: np.ndarray
    size: tuple[int, int]  # (width, height)
    registered: np.ndarray  # (N,) bool
    R: np.ndarray  # (N, 3, 3) camera_from_world (NaN if not registered)
    t: np.ndarray  # (N, 3)
    keypoints: list[np.ndarray]  # per image (n_i, 2) valid keypoints (u, v)
    points: np.ndarray  # (P, 3) triangulated points
    colors: np.ndarray  # (P, 3) uint8
    point_obs: list[list[tuple[int, int]]]  # per point: (image, keypoint index)
    reasons: dict[int, str]
    view_graph: list[dict]
    times_s: dict[str, float] = field(default_factory=dict)
    rms_px: float = float("nan")
    registration_order: list[int] = field(default_factory=list)
    focal: dict | None = None  # how the focal length was found when no intrinsics were given
    ba_calls: list[dict] = field(default_factory=list)  # per bundle adjustment: kind, cameras, points, ...

    @property
    def centres(self) -> np.ndarray:
        """(N, 3) camera centres in the world."""
        return -np.einsum("nji,nj->ni", self.R, self.t)


def grey_image(rgb: np.ndarray) -> np.ndarray:
    """float32 grey in [0, 1] of an (H, W, 3) uint8 or float image (Rec. 601 luma)."""
    a = np.asarray(rgb)
    a = a.astype(np.float32) / (255.0 if a.dtype == np.uint8 else 1.0)
    return a if a.ndim == 2 else (a[..., 0] * 0.299 + a[..., 1] * 0.587 + a[..., 2] * 0.114).astype(np.float32)


class _UF:
    def __init__(self, n):
        self.p = np.arange(n)

    def find(self, a):
        p = self.p
        root = a
        while p[root] != root:
            root = p[root]
        while p[a] != root:
            p[a], a = root, p[a]
        return root

    def union(self, a, b):
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.p[max(ra, rb)] = min(ra, rb)


def _angle_deg(X, C1, C2):
    a = X - C1
    b = X - C2
    c = np.sum(a * b, -1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-300)
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


def _bucket(k: int, lo: int, linear: bool = False) -> int:
    """Capacity for ``k`` items: a multiple of ``lo`` (linear) or ``lo`` times a power of two."""
    if linear:
        return max(lo, -(-k // lo) * lo)
    c = lo
    while c < k:
        c *= 2
    return c


_parallax = jax.jit(rotation_parallax)


def _parallax_px(uv1, uv2, inl, K, m_pad) -> float:
    """Median residual (px) of the best single rotation aligning the bearings of the inliers ``inl``."""
    Kinv = np.linalg.inv(K)
    x1 = (np.c_[uv1, np.ones(len(uv1))] @ Kinv.T)[:, :2]
    x2 = (np.c_[uv2, np.ones(len(uv2))] @ Kinv.T)[:, :2]
    _, res = _parallax(jnp.asarray(_pad(x1, m_pad, 0.0)), jnp.asarray(_pad(x2, m_pad, 0.0)),
                       jnp.asarray(_pad(inl.astype(np.float64), m_pad, 0.0)))
    return float(np.median(np.asarray(res)[:len(inl)][inl]) * 0.5 * (K[0, 0] + K[1, 1]))


def _planar_pose(H, uv1, uv2, K):
    """Pose of a planar pair from its homography: of the two solutions whose plane faces camera 1
    (:func:`fsjax.fit.twoview.decompose_homography`), the one putting more H inliers in front of
    both cameras; ``(R, unit t, camera-1 points in front, (in front, in front for the other))``.
    The two are often both physical (Longuet-Higgins 1986): then the choice is a guess the report
    shows (``front`` counts nearly equal)."""
    Rs, ts, _ = (np.asarray(v) for v in decompose_homography(jnp.asarray(H), jnp.asarray(K)))
    Kinv = np.linalg.inv(K)
    x1 = np.c_[uv1, np.ones(len(uv1))] @ Kinv.T
    x2 = np.c_[uv2, np.ones(len(uv2))] @ Kinv.T
    best = []
    for R, t in zip(Rs[:2], ts[:2]):
        t = t / np.linalg.norm(t)
        P2 = np.c_[R, t]
        P1 = np.eye(3, 4)
        A = np.stack([x1[:, :1] * P1[2] - P1[0], x1[:, 1:2] * P1[2] - P1[1],
                      x2[:, :1] * P2[2] - P2[0], x2[:, 1:2] * P2[2] - P2[1]], 1)
        Xh = np.linalg.svd(A)[2][:, -1]
        X = Xh[:, :3] / np.where(np.abs(Xh[:, 3:]) > 1e-12, Xh[:, 3:], np.nan)
        ok = np.isfinite(X).all(1) & (X[:, 2] > 0) & (X @ R[2] + t[2] > 0)
        best.append((int(ok.sum()), R, t, X[ok]))
    k = int(best[1][0] > best[0][0])
    return best[k][1], best[k][2], best[k][3], (best[k][0], best[1 - k][0])


def _pad(a, n, fill=np.nan):
    out = np.full((n,) + a.shape[1:], fill, np.float64)
    out[:len(a)] = a
    return out


def reconstruct(images, K=None, *, names=None, n_max: int = 4096, n_octaves: int = 5, seed: int = 0, min_inliers: int = 30,
                threshold_px: float = 1.5, max_reproj_px: float = 4.0, min_tri_angle_deg: float = 1.5,
                init_angle_deg: float = 3.0, n_hypotheses: int = 512, local_ba_views: int = 6,
                global_ba_growth: float = 1.1, h_ratio: float = 0.9, min_parallax_px: float = 1.5,
                log=None) -> Reconstruction:
    """Incremental SfM of images of one size with known (or guessed) intrinsics (module notes).

    Args:
      images: sequence of ``(H, W, 3)`` uint8 (or float in [0, 1]) images, or grey ``(H, W)``.
      K: ``(3, 3)`` intrinsics; ``None``: one focal length (fx = fy, principal point at the image
        centre) is self-calibrated from the verified pairs (:func:`fsjax.sfm.focal.estimate_focal`,
        starting from the guess ``f = 1.2 max(W, H)``) and verification is repeated with it;
        ``Reconstruction.focal`` says how it was found.
      names: image names for reports. n_max: keypoint capacity per image. n_octaves: detector
        octaves. seed: RANSAC key.
      min_inliers: view-graph edge threshold. threshold_px: Sampson inlier threshold (px) of the
        essential matrix; the homography's threshold on the transfer distance is 1.25x it
        (``sqrt(5.99 / 3.84)``, Hartley and Zisserman 2004, table 4.1: codimension 2 against 1).
      h_ratio: a pair whose homography has >= ``h_ratio`` times the essential matrix's inliers
        is flagged ``planar``, or ``pure_rotation`` when its H inliers have less than
        ``min_parallax_px`` of parallax (module notes).
      max_reproj_px: PnP / triangulation / filtering reprojection threshold (px).
      min_tri_angle_deg: smallest ray angle of a triangulated point. init_angle_deg: median ray
        angle an initial pair needs. n_hypotheses: RANSAC samples (two-view and PnP).
      local_ba_views: views in the local bundle adjustment after a registration (the new view and
        its most covisible registered views; COLMAP's ``local_ba_num_images``, 6).
      global_ba_growth: a global bundle adjustment runs after a registration when the registered
        views or the points grew by this factor since the last one (COLMAP's ``ba_global_*_ratio``,
        1.1), and once at the end.
      log: optional callable(str) for progress lines.

    Returns:
      :class:`Reconstruction`.
    """
    say = log or (lambda s: None)
    imgs = [np.asarray(im) for im in images]
    if len(imgs) < 2:
        raise ValueError(f"reconstruct: argument 'images' must hold >= 2 images, got {len(imgs)}")
    shapes = {im.shape[:2] for im in imgs}
    if len(shapes) != 1:
        raise ValueError(f"reconstruct: argument 'images' must be of one size, got sizes {sorted(shapes)}")
    h, w = imgs[0].shape[:2]
    n = len(imgs)
    names = list(names) if names is not None else [f"{i:04d}" for i in range(n)]
    focal_info = None
    if K is None:  # guess (COLMAP's prior), then self-calibrate after verification (fsjax.sfm.focal)
        f = 1.2 * max(w, h)
        K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
        focal_info = dict(guess_px=f)
    K = np.asarray(K, np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"reconstruct: argument 'K' must be a finite (3, 3) intrinsics matrix, got {K}")
    times: dict[str, float] = {}
    key = jax.random.PRNGKey(seed)

    # 1. features
    t0 = time.perf_counter()
    feats = []
    for i, im in enumerate(imgs):
        feats.append(jax.block_until_ready(detect_and_describe(jnp.asarray(grey_image(im)), n_max=n_max,
                                                                      n_octaves=n_octaves)))
        say(f"features {i + 1}/{n}: {int(feats[-1].valid.sum())} keypoints")
    valid = np.stack([np.asarray(f.valid) for f in feats])
    # valid keypoints come first (sorted by contrast): later stages work on a capacity sized from
    # the largest count (a multiple of 256), not on n_max (matching costs capacity squared)
    n_kp = min(n_max, _bucket(int(valid.sum(1).max()), 256, linear=True))
    valid = valid[:, :n_kp]
    uv_all = np.stack([np.asarray(f.uv, np.float64)[:n_kp] for f in feats])
    desc = jnp.stack([f.descriptors[:n_kp] for f in feats])
    times["features"] = time.perf_counter() - t0

    # 2. matching (all pairs, one call)
    t0 = time.perf_counter()
    pairs = np.array([(i, j) for i in range(n) for j in range(i + 1, n)], np.int32)
    M = np.asarray(jax.block_until_ready(match_pairs(desc, jnp.asarray(valid), pairs)))
    times["matching"] = time.perf_counter() - t0
    say(f"matching: {len(pairs)} pairs, median {int(np.median((M >= 0).sum(1)))} matches")

    # 3. geometric verification
    t0 = time.perf_counter()

    h_threshold_px = float(np.sqrt(5.99 / 3.84)) * threshold_px  # H&Z table 4.1: codimension 2 vs 1

    def verify(K):
        graph, edges, rel = [], [], {}
        Kj = jnp.asarray(K)
        for p, (i, j) in enumerate(pairs):
            a = np.nonzero(M[p] >= 0)[0]
            b = M[p][a]
            e = dict(i=int(i), j=int(j), matches=int(len(a)), inliers=0, flag="few_matches")
            if len(a) >= min_inliers:
                # padded to a power-of-two bucket of the pair's matches (from 256), not to the
                # keypoint capacity: the RANSAC's cost grows with the padded length (600 matches:
                # 0.09 s padded to 1,024, 0.63 s to 4,096), for one compile per bucket
                m_pad = min(n_kp, _bucket(len(a), 256))
                res = relative_pose(jax.random.fold_in(key, p), jnp.asarray(_pad(uv_all[i][a], m_pad)),
                                    jnp.asarray(_pad(uv_all[j][b], m_pad)), Kj, threshold_px=threshold_px,
                                    n_hypotheses=n_hypotheses)
                inl = np.asarray(res.inliers)[:len(a)]
                e["inliers"] = int(inl.sum())
                # the homography beside E: a plane or a pure rotation maps every correspondence by one
                # H, so H explains (nearly) all of E's inliers (rule in the module notes)
                hres = homography_ransac(jax.random.fold_in(key, 100_000 + p), jnp.asarray(_pad(uv_all[i][a], m_pad)),
                                         jnp.asarray(_pad(uv_all[j][b], m_pad)), threshold_px=h_threshold_px,
                                         n_hypotheses=max(64, n_hypotheses // 2))
                hin = np.asarray(hres.inliers)[:len(a)]
                e["h_inliers"] = int(hin.sum())
                h_explains = e["h_inliers"] >= min_inliers and e["h_inliers"] >= h_ratio * max(e["inliers"], 1)
                if h_explains:  # parallax of the H inliers (E's inliers of a degenerate E admit outliers)
                    e["parallax_px"] = _parallax_px(uv_all[i][a], uv_all[j][b], hin, K, m_pad)
                if e["inliers"] < min_inliers and not h_explains:
                    e["flag"] = "few_inliers"
                elif bool(res.degenerate) or (h_explains and e["parallax_px"] < min_parallax_px):
                    e["flag"] = "pure_rotation"
                    inl = hin if h_explains else inl
                elif h_explains:
                    # a plane seen with parallax: the 8-point essential matrix of a plane is not unique,
                    # so the pose comes from the homography (two physical solutions: module notes) and
                    # the H inliers feed the tracks
                    e["flag"] = "planar"
                    inl = hin
                    Rr, tr, X1, e["front"] = _planar_pose(np.asarray(hres.H), uv_all[i][a][hin], uv_all[j][b][hin], K)
                    e["median_angle_deg"] = float(np.median(_angle_deg(X1, np.zeros(3), -Rr.T @ tr))) if len(X1) else 0.0
                    e["pose"] = "homography"
                    rel[(int(i), int(j))] = (Rr, tr)
                elif bool(res.converged):
                    e["flag"] = "ok"
                    X1 = np.asarray(res.points)[:len(a)][inl]
                    Rr, tr = np.asarray(res.R), np.asarray(res.t)
                    X1 = X1[np.all(np.isfinite(X1), 1)]
                    e["median_angle_deg"] = float(np.median(_angle_deg(X1, np.zeros(3), -Rr.T @ tr))) if len(X1) else 0.0
                    e["pose"] = "essential"
                    rel[(int(i), int(j))] = (Rr, tr)
                else:
                    e["flag"] = "no_pose"
                if e["flag"] in ("ok", "planar", "pure_rotation"):
                    edges.append((int(i), int(j), a[inl], b[inl]))
            graph.append(e)
        return graph, edges, rel

    graph, edges, rel = verify(K)
    if focal_info is not None:
        ok = [(uv_all[i][a], uv_all[j][b]) for (i, j, a, b), e in
              zip(edges, [e for e in graph if e["flag"] in ("ok", "planar", "pure_rotation")]) if e["flag"] == "ok"]
        if ok:
            est = estimate_focal(ok, (w, h), principal_point=(K[0, 2], K[1, 2]))
            focal_info.update(est)
            if not est["at_bound"]:
                f = est["focal_px"]
                K = np.array([[f, 0, K[0, 2]], [0, f, K[1, 2]], [0, 0, 1.0]])
                say(f"focal length: {f:.1f} px (guess {focal_info['guess_px']:.1f}); verification repeated")
                graph, edges, rel = verify(K)
            else:
                focal_info["note"] = "self-calibration minimum at the search bound: guess kept"
        else:
            focal_info["note"] = "no verified pair: guess kept"
    Kj = jnp.asarray(K)
    times["verification"] = time.perf_counter() - t0
    say(f"verification: {sum(e['flag'] == 'ok' for e in graph)} of {len(pairs)} pairs verified")

    # 4. tracks
    t0 = time.perf_counter()
    uf = _UF(n * n_kp)
    for i, j, a, b in edges:
        for x, y in zip(i * n_kp + a, j * n_kp + b):
            uf.union(int(x), int(y))
    nodes = np.unique(np.concatenate([np.concatenate([i * n_kp + a, j * n_kp + b]) for i, j, a, b in edges])) \
        if edges else np.zeros(0, np.int64)
    roots = np.array([uf.find(int(x)) for x in nodes], np.int64)
    _, tid = np.unique(roots, return_inverse=True)
    obs_img, obs_kp = nodes // n_kp, nodes % n_kp
    T = int(tid.max()) + 1 if len(tid) else 0
    # drop tracks with two keypoints in one image
    dup = np.zeros(T, bool)
    key2 = tid * n + obs_img
    u, c = np.unique(key2, return_counts=True)
    dup[u[c > 1] // n] = True
    keep = ~dup[tid]
    _, tid = np.unique(tid[keep], return_inverse=True)
    obs_img, obs_kp = obs_img[keep], obs_kp[keep]
    T = int(tid.max()) + 1 if len(tid) else 0
    obs_uv = uv_all[obs_img, obs_kp]
    O = len(tid)  # noqa: E741
    times["tracks"] = time.perf_counter() - t0
    say(f"tracks: {T} tracks, {O} observations ({int(dup.sum())} inconsistent tracks dropped)")

    # 5. incremental reconstruction
    t0 = time.perf_counter()
    reasons: dict[int, str] = {}
    R = np.full((n, 3, 3), np.nan)
    t = np.full((n, 3), np.nan)
    reg = np.zeros(n, bool)
    X = np.zeros((max(T, 1), 3))
    has_pt = np.zeros(max(T, 1), bool)
    obs_ok = np.zeros(O, bool)
    order: list[int] = []
    # initial pair: general pairs first; a planar pair's pose only when no general pair has the angle
    cand = [e for e in graph if e.get("pose")]
    good = [e for e in cand if e["flag"] == "ok" and e["median_angle_deg"] >= init_angle_deg] or \
        [e for e in cand if e["median_angle_deg"] >= init_angle_deg]
    if not cand:
        for i in range(n):
            reasons[i] = "no verified pair with parallax (view graph has no usable edge)"
        return _finish(names, K, (w, h), reg, R, t, uv_all, valid, X, has_pt, obs_ok, tid, obs_img, obs_kp, imgs,
                       reasons, graph, times, np.nan, order, t0, focal_info)
    e0 = max(good or cand, key=lambda e: (e["inliers"] if good else e.get("median_angle_deg", 0)))
    a0, b0 = e0["i"], e0["j"]
    R[a0], t[a0] = np.eye(3), np.zeros(3)
    R[b0], t[b0] = rel[(a0, b0)]
    reg[a0] = reg[b0] = True
    order += [a0, b0]
    say(f"initial pair {names[a0]}-{names[b0]}: {e0['inliers']} inliers, "
        f"median angle {e0.get('median_angle_deg', 0):.1f} deg")
    fixed_t = int(np.argmax(np.abs(t[b0])))
    Kinv = np.linalg.inv(K)

    def project(Xp, i_obs):
        xc = np.einsum("kij,kj->ki", R[obs_img[i_obs]], Xp) + t[obs_img[i_obs]]
        z = xc[:, 2]
        uvp = (xc[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None]) * K[[0, 1], [0, 1]] + K[:2, 2]
        return uvp, z

    def triangulate():
        """New points for tracks without one that have >= 2 registered views."""
        sel = reg[obs_img] & ~has_pt[tid]
        cnt = np.bincount(tid[sel], minlength=T)
        ok_t = cnt >= 2
        sel = sel & ok_t[tid]
        if not sel.any():
            return 0
        k = np.nonzero(sel)[0]
        xn = (np.c_[obs_uv[k], np.ones(len(k))] @ Kinv.T)[:, :2]
        P = np.concatenate([R[obs_img[k]], t[obs_img[k]][:, :, None]], 2)  # (k, 3, 4)
        rows = np.stack([xn[:, :1] * P[:, 2] - P[:, 0], xn[:, 1:] * P[:, 2] - P[:, 1]], 1)  # (k, 2, 4)
        A = np.zeros((T, 4, 4))
        np.add.at(A, tid[k], np.einsum("kri,krj->kij", rows, rows))
        tt = np.nonzero(ok_t)[0]
        _, V = np.linalg.eigh(A[tt])
        Xh = V[:, :, 0]
        Xn = Xh[:, :3] / np.where(np.abs(Xh[:, 3:]) > 1e-12, Xh[:, 3:], np.nan)
        Xt = np.full((T, 3), np.nan)
        Xt[tt] = Xn
        uvp, z = project(Xt[tid[k]], k)
        err = np.linalg.norm(uvp - obs_uv[k], axis=1)
        okk = (z > 0) & (err < max_reproj_px) & np.isfinite(err)
        good_cnt = np.bincount(tid[k][okk], minlength=T)
        C = -np.einsum("kji,kj->ki", R[obs_img[k]], t[obs_img[k]])
        # largest ray angle: angle of each ray to the track's first good ray
        ang = np.zeros(T)
        first = np.full(T, -1)
        for kk in np.nonzero(okk)[0][::-1]:
            first[tid[k][kk]] = kk
        ref_c = C[np.maximum(first[tid[k]], 0)]
        ai = _angle_deg(Xt[tid[k]], C, ref_c)
        np.maximum.at(ang, tid[k][okk], np.where(np.isfinite(ai[okk]), ai[okk], 0))
        newp = (good_cnt >= 2) & (ang >= min_tri_angle_deg) & ok_t & np.all(np.isfinite(Xt), 1)
        X[newp] = Xt[newp]
        has_pt[newp] = True
        obs_ok[k[okk & newp[tid[k]]]] = True
        return int(newp.sum())

    def refresh():
        """Observations of registered images on existing points: keep those reprojecting within the threshold."""
        k = np.nonzero(reg[obs_img] & has_pt[tid])[0]
        uvp, z = project(X[tid[k]], k)
        err = np.linalg.norm(uvp - obs_uv[k], axis=1)
        obs_ok[:] = False
        obs_ok[k] = (z > 0) & (err < max_reproj_px)
        cnt = np.bincount(tid[obs_ok], minlength=T)
        has_pt[:T] &= cnt >= 2
        obs_ok[:] &= has_pt[tid]

    # each bundle adjustment gets the problem it solves, compacted (its points renumbered, its
    # observations and observation pairs gathered) and padded to power-of-two buckets: one compile
    # per bucket, and an iteration costs what the problem holds, not the whole run's capacity
    nc = _bucket(n, 8, linear=True)
    # LM stops when an accepted step lowers the cost by less than 1e-6 of it (Ceres' default
    # function tolerance; 1e-8 is below float32's resolution, so the final BAs ran 50 + 32 iterations
    # on herzjesu-P8 instead of 9 + 3 for the same cameras within 0.0004 deg and 0.01 mm)
    ba_tol = 1e-6
    ba_time = [0.0]
    ba_log: list[dict] = []

    def ba(iters, local=None):
        """Bundle adjustment of every registered camera and point (``local=None``) or of the cameras
        ``local`` and the points they see (observations of those points in other cameras count,
        those cameras stay fixed)."""
        tb = time.perf_counter()
        if local is None:
            cams = reg.copy()
            k = np.nonzero(obs_ok)[0]
        else:
            cams = np.zeros(n, bool)
            cams[local] = True
            cams &= reg
            pts = np.zeros(T, bool)
            pts[tid[obs_ok & cams[obs_img]]] = True
            k = np.nonzero(obs_ok & pts[tid])[0]
        up, pk = np.unique(tid[k], return_inverse=True)
        o_, m_ = len(k), len(up)
        prs = observation_pairs(pk)
        # one bucket level for the three capacities (observations oc, points oc / 2, pairs 1.5 oc), so
        # a run compiles one program per level (fountain-P11: 4) rather than per combination (6)
        oc = _bucket(max(o_, 2 * m_, -(-2 * len(prs) // 3)), 1024)
        mc, pc = oc // 2, 3 * oc // 2
        free = np.zeros((nc, 6))
        free[:n][cams] = 1
        free[a0] = 0
        free[b0, 3 + fixed_t] = 0
        Rp = np.tile(np.eye(3), (nc, 1, 1))
        Rp[:n][reg] = R[reg]
        tp = np.zeros((nc, 3))
        tp[:n][reg] = t[reg]
        out = bundle_adjust_masked(Kj, jnp.asarray(Rp), jnp.asarray(tp), jnp.asarray(_pad(X[up], mc, 0.0)),
                                   jnp.asarray(np.pad(obs_img[k], (0, oc - o_)), jnp.int32),
                                   jnp.asarray(np.pad(pk, (0, oc - o_)), jnp.int32),
                                   jnp.asarray(_pad(obs_uv[k], oc, 0.0)), jnp.asarray(np.arange(oc) < o_),
                                   jnp.asarray(free), jnp.asarray(np.arange(mc) < m_),
                                   obs_pairs=jnp.asarray(np.concatenate([prs, np.full((pc - len(prs), 2), -1, np.int32)])),
                                   max_iter=iters, tol=ba_tol)
        Rn, tn, Xn, rms, it = jax.block_until_ready(out)
        R[cams], t[cams] = np.asarray(Rn)[:n][cams], np.asarray(tn)[:n][cams]
        X[up] = np.asarray(Xn)[:m_]
        refresh()
        ba_time[0] += time.perf_counter() - tb
        ba_log.append(dict(kind="global" if local is None else "local", cameras=int(cams.sum()), points=m_,
                           observations=o_, pairs=len(prs), bucket=(mc, oc, pc),
                           iterations=int(it)))
        return float(rms)

    triangulate()
    rms = ba(30)
    say(f"initial: {int(has_pt.sum())} points, rms {rms:.3f} px")
    last_global = [int(reg.sum()), int(has_pt.sum())]  # model size at the last global BA
    tried: dict[int, int] = {}
    pkey = jax.random.fold_in(key, 10_000)
    while not reg.all():
        seen = np.bincount(obs_img[obs_ok | (has_pt[tid] & ~reg[obs_img])], minlength=n)
        seen[reg] = -1
        for i, c in tried.items():
            if seen[i] < 1.2 * c + 10:  # retry a failed image only when it sees clearly more points
                seen[i] = -1
        nxt = int(np.argmax(seen))
        if seen[nxt] < 0:
            break
        k = np.nonzero((obs_img == nxt) & has_pt[tid])[0]
        if len(k) < 12:
            tried[nxt] = len(k)
            reasons[nxt] = f"sees only {len(k)} triangulated points (PnP needs >= 12)"
            continue
        # padded to a power-of-two bucket of the correspondences (from 256) rather than the keypoint
        # capacity, as in verification: 1,500 correspondences took 0.69 s padded to 2,048 and 1.36 s
        # padded to 2,304 (load 15)
        k_pad = min(n_kp, _bucket(len(k), 256))
        res = solve_pnp_ransac(jax.random.fold_in(pkey, nxt * 100 + len(tried)), jnp.asarray(_pad(X[tid[k]], k_pad)),
                               jnp.asarray(_pad(obs_uv[k], k_pad)), Kj, threshold_px=max_reproj_px,
                               n_hypotheses=n_hypotheses)
        n_in = int(res.n_inliers)
        pose = int(res.reason) in (reason_code("ok"), reason_code("max_iterations"))
        if not pose or n_in < max(12, 0.2 * len(k)):
            tried[nxt] = len(k)
            reasons[nxt] = (f"PnP failed: {n_in} inliers of {len(k)} 2D-3D correspondences "
                            f"({res.message if not pose else 'too few inliers'})")
            continue
        reasons.pop(nxt, None)
        tried.pop(nxt, None)
        R[nxt], t[nxt] = np.asarray(res.R), np.asarray(res.t)
        reg[nxt] = True
        order.append(nxt)
        refresh()
        nnew = triangulate()
        # a global BA when the model grew by ``global_ba_growth`` (registered views or points) since
        # the last global one (COLMAP's rule); otherwise a local BA of the new view and its most
        # covisible registered views (COLMAP runs the local one every time; here it is skipped when
        # the global one follows, whose problem contains it)
        if reg.sum() >= global_ba_growth * last_global[0] or has_pt.sum() >= global_ba_growth * last_global[1]:
            rms = ba(10)
            last_global[:] = [int(reg.sum()), int(has_pt.sum())]
        else:
            seen_new = np.zeros(T, bool)
            seen_new[tid[obs_ok & (obs_img == nxt)]] = True
            covis = np.bincount(obs_img[obs_ok & seen_new[tid]], minlength=n)
            covis[nxt] = -1
            covis[~reg] = -1
            rms = ba(10, [nxt] + [int(c) for c in np.argsort(-covis, kind="stable")[:local_ba_views - 1] if covis[c] > 0])
        nnew += triangulate()
        say(f"registered {names[nxt]} ({int(reg.sum())}/{n}): {n_in}/{len(k)} PnP inliers, {nnew} new points, "
            f"{int(has_pt.sum())} points, rms {rms:.3f} px")
    triangulate()
    rms = ba(50)
    rms = ba(50)
    for i in np.nonzero(~reg)[0]:
        mine = [e for e in graph if int(i) in (e["i"], e["j"])]
        if not any(e["flag"] in ("ok", "planar", "pure_rotation") for e in mine):
            # no edge at all: say so, with its best pair (an unrelated photograph)
            b = max(mine, key=lambda e: (max(e["inliers"], e.get("h_inliers", 0)), e["matches"]))
            other = names[b["j"] if b["i"] == i else b["i"]]
            reasons[int(i)] = (f"no verified pair with any image (best: {other}, {b['matches']} matches, "
                               f"{max(b['inliers'], b.get('h_inliers', 0))} inliers; an edge needs >= {min_inliers})")
        reasons.setdefault(int(i), "never reached: no verified pair links it to the registered images")
    times["reconstruction"] = time.perf_counter() - t0
    times["bundle_adjustment"] = ba_time[0]
    say(f"done: {int(reg.sum())}/{n} registered, {int(has_pt.sum())} points, rms {rms:.3f} px")
    out = _finish(names, K, (w, h), reg, R, t, uv_all, valid, X, has_pt, obs_ok, tid, obs_img, obs_kp, imgs,
                  reasons, graph, times, rms, order, None, focal_info)
    out.ba_calls = ba_log
    return out


def _finish(names, K, size, reg, R, t, uv_all, valid, X, has_pt, obs_ok, tid, obs_img, obs_kp, imgs, reasons, graph,
            times, rms, order, t0, focal=None):
    if t0 is not None:
        times["reconstruction"] = time.perf_counter() - t0
    n = len(names)
    # keypoint indices per image restricted to valid ones (valid keypoints come first: top-k order)
    kps = [uv_all[i][valid[i]] for i in range(n)]
    T = int(tid.max()) + 1 if len(tid) else 0
    pts_ids = np.nonzero(has_pt[:T])[0]
    remap = -np.ones(max(T, 1), np.int64)
    remap[pts_ids] = np.arange(len(pts_ids))
    point_obs: list[list[tuple[int, int]]] = [[] for _ in pts_ids]
    colors = np.zeros((len(pts_ids), 3), np.uint8)
    got = np.zeros(len(pts_ids), bool)
    for k in np.nonzero(obs_ok)[0]:
        p = remap[tid[k]]
        if p < 0:
            continue
        i, j = int(obs_img[k]), int(obs_kp[k])
        point_obs[p].append((i, j))
        if not got[p]:
            im = imgs[i]
            u, v = np.round(uv_all[i, j]).astype(int)
            px = im[min(max(v, 0), im.shape[0] - 1), min(max(u, 0), im.shape[1] - 1)]
            px = np.asarray(px)
            if im.dtype != np.uint8:
                px = np.clip(px * 255 + 0.5, 0, 255)
            colors[p] = px if px.ndim else np.array([px] * 3)
            got[p] = True
    R = np.where(reg[:, None, None], R, np.nan)
    t = np.where(reg[:, None], t, np.nan)
    return Reconstruction(names=list(names), K=K, size=size, registered=reg.copy(), R=R, t=t, keypoints=kps,
                          points=X[pts_ids].copy(), colors=colors, point_obs=point_obs, reasons=dict(reasons),
                          view_graph=graph, times_s=dict(times), rms_px=float(rms), registration_order=list(order), focal=focal)


def align_to_ground_truth(centres_est, R_cw_est, centres_gt, R_wc_gt, *, rotation_from: str = "centres"):
    """Similarity from the estimated to the ground-truth frame; returns ``(rotation_errors_deg,
    centre_errors (gt units))`` per camera after alignment.

    ``rotation_from="centres"``: Umeyama (1991) on the camera centres alone (the usual SfM
    evaluation; ill-conditioned when the centres are nearly collinear, e.g. three views on an
    arc). ``"rotations"``: the aligning rotation is the chordal mean of ``R_gt R_est^T`` over the
    cameras, then scale and translation by least squares on the centres.
    """
    A, B = np.asarray(centres_est, float), np.asarray(centres_gt, float)
    ma, mb = A.mean(0), B.mean(0)
    Ac, Bc = A - ma, B - mb
    if rotation_from == "centres":
        U, S, Vt = np.linalg.svd(Bc.T @ Ac / len(A))
        D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
        Rs = U @ D @ Vt
        s = np.trace(np.diag(S) @ D) / (np.sum(Ac * Ac) / len(A))
    elif rotation_from == "rotations":
        Msum = sum(np.asarray(Rg) @ np.asarray(Rcw) for Rcw, Rg in zip(R_cw_est, R_wc_gt))
        U, _, Vt = np.linalg.svd(Msum)
        Rs = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        RA = Ac @ Rs.T
        s = np.sum(RA * Bc) / np.sum(RA * RA)
    else:
        raise ValueError(f"align_to_ground_truth: argument 'rotation_from' must be 'centres' or 'rotations', "
                         f"got {rotation_from!r}")
    C = s * A @ Rs.T + (mb - s * Rs @ ma)
    cerr = np.linalg.norm(C - B, axis=1)
    rerr = []
    for Rcw, Rg in zip(R_cw_est, R_wc_gt):
        M = np.asarray(Rg, float).T @ (Rs @ np.asarray(Rcw, float).T)
        # angle by atan2(sin, cos): arccos of (trace - 1) / 2 loses small angles (float32 poses: ~0.03 deg)
        sin = 0.5 * np.linalg.norm([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
        rerr.append(np.degrees(np.arctan2(sin, (np.trace(M) - 1) / 2)))
    return np.asarray(rerr), cerr
