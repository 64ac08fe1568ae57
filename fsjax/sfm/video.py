"""Structure from motion on a video: frames chosen by the camera's rotation, then :func:`reconstruct`.

``fsjax sfm VIDEO.mp4`` (:func:`run_video`):

1. **Read** the frames with PyAV (the ``av`` package, FFmpeg's libraries; an optional extra:
   ``pip install 'fsjax[video]'``). The video is decoded twice, so memory does not grow with its
   length: the first pass keeps a grey copy downsampled to ``max_side`` pixels, the second only the
   chosen frames at full size.
2. **Rotation between consecutive frames** (:func:`consecutive_rotations`): DoG + RootSIFT
   features (:func:`fsjax.sfm.detect_and_describe_batch`, frames in fixed-size chunks, one compile),
   mutual-NN + ratio matches of frame ``k`` with ``k + 1``, and the relative rotation from
   :func:`fsjax.fit.twoview.relative_pose` (8-point essential-matrix RANSAC; for a pair without
   parallax the rotation of the bearing alignment). The intrinsics are scaled to the small frames
   (``f s``, ``(c + 0.5) s - 0.5``). A pair with fewer than ``min_matches`` matches or inliers, or
   no pose, has an *unknown* step (reported, never replaced by a guess).
3. **Selection** (:func:`select_video_frames`): the steps are chained into orientations
   (``world_from_camera_k = world_from_camera_{k-1} R_{k-1,k}^T``, quaternions) and thinned by
   :func:`fsjax.fit.select_frames_by_rotation`: a frame is kept when the rotation accumulated since
   the last kept one (path length, the sum of the step angles) reaches ``threshold_deg``, or when
   ``max_gap`` frames have passed. Its identical-quaternion guard applies to the whole stream with a
   tolerance fit for *estimated* rotations (``identical_tol_deg``, default 0.25 deg, above the
   estimation noise): a video whose camera never turns by more than that, such as a still camera
   or a frozen stream, is refused, not thinned by a meaningless rule. An unknown step splits the
   stream: the frame after it is kept (the reason says why) and selection restarts there.
4. **Reconstruction** of the chosen frames at full size (:func:`fsjax.sfm.reconstruct`), the
   outputs of :func:`fsjax.sfm.run.run_folder`, and a ``report.md`` section listing every chosen
   frame with its time, the rotation accumulated since the previous chosen frame and why it was
   chosen.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_positive, check_static_int
from ..fit.frames import select_frames_by_rotation
from ..fit.twoview import normalized_points, relative_pose, rotation_parallax
from ..types.results import reason_code, reason_message
from .export import quat_from_matrix
from .features import detect_and_describe_batch
from .matching import match_pairs
from .reconstruct import _pad, grey_image

__all__ = ["VIDEO_SUFFIXES", "read_video", "write_video", "video_info", "consecutive_rotations",
           "FrameRotations", "VideoSelection", "select_video_frames", "run_video", "is_video"]

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".mkv", ".avi", ".webm", ".mpg", ".mpeg", ".ts")
_WHY = {0: "first frame", 1: "rotation threshold", 2: "maximum gap", 3: "previous step unknown"}


def is_video(path) -> bool:
    """``path`` is an existing file with a video suffix (:data:`VIDEO_SUFFIXES`)."""
    p = Path(path)
    return p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES


def _av(fn: str):
    try:
        import av
    except ImportError as e:  # optional extra
        raise ImportError(f"{fn}: reading or writing video needs the package 'av' (PyAV, FFmpeg's libraries), "
                          "which is not installed; install it with `pip install av` or "
                          "`pip install 'fsjax[video]'`") from e
    return av


def _open(path, fn: str):
    av = _av(fn)
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{fn}: argument 'path' is not a file: {p}")
    try:
        c = av.open(str(p))
    except Exception as e:  # FFmpeg's errors (not a video, unsupported codec) as one clear message
        raise ValueError(f"{fn}: argument 'path' could not be opened as a video ({type(e).__name__}: {e}): {p}") from e
    if not c.streams.video:
        c.close()
        raise ValueError(f"{fn}: argument 'path' holds no video stream: {p}")
    return c


def _frames(path, fn: str):
    """Yield every decoded frame of the first video stream as (H, W, 3) uint8 RGB."""
    c = _open(path, fn)
    try:
        for fr in c.decode(video=0):
            yield fr.to_ndarray(format="rgb24")
    finally:
        c.close()


def video_info(path) -> dict:
    """``{"fps": float, "width": int, "height": int}`` of the first video stream (from its header)."""
    c = _open(path, "video_info")
    try:
        s = c.streams.video[0]
        rate = s.average_rate or s.guessed_rate
        return {"fps": float(rate) if rate else float("nan"), "width": int(s.width), "height": int(s.height)}
    finally:
        c.close()


def read_video(path, *, indices=None) -> np.ndarray:
    """Decode the frames of a video: ``(N, H, W, 3)`` uint8 RGB (all, or only the frame ``indices``).

    Example:
        >>> from fsjax.sfm.video import read_video, write_video
        >>> import tempfile, os
        >>> frames = np.zeros((3, 16, 16, 3), np.uint8); frames[1] += 128; frames[2] += 255
        >>> p = os.path.join(tempfile.mkdtemp(), "v.mp4")
        >>> _ = write_video(p, frames, fps=5)
        >>> v = read_video(p)
        >>> v.shape, [int(round(float(f.mean()) / 8)) * 8 for f in v]
        ((3, 16, 16, 3), [0, 128, 256])
    """
    want = None if indices is None else {int(i) for i in indices}
    out = [f for k, f in enumerate(_frames(path, "read_video")) if want is None or k in want]
    if not out:
        raise ValueError(f"read_video: no frame decoded from {path}" + ("" if want is None else f" at indices {sorted(want)[:10]}"))
    return np.stack(out)


def write_video(path, frames, *, fps: float = 10.0, qp: int = 12) -> Path:
    """Write ``(N, H, W, 3)`` uint8 RGB frames (even ``H`` and ``W``) as H.264 (``libx264``, yuv420p,
    constant quantiser ``qp``: 0 lossless, 12 visually lossless; one encoder thread).

    Constant quantiser and one thread make the file a function of the frames: with x264's default
    rate control (``crf``) the same frames gave different files from run to run in a process that
    had run JAX computations (seen here; not investigated further)."""
    av = _av("write_video")
    f = np.asarray(frames)
    if f.ndim != 4 or f.shape[-1] != 3 or f.dtype != np.uint8:
        raise ValueError(f"write_video: argument 'frames' must be (N, H, W, 3) uint8, got {f.shape} {f.dtype}")
    if f.shape[1] % 2 or f.shape[2] % 2:
        raise ValueError(f"write_video: argument 'frames' must have even height and width (yuv420p), got {f.shape[1:3]}")
    check_positive("write_video", "fps", fps)
    if isinstance(qp, bool) or int(qp) != qp or not 0 <= int(qp) <= 51:
        raise ValueError(f"write_video: argument 'qp' must be an int in [0, 51] (H.264 quantiser), got {qp!r}")
    from fractions import Fraction

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    c = av.open(str(p), mode="w")
    try:
        s = c.add_stream("libx264", rate=Fraction(fps).limit_denominator(1000))
        s.width, s.height, s.pix_fmt = f.shape[2], f.shape[1], "yuv420p"
        s.options = {"qp": str(int(qp)), "threads": "1"}
        s.thread_count = 1
        for im in f:
            for pkt in s.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(im), format="rgb24")):
                c.mux(pkt)
        for pkt in s.encode():
            c.mux(pkt)
    finally:
        c.close()
    return p


def _small(rgb: np.ndarray, max_side: int) -> np.ndarray:
    g = grey_image(rgb)
    h, w = g.shape
    s = min(1.0, max_side / max(h, w))
    if s == 1.0:
        return g
    from PIL import Image

    return np.asarray(Image.fromarray(g, mode="F").resize((round(w * s), round(h * s)), Image.BOX), np.float32)


def _scale_K(K, size_from, size_to) -> np.ndarray:
    """Intrinsics of an image resized from (w, h) to (w', h') (pixel centres on integers)."""
    sx, sy = size_to[0] / size_from[0], size_to[1] / size_from[1]
    K = np.asarray(K, float)
    return np.array([[K[0, 0] * sx, 0, (K[0, 2] + 0.5) * sx - 0.5], [0, K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5],
                     [0, 0, 1.0]])


def _guess_K(w, h) -> np.ndarray:
    f = 1.2 * max(w, h)
    return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])


@dataclass
class FrameRotations:
    """Rotations between consecutive frames (:func:`consecutive_rotations`); ``N`` frames, ``N - 1`` steps.

    ``R`` ``(N - 1, 3, 3)``: ``camera_{k+1}_from_camera_k`` (NaN where unknown); ``known`` ``(N - 1,)``;
    ``matches`` and ``inliers`` ``(N - 1,)`` counts; ``flag`` per step: ``ok``, ``pure_rotation``
    (no parallax: the rotation of the bearing alignment), ``few_matches``, ``few_inliers`` or the
    two-view fit's reason; ``K`` the intrinsics used at the ``size`` (w, h) of the small frames."""

    R: np.ndarray
    known: np.ndarray
    matches: np.ndarray
    inliers: np.ndarray
    flag: list[str]
    K: np.ndarray
    size: tuple[int, int]
    times_s: dict[str, float] = field(default_factory=dict)

    @property
    def step_deg(self) -> np.ndarray:
        """(N - 1,) rotation angle of each step (degrees; NaN where unknown)."""
        c = (np.trace(self.R, axis1=1, axis2=2) - 1) / 2
        return np.degrees(np.arccos(np.clip(c, -1, 1)))


def consecutive_rotations(frames, K=None, *, n_max: int = 512, n_octaves: int = 4, chunk: int = 8,
                          min_matches: int = 20, threshold_px: float = 1.0, n_hypotheses: int = 256,
                          min_parallax_px: float = 0.3, max_fallback_px: float = 2.0, upsample: bool = True,
                          seed: int = 0, log=None) -> FrameRotations:
    """Relative rotation of every pair of consecutive grey frames (module notes, step 2).

    Args:
      frames: sequence of ``(H, W)`` grey frames in [0, 1] (or RGB), all one size, ``N >= 2``.
      K: ``(3, 3)`` intrinsics of these frames; ``None`` guesses ``f = 1.2 max(W, H)``.
      n_max, n_octaves: detector capacity and octaves. chunk: frames per detector call (static).
      min_matches: fewest matches and inliers of a known step. threshold_px, n_hypotheses: RANSAC.
      seed: RANSAC key. log: optional callable(str) for progress lines.

    Returns:
      :class:`FrameRotations`.
    """
    fn = "consecutive_rotations"
    say = log or (lambda s: None)
    n_max = check_static_int(fn, "n_max", n_max, lo=8)
    chunk = check_static_int(fn, "chunk", chunk, lo=1)
    min_matches = check_static_int(fn, "min_matches", min_matches, lo=8)
    g = [grey_image(f) for f in frames]
    if len(g) < 2:
        raise ValueError(f"{fn}: argument 'frames' must hold >= 2 frames, got {len(g)}")
    shapes = {x.shape for x in g}
    if len(shapes) != 1:
        raise ValueError(f"{fn}: argument 'frames' must be of one size, got sizes {sorted(shapes)}")
    h, w = g[0].shape
    K = _guess_K(w, h) if K is None else np.asarray(K, float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"{fn}: argument 'K' must be a finite (3, 3) intrinsics matrix, got {K}")
    n = len(g)
    t0 = time.perf_counter()
    uv, desc, valid = [], [], []
    for s in range(0, n, chunk):
        block = np.stack(g[s:s + chunk] + [g[-1]] * max(0, s + chunk - n))  # the last chunk padded: one compile
        f = detect_and_describe_batch(jnp.asarray(block), n_max=n_max, n_octaves=n_octaves, upsample=upsample)
        k = min(chunk, n - s)
        uv.append(np.asarray(f.uv, np.float64)[:k])
        desc.append(np.asarray(f.descriptors)[:k])
        valid.append(np.asarray(f.valid)[:k])
        say(f"video features: frames {s + 1}-{s + k} of {n}")
    uv, desc, valid = np.concatenate(uv), np.concatenate(desc), np.concatenate(valid)
    t1 = time.perf_counter()
    pairs = np.stack([np.arange(n - 1), np.arange(1, n)], 1).astype(np.int32)
    M = np.asarray(match_pairs(jnp.asarray(desc), jnp.asarray(valid), pairs))
    t2 = time.perf_counter()
    R = np.full((n - 1, 3, 3), np.nan)
    matches, inliers, flags = np.zeros(n - 1, int), np.zeros(n - 1, int), []
    key, Kj = jax.random.PRNGKey(seed), jnp.asarray(K)
    ok, pure, chei = reason_code("ok"), reason_code("pure_rotation"), reason_code("cheirality")
    for k in range(n - 1):
        a = np.nonzero(M[k] >= 0)[0]
        matches[k] = len(a)
        if len(a) < min_matches:
            flags.append("few_matches")
            continue
        res = relative_pose(jax.random.fold_in(key, k), jnp.asarray(_pad(uv[k][a], n_max)),
                            jnp.asarray(_pad(uv[k + 1][M[k][a]], n_max)), Kj, threshold_px=threshold_px,
                            n_hypotheses=n_hypotheses, min_parallax_px=min_parallax_px)
        inliers[k] = int(res.n_inliers)
        code = int(res.reason)
        if inliers[k] < min_matches:
            flags.append("few_inliers")
        elif code in (ok, pure):
            R[k] = np.asarray(res.R, float)
            flags.append("ok" if code == ok else "pure_rotation")
        elif code == chei and float(res.parallax_px) < max_fallback_px:
            # a small baseline whose sign the inliers do not settle: the rotation of the bearing
            # alignment, which explains the inliers to within parallax_px (flagged with it)
            inl = np.asarray(res.inliers)[:len(a)]
            Rb, _ = rotation_parallax(normalized_points(jnp.asarray(uv[k][a][inl]), Kj),
                                      normalized_points(jnp.asarray(uv[k + 1][M[k][a]][inl]), Kj))
            R[k] = np.asarray(Rb, float)
            flags.append(f"rotation_only (cheirality undecided, alignment residual {float(res.parallax_px):.2f} px)")
        else:
            flags.append(str(reason_message(code)))
    t3 = time.perf_counter()
    known = np.all(np.isfinite(R.reshape(n - 1, -1)), 1)
    say(f"video rotations: {int(known.sum())} of {n - 1} steps known, median {int(np.median(inliers))} inliers")
    return FrameRotations(R=R, known=known, matches=matches, inliers=inliers, flag=flags, K=K, size=(w, h),
                          times_s={"features": t1 - t0, "matching": t2 - t1, "rotations": t3 - t2})


@dataclass
class VideoSelection:
    """Frames chosen from a video by accumulated rotation (:func:`select_video_frames`).

    ``indices`` (sorted) of the kept frames; per frame ``quats`` ``(N, 4)`` the chained
    world_from_camera orientation (``w, x, y, z``; restarted at the identity after an unknown
    step), ``step_deg`` ``(N,)`` (0 for frame 0, NaN where unknown), ``why`` ``(N,)`` (0 first
    frame, 1 rotation threshold, 2 maximum gap, 3 the step before it is unknown, -1 not kept),
    ``accumulated_deg`` ``(K,)`` the rotation summed since the previous kept frame (path length;
    0 for the first and for frames after an unknown step), and the :class:`FrameRotations`."""

    indices: np.ndarray
    quats: np.ndarray
    step_deg: np.ndarray
    why: np.ndarray
    accumulated_deg: np.ndarray
    rotations: FrameRotations
    threshold_deg: float
    max_gap: int | None

    def why_text(self, i: int) -> str:
        """Why frame ``i`` was kept, in words."""
        w = int(self.why[i])
        k = int(np.searchsorted(self.indices, i))
        if w == 1:
            return f"rotation since the previous chosen frame {self.accumulated_deg[k]:.2f} deg >= {self.threshold_deg:g} deg"
        if w == 2:
            return f"maximum gap of {self.max_gap} frames reached (rotation {self.accumulated_deg[k]:.2f} deg)"
        if w == 3:
            return f"rotation from frame {i - 1} unknown ({self.rotations.flag[i - 1]}); selection restarts here"
        return _WHY.get(w, "not kept")


def select_video_frames(rotations: FrameRotations, *, threshold_deg: float = 10.0, min_gap: int = 1,
                        max_gap: int | None = 30, identical_tol_deg: float = 0.25) -> VideoSelection:
    """Choose frames by the rotation accumulated between consecutive frames (module notes, step 3).

    Raises:
      ValueError: the camera never turns by more than ``identical_tol_deg`` from frame 0 (a still
        camera or a frozen stream: refused, as :func:`fsjax.fit.select_frames_by_rotation` refuses
        identical quaternions), or no step could be estimated.
    """
    fn = "select_video_frames"
    check_positive(fn, "threshold_deg", threshold_deg)
    R, known = rotations.R, rotations.known
    n = len(R) + 1
    if not known.any():
        raise ValueError(f"{fn}: no rotation between consecutive frames could be estimated "
                         f"(flags: {sorted(set(rotations.flag))}); the frames are too different or too plain")
    # chain: world_from_camera_k = world_from_camera_{k-1} @ (camera_k_from_camera_{k-1})^T
    Rw = np.zeros((n, 3, 3))
    Rw[0] = np.eye(3)
    for k in range(1, n):
        Rw[k] = Rw[k - 1] @ R[k - 1].T if known[k - 1] else np.eye(3)
    q = np.stack([quat_from_matrix(r) for r in Rw])
    step = np.concatenate([[0.0], np.where(known, rotations.step_deg, np.nan)])
    # the identical-quaternion guard on the whole stream (a segment restarted after an unknown step is
    # compared with its own first frame)
    seg_start = np.concatenate([[0], np.flatnonzero(~known) + 1])
    seg_end = np.concatenate([seg_start[1:], [n]])
    from ..fit.frames import quaternion_angle_deg

    turn = max(float(np.max(quaternion_angle_deg(q[a:a + 1], q[a:b]))) for a, b in zip(seg_start, seg_end))
    if turn <= identical_tol_deg:
        raise ValueError(f"{fn}: the camera does not turn: over {n} frames no orientation differs from the first by "
                         f"more than {turn:.3f} deg (identical_tol_deg {identical_tol_deg:g}); a still camera or a "
                         "frozen stream gives no frames to choose by rotation (refusing; extract frames to a folder "
                         "and run `fsjax sfm DIR` instead)")
    keep_why = np.full(n, -1, np.int32)
    for a, b in zip(seg_start, seg_end):
        if b - a == 1:
            keep_why[a] = 0 if a == 0 else 3
            continue
        # the guard ran above on the whole stream; a short still segment is not a stuck stream
        sel = select_frames_by_rotation(q[a:b], threshold_deg=threshold_deg, min_gap=min_gap, max_gap=max_gap,
                                        identical_tol_deg=-1.0)
        w = np.asarray(sel.why_kept).copy()
        if a > 0:
            w[0] = 3
        keep_why[a:b] = w
    idx = np.flatnonzero(keep_why >= 0)
    acc = np.zeros(len(idx))
    for j in range(1, len(idx)):
        if keep_why[idx[j]] != 3:
            acc[j] = float(np.sum(step[idx[j - 1] + 1:idx[j] + 1]))
    return VideoSelection(indices=idx, quats=q, step_deg=step, why=keep_why, accumulated_deg=acc,
                          rotations=rotations, threshold_deg=float(threshold_deg), max_gap=max_gap)


def _selection_section(sel: VideoSelection, info: dict, video, t_read: float) -> list[str]:
    rot = sel.rotations
    n = len(sel.quats)
    fps = info["fps"]
    L = ["## Frames chosen from the video", "",
         f"`{Path(video).name}`: {n} frames of {info['width']} x {info['height']} at {fps:.3g} fps; rotation "
         f"between consecutive frames estimated on grey copies of {rot.size[0]} x {rot.size[1]} "
         f"(features, mutual-NN + ratio matches, 8-point essential RANSAC; pure rotation by bearing alignment). "
         f"Known steps: {int(rot.known.sum())}/{n - 1} (median {int(np.median(rot.inliers))} inliers); "
         f"total rotation (path length) {np.nansum(sel.step_deg):.1f} deg. Chosen: **{len(sel.indices)}** frames, a frame "
         f"kept when the accumulated rotation reaches {sel.threshold_deg:g} deg"
         + (f" or {sel.max_gap} frames have passed." if sel.max_gap else "."), "",
         "| frame | time (s) | rotation since previous chosen (deg) | why |", "|---|---|---|---|"]
    for k, i in enumerate(sel.indices):
        ts = f"{i / fps:.2f}" if np.isfinite(fps) and fps > 0 else ""
        L.append(f"| {i} | {ts} | {sel.accumulated_deg[k]:.2f} | {sel.why_text(int(i))} |")
    bad = [k for k in range(n - 1) if not rot.known[k]]
    if bad:
        L += ["", "Unknown steps: " + ", ".join(f"{k}->{k + 1} ({rot.flag[k]}, {rot.matches[k]} matches)" for k in bad[:50])]
    L += ["", f"Video stages (s): reading {t_read:.2f}, " + ", ".join(f"{k} {v:.2f}" for k, v in rot.times_s.items()), ""]
    return L


def run_video(video, out_dir, *, intrinsics=None, threshold_deg: float = 10.0, max_gap: int | None = 30,
              max_side: int = 320, n_max: int = 4096, n_octaves: int = 5, seed: int = 0, log=print):
    """``fsjax sfm VIDEO``: choose frames by rotation, reconstruct them, write the outputs of
    :func:`fsjax.sfm.run.run_folder` plus the chosen frames (``frames/``) and their table in ``report.md``.

    ``intrinsics``: ``(fx, fy, cx, cy)`` of the full-size frames (pixel centres on integers); ``None``
    guesses ``f = 1.2 max(W, H)``. ``threshold_deg``, ``max_gap``: the selection rule. ``max_side``:
    long side of the grey frames the rotations are estimated on. ``n_max``, ``n_octaves``: detector of
    the reconstruction (full-size frames).

    Returns:
      ``(Reconstruction, VideoSelection)``.
    """
    from PIL import Image

    from .export import write_colmap_text, write_ply_points, write_report
    from .reconstruct import reconstruct

    say = log or (lambda s: None)
    info = video_info(video)
    t0 = time.perf_counter()
    small = [_small(f, max_side) for f in _frames(video, "run_video")]
    t_read = time.perf_counter() - t0
    if len(small) < 2:
        raise ValueError(f"run_video: argument 'video' must hold >= 2 frames, got {len(small)}")
    W, H = info["width"], info["height"]
    K = _guess_K(W, H) if intrinsics is None else np.array(
        [[intrinsics[0], 0, intrinsics[2]], [0, intrinsics[1], intrinsics[3]], [0, 0, 1.0]], float)
    hs, ws = small[0].shape
    say(f"video: {len(small)} frames of {W} x {H}; rotations on {ws} x {hs}")
    rot = consecutive_rotations(small, _scale_K(K, (W, H), (ws, hs)), n_octaves=min(4, _octaves_for(hs, ws)),
                                seed=seed, log=say)
    sel = select_video_frames(rot, threshold_deg=threshold_deg, max_gap=max_gap)
    say(f"video: chose {len(sel.indices)} of {len(small)} frames: {sel.indices.tolist()}")
    if len(sel.indices) < 2:
        raise ValueError(f"run_video: only {len(sel.indices)} frame chosen (the camera turned {np.nansum(sel.step_deg):.1f} deg "
                         f"in all, threshold_deg {threshold_deg:g}); lower the threshold or the maximum gap")
    frames = read_video(video, indices=sel.indices)
    out = Path(out_dir)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    names = [f"frame_{i:06d}.png" for i in sel.indices]
    for nm, im in zip(names, frames):
        Image.fromarray(im).save(out / "frames" / nm)
    rec = reconstruct(list(frames), K if intrinsics is not None else None, names=names, n_max=n_max,
                      n_octaves=n_octaves, seed=seed, log=say)
    rec.times_s = {"video: read + rotations + selection": t_read + sum(rot.times_s.values()), **rec.times_s}
    write_colmap_text(rec, out / "sparse")
    write_ply_points(out / "points.ply", rec.points, rec.colors)
    title = f"fsjax sfm: {Path(video).name}" + ("" if intrinsics is not None else " (intrinsics guessed: f = 1.2 max(W, H))")
    rp = write_report(rec, out, title=title)
    rp.write_text(rp.read_text() + "\n" + "\n".join(_selection_section(sel, info, video, t_read)))
    say(f"wrote {rp}, {out / 'points.ply'}, {out / 'sparse'}, {out / 'frames'}")
    return rec, sel


def _octaves_for(h: int, w: int) -> int:
    """Most detector octaves whose last octave keeps >= 16 px on the short side."""
    k = 2
    while min(h, w) >> (k - 1) >= 16:
        k += 1
    return k
