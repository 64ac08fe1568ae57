"""Tour sections for calibration (issue 7): the real chessboard vs OpenCV, and plumb-line calibration.

Each section wraps a pure ``measure_*`` function that returns a dict of numbers;
``tests/tour/test_tour_calibration.py`` (and the calibration tests) assert those numbers.
:func:`measure_real_chessboard` is cached per process, so the 14 detections and the two
calibrations run once however many tests read them.

Nulls:

* real chessboard: the *integer-pixel* corners (the saddle-response peaks before sub-pixel
  refinement), calibrated with the same LM -- what the sub-pixel stage buys;
* plumb line: the uncorrected image (distortion parameters all zero).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from ._core import Section, _panel

__all__ = ["measure_real_chessboard", "measure_plumb_line", "measure_length_sensitivity", "SECTIONS"]

OPENCV_FIGURES = {"rms": 0.124, "fx": 516.2, "fy": 516.4, "cx": 315.1, "cy": 250.0}


@lru_cache(maxsize=1)
def measure_real_chessboard() -> dict:
    """Detect the 9x6 corners on the 14 bundled photographs with fsjax and with OpenCV, calibrate both ways.

    Returns a dict: ``fsjax_corners``/``cv_corners`` ``(14, 54, 2)`` (OpenCV's re-ordered to
    fsjax's order by nearest neighbour), ``found`` (per image), ``corner_dist`` (54*14
    distances, px), ``cal`` (fsjax calibration on fsjax's corners), ``cal_on_cv`` (fsjax
    calibration on OpenCV's corners), ``cv`` (``cv2.calibrateCamera`` on OpenCV's corners:
    rms, K, dist), ``cal_null`` (fsjax calibration on the integer-pixel corners).
    """
    try:
        import cv2
    except ImportError:  # OpenCV is a test/bench extra: the comparison is then left out
        cv2 = None

    from fsjax.data.chessboard import chessboard_images
    from fsjax.fit.calibrate import calibrate_camera
    from fsjax.fit.chessboard import board_points, find_chessboard

    ims = chessboard_images(as_float=False)
    res = [find_chessboard(g, (9, 6)) for g in ims]
    found = np.array([bool(r.converged) for r in res])
    ours = np.stack([np.asarray(r.corners) for r in res])
    board = board_points((9, 6))
    # null: integer-pixel corners (the response peaks the refinement started from)
    from fsjax.fit.chessboard import _candidates, saddle_response

    null = []
    for g, q in zip(ims, ours):
        p, _ = _candidates(np.asarray(saddle_response(g / 255.0, sigma=2.0)), 4, 0.1, 400)
        d = np.linalg.norm(q[:, None] - p[None], axis=2)
        null.append(p[d.argmin(1)])
    coarse = np.stack(null)
    out = {
        "images": ims, "found": found, "fsjax_corners": ours,
        "cal": calibrate_camera(board, ours, (640, 512)),
        "cal_null": calibrate_camera(board, coarse, (640, 512)),
        "cv_corners": None, "corner_dist": None, "cal_on_cv": None, "cv": None,
    }
    if cv2 is None:
        return out
    cv_pts, dists = [], []
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
    for g, q in zip(ims, ours):
        ok, c = cv2.findChessboardCorners(g, (9, 6))
        c = cv2.cornerSubPix(g, c, (11, 11), (-1, -1), crit).reshape(-1, 2).astype(np.float64)
        d = np.linalg.norm(q[:, None] - c[None], axis=2)
        idx = d.argmin(1)
        cv_pts.append(c[idx])
        dists.append(d[np.arange(len(q)), idx])
    cv_pts = np.stack(cv_pts)
    obj = [board.astype(np.float32)] * len(ims)
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, [c.astype(np.float32).reshape(-1, 1, 2) for c in cv_pts],
                                             (640, 512), None, None)
    out.update(cv_corners=cv_pts, corner_dist=np.concatenate(dists),
               cal_on_cv=calibrate_camera(board, cv_pts, (640, 512)),
               cv={"rms": float(rms), "K": K, "dist": dist.ravel()})
    return out


def _cal_row(cal) -> str:
    p = cal.params
    return (f"RMS {float(cal.rms_px):.4f} px, fx {p['fx']:.2f}, fy {p['fy']:.2f}, cx {p['cx']:.2f}, "
            f"cy {p['cy']:.2f}")


def real_chessboard(out: Path, quick: bool) -> Section:
    """fsjax's chessboard detection and calibration vs OpenCV on the 14 bundled photographs."""
    r = measure_real_chessboard()
    cal, cv = r["cal"], r["cv"]
    K = cv["K"] if cv is not None else None
    img = r["images"][0].astype(float) / 255.0
    mark = img.copy()
    for (u, v) in r["fsjax_corners"][0]:
        iu, iv = int(round(u)), int(round(v))
        mark[iv, max(iu - 3, 0):iu + 4] = 1.0
        mark[max(iv - 3, 0):iv + 4, iu] = 1.0
    fig = _panel(out / "calibration_chessboard.png", [img, mark], ["left01", "fsjax corners"])
    null = r["cal_null"]
    rows = [("fsjax corners + fsjax LM", _cal_row(cal))]
    if cv is not None:
        rows += [
            ("OpenCV corners + fsjax LM", _cal_row(r["cal_on_cv"])),
            ("OpenCV corners + cv2.calibrateCamera",
             f"RMS {cv['rms']:.4f} px, fx {K[0, 0]:.2f}, fy {K[1, 1]:.2f}, cx {K[0, 2]:.2f}, cy {K[1, 2]:.2f}"),
        ]
    rows.append(("null: integer-pixel corners + fsjax LM", _cal_row(null)))
    if cv is not None:
        rows.append(("corners fsjax vs cv2.cornerSubPix", f"median {np.median(r['corner_dist']):.4f} px, "
                                                          f"max {r['corner_dist'].max():.4f} px"))
    else:
        rows.append(("OpenCV comparison", "skipped: OpenCV is not installed "
                                          "(pip install opencv-python-headless, or the test extra)"))
    return Section(
        title="Camera calibration on 14 real chessboard photographs",
        truth="OpenCV's calibration of the same images (no ground truth exists for a real lens)",
        rows=rows, fsjax_figure=f"RMS {float(cal.rms_px):.4f} px" + (f" (OpenCV {cv['rms']:.4f})" if cv is not None else ""),
        null_figure=f"RMS {float(null.rms_px):.4f} px", beats_null=bool(cal.rms_px < null.rms_px), figure=fig,
        notes="Zhang closed form, then optimistix LM over 9 intrinsics and 84 pose parameters.")



# ---------------------------------------------------------------------------
# differentiable metrology: plumb-line distortion calibration, length sensitivity
# ---------------------------------------------------------------------------

PLUMB = {"shape": (128, 160), "f": 150.0, "c": (79.5, 63.5), "dist": (-0.25, 0.06, 0.0, 0.0, 0.0),
         "v_edges": (35.0, 80.0, 125.0), "h_edges": (25.0, 64.0, 103.0), "blur": 0.8}


def _plumb_scene(u, v):
    """Undistorted scene: three vertical and three horizontal straight step edges (tanh profiles)."""
    p = PLUMB
    s = sum(0.5 * (1 + np.tanh((u - e) / p["blur"])) * (-1) ** i for i, e in enumerate(p["v_edges"]))
    t = sum(0.5 * (1 + np.tanh((v - e) / p["blur"])) * (-1) ** i for i, e in enumerate(p["h_edges"]))
    return 0.15 + 0.35 * s + 0.35 * t


def plumb_image() -> np.ndarray:
    """The scene seen through the distorted lens: ``D(u_d, v_d) = scene(undistort(u_d, v_d))`` (Newton inverse)."""
    import jax.numpy as jnp

    from fsjax.render.camera import undistort_normalized

    p = PLUMB
    h, w = p["shape"]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xy = np.stack([(u - p["c"][0]) / p["f"], (v - p["c"][1]) / p["f"]], -1)
    und = undistort_normalized(jnp.asarray(p["dist"]), jnp.asarray(xy))
    assert bool(np.all(np.asarray(und.converged)))
    xu = np.asarray(und.xy)
    return _plumb_scene(xu[..., 0] * p["f"] + p["c"][0], xu[..., 1] * p["f"] + p["c"][1])


def _plumb_measure(img, k):
    """Edge points measured by ``measure_pos`` calipers on the image rectified with distortion ``k = (k1, k2)``."""
    import jax
    import jax.numpy as jnp

    import fsjax
    from fsjax.ops.measure2d._caliper import bilinear
    from fsjax.render.camera import distort_normalized

    p = PLUMB
    h, w = p["shape"]
    v, u = jnp.meshgrid(jnp.arange(h, dtype=img.dtype), jnp.arange(w, dtype=img.dtype), indexing="ij")
    xy = jnp.stack([(u - p["c"][0]) / p["f"], (v - p["c"][1]) / p["f"]], -1)
    d = jnp.concatenate([k, jnp.zeros(3, k.dtype)])
    xd = distort_normalized(d, xy)
    rect = bilinear(img, xd[..., 1] * p["f"] + p["c"][1], xd[..., 0] * p["f"] + p["c"][0], mode="nearest")
    im = fsjax.Image(rect)
    rows = jnp.linspace(12.0, h - 13.0, 9)
    cols = jnp.linspace(14.0, w - 15.0, 11)
    hor = jax.vmap(lambda r: fsjax.ops.measure_pos(im, row=r, col=(w - 1) / 2, angle_deg=0.0, length=w - 12,
                                                   sigma=1.5, threshold=0.05, capacity=3))(rows)
    ver = jax.vmap(lambda c: fsjax.ops.measure_pos(im, row=(h - 1) / 2, col=c, angle_deg=-90.0, length=h - 12,
                                                   sigma=1.5, threshold=0.05, capacity=3))(cols)
    # line j of the vertical edges: points (row, col) of slot j of every horizontal caliper
    vlines = jnp.stack([hor.row, hor.col], -1).transpose(1, 0, 2)  # (3, 9, 2)
    hlines = jnp.stack([ver.row, ver.col], -1).transpose(1, 0, 2)  # (3, 11, 2)
    ok = jnp.all(hor.valid) & jnp.all(ver.valid) & ~jnp.any(hor.truncated) & ~jnp.any(ver.truncated)
    return vlines, hlines, ok


def _straightness(pts):
    """Perpendicular residuals of points to their total-least-squares line, over the line's spread (unitless)."""
    import jax.numpy as jnp

    c = pts - jnp.mean(pts, axis=0)
    lam, vec = jnp.linalg.eigh(c.T @ c)
    n = vec[:, 0]
    return (c @ n) / jnp.sqrt(lam[1] / pts.shape[0])


def plumb_residuals(k, img):
    """All lines' normalised perpendicular residuals (vector) for distortion ``k = (k1, k2)``."""
    import jax.numpy as jnp

    vl, hl, _ = _plumb_measure(img, k)
    return jnp.concatenate([_straightness(pl) for pl in list(vl) + list(hl)])


def plumb_curvature(k, img):
    """Scalar curvature objective: the sum of squares of :func:`plumb_residuals`."""
    import jax.numpy as jnp

    r = plumb_residuals(k, img)
    return jnp.sum(r * r)


def _plumb_solve(img):
    import equinox as eqx
    import jax.numpy as jnp
    import optimistix as optx

    @eqx.filter_jit
    def solve(img):
        return optx.least_squares(lambda k, a: plumb_residuals(k, a), optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10),
                                  jnp.zeros(2, img.dtype), img, max_steps=100, throw=False)

    return solve(img)


def measure_plumb_line(fd_step: float = 1e-6) -> dict:
    """Plumb-line calibration of ``(k1, k2)`` through ``measure_pos``: gradient FD check and the LM solve."""
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    img = jnp.asarray(plumb_image())
    truth = np.asarray(PLUMB["dist"][:2])
    k_probe = jnp.asarray([-0.1, 0.0])
    curv = jax.jit(plumb_curvature)
    g = jax.jit(jax.grad(plumb_curvature))(k_probe, img)
    fd = np.array([(float(curv(k_probe + fd_step * e, img)) - float(curv(k_probe - fd_step * e, img)))
                   / (2 * fd_step) for e in np.eye(2)])
    sol = _plumb_solve(img)
    k = np.asarray(sol.value)
    _, _, ok = jax.jit(_plumb_measure)(img, sol.value)
    # displacement error of the recovered distortion over the image, in pixels
    p = PLUMB
    h, w = p["shape"]
    v, u = np.mgrid[0:h:8, 0:w:8].astype(float)
    xy = np.stack([(u - p["c"][0]) / p["f"], (v - p["c"][1]) / p["f"]], -1)
    from fsjax.render.camera import distort_normalized

    dd = lambda kk: np.asarray(distort_normalized(jnp.asarray(np.r_[kk, 0, 0, 0]), jnp.asarray(xy)))  # noqa: E731
    field_err = np.abs(dd(k) - dd(truth)).max() * p["f"]
    field_max = np.abs(dd(truth) - xy).max() * p["f"]
    res = jax.jit(plumb_residuals)
    rms = lambda kk: float(np.sqrt(np.mean(np.asarray(res(jnp.asarray(kk), img)) ** 2)))  # noqa: E731
    return {"image": np.asarray(img), "truth": truth, "k": k, "converged": bool(sol.result == optx.RESULTS.successful),
            "measured_ok": bool(ok), "grad": np.asarray(g), "fd": fd, "field_err_px": float(field_err),
            "field_max_px": float(field_max), "straightness_fit": rms(k), "straightness_null": rms(np.zeros(2)),
            "steps": int(sol.stats["num_steps"])}


LENGTH = {"shape": (120, 200), "theta": (516.2, 516.4, 99.5, 59.5, -0.06, 0.07, 0.0001, 0.0013, 0.07),
          "depth_mm": 500.0, "bar_mm": (-10.0, 40.0), "y_mm": 20.0, "blur": 0.7}


def _length_camera(theta):
    import jax.numpy as jnp

    from fsjax.types import Camera

    z, o = jnp.zeros_like(theta[0]), jnp.ones_like(theta[0])
    K = jnp.stack([jnp.stack([theta[0], z, theta[2]]), jnp.stack([z, theta[1], theta[3]]), jnp.stack([z, z, o])])
    h, w = LENGTH["shape"]
    return Camera(K, width=w, height=h, dist=theta[4:9])


def length_image() -> np.ndarray:
    """A bright bar ``bar_mm`` wide (X from -10 to 40 mm) on a fronto-parallel plane at 500 mm, seen through the lens."""
    import jax.numpy as jnp

    from fsjax.render.camera import backproject

    h, w = LENGTH["shape"]
    cam = _length_camera(jnp.asarray(LENGTH["theta"]))
    v, u = np.mgrid[0:h, 0:w].astype(float)
    X = np.asarray(backproject(cam, jnp.stack([jnp.asarray(u), jnp.asarray(v)], -1), LENGTH["depth_mm"]))
    a, b = LENGTH["bar_mm"]
    px_mm = LENGTH["theta"][0] / LENGTH["depth_mm"]  # blur in px -> mm
    s = 0.5 * (np.tanh((X[..., 0] - a) * px_mm / LENGTH["blur"]) - np.tanh((X[..., 0] - b) * px_mm / LENGTH["blur"]))
    return 0.2 + 0.6 * s


def measured_length(theta, img):
    """Physical bar width (mm): two ``measure_pos`` edges on a caliper, back-projected with intrinsics ``theta``."""
    import jax.numpy as jnp

    import fsjax
    from fsjax.render.camera import backproject

    h, w = LENGTH["shape"]
    cam = _length_camera(theta)
    row = LENGTH["theta"][3] + LENGTH["theta"][1] * LENGTH["y_mm"] / LENGTH["depth_mm"]
    e = fsjax.ops.measure_pos(fsjax.Image(img), row=row, col=(w - 1) / 2, angle_deg=0.0, length=w - 10,
                              sigma=1.5, threshold=0.05, capacity=2)
    uv = jnp.stack([e.col, e.row], -1)
    X = backproject(cam, uv, jnp.full((2,), LENGTH["depth_mm"], uv.dtype))
    return jnp.linalg.norm(X[1] - X[0])


def measure_length_sensitivity(fd_step: float = 1e-6) -> dict:
    """Jacobian of the measured bar width w.r.t. the 9 intrinsics (``jax.jacfwd``) vs central differences."""
    import jax
    import jax.numpy as jnp

    img = jnp.asarray(length_image())
    theta = jnp.asarray(LENGTH["theta"])
    f = jax.jit(measured_length)
    L = float(f(theta, img))
    J = np.asarray(jax.jit(jax.jacfwd(measured_length))(theta, img))
    fd = np.zeros(9)
    for i in range(9):
        h = fd_step * max(1.0, abs(float(theta[i])))
        e = jnp.zeros(9).at[i].set(h)
        fd[i] = (float(f(theta + e, img)) - float(f(theta - e, img))) / (2 * h)
    a, b = LENGTH["bar_mm"]
    return {"image": np.asarray(img), "length_mm": L, "truth_mm": b - a, "jacobian": J, "fd": fd}


def plumb_line(out: Path, quick: bool) -> Section:
    """Plumb-line distortion calibration through ``measure_pos`` (gradient through the measurement)."""
    import jax.numpy as jnp

    r = measure_plumb_line()
    img = r["image"]
    # the rectified image with the recovered distortion, for the figure
    p = PLUMB
    h, w = p["shape"]
    v, u = np.mgrid[0:h, 0:w].astype(float)
    from fsjax.ops.measure2d._caliper import bilinear
    from fsjax.render.camera import distort_normalized

    xy = np.stack([(u - p["c"][0]) / p["f"], (v - p["c"][1]) / p["f"]], -1)
    xd = np.asarray(distort_normalized(jnp.asarray(np.r_[r["k"], 0, 0, 0]), jnp.asarray(xy)))
    rect = np.asarray(bilinear(jnp.asarray(img), jnp.asarray(xd[..., 1] * p["f"] + p["c"][1]),
                               jnp.asarray(xd[..., 0] * p["f"] + p["c"][0])))
    fig = _panel(out / "calibration_plumb_line.png", [img, rect], ["distorted (k1 -0.25, k2 0.06)", "rectified"])
    rows = [
        ("truth (k1, k2)", f"{r['truth'][0]:.4f}, {r['truth'][1]:.4f}"),
        ("fsjax plumb line (LM through measure_pos)", f"{r['k'][0]:.4f}, {r['k'][1]:.4f}; field error "
                                                      f"{r['field_err_px']:.3f} px of {r['field_max_px']:.2f} px"),
        ("d curvature / d (k1, k2): jax.grad vs FD", f"{r['grad'][0]:.6f}, {r['grad'][1]:.6f} vs "
                                                     f"{r['fd'][0]:.6f}, {r['fd'][1]:.6f}"),
        ("straightness RMS (corrected / null)", f"{r['straightness_fit']:.2e} / {r['straightness_null']:.2e}"),
    ]
    return Section(
        title="Plumb-line distortion calibration through sub-pixel calipers",
        truth="the synthetic lens distortion (k1, k2) = (-0.25, 0.06)",
        rows=rows, fsjax_figure=f"distortion field error {r['field_err_px']:.3f} px",
        null_figure=f"no correction: field error {r['field_max_px']:.2f} px",
        beats_null=bool(r["field_err_px"] < r["field_max_px"]), figure=fig,
        notes="The image is rectified with candidate (k1, k2), edges measured by measure_pos, the lines' "
              "straightness residuals minimised by optimistix LM; gradients flow through the caliper.")


def length_sensitivity(out: Path, quick: bool) -> Section:
    """Jacobian of a measured physical length w.r.t. the intrinsics, vs finite differences."""
    r = measure_length_sensitivity()
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    rel = np.abs(r["jacobian"] - r["fd"]) / np.maximum(np.abs(r["fd"]), 1e-12)
    fig = _panel(out / "calibration_length.png", [r["image"]], ["bar 50 mm at 500 mm"])
    rows = [(f"dL/d{n}", f"{j:.4e} (FD {f:.4e})") for n, j, f in zip(names, r["jacobian"], r["fd"])]
    rows.insert(0, ("measured length", f"{r['length_mm']:.4f} mm (truth {r['truth_mm']:.1f} mm)"))
    return Section(
        title="Sensitivity of a measured length to the intrinsics",
        truth="central finite differences of the same measurement; the bar's true width",
        rows=rows, fsjax_figure=f"max rel. diff jacfwd vs FD {rel.max():.1e}",
        null_figure=f"length error {abs(r['length_mm'] - r['truth_mm']):.3f} mm",
        beats_null=bool(rel.max() < 1e-3), figure=fig,
        notes="measure_pos edges back-projected through the camera model (Newton undistortion with implicit "
              "gradient) to the plane at 500 mm.")


SECTIONS = [real_chessboard, plumb_line, length_sensitivity]
