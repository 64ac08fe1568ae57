"""Run structure from motion on a folder of photographs and write every output (``fsjax sfm``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .export import load_image_dir, write_colmap_text, write_ply_points, write_report
from .reconstruct import Reconstruction, align_to_ground_truth, reconstruct

__all__ = ["run_folder", "load_ground_truth", "evaluate", "check_one_size"]


def check_one_size(names, imgs) -> None:
    """Refuse photographs of more than one size, naming the files that differ from the most common size.

    :func:`fsjax.sfm.reconstruct` models one camera (one ``K``, one feature program); a photograph of
    another size is another camera or a resized copy, so ``fsjax sfm`` refuses it rather than
    resizing it silently (a resize would make the given intrinsics wrong for it).
    """
    sizes = [im.shape[1::-1] for im in imgs]  # (width, height)
    common = max(set(sizes), key=sizes.count)
    odd = [f"'{nm}' ({w}x{h})" for nm, (w, h) in zip(names, sizes) if (w, h) != common]
    if odd:
        raise ValueError(f"fsjax sfm: every photograph must have one size (one camera): {sizes.count(common)} "
                         f"are {common[0]}x{common[1]}, but not {', '.join(odd)}; resize or remove them")


def load_ground_truth(path) -> dict:
    """Ground-truth cameras of a ``cameras.json`` as in ``../shared/data/sfm`` (Strecha et al. 2008 sets):
    ``{name: (K at the stored image size, world_from_camera R, centre)}``; the full-resolution ``K`` is
    mapped to the downsampled images with pixel centres on integers: ``f / d``, ``(c + 0.5) / d - 0.5``."""
    js = json.loads(Path(path).read_text())
    d = float(js.get("downsample", 1))
    out = {}
    for c in js["cameras"]:
        K = np.asarray(c["K_full"], float)
        Ks = np.array([[K[0, 0] / d, K[0, 1] / d, (K[0, 2] + 0.5) / d - 0.5], [0, K[1, 1] / d, (K[1, 2] + 0.5) / d - 0.5],
                       [0, 0, 1.0]])
        out[c["image"]] = (Ks, np.asarray(c["world_from_camera_R"], float), np.asarray(c["centre_m"], float))
    return out


def evaluate(rec: Reconstruction, gt: dict) -> dict:
    """Registered count and rotation / centre errors (median, max) after a similarity alignment
    (Umeyama on the centres) to the ground truth; centre errors in the ground truth's unit x 1000 (mm for metres)."""
    idx = [i for i, nm in enumerate(rec.names) if rec.registered[i] and nm in gt]
    if len(idx) < 3:
        return {"registered": f"{int(rec.registered.sum())}/{len(rec.names)}", "note": "fewer than 3 registered images"}
    rot, cen = align_to_ground_truth(rec.centres[idx], rec.R[idx], np.array([gt[rec.names[i]][2] for i in idx]),
                                     np.array([gt[rec.names[i]][1] for i in idx]))
    return {"registered": f"{int(rec.registered.sum())}/{len(rec.names)}",
            "rotation error median / max (deg)": f"{np.median(rot):.3f} / {rot.max():.3f}",
            "centre error median / max (mm)": f"{1000 * np.median(cen):.1f} / {1000 * cen.max():.1f}",
            "_rot": rot, "_cen": cen}


def run_folder(image_dir, out_dir, *, intrinsics=None, ground_truth=None, n_max: int = 4096, n_octaves: int = 5,
               seed: int = 0, log=print) -> Reconstruction:
    """Reconstruct the photographs of ``image_dir`` (all of one size: :func:`check_one_size`); write ``sparse/{cameras,images,points3D}.txt``
    (COLMAP text), ``points.ply`` (coloured sparse points), ``report.md``, ``cameras.png`` and ``source.json``
    (the photographs' folder, read by ``fsjax splat``) to ``out_dir``.

    ``intrinsics``: ``(fx, fy, cx, cy)`` in pixels (centres on integers); ``None`` self-calibrates
    one focal length (``fsjax.sfm.focal``; how, stated in the report). ``ground_truth``: an optional ``cameras.json`` to score against.
    """
    names, imgs = load_image_dir(image_dir)
    check_one_size(names, imgs)
    K = None
    if intrinsics is not None:
        fx, fy, cx, cy = (float(v) for v in intrinsics)
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    rec = reconstruct(imgs, K, names=names, n_max=n_max, n_octaves=n_octaves, seed=seed, log=log)
    out = Path(out_dir)
    write_colmap_text(rec, out / "sparse")
    (out / "source.json").write_text(json.dumps({"image_dir": str(Path(image_dir).resolve())}) + "\n")  # for fsjax splat
    write_ply_points(out / "points.ply", rec.points, rec.colors)
    ev = None
    if ground_truth is not None:
        ev = {k: v for k, v in evaluate(rec, load_ground_truth(ground_truth)).items() if not k.startswith("_")}
    title = f"fsjax sfm: {Path(image_dir).name}" + ("" if K is not None else " (focal length self-calibrated)")
    write_report(rec, out, title=title, evaluation=ev)
    log(f"wrote {out / 'report.md'}, {out / 'points.ply'}, {out / 'sparse'}")
    return rec
