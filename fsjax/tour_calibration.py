"""Tour sections for calibration (issue 7): the real chessboard vs OpenCV, and plumb-line calibration.

Each section wraps a pure ``measure_*`` function that returns a dict of numbers;
``tests/test_tour_calibration.py`` (and the calibration tests) assert those numbers.
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

from fsjax.tour import Section, _panel

__all__ = ["measure_real_chessboard", "measure_plumb_line", "SECTIONS"]

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
    import cv2

    from fsjax.data.chessboard import chessboard_images
    from fsjax.fit.calibrate import calibrate_camera
    from fsjax.fit.chessboard import board_points, find_chessboard

    ims = chessboard_images(as_float=False)
    res = [find_chessboard(g, (9, 6)) for g in ims]
    found = np.array([bool(r.found) for r in res])
    ours = np.stack([np.asarray(r.corners) for r in res])
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
    board = board_points((9, 6))
    obj = [board.astype(np.float32)] * len(ims)
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, [c.astype(np.float32).reshape(-1, 1, 2) for c in cv_pts],
                                             (640, 512), None, None)
    # null: integer-pixel corners (the response peaks the refinement started from)
    from fsjax.fit.chessboard import _candidates, saddle_response

    null = []
    for g, q in zip(ims, ours):
        p, _ = _candidates(np.asarray(saddle_response(g / 255.0, sigma=2.0)), 4, 0.1, 400)
        d = np.linalg.norm(q[:, None] - p[None], axis=2)
        null.append(p[d.argmin(1)])
    coarse = np.stack(null)
    return {
        "images": ims, "found": found, "fsjax_corners": ours, "cv_corners": cv_pts,
        "corner_dist": np.concatenate(dists),
        "cal": calibrate_camera(board, ours, (640, 512)),
        "cal_on_cv": calibrate_camera(board, cv_pts, (640, 512)),
        "cal_null": calibrate_camera(board, coarse, (640, 512)),
        "cv": {"rms": float(rms), "K": K, "dist": dist.ravel()},
    }


def _cal_row(cal) -> str:
    p = cal.params
    return (f"RMS {float(cal.rms):.4f} px, fx {p['fx']:.2f}, fy {p['fy']:.2f}, cx {p['cx']:.2f}, "
            f"cy {p['cy']:.2f}")


def real_chessboard(out: Path, quick: bool) -> Section:
    """fsjax's chessboard detection and calibration vs OpenCV on the 14 bundled photographs."""
    r = measure_real_chessboard()
    cal, cv = r["cal"], r["cv"]
    K = cv["K"]
    img = r["images"][0].astype(float) / 255.0
    mark = img.copy()
    for (u, v) in r["fsjax_corners"][0]:
        iu, iv = int(round(u)), int(round(v))
        mark[iv, max(iu - 3, 0):iu + 4] = 1.0
        mark[max(iv - 3, 0):iv + 4, iu] = 1.0
    fig = _panel(out / "calibration_chessboard.png", [img, mark], ["left01", "fsjax corners"])
    null = r["cal_null"]
    rows = [
        ("fsjax corners + fsjax LM", _cal_row(cal)),
        ("OpenCV corners + fsjax LM", _cal_row(r["cal_on_cv"])),
        ("OpenCV corners + cv2.calibrateCamera",
         f"RMS {cv['rms']:.4f} px, fx {K[0, 0]:.2f}, fy {K[1, 1]:.2f}, cx {K[0, 2]:.2f}, cy {K[1, 2]:.2f}"),
        ("null: integer-pixel corners + fsjax LM", _cal_row(null)),
        ("corners fsjax vs cv2.cornerSubPix", f"median {np.median(r['corner_dist']):.4f} px, "
                                              f"max {r['corner_dist'].max():.4f} px"),
    ]
    return Section(
        title="Camera calibration on 14 real chessboard photographs",
        truth="OpenCV's calibration of the same images (no ground truth exists for a real lens)",
        rows=rows, fsjax_figure=f"RMS {float(cal.rms):.4f} px (OpenCV {cv['rms']:.4f})",
        null_figure=f"RMS {float(null.rms):.4f} px", beats_null=bool(cal.rms < null.rms), figure=fig,
        notes="Zhang closed form, then optimistix LM over 9 intrinsics and 84 pose parameters.")


SECTIONS = [real_chessboard]
