"""Gaussian splats trained on the photographs of a structure-from-motion result (``fsjax splat``).

Input: a COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``, read by
:func:`fsjax.sfm.export.read_colmap_text`), in ``SFM_DIR/sparse`` (as ``fsjax sfm`` writes it) or
in ``SFM_DIR`` itself, and the photographs it was made from (``--images``, else ``SFM_DIR/images``,
else ``SFM_DIR/frames`` (the frames ``fsjax sfm VIDEO`` chose), else the folder ``fsjax sfm`` recorded
in ``SFM_DIR/source.json``).

Method:

* **Views.** Every registered image, in name order, resized by area averaging to ``width`` pixels
  (height in proportion, rounded); the intrinsics follow (pixel centres on integers:
  ``f' = s f``, ``c' = s (c + 0.5) - 0.5``). The pose is COLMAP's ``camera_from_world``
  inverted into fsjax's ``world_from_camera``. Every ``holdout_every``-th image (the 4th, 8th, ...
  in name order: index ``i % holdout_every == holdout_every - 1``) is held out.
* **Initialisation** (:func:`init_from_points`): one splat per sparse point, coloured by the
  point's RGB, isotropic with scale = root mean square distance to its 3 nearest neighbours
  (as 3DGS, Kerbl et al. 2023), opacity 0.1.
* **Training**: :func:`fsjax.fit.train_splats` (L1 + 0.2 D-SSIM, Adam, densify / prune under a
  fixed maximum count) started from that initialisation; the scene extent (for the position
  learning rate and the split/clone size) is 1.1 x the largest distance of a camera centre from
  their mean (as 3DGS).
* **Evaluation** (:func:`evaluate_views`) on the held-out views: PSNR and SSIM
  (:func:`fsjax.fit.ssim_color`, skimage's Gaussian SSIM) of the rendering clipped to [0, 1],
  each render's pair buffer sized from its measured demand and its ``overflow`` (splat-tile
  pairs dropped) checked to be 0. **Nulls**: the initial splats rendered before any training
  (``init``), and the same points at opacity 0.9 (``opaque points``, a stronger null: the best
  a sparse cloud shows without optimisation).

Outputs (``OUT``): ``splats.splat`` and ``splats.ply`` (valid splats; :mod:`fsjax.io.splat`),
``viewer.html`` (self-contained WebGL page, :mod:`fsjax.render.viewer`, from the first held-out
camera at the photographs' size), ``heldout.png`` (photo | null | trained per held-out view) and
``report.md``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..fit.splat_train import MultiViewData, _psnr, ssim_color, train_splats
from ..render.splat import _bucket, count_splat_pairs, render_splats, rgb_to_sh0
from ..types import Camera, Gaussians
from .export import read_colmap_text

__all__ = ["SfmViews", "load_sfm_views", "init_from_points", "evaluate_views", "splat_from_sfm"]


@dataclass
class SfmViews:
    """Posed photographs of a COLMAP model, resized: ``data`` (:class:`fsjax.fit.MultiViewData`;
    its ``points`` are ``(xyz (P, 3), rgb (P, 3) in [0, 1])``), image ``names``, the model's image
    size ``full_size`` ``(width, height)``, per-view ``K_full`` at that size, and ``image_dir``."""

    data: MultiViewData
    names: list[str]
    full_size: tuple[int, int]
    K_full: np.ndarray
    image_dir: Path
    extra: dict = field(default_factory=dict)


def _model_dir(sfm_dir: Path) -> Path:
    for d in (sfm_dir / "sparse", sfm_dir / "sparse" / "0", sfm_dir):
        if (d / "cameras.txt").exists():
            return d
    raise FileNotFoundError(f"fsjax splat: argument 'SFM_DIR' holds no COLMAP text model (cameras.txt) in "
                            f"{sfm_dir}/sparse or {sfm_dir}")


def _image_dir(sfm_dir: Path, image_dir) -> Path:
    if image_dir is not None:
        d = Path(image_dir)
    elif (sfm_dir / "images").is_dir():
        d = sfm_dir / "images"
    elif (sfm_dir / "frames").is_dir():  # `fsjax sfm VIDEO` writes its chosen frames there
        d = sfm_dir / "frames"
    elif (sfm_dir / "source.json").exists():
        d = Path(json.loads((sfm_dir / "source.json").read_text())["image_dir"])
    else:
        raise FileNotFoundError(f"fsjax splat: no photographs for {sfm_dir}: pass --images IMAGE_DIR "
                                "(or put them in SFM_DIR/images)")
    if not d.is_dir():
        raise FileNotFoundError(f"fsjax splat: argument 'images' is not a folder: {d}")
    return d


def _resize(img: np.ndarray, w: int, h: int) -> np.ndarray:
    from PIL import Image

    if img.shape[1] == w and img.shape[0] == h:
        return img
    return np.asarray(Image.fromarray(img).resize((w, h), Image.BOX))


def load_sfm_views(sfm_dir, image_dir=None, *, width: int = 192, holdout_every: int = 4) -> SfmViews:
    """Read a COLMAP text model and its photographs (see the module docstring)."""
    from PIL import Image

    sfm_dir = Path(sfm_dir)
    if holdout_every < 2:
        raise ValueError(f"load_sfm_views: argument 'holdout_every' must be >= 2, got {holdout_every}")
    model = read_colmap_text(_model_dir(sfm_dir))
    idir = _image_dir(sfm_dir, image_dir)
    ims = sorted(model["images"].values(), key=lambda r: r["name"])
    if len(ims) < 2:
        raise ValueError(f"fsjax splat: the model in {sfm_dir} has {len(ims)} registered image(s); need >= 2")
    sizes = {(model["cameras"][r["camera_id"]]["width"], model["cameras"][r["camera_id"]]["height"]) for r in ims}
    if len(sizes) != 1:
        raise ValueError(f"fsjax splat: all images must share one size, the model has {sorted(sizes)}")
    (W0, H0), = sizes
    if not 8 <= int(width) <= W0:
        raise ValueError(f"load_sfm_views: argument 'width' must be in [8, {W0}] (the model's width), got {width}")
    s = int(width) / W0
    W, H = int(width), max(1, int(round(H0 * s)))
    sx, sy = W / W0, H / H0
    imgs, Ks, Kf, Rs, ts = [], [], [], [], []
    for r in ims:
        p = idir / r["name"]
        if not p.exists():
            raise FileNotFoundError(f"fsjax splat: image {r['name']!r} of the model is not in {idir}")
        a = np.asarray(Image.open(p).convert("RGB"))
        if a.shape[:2] != (H0, W0):
            raise ValueError(f"fsjax splat: image {p} is {a.shape[1]} x {a.shape[0]}, the model says {W0} x {H0}")
        imgs.append(_resize(a, W, H).astype(np.float32) / 255.0)
        K = model["cameras"][r["camera_id"]]["K"]
        Kf.append(K)
        Ks.append([[K[0, 0] * sx, 0.0, (K[0, 2] + 0.5) * sx - 0.5], [0.0, K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5],
                   [0.0, 0.0, 1.0]])
        Rs.append(r["R"].T)  # world_from_camera
        ts.append(-r["R"].T @ r["t"])  # camera centre
    n = len(ims)
    i = np.arange(n)
    test = i[i % holdout_every == holdout_every - 1]
    train = np.setdiff1d(i, test)
    pts = model["points"]
    if not pts:
        raise ValueError(f"fsjax splat: the model in {sfm_dir} has no 3-D points to initialise from")
    xyz = np.array([p["xyz"] for p in pts.values()], float)
    rgb = np.array([p["rgb"] for p in pts.values()], float) / 255.0
    C = np.asarray(ts)
    extent = 1.1 * float(np.max(np.linalg.norm(C - C.mean(0), axis=1)))
    if not extent > 0:
        raise ValueError("fsjax splat: all camera centres coincide; the scene extent is 0")
    cams = Camera(jnp.asarray(np.asarray(Ks)), width=W, height=H, R=jnp.asarray(np.asarray(Rs)),
                  t=jnp.asarray(C))
    imgs = jnp.asarray(np.stack(imgs))
    data = MultiViewData(images=imgs, masks=jnp.ones(imgs.shape[:3], bool), depths=jnp.zeros(imgs.shape[:3]),
                         cameras=cams, train=train, test=test, points=(xyz, rgb), extent=extent)
    return SfmViews(data=data, names=[r["name"] for r in ims], full_size=(W0, H0), K_full=np.asarray(Kf),
                    image_dir=idir)


def _knn_rms(xyz: np.ndarray, k: int = 3) -> np.ndarray:
    """Root mean square distance of each point to its ``k`` nearest other points."""
    from scipy.spatial import cKDTree

    kk = min(k, len(xyz) - 1)
    if kk < 1:
        return np.ones(len(xyz))
    d, _ = cKDTree(xyz).query(xyz, k=kk + 1)
    return np.sqrt(np.mean(d[:, 1:] ** 2, axis=1))


def init_from_points(xyz, rgb, max_splats: int, *, opacity: float = 0.1, dtype=jnp.float32) -> Gaussians:
    """``max_splats`` slots, the first ``len(xyz)`` valid: one isotropic splat per point, scale = RMS
    distance to the 3 nearest neighbours (floored at 1e-7 and at 1e-3 x their median), colour ``rgb``
    (in [0, 1]), the given ``opacity``."""
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    rgb = np.asarray(rgb, float).reshape(-1, 3)
    P = len(xyz)
    if P > max_splats:
        raise ValueError(f"init_from_points: argument 'max_splats' must be >= the {P} points, got {max_splats}")
    if len(rgb) != P:
        raise ValueError(f"init_from_points: argument 'rgb' must have one row per point ({P}), got {len(rgb)}")
    if not np.all(np.isfinite(xyz)):
        raise ValueError("init_from_points: argument 'xyz' holds non-finite coordinates")
    if not 0 < opacity < 1:
        raise ValueError(f"init_from_points: argument 'opacity' must be in (0, 1), got {opacity}")
    sc = _knn_rms(xyz)
    sc = np.maximum(sc, max(1e-7, 1e-3 * float(np.median(sc))))
    means = np.zeros((max_splats, 3))
    means[:P] = xyz
    logs = np.zeros((max_splats, 3))
    logs[:P] = np.log(sc)[:, None]
    cols = np.zeros((max_splats, 1, 3))
    cols[:P, 0] = np.asarray(rgb_to_sh0(jnp.asarray(np.clip(rgb, 0, 1))))
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (max_splats, 1))
    return Gaussians(jnp.asarray(means, dtype), jnp.asarray(logs, dtype), jnp.asarray(quats, dtype),
                     jnp.full((max_splats,), np.log(opacity / (1 - opacity)), dtype), jnp.asarray(cols, dtype),
                     valid=jnp.asarray(np.arange(max_splats) < P))


def evaluate_views(g: Gaussians, data: MultiViewData, views=None, *, tile_size: int = 16) -> dict:
    """PSNR and SSIM per view (default the held-out ``data.test``) and their means; each render's
    pair buffer is the measured demand (``pairs``, ``buffer``) and ``overflow`` the pairs it dropped
    (summed over the views; 0 unless the renderer's sizing failed). ``renders`` holds the images."""
    views = np.asarray(data.test if views is None else views)
    ps, ss, ov, pairs, buf, renders = [], [], [], [], [], []
    for vi in views:
        cam = jax.tree_util.tree_map(lambda a, i=int(vi): a[i].astype(g.means.dtype)
                                     if jnp.issubdtype(a.dtype, jnp.floating) else a[i], data.cameras)
        demand = int(count_splat_pairs(g, cam, tile_size=tile_size))
        B = _bucket(max(demand, 1))
        out = render_splats(g, cam, tile_size=tile_size, max_pairs=B, distortion=False)
        img = data.images[vi].astype(out.color.dtype)
        col = jnp.clip(out.color, 0, 1)
        ps.append(float(_psnr(col, img)))
        ss.append(float(ssim_color(col, img)))
        ov.append(int(out.overflow))
        pairs.append(int(out.pairs))
        buf.append(B)
        renders.append(np.asarray(col))
    return {"views": views.tolist(), "psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "psnr_per_view": ps,
            "ssim_per_view": ss, "overflow": int(np.sum(ov)), "pairs": pairs, "buffer": buf, "renders": renders}


def _figure(path, photos, rows):
    """One row per view: the photo, then each entry of ``rows`` (lists of images), side by side."""
    from PIL import Image

    tiles = []
    for k in range(len(photos)):
        tiles.append(np.concatenate([photos[k]] + [r[k] for r in rows], axis=1))
    a = np.clip(np.concatenate(tiles, axis=0), 0, 1)
    Image.fromarray((a * 255 + 0.5).astype(np.uint8)).save(path)
    return Path(path)


def splat_from_sfm(sfm_dir, out_dir, *, image_dir=None, width: int = 192, holdout_every: int = 4,
                   iterations: int = 3000, max_splats: int = 30000, seed: int = 0, progress: bool = True,
                   log=print, **train_kw) -> dict:
    """Train splats on a structure-from-motion result and write every output (module docstring).

    Returns a dict: ``null`` (init), ``null_opaque``, ``trained`` (each :func:`evaluate_views`
    without the renders), ``beats_null`` (trained PSNR and SSIM above both nulls), ``steps``,
    ``train_seconds``, ``n_splats``, ``files``, ``result`` (the :class:`fsjax.fit.SplatTrainResult`).
    Raises ``RuntimeError`` if any evaluation render dropped splat-tile pairs (overflow): its
    figures would not be a valid measurement.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    v = load_sfm_views(sfm_dir, image_dir, width=width, holdout_every=holdout_every)
    d = v.data
    if len(d.test) == 0:
        raise ValueError(f"splat_from_sfm: {len(v.names)} registered images hold none out (every {holdout_every}th); "
                         f"need >= {holdout_every}")
    xyz, rgb = d.points
    if len(xyz) > max_splats:
        raise ValueError(f"splat_from_sfm: argument 'max_splats' ({max_splats}) is below the {len(xyz)} sparse points")
    W, H = d.cameras.width, d.cameras.height
    log(f"{len(v.names)} views at {W} x {H} ({len(d.train)} train, held out: "
        f"{', '.join(v.names[i] for i in d.test)}), {len(xyz)} sparse points, extent {d.extent:.3g}")
    g0 = init_from_points(xyz, rgb, max_splats)
    null = evaluate_views(g0, d)
    null_op = evaluate_views(init_from_points(xyz, rgb, max_splats, opacity=0.9), d)
    log(f"null (sparse points as splats, before training): PSNR {null['psnr']:.2f} dB, SSIM {null['ssim']:.3f}")
    t0 = time.perf_counter()
    res = train_splats(jax.random.PRNGKey(seed), d, init=g0, iterations=iterations, progress=progress, **train_kw)
    t_train = time.perf_counter() - t0
    g = res.gaussians
    tr = evaluate_views(g, d)
    trv = evaluate_views(g, d, d.train)
    n = int(np.asarray(g.valid).sum())
    log(f"trained {iterations} steps in {t_train:.1f} s, {n} splats: held-out PSNR {tr['psnr']:.2f} dB, "
        f"SSIM {tr['ssim']:.3f}")
    for nm, e in (("null", null), ("opaque null", null_op), ("trained", tr), ("trained (train views)", trv)):
        if e["overflow"]:
            raise RuntimeError(f"fsjax splat: evaluation render of the {nm} splats dropped {e['overflow']} "
                               "splat-tile pairs (tile overflow); its figures are not valid")
    beats = bool(tr["psnr"] > max(null["psnr"], null_op["psnr"]) and tr["ssim"] > max(null["ssim"], null_op["ssim"]))
    from ..io.splat import write_ply_gaussians, write_splat
    from ..render.viewer import write_viewer_page

    files = {"splat": out / "splats.splat", "ply": out / "splats.ply", "viewer": out / "viewer.html",
             "figure": out / "heldout.png", "report": out / "report.md"}
    write_splat(files["splat"], g)
    write_ply_gaussians(files["ply"], g)
    vi = int(d.test[0]) if len(d.test) else 0
    W0, H0 = v.full_size
    vcam = Camera(jnp.asarray(v.K_full[vi]), width=W0, height=H0, R=d.cameras.R[vi], t=d.cameras.t[vi])
    write_viewer_page(files["viewer"], files["splat"], vcam, near=0.01 * d.extent)
    photos = [np.asarray(d.images[i]) for i in d.test]
    _figure(files["figure"], photos, [null["renders"], tr["renders"]])
    summary = {"null": {k: x for k, x in null.items() if k != "renders"},
               "null_opaque": {k: x for k, x in null_op.items() if k != "renders"},
               "trained": {k: x for k, x in tr.items() if k != "renders"},
               "trained_train_views": {k: x for k, x in trv.items() if k != "renders"},
               "beats_null": beats, "steps": iterations, "train_seconds": t_train,
               "step_seconds": res.step_seconds, "compile_seconds": res.compile_seconds, "n_splats": n,
               "n_points": len(xyz), "size": [W, H], "names": v.names,
               "held_out": [v.names[i] for i in d.test], "holdout_every": holdout_every,
               "max_training_overflow": int(np.max(res.overflow)) if len(res.overflow) else 0}
    _write_report(files["report"], summary, sfm_dir, v, res)
    (out / "metrics.json").write_text(json.dumps(summary, indent=1))
    log(f"wrote {', '.join(str(p) for p in files.values())}")
    return dict(summary, files=files, result=res)


def _write_report(path, s, sfm_dir, v, res):
    n, o, t, tv = s["null"], s["null_opaque"], s["trained"], s["trained_train_views"]
    W, H = s["size"]
    L = [f"# fsjax splat: {Path(sfm_dir).name}", "",
         f"{len(s['names'])} photographs from `{v.image_dir}` at {W} x {H} with the cameras of the COLMAP model in "
         f"`{sfm_dir}`; held out (every {s['holdout_every']}th): {', '.join(s['held_out'])}. {s['n_points']} sparse points "
         f"initialise {s['n_points']} splats.", "",
         f"Trained **{s['steps']} steps** in **{s['train_seconds']:.1f} s** (median step {s['step_seconds']:.3f} s, "
         f"compile {s['compile_seconds']:.1f} s), {s['n_splats']} splats at the end; largest pair overflow during "
         f"training {s['max_training_overflow']}.", "",
         "| splats | held-out PSNR (dB) | held-out SSIM | eval. overflow |", "|---|---|---|---|",
         f"| null: sparse points as splats before training (opacity 0.1, the initialisation) | {n['psnr']:.2f} | "
         f"{n['ssim']:.3f} | {n['overflow']} |",
         f"| null: same points at opacity 0.9 | {o['psnr']:.2f} | {o['ssim']:.3f} | {o['overflow']} |",
         f"| **trained** | **{t['psnr']:.2f}** | **{t['ssim']:.3f}** | {t['overflow']} |",
         f"| trained, on the training views | {tv['psnr']:.2f} | {tv['ssim']:.3f} | {tv['overflow']} |", "",
         f"Trained splats beat both nulls (PSNR and SSIM): **{'yes' if s['beats_null'] else 'NO'}**. "
         "Overflow = splat-tile pairs dropped by an evaluation render (each buffer sized from the measured demand; "
         "checked 0, else the command fails).", "",
         "| held-out view | null PSNR / SSIM | trained PSNR / SSIM |", "|---|---|---|"]
    for k, vi in enumerate(t["views"]):
        L.append(f"| {s['names'][vi]} | {n['psnr_per_view'][k]:.2f} / {n['ssim_per_view'][k]:.3f} | "
                 f"{t['psnr_per_view'][k]:.2f} / {t['ssim_per_view'][k]:.3f} |")
    L += ["", "![held-out views: photo, null, trained](heldout.png)", "",
          "Files: `splats.splat`, `splats.ply` (3DGS layout), `viewer.html` (open from disk), `metrics.json`."]
    Path(path).write_text("\n".join(L) + "\n")
