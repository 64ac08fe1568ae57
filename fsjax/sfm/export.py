"""Files of a reconstruction: COLMAP text model (write and read), PLY of the sparse points, report.md.

COLMAP text format (``cameras.txt``, ``images.txt``, ``points3D.txt``; documented at
colmap.github.io/format.html): one ``PINHOLE`` camera ``fx fy cx cy``; per image the
``camera_from_world`` rotation as a unit quaternion ``qw qx qy qz`` and translation, then its 2-D
points ``x y point3D_id`` (-1 when not triangulated); per point ``x y z r g b error`` and its track
``image_id point2D_idx``. COLMAP puts the *corner* of the top-left pixel at (0, 0) (pixel centres on
half integers); fsjax puts pixel centres on integers, so ``cx``, ``cy`` and every 2-D point gain
0.5 on writing and lose it on reading. Image and point ids are 1-based.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["write_colmap_text", "read_colmap_text", "write_ply_points", "write_report", "load_image_dir",
           "quat_from_matrix", "matrix_from_quat"]


def quat_from_matrix(R) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, float)
    tr = np.trace(R)
    c = np.array([tr, R[0, 0], R[1, 1], R[2, 2]])
    i = int(np.argmax(c))
    if i == 0:
        s = 2 * np.sqrt(1 + tr)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif i == 1:
        s = 2 * np.sqrt(1 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif i == 2:
        s = 2 * np.sqrt(1 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2 * np.sqrt(1 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q = q / np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def matrix_from_quat(q) -> np.ndarray:
    """Rotation matrix of a quaternion ``(w, x, y, z)``; a zero-length quaternion is an error."""
    q = np.asarray(q, float)
    nrm = np.linalg.norm(q)
    if not np.isfinite(nrm) or nrm < 1e-12:
        raise ValueError(f"matrix_from_quat: argument 'q' must be a non-zero finite quaternion, got {q}")
    w, x, y, z = q / nrm
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _point_errors(rec) -> np.ndarray:
    K = rec.K
    err = np.zeros(len(rec.points))
    for p, obs in enumerate(rec.point_obs):
        e = []
        for i, j in obs:
            x = rec.R[i] @ rec.points[p] + rec.t[i]
            uv = K[:2, :2] @ (x[:2] / x[2]) + K[:2, 2]
            e.append(np.linalg.norm(uv - rec.keypoints[i][j]))
        err[p] = float(np.mean(e)) if e else 0.0
    return err


def _f(v) -> str:
    return repr(float(v))


def write_colmap_text(rec, out_dir) -> list[Path]:
    """Write ``cameras.txt``, ``images.txt``, ``points3D.txt`` of a :class:`~fsjax.sfm.Reconstruction`
    (registered images only) into ``out_dir``; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    K = rec.K
    w, h = rec.size
    cams = out / "cameras.txt"
    cams.write_text("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
                    "# Number of cameras: 1\n"
                    f"1 PINHOLE {w} {h} {_f(K[0, 0])} {_f(K[1, 1])} {_f(K[0, 2] + 0.5)} {_f(K[1, 2] + 0.5)}\n")
    p2d = {}  # (image, keypoint) -> point id
    for p, obs in enumerate(rec.point_obs):
        for i, j in obs:
            p2d[(i, j)] = p + 1
    lines = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)", f"# Number of images: {int(rec.registered.sum())}"]
    for i in np.nonzero(rec.registered)[0]:
        q = quat_from_matrix(rec.R[i])
        t = rec.t[i]
        lines.append(" ".join([str(i + 1)] + [repr(float(v)) for v in q] + [repr(float(v)) for v in t] + ["1", rec.names[i]]))
        kp = rec.keypoints[i]
        lines.append(" ".join(f"{_f(u + 0.5)} {_f(v + 0.5)} {p2d.get((int(i), j), -1)}" for j, (u, v) in enumerate(kp)))
    imgs = out / "images.txt"
    imgs.write_text("\n".join(lines) + "\n")
    err = _point_errors(rec)
    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
             f"# Number of points: {len(rec.points)}"]
    for p, (X, c, obs) in enumerate(zip(rec.points, rec.colors, rec.point_obs)):
        track = " ".join(f"{i + 1} {j}" for i, j in obs)
        lines.append(f"{p + 1} {_f(X[0])} {_f(X[1])} {_f(X[2])} {int(c[0])} {int(c[1])} {int(c[2])} {_f(err[p])} {track}")
    pts = out / "points3D.txt"
    pts.write_text("\n".join(lines) + "\n")
    return [cams, imgs, pts]


def _data_lines(path: Path):
    for line in path.read_text().splitlines():
        s = line.strip()
        if s and not s.startswith("#"):
            yield s


def read_colmap_text(model_dir) -> dict:
    """Read a COLMAP text model into plain arrays (fsjax pixel convention: 0.5 subtracted).

    Returns a dict: ``cameras`` {id: dict(model, width, height, K)} (PINHOLE, SIMPLE_PINHOLE,
    SIMPLE_RADIAL and RADIAL read their focal length and centre; distortion is ignored and
    reported as ``params``), ``images`` {id: dict(name, camera_id, R, t, xy (n, 2), point_ids (n,))}
    with ``R``, ``t`` ``camera_from_world``, and ``points`` {id: dict(xyz, rgb, error, track [(image_id, idx)])}.
    """
    d = Path(model_dir)
    for nm in ("cameras.txt", "images.txt", "points3D.txt"):
        if not (d / nm).exists():
            raise FileNotFoundError(f"read_colmap_text: argument 'model_dir' has no {nm} ({d})")
    cams = {}
    for s in _data_lines(d / "cameras.txt"):
        f = s.split()
        cid, model, w, h, prm = int(f[0]), f[1], int(f[2]), int(f[3]), [float(v) for v in f[4:]]
        if model == "PINHOLE":
            fx, fy, cx, cy = prm[:4]
        elif model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            fx = fy = prm[0]
            cx, cy = prm[1:3]
        elif model in ("OPENCV", "FULL_OPENCV"):
            fx, fy, cx, cy = prm[:4]
        else:
            raise ValueError(f"read_colmap_text: camera model {model!r} is not supported")
        K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1.0]])
        cams[cid] = dict(model=model, width=w, height=h, K=K, params=prm)
    images = {}
    # two lines per image; an image without 2-D points has an empty second line
    raw = [ln for ln in (d / "images.txt").read_text().splitlines() if not ln.startswith("#")]
    while raw and not raw[-1].strip():
        raw.pop()
    for k in range(0, len(raw), 2):
        f = raw[k].split()
        q = [float(v) for v in f[1:5]]
        t = np.array([float(v) for v in f[5:8]])
        arr = np.array((raw[k + 1] if k + 1 < len(raw) else "").split(), float).reshape(-1, 3)
        images[int(f[0])] = dict(name=f[9], camera_id=int(f[8]), R=matrix_from_quat(q), t=t, xy=arr[:, :2] - 0.5,
                                 point_ids=arr[:, 2].astype(np.int64))
    points = {}
    for s in _data_lines(d / "points3D.txt"):
        f = s.split()
        tr = [int(v) for v in f[8:]]
        points[int(f[0])] = dict(xyz=np.array([float(v) for v in f[1:4]]), rgb=np.array([int(v) for v in f[4:7]], np.uint8),
                                 error=float(f[7]), track=list(zip(tr[0::2], tr[1::2])))
    return dict(cameras=cams, images=images, points=points)


def write_ply_points(path, points, colors=None) -> Path:
    """Binary little-endian PLY of points ``(P, 3)`` (float32) with optional uint8 colours ``(P, 3)``."""
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    head = ["ply", "format binary_little_endian 1.0", f"element vertex {len(pts)}",
            "property float x", "property float y", "property float z"]
    if colors is not None:
        col = np.asarray(colors, np.uint8).reshape(-1, 3)
        if len(col) != len(pts):
            raise ValueError(f"write_ply_points: argument 'colors' must have one row per point ({len(pts)}), got {len(col)}")
        head += ["property uchar red", "property uchar green", "property uchar blue"]
        rec = np.empty(len(pts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
        rec["r"], rec["g"], rec["b"] = col[:, 0], col[:, 1], col[:, 2]
    else:
        rec = np.empty(len(pts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        fh.write(("\n".join(head + ["end_header"]) + "\n").encode("ascii"))
        fh.write(rec.tobytes())
    return path


def _plot(rec, path) -> Path | None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # matplotlib is optional
        return None
    fig, ax = plt.subplots(figsize=(6, 5))
    P = rec.points
    if len(P):
        lo, hi = np.percentile(P, [2, 98], axis=0)
        keep = np.all((P >= lo) & (P <= hi), 1)
        ax.scatter(P[keep, 0], P[keep, 2], s=0.5, c=rec.colors[keep] / 255.0)
    C = rec.centres
    for i in np.nonzero(rec.registered)[0]:
        z = rec.R[i][2]  # optical axis in the world (row 2 of camera_from_world)
        ax.plot([C[i, 0], C[i, 0] + 0.3 * z[0]], [C[i, 2], C[i, 2] + 0.3 * z[2]], "r-")
        ax.plot(C[i, 0], C[i, 2], "r^")
        ax.annotate(rec.names[i], (C[i, 0], C[i, 2]), fontsize=6)
    ax.set_xlabel("x (world, first camera's frame)")
    ax.set_ylabel("z")
    ax.set_aspect("equal")
    ax.set_title("cameras (red) and sparse points, top view")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def write_report(rec, out_dir, *, title: str = "fsjax sfm", evaluation: dict | None = None) -> Path:
    """``report.md`` (stage times, registered count, reprojection RMS, reasons, view graph) and
    ``cameras.png`` (top view) in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    png = _plot(rec, out / "cameras.png")
    n = len(rec.names)
    L = [f"# {title}", "", f"Registered **{int(rec.registered.sum())}/{n}** images, {len(rec.points)} points, "
         f"reprojection RMS **{rec.rms_px:.3f} px** (all kept observations).", "",
         f"Intrinsics: fx {rec.K[0, 0]:.2f}, fy {rec.K[1, 1]:.2f}, cx {rec.K[0, 2]:.2f}, cy {rec.K[1, 2]:.2f} "
         f"(pixel centres on integers), image {rec.size[0]} x {rec.size[1]}.", ""]
    fi = getattr(rec, "focal", None)
    if fi:
        L += [f"No intrinsics given: focal length **{rec.K[0, 0]:.2f} px** (guess {fi['guess_px']:.1f} px = "
              f"1.2 max(W, H)); found by {fi.get('method', 'nothing: the guess was kept')}"
              + (f"; {fi['note']}" if fi.get("note") else "") + ".", ""]
    if png:
        L += [f"![cameras and points]({png.name})", ""]
    L += ["## Time per stage", "", "| stage | s |", "|---|---|"]
    L += [f"| {k} | {v:.2f} |" for k, v in rec.times_s.items()]
    L += ["", "(first run includes XLA compilation; later runs reuse the persistent cache.)", ""]
    if evaluation:
        L += ["## Against the ground truth", "", "| measure | value |", "|---|---|"]
        L += [f"| {k} | {v} |" for k, v in evaluation.items()]
        L += [""]
    L += ["## Images", "", "| image | registered | order | reason if left out |", "|---|---|---|---|"]
    for i, nm in enumerate(rec.names):
        o = rec.registration_order.index(i) + 1 if i in rec.registration_order else ""
        L.append(f"| {nm} | {'yes' if rec.registered[i] else 'no'} | {o} | {rec.reasons.get(i, '')} |")
    L += ["", "## View graph (pairs with matches)", "",
          "Flags: `ok` a general pair (essential matrix); `planar` a homography explains >= 90 % of the essential "
          "matrix's inliers and they show parallax (a plane: pose from the homography, whose two solutions are "
          "told apart by the inliers in front of both cameras, counts given); `pure_rotation` the homography "
          "explains them without parallax (never triangulated alone); `few_matches`, `few_inliers`, `no_pose`: "
          "not an edge.", "",
          "| pair | matches | inliers (E) | inliers (H) | flag | note |", "|---|---|---|---|---|---|"]
    for e in rec.view_graph:
        if e["matches"]:
            note = ""
            if e["flag"] == "planar":
                note = f"in front: {e['front'][0]} (chosen) vs {e['front'][1]} (other solution)"
            elif "parallax_px" in e:
                note = f"parallax {e['parallax_px']:.2f} px"
            L.append(f"| {rec.names[e['i']]}-{rec.names[e['j']]} | {e['matches']} | {e['inliers']} | "
                     f"{e.get('h_inliers', '')} | {e['flag']} | {note} |")
    path = out / "report.md"
    path.write_text("\n".join(L) + "\n")
    return path


def load_image_dir(image_dir):
    """(names, images) of the .jpg/.jpeg/.png files of a folder, sorted by name (RGB uint8)."""
    from PIL import Image

    d = Path(image_dir)
    if not d.is_dir():
        raise FileNotFoundError(f"fsjax sfm: argument 'IMAGE_DIR' is not a folder: {d}")
    names = sorted(f for f in os.listdir(d) if f.lower().endswith((".jpg", ".jpeg", ".png")))
    if len(names) < 2:
        raise ValueError(f"fsjax sfm: argument 'IMAGE_DIR' must hold >= 2 images (.jpg/.png), found {len(names)}")
    return names, [np.asarray(Image.open(d / nm).convert("RGB")) for nm in names]
