"""2-D inspection benchmark: fsjax against SciPy, scikit-image and OpenCV.

Workloads (1024 x 1024 unless stated; one process, the same inputs for everybody):

* ``pipeline``: Otsu threshold + 8-connected labelling + per-label areas on a
  grey blobs image (``skimage.data.binary_blobs``, blurred, noisy, quantised to
  256 grey levels);
* ``label``: 8-connected labelling alone, on the same binary mask for everybody;
* ``edt``: exact Euclidean distance transform of that mask;
* ``ncc``: normalised cross-correlation (``TM_CCOEFF_NORMED``) of a 64 x 64
  template in a 1024 x 1024 photograph;
* ``shape``: ``fsjax.ops.shape_locate`` on the workpiece alignment scene of
  ``fsjax/synth/_workpiece.py`` (no peer in these libraries).

fsjax runs jitted on one image and, for ``pipeline``, ``label``, ``edt`` and
``ncc``, as ``jax.jit(jax.vmap(f))`` over a batch of 8 different images (time
reported per image beside the single-image time). Timing, compile time and
memory come from ``benchmarks/_harness.py``: medians of round-robin repeats
after warm-up, compile time measured apart.

Run ``python benchmarks/bench_inspection.py`` (``--quick`` for a smoke run,
``--write-docs`` to regenerate ``docs/benchmarks_inspection.md`` and
``docs/figures/bench_insp_*.png``).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))

from _harness import (  # noqa: E402
    Timing,
    jax_compile,
    load_average,
    machine_info,
    time_round_robin,
    tracemalloc_peak_bytes,
    xla_memory_bytes,
)

SIZE = 1024
TPL = 64
BATCH = 8
CAPACITY = 2048  # label capacity; every run checks that no output is truncated
S8 = np.ones((3, 3), bool)  # SciPy's structure for 8-connectivity

WORKLOADS = ("pipeline", "label", "edt", "ncc", "shape")
TITLES = {
    "pipeline": "Otsu + labelling (8-conn.) + areas, 1024x1024",
    "label": "Labelling alone (8-conn.), 1024x1024",
    "edt": "Exact Euclidean distance transform, 1024x1024",
    "ncc": "NCC (TM_CCOEFF_NORMED), 64x64 template in 1024x1024",
    "shape": "Shape matching (shape_locate), workpiece scene 240x320",
}
# goal: (workload, peer, limit) -- fsjax per-image time / peer time <= limit
GOALS = {"pipeline": ("SciPy", 2.0), "label": ("SciPy", 2.0), "edt": ("SciPy", 1.5), "ncc": ("OpenCV", 1.5)}


# --------------------------------------------------------------------------- inputs

def blobs_masks(n: int, size: int, seed: int = 1) -> np.ndarray:
    """``n`` boolean blobs masks ``(size, size)``, seeds ``seed .. seed + n - 1``."""
    from skimage import data

    return np.stack([data.binary_blobs(length=size, blob_size_fraction=0.02, volume_fraction=0.3,
                                       rng=seed + i) for i in range(n)])


def blobs_grey(masks: np.ndarray, seed: int = 0) -> np.ndarray:
    """Grey images from masks: levels 0.25 / 0.75, Gaussian blur sigma 1, noise sd 0.05,
    quantised to k / 255 (so the 8-bit copy OpenCV needs is lossless), float32."""
    from scipy import ndimage as ndi

    rng = np.random.default_rng(seed)
    out = np.empty(masks.shape, np.float32)
    for i, m in enumerate(masks):
        g = ndi.gaussian_filter(0.25 + 0.5 * m.astype(np.float64), 1.0) + rng.normal(0.0, 0.05, m.shape)
        out[i] = np.round(np.clip(g, 0.0, 1.0) * 255.0) / 255.0
    return out


NCC_SOURCES = ("camera", "astronaut", "brick", "coffee", "grass", "rocket", "gravel", "chelsea")


def ncc_inputs(n: int, size: int, tpl: int, seed: int = 0):
    """``n`` grey photographs resized to ``(size, size)`` (bicubic) plus mild noise, and a
    ``tpl x tpl`` template cut from each at a random place with its own noise (float32).
    Returns ``(images, templates, positions)``."""
    import cv2
    from skimage import color, data

    rng = np.random.default_rng(seed)
    imgs = np.empty((n, size, size), np.float32)
    tpls = np.empty((n, tpl, tpl), np.float32)
    pos = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i in range(n):
            im = getattr(data, NCC_SOURCES[i % len(NCC_SOURCES)])()
            im = color.rgb2gray(im[..., :3]) if im.ndim == 3 else im / 255.0
            im = cv2.resize(im.astype(np.float32), (size, size), interpolation=cv2.INTER_CUBIC)
            im = np.clip(im + rng.normal(0.0, 0.01, im.shape), 0.0, 1.0).astype(np.float32)
            r, c = (int(v) for v in rng.integers(0, size - tpl + 1, 2))
            t = im[r:r + tpl, c:c + tpl] + rng.normal(0.0, 0.02, (tpl, tpl))
            imgs[i], tpls[i] = im, t.astype(np.float32)
            pos.append((r, c))
    return imgs, tpls, pos


# --------------------------------------------------------------------------- competitors

@dataclass
class Comp:
    """One way of running one workload."""

    method: str
    run: Callable[[], Any]          # runs the workload once and blocks; returns the result
    kind: str                       # "jax" | "numpy"
    n: int = 1                      # images per call
    lib: str = ""                   # "fsjax" | "SciPy" | "scikit-image" | "OpenCV"
    compile_s: float | None = None
    mem_bytes: int | None = None
    mem_method: str = ""
    note: str = ""
    accuracy: str = ""
    times: Timing | None = None

    @property
    def per_image(self) -> float:
        return self.times.median / self.n


@dataclass
class Result:
    key: str
    comps: list[Comp]
    missing: list[str] = field(default_factory=list)
    load_before: Any = None
    load_after: Any = None
    extra: dict = field(default_factory=dict)


def _jax_comp(method: str, f: Callable, args: tuple, n: int, note: str = "") -> Comp:
    """A jitted fsjax competitor; compile time and XLA memory measured on a fresh jit."""
    import jax

    c_s, compiled = jax_compile(f, *args)
    mem = xla_memory_bytes(compiled)
    jf = jax.jit(f)
    return Comp(method, lambda: jax.block_until_ready(jf(*args)), "jax", n=n, lib="fsjax", compile_s=c_s,
                mem_bytes=None if mem is None else mem["temp"] + mem["output"], mem_method="XLA temp+output",
                note=note)


def _areas_from_labels(lab: np.ndarray) -> np.ndarray:
    return np.bincount(lab.ravel())[1:]


def partition_check(lab: np.ndarray, ref: np.ndarray) -> tuple[bool, bool]:
    """(same partition as ``ref``, identical array). Same partition: the same background
    and a one-to-one correspondence between labels."""
    if lab.shape != ref.shape or not np.array_equal(lab > 0, ref > 0):
        return False, False
    if np.array_equal(lab, ref):
        return True, True
    fg = ref > 0
    a, b = lab[fg].astype(np.int64), ref[fg].astype(np.int64)
    pairs = np.unique(a * (int(b.max()) + 1) + b)
    return len(pairs) == len(np.unique(a)) == len(np.unique(b)), False


def areas_check(count: int, areas: np.ndarray, ref_areas: np.ndarray) -> tuple[bool, str]:
    areas = np.sort(np.asarray(areas)[np.asarray(areas) > 0])
    ref = np.sort(ref_areas)
    if count == len(ref) and len(areas) == len(ref) and np.array_equal(areas, ref):
        return True, f"{count} labels, area multiset identical"
    n_bad = len(np.setxor1d(areas, ref)) if len(areas) != len(ref) else int((areas != ref).sum())
    return False, f"{count} labels (ref {len(ref)}), areas differ ({n_bad} entries)"


# ---- 1. Otsu + labelling + areas

def build_pipeline(grey: np.ndarray, batch: bool) -> tuple[list[Comp], list[str], dict]:
    import cv2
    import jax
    import jax.numpy as jnp
    from scipy import ndimage as ndi
    from skimage import filters, measure

    import fsjax

    g = grey[0]
    comps: list[Comp] = []
    missing: list[str] = []

    def fs_pipe(x):
        lab = fsjax.ops.label(fsjax.ops.otsu(fsjax.Image(x)), connectivity=8, capacity=CAPACITY)
        areas = jax.ops.segment_sum(jnp.ones(lab.data.size, jnp.int32), lab.data.ravel(),
                                    num_segments=CAPACITY + 1)[1:]
        return lab.count, lab.truncated, areas

    def fs_pipe_rs(x):
        lab = fsjax.ops.label(fsjax.ops.otsu(fsjax.Image(x)), connectivity=8, capacity=CAPACITY)
        props = fsjax.ops.region_shape(lab, capacity=CAPACITY, columns=("area",))
        return lab.count, lab.truncated, props["area"]

    xj = jax.device_put(g)
    comps.append(_jax_comp("fsjax otsu+label+segment_sum", fs_pipe, (xj,), 1))
    comps.append(_jax_comp("fsjax otsu+label+region_shape(area)", fs_pipe_rs, (xj,), 1,
                           note="areas from `region_shape(columns=('area',), capacity=2048)`"))
    if batch:
        xb = jax.device_put(grey)
        comps.append(_jax_comp(f"fsjax jit(vmap) batch of {len(grey)}", jax.vmap(fs_pipe), (xb,), len(grey),
                               note="otsu+label+segment_sum; time per image = batch time / batch size"))

    def sp():
        m = g > filters.threshold_otsu(g)
        lab, n = ndi.label(m, structure=S8)
        return n, np.bincount(lab.ravel(), minlength=n + 1)[1:]

    comps.append(Comp("SciPy (skimage otsu, ndi.label, bincount)", sp, "numpy", lib="SciPy",
                      note="SciPy has no Otsu: `skimage.filters.threshold_otsu`; areas by `np.bincount` "
                           "(faster here than `ndi.sum_labels`)"))

    def sk():
        m = g > filters.threshold_otsu(g)
        lab = measure.label(m, connectivity=2)
        return int(lab.max()), np.bincount(lab.ravel())[1:]

    comps.append(Comp("scikit-image (otsu, label, bincount)", sk, "numpy", lib="scikit-image"))

    def sk_rp():
        m = g > filters.threshold_otsu(g)
        lab = measure.label(m, connectivity=2)
        a = measure.regionprops_table(lab, properties=("area",))["area"]
        return len(a), a.astype(np.int64)

    comps.append(Comp("scikit-image (otsu, label, regionprops_table)", sk_rp, "numpy", lib="scikit-image"))

    def cv():
        u8 = cv2.convertScaleAbs(g, alpha=255.0)  # exact: the image holds k / 255
        _, m = cv2.threshold(u8, 0, 1, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
        n, _, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8, ltype=cv2.CV_32S)
        return n - 1, stats[1:, cv2.CC_STAT_AREA]

    comps.append(Comp("OpenCV (uint8, THRESH_OTSU, connectedComponentsWithStats)", cv, "numpy", lib="OpenCV",
                      note="8-bit Otsu (`cv2.threshold`) on the exact uint8 copy; conversion included"))

    # accuracy: reference = the SciPy pipeline on every image
    refs = []
    for k in range(len(grey)):
        m = grey[k] > filters.threshold_otsu(grey[k])
        lab, n = ndi.label(m, structure=S8)
        refs.append((n, _areas_from_labels(lab)))
    extra = {"ref_count": refs[0][0], "otsu_level": float(filters.threshold_otsu(g))}
    for c in comps:
        out = c.run()
        if c.n == 1:
            cnt, *rest = out
            if c.lib == "fsjax":
                cnt, trunc, areas = int(out[0]), bool(out[1]), np.asarray(out[2]).astype(np.int64)
                assert not trunc, "label capacity too small"
            else:
                areas = np.asarray(rest[-1]).astype(np.int64)
            _, txt = areas_check(int(cnt), areas, refs[0][1])
        else:
            cnts, truncs, areas = (np.asarray(v) for v in out)
            assert not truncs.any(), "label capacity too small"
            oks = [areas_check(int(cnts[k]), areas[k].astype(np.int64), refs[k][1])[0] for k in range(c.n)]
            txt = (f"{sum(oks)}/{c.n} images: count and area multiset identical "
                   f"({int(cnts.min())}-{int(cnts.max())} labels)")
        c.accuracy = txt
    return comps, missing, extra


# ---- 2. labelling alone

def build_label(masks: np.ndarray, batch: bool) -> tuple[list[Comp], list[str], dict]:
    import cv2
    import jax
    from scipy import ndimage as ndi
    from skimage import measure

    import fsjax

    m = masks[0]
    m8 = m.view(np.uint8)
    comps: list[Comp] = []

    def fs_label(x):
        lab = fsjax.ops.label(fsjax.Region(x), connectivity=8, capacity=CAPACITY)
        return lab.data, lab.count, lab.truncated

    comps.append(_jax_comp("fsjax label", fs_label, (jax.device_put(m),), 1))
    if batch:
        comps.append(_jax_comp(f"fsjax jit(vmap) batch of {len(masks)}", jax.vmap(fs_label),
                               (jax.device_put(masks),), len(masks),
                               note="time per image = batch time / batch size"))
    comps.append(Comp("SciPy ndi.label", lambda: ndi.label(m, structure=S8)[0], "numpy", lib="SciPy"))
    comps.append(Comp("scikit-image measure.label", lambda: measure.label(m, connectivity=2), "numpy",
                      lib="scikit-image"))
    comps.append(Comp("OpenCV connectedComponents",
                      lambda: cv2.connectedComponents(m8, connectivity=8, ltype=cv2.CV_32S)[1], "numpy",
                      lib="OpenCV", note="default algorithm (Spaghetti / BBDT family), uint8 view of the mask"))
    refs = [ndi.label(mk, structure=S8)[0] for mk in masks]
    for c in comps:
        out = c.run()
        if c.lib == "fsjax":
            labs, cnts, truncs = (np.asarray(v) for v in out)
            assert not truncs.any(), "label capacity too small"
            if c.n == 1:
                labs = labs[None]
        else:
            labs = np.asarray(out)[None]
        res = [partition_check(labs[k], refs[k]) for k in range(len(labs))]
        same = sum(r[0] for r in res)
        ident = sum(r[1] for r in res)
        cnt = int(refs[0].max())
        if c.n == 1:
            c.accuracy = (f"{int(labs[0].max())} labels (SciPy {cnt}); "
                          + ("same array as SciPy" if ident else "same partition, other numbering" if same
                             else "DIFFERENT partition"))
        else:
            c.accuracy = f"{same}/{c.n} same partition as SciPy ({ident}/{c.n} the same array)"
    return comps, [], {"ref_count": int(refs[0].max())}


# ---- 3. EDT

def build_edt(masks: np.ndarray, batch: bool) -> tuple[list[Comp], list[str], dict]:
    import cv2
    import jax
    from scipy import ndimage as ndi

    import fsjax

    m = masks[0]
    m8 = m.view(np.uint8)
    comps: list[Comp] = []

    def fs_edt(x):
        return fsjax.ops.distance_transform(fsjax.Region(x)).data

    comps.append(_jax_comp("fsjax distance_transform", fs_edt, (jax.device_put(m),), 1, note="float32 output"))
    if batch:
        comps.append(_jax_comp(f"fsjax jit(vmap) batch of {len(masks)}", jax.vmap(fs_edt),
                               (jax.device_put(masks),), len(masks),
                               note="time per image = batch time / batch size"))
    comps.append(Comp("SciPy distance_transform_edt", lambda: ndi.distance_transform_edt(m), "numpy", lib="SciPy",
                      note="float64 output"))
    comps.append(Comp("OpenCV distanceTransform(DIST_L2, DIST_MASK_PRECISE)",
                      lambda: cv2.distanceTransform(m8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE), "numpy", lib="OpenCV",
                      note="float32 output"))
    refs = np.stack([ndi.distance_transform_edt(mk) for mk in masks])
    for c in comps:
        out = np.asarray(c.run())
        ref = refs[: c.n] if c.n > 1 else refs[:1]
        out = out.reshape(ref.shape).astype(np.float64)
        d = float(np.abs(out - ref).max())
        d32 = float(np.abs(out - ref.astype(np.float32).astype(np.float64)).max())
        c.accuracy = f"max|diff| {_fmt(d)} (vs SciPy rounded to float32: {_fmt(d32)})"
    return comps, [], {"max_distance": float(refs[0].max())}


# ---- 4. NCC

def build_ncc(imgs: np.ndarray, tpls: np.ndarray, pos: list, batch: bool) -> tuple[list[Comp], list[str], dict]:
    import cv2
    import jax
    from skimage import feature

    import fsjax

    x, t = imgs[0], tpls[0]
    comps: list[Comp] = []

    def fs_ncc(a, b):
        return fsjax.ops.ncc_map(fsjax.Image(a), fsjax.Image(b)).data

    comps.append(_jax_comp("fsjax ncc_map", fs_ncc, (jax.device_put(x), jax.device_put(t)), 1,
                           note="float32; FFT correlation + box sums"))
    if batch:
        comps.append(_jax_comp(f"fsjax jit(vmap) batch of {len(imgs)}", jax.vmap(fs_ncc),
                               (jax.device_put(imgs), jax.device_put(tpls)), len(imgs),
                               note="a different image and template per member; time per image = batch / size"))
    comps.append(Comp("OpenCV matchTemplate(TM_CCOEFF_NORMED)",
                      lambda: cv2.matchTemplate(x, t, cv2.TM_CCOEFF_NORMED), "numpy", lib="OpenCV",
                      note="float32 input"))
    comps.append(Comp("scikit-image match_template", lambda: feature.match_template(x, t), "numpy",
                      lib="scikit-image", note="float32 input; works and returns in float32"))
    refs_cv = np.stack([cv2.matchTemplate(imgs[k], tpls[k], cv2.TM_CCOEFF_NORMED) for k in range(len(imgs))])
    refs_64 = np.stack([feature.match_template(imgs[k].astype(np.float64), tpls[k].astype(np.float64))
                        for k in range(len(imgs))])
    acc64: dict[str, tuple[float, float]] = {}
    textured = np.stack([window_sd(imgs[k], tpls.shape[1], tpls.shape[2]) >= NCC_SD for k in range(len(imgs))])
    for c in comps:
        out = np.asarray(c.run()).astype(np.float64)
        k = c.n if c.n > 1 else 1
        out = out.reshape(refs_cv[:k].shape)
        d_cv = float(np.abs(out - refs_cv[:k]).max())
        d64 = np.abs(out - refs_64[:k])
        d64_tex = float(d64[textured[:k]].max())
        peaks = [np.unravel_index(int(np.argmax(out[j])), out[j].shape) for j in range(k)]
        hit = sum(tuple(int(v) for v in p) == tuple(pos[j]) for j, p in enumerate(peaks))
        acc64[c.method] = (float(d64.max()), d64_tex)
        c.accuracy = (f"max|diff| vs OpenCV {_fmt(d_cv)}; vs float64 {_fmt(float(d64.max()))} "
                      f"(windows with sd >= {NCC_SD:g}: {_fmt(d64_tex)}); peak at the cut position {hit}/{k}")
    return comps, [], {"textured_fraction": float(textured[0].mean()), "acc64": acc64,
                       "sd_min": float(window_sd(imgs[0], tpls.shape[1], tpls.shape[2]).min())}


NCC_SD = 0.05  # window standard deviation (grey levels of [0, 1]) above which a window counts as textured


def window_sd(x: np.ndarray, h: int, w: int) -> np.ndarray:
    """Standard deviation of every ``h x w`` window (top-left anchored, NCC output size), float64."""
    x = x.astype(np.float64)
    c1 = np.pad(x, ((1, 0), (1, 0))).cumsum(0).cumsum(1)
    c2 = np.pad(x * x, ((1, 0), (1, 0))).cumsum(0).cumsum(1)

    def box(c):
        return c[h:, w:] - c[:-h, w:] - c[h:, :-w] + c[:-h, :-w]

    n = h * w
    var = box(c2) / n - (box(c1) / n) ** 2
    return np.sqrt(np.maximum(var, 0.0))


# ---- 5. shape matching

def build_shape() -> tuple[list[Comp], list[str], dict]:
    import jax

    import fsjax

    try:
        from fsjax.synth._workpiece import alignment_scene, workpiece_template
    except ImportError as e:
        return [], [f"fsjax.synth._workpiece not available ({e})"], {}
    if "shape_locate" not in {s.name for s in fsjax.list_ops()}:
        return [], ["fsjax `shape_locate` not registered"], {}
    img, truth = alignment_scene()
    tpl = workpiece_template()

    def fs_shape(a, b):
        m = fsjax.ops.shape_locate(fsjax.Image(a), fsjax.Image(b))
        return m.row, m.col, m.angle_deg, m.score, m.valid, m.truncated

    args = (jax.device_put(img.astype(np.float32)), jax.device_put(tpl.astype(np.float32)))
    c = _jax_comp("fsjax shape_locate", fs_shape, args, 1,
                  note="defaults: full 360 deg, automatic pyramid and angle step, min_score 0.8, float32")
    row, col, ang, score, valid, trunc = (np.asarray(v) for v in c.run())
    errs, aerrs = [], []
    for r, cc, a in truth["poses"]:
        d = np.where(valid, np.hypot(row - r, col - cc), np.inf)
        i = int(np.argmin(d))
        errs.append(float(d[i]))
        aerrs.append(abs(float((ang[i] - a + 180.0) % 360.0 - 180.0)))
    decoys = sum(bool(np.any(valid & (np.hypot(row - r, col - cc) < 20))) for r, cc, _, _ in truth["decoys"])
    c.accuracy = (f"{int(valid.sum())} found (truth 3; decoys matched: {decoys}); max position error "
                  f"{max(errs):.3f} px, max angle error {max(aerrs):.3f} deg")
    comps = [c]
    missing = ["SciPy / scikit-image: no rotation-invariant shape matcher"]
    try:
        import cv2

        u8 = lambda a: np.clip(a * 255.0 + 0.5, 0, 255).astype(np.uint8)  # noqa: E731
        g = cv2.createGeneralizedHoughGuil()
        g.setMinDist(20)
        g.setLevels(360)
        g.setDp(2)
        g.setMinAngle(0)
        g.setMaxAngle(360)
        g.setAngleStep(1)
        g.setMinScale(0.95)  # OpenCV needs minScale < maxScale
        g.setMaxScale(1.05)
        g.setScaleStep(0.05)
        g.setAngleThresh(100)
        g.setScaleThresh(50)
        g.setPosThresh(100)
        g.setCannyLowThresh(30)
        g.setCannyHighThresh(90)
        g.setTemplate(u8(tpl))
        img8 = u8(img)
        cv = Comp("OpenCV GeneralizedHoughGuil", lambda: g.detect(img8), "numpy", lib="OpenCV",
                  note="uint8 input; angle step 1 deg, scales 0.95/1.0/1.05, dp 2, Canny 30/90, "
                       "position threshold 100 (hand-tuned on this scene)")
        det, _ = cv.run()
        det = np.zeros((0, 4)) if det is None else np.asarray(det)[0]
        # OpenCV: (x, y, scale, angle clockwise on screen); fsjax: (row, col, angle counter-clockwise)
        rows, cols, angs = det[:, 1], det[:, 0], -det[:, 3]
        errs, aerrs, used = [], [], set()
        for r, cc, a in truth["poses"]:
            d = np.hypot(rows - r, cols - cc)
            i = int(np.argmin(d)) if len(d) else -1
            if i >= 0 and d[i] < 5:
                used.add(i)
                errs.append(float(d[i]))
                aerrs.append(abs(float((angs[i] - a + 180.0) % 360.0 - 180.0)))
        cv.accuracy = (f"{len(errs)}/3 found within 5 px, {len(det) - len(used)} other detections; "
                       + (f"max position error {max(errs):.2f} px, max angle error {max(aerrs):.2f} deg"
                          if errs else "no instance found"))
        comps.append(cv)
    except (ImportError, AttributeError) as e:
        missing.append(f"OpenCV GeneralizedHoughGuil: {e}")
    return comps, missing, {"scene": f"{img.shape[0]}x{img.shape[1]}", "template": f"{tpl.shape[0]}x{tpl.shape[1]}"}


# --------------------------------------------------------------------------- profiling

def _median_time(f: Callable[[], Any], reps: int = 7) -> float:
    import jax

    jax.block_until_ready(f())
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(f())
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def profile(grey: np.ndarray, masks: np.ndarray, imgs: np.ndarray, tpls: np.ndarray, reps: int) -> dict:
    """Break the fsjax times into parts (medians of ``reps`` calls; not round-robin)."""
    import jax
    import jax.numpy as jnp
    from jax import lax
    from scipy import ndimage as ndi
    from skimage import filters

    import fsjax
    from fsjax.ops.measure2d import _label as L

    out: dict[str, Any] = {}
    g, m = jax.device_put(grey[0]), jax.device_put(masks[0])
    lab = fsjax.ops.label(fsjax.Region(m), capacity=CAPACITY)
    f_otsu = jax.jit(lambda x: fsjax.ops.otsu(fsjax.Image(x)).data)
    f_label = jax.jit(lambda x: fsjax.ops.label(fsjax.Region(x), capacity=CAPACITY).data)
    f_area = jax.jit(lambda a: jax.ops.segment_sum(jnp.ones(a.size, jnp.int32), a.ravel(),
                                                   num_segments=CAPACITY + 1))
    f_rs = jax.jit(lambda lb: fsjax.ops.region_shape(lb, capacity=CAPACITY, columns=("area",))["area"])
    out["fsjax otsu"] = _median_time(lambda: f_otsu(g), reps)
    out["fsjax label"] = _median_time(lambda: f_label(m), reps)
    out["fsjax segment_sum areas"] = _median_time(lambda: f_area(lab.data), reps)
    out["fsjax region_shape(area)"] = _median_time(lambda: f_rs(lab), reps)
    gn = grey[0]
    mn = masks[0]
    out["skimage threshold_otsu"] = _median_time(lambda: filters.threshold_otsu(gn), reps)
    out["SciPy ndi.label"] = _median_time(lambda: ndi.label(mn, structure=S8), reps)
    labn = ndi.label(mn, structure=S8)[0]
    out["np.bincount areas"] = _median_time(lambda: np.bincount(labn.ravel()), reps)

    # labelling: rounds of the union-find loop, and the parts of the program
    rounds = [int(L.label_array(jax.device_put(mk), 8, CAPACITY)[3]) for mk in masks]
    out["label rounds"] = rounds
    f_uf = jax.jit(lambda x: L.components(x, 8).root)
    out["label union-find (block graph + while_loop)"] = _median_time(lambda: f_uf(m), reps)
    out["size"] = S = int(masks.shape[1])
    n = (S // 2) ** 2
    idx = jax.device_put(np.random.default_rng(0).integers(0, n, n).astype(np.int32))
    vals = jax.device_put(np.arange(n, dtype=np.int32))
    f_gather = jax.jit(lambda v, i: v.at[i].get(mode="promise_in_bounds"))
    f_scatter = jax.jit(lambda v, i: v.at[i].min(v[::-1], mode="promise_in_bounds"))
    out["gather, one int32 per 2x2 block (random indices)"] = _median_time(lambda: f_gather(vals, idx), reps)
    out["scatter-min, one int32 per 2x2 block (random indices)"] = _median_time(lambda: f_scatter(vals, idx), reps)

    # EDT: the sequential scans
    f_edt = jax.jit(lambda x: fsjax.ops.distance_transform(fsjax.Region(x)).data)
    out["fsjax distance_transform"] = _median_time(lambda: f_edt(m), reps)

    def scan_rows(x):
        def step(c, b):
            c = jnp.where(b, jnp.zeros_like(c), c + 1)
            return c, c
        return lax.scan(step, jnp.zeros(x.shape[1], jnp.float32), x)[1]

    f_scan = jax.jit(scan_rows)
    out["one trivial lax.scan over the rows"] = _median_time(lambda: f_scan(m), reps)
    try:
        from fsjax.ops.image import _distance as D

        f_line = jax.jit(lambda x: D._line_dist((~x).T, jnp.float32))
        gsq = (f_line(m) ** 2).T
        f_env = jax.jit(lambda a: D._parabola_envelope(a, 1.0))
        out["EDT 1-D pass (two scans)"] = _median_time(lambda: f_line(m), reps)
        out["EDT parabola envelope (two scans with inner while_loops)"] = _median_time(lambda: f_env(gsq), reps)
        out["EDT envelope loop iterations (push, read)"] = envelope_iterations(np.asarray(gsq))
    except (ImportError, AttributeError) as e:  # private helpers renamed: skip the breakdown
        log(f"   EDT breakdown skipped: {e}")

    # NCC: the FFTs
    x, t = jax.device_put(imgs[0]), jax.device_put(tpls[0])
    f_ncc = jax.jit(lambda a, b: fsjax.ops.ncc_map(fsjax.Image(a), fsjax.Image(b)).data)
    out["fsjax ncc_map"] = _median_time(lambda: f_ncc(x, t), reps)
    f_fft = jax.jit(lambda a: jnp.fft.irfft2(jnp.fft.rfft2(a) * jnp.fft.rfft2(a), s=a.shape))
    out["XLA rfft2 x2 + irfft2 at image size, float32"] = _median_time(lambda: f_fft(x), reps)
    xn = imgs[0]
    out["numpy.fft rfft2 x2 + irfft2 at image size"] = _median_time(
        lambda: np.fft.irfft2(np.fft.rfft2(xn) * np.fft.rfft2(xn), s=xn.shape), reps)
    return out


def envelope_iterations(f: np.ndarray) -> tuple[int, int]:
    """Inner-loop iterations of a lane-parallel Felzenszwalb-Huttenlocher envelope on ``f`` ``(n, L)``.

    A NumPy re-enactment of the algorithm (not of fsjax's code): when the lanes
    run in lock-step, the loop that pops the stack after pushing site ``q`` runs
    as often as the lane that pops most at ``q``; likewise the read-out loop at
    each output row. Returns the sums over the ``n`` steps of those maxima
    (push, read).
    """
    n, L = f.shape
    push = np.zeros(n, int)
    read = np.zeros(n, int)
    for lane in range(L):
        col = f[:, lane]
        st: list[int] = []
        z: list[float] = []
        for q in np.flatnonzero(np.isfinite(col)):
            q = int(q)
            pops = 0
            while len(st) > 1:
                k = st[-1]
                s = ((col[q] + q * q) - (col[k] + k * k)) / (2 * (q - k))
                if s > z[-1]:
                    break
                st.pop()
                z.pop()
                pops += 1
            if st:
                k = st[-1]
                z.append(((col[q] + q * q) - (col[k] + k * k)) / (2 * (q - k)))
            else:
                z.append(-np.inf)
            st.append(q)
            push[q] = max(push[q], pops)
        i = len(st) - 1
        for j in range(n - 1, -1, -1):
            moves = 0
            while i > 0 and z[i] > j:
                i -= 1
                moves += 1
            read[j] = max(read[j], moves)
    return int(push.sum()), int(read.sum())


# --------------------------------------------------------------------------- running

def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _fmt(v: float) -> str:
    if v != v:
        return "n/a"
    return "0" if v == 0 else f"{v:.1e}"


def _fmt_load(v: Any) -> str:
    return "n/a" if v is None else ", ".join(f"{x:.1f}" for x in v)


def wait_for_load(max_load: float, max_wait: float) -> None:
    """Wait (at most ``max_wait`` s) until the 1-minute load average is below ``max_load``."""
    if max_load <= 0:
        return
    t0 = time.time()
    while True:
        la = load_average()
        if la is None or la[0] < max_load or time.time() - t0 > max_wait:
            return
        log(f"   load {la[0]:.1f} >= {max_load}; waiting ...")
        time.sleep(20)


def run_workload(key: str, build: Callable[[], tuple], repeats: int, warmup: int, args) -> Result:
    log(f"== {key}: building competitors (compiling fsjax, accuracy checks)")
    comps, missing, extra = build()
    for c in comps:
        if c.kind == "numpy":
            c.mem_bytes = tracemalloc_peak_bytes(c.run)
            c.mem_method = "tracemalloc peak"
    res = Result(key, comps, missing, extra=extra)
    if not comps:
        return res
    wait_for_load(args.max_load, args.max_wait)
    res.load_before = load_average()
    log(f"== {key}: timing {len(comps)} competitors x {repeats} repeats (load {_fmt_load(res.load_before)})")
    timings = time_round_robin({c.method: c.run for c in comps}, repeats=repeats, warmup=warmup)
    for c in comps:
        c.times = timings[c.method]
    res.load_after = load_average()
    print(format_table(res), flush=True)
    return res


def _peer(res: Result, lib: str) -> Comp | None:
    return next((c for c in res.comps if c.lib == lib and c.n == 1 and "regionprops" not in c.method), None)


HEADER = ["method", "images/call", "median s/call [IQR]", "ms per image", "x SciPy", "x OpenCV", "compile s",
          "peak MB", "accuracy"]


def table_rows(res: Result) -> list[list[str]]:
    sp, cv = _peer(res, "SciPy"), _peer(res, "OpenCV")
    rows = []
    for c in res.comps:
        t = c.times
        rows.append([
            c.method, str(c.n), f"{t.median:.4f} [{t.q1:.4f}, {t.q3:.4f}]", f"{1e3 * c.per_image:.2f}",
            f"{c.per_image / sp.per_image:.2f}" if sp else "-",
            f"{c.per_image / cv.per_image:.2f}" if cv else "-",
            f"{c.compile_s:.2f}" if c.compile_s is not None else "-",
            f"{c.mem_bytes / 2**20:.1f}" if c.mem_bytes is not None else "n/a",
            c.accuracy,
        ])
    return rows


def format_table(res: Result) -> str:
    rows = table_rows(res)
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(HEADER)]
    lines = [f"-- {TITLES[res.key]} (load before/after: {_fmt_load(res.load_before)} / "
             f"{_fmt_load(res.load_after)})"]
    lines.append("  ".join(h.ljust(w) for h, w in zip(HEADER, widths, strict=True)))
    lines += ["  ".join(v.ljust(w) for v, w in zip(r, widths, strict=True)) for r in rows]
    return "\n".join(lines)


def markdown_table(res: Result) -> str:
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    lines += ["| " + " | ".join(r) + " |" for r in table_rows(res)]
    return "\n".join(lines)


def goal_rows(results: list[Result]) -> list[dict]:
    rows = []
    for r in results:
        if r.key not in GOALS or not r.comps:
            continue
        lib, limit = GOALS[r.key]
        peer = _peer(r, lib)
        single = next((c for c in r.comps if c.lib == "fsjax" and c.n == 1), None)
        bat = next((c for c in r.comps if c.lib == "fsjax" and c.n > 1), None)
        if peer is None or single is None:
            continue
        row = {"key": r.key, "peer": peer.method, "lib": lib, "limit": limit, "peer_ms": 1e3 * peer.per_image,
               "single_ms": 1e3 * single.per_image, "single_x": single.per_image / peer.per_image,
               "single_lo": single.times.q1 / peer.times.q3, "single_hi": single.times.q3 / peer.times.q1}
        if bat is not None:
            row["batch_ms"] = 1e3 * bat.per_image
            row["batch_x"] = bat.per_image / peer.per_image
        rows.append(row)
    return rows


def goals_markdown(results: list[Result]) -> list[str]:
    L = ["| workload | goal | peer ms | fsjax single ms (ratio) | ratio range from IQRs | single | "
         "fsjax batched ms/image (ratio) | batched |",
         "|---|---|---|---|---|---|---|---|"]
    for g in goal_rows(results):
        ok1 = "**reached**" if g["single_x"] <= g["limit"] else "**not reached**"
        b = (f"{g['batch_ms']:.1f} (x{g['batch_x']:.2f})", "**reached**" if g["batch_x"] <= g["limit"]
             else "**not reached**") if "batch_ms" in g else ("-", "-")
        L.append(f"| {TITLES[g['key']].split(',')[0]} | <= {g['limit']:g}x {g['lib']} | {g['peer_ms']:.1f} | "
                 f"{g['single_ms']:.1f} (x{g['single_x']:.2f}) | {g['single_lo']:.2f}-{g['single_hi']:.2f} | "
                 f"{ok1} | {b[0]} | {b[1]} |")
    return L


def goals_text(results: list[Result]) -> str:
    out = []
    for g in goal_rows(results):
        s = (f"{g['key']}: fsjax {g['single_ms']:.1f} ms vs {g['lib']} {g['peer_ms']:.1f} ms = "
             f"x{g['single_x']:.2f} (limit x{g['limit']:g}) -> {'reached' if g['single_x'] <= g['limit'] else 'NOT reached'}")
        if "batch_ms" in g:
            s += (f"; batched {g['batch_ms']:.1f} ms/image = x{g['batch_x']:.2f} -> "
                  f"{'reached' if g['batch_x'] <= g['limit'] else 'NOT reached'}")
        out.append(s)
    return "\n".join(out)


def plot(res: Result, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    comps = res.comps
    colors = {"fsjax": "#1f77b4", "SciPy": "#2ca02c", "scikit-image": "#ff7f0e", "OpenCV": "#d62728"}
    fig, ax = plt.subplots(figsize=(7.6, 0.55 * len(comps) + 1.6), dpi=110)
    y = np.arange(len(comps))[::-1]
    for yi, c in zip(y, comps, strict=True):
        med, q1, q3 = (1e3 * v / c.n for v in (c.times.median, c.times.q1, c.times.q3))
        ax.barh(yi, med, color=colors.get(c.lib, "grey"), alpha=0.85)
        ax.errorbar([med], [yi], xerr=[[med - q1], [q3 - med]], color="k", capsize=3, lw=1)
        ax.text(max(q3, med) * 1.12, yi, f"{med:.1f} ms", va="center", fontsize=8)
    ax.set_yticks(y)
    ax.set_yticklabels([c.method if len(c.method) < 46 else c.method[:44] + "..." for c in comps], fontsize=7)
    ax.set_xscale("log")
    ax.set_xlabel("ms per image (median of round-robin repeats, IQR bars; log)")
    if res.key in GOALS:
        lib, limit = GOALS[res.key]
        peer = _peer(res, lib)
        if peer is not None:
            ax.axvline(1e3 * peer.per_image * limit, color="k", ls="--", lw=1)
            ax.text(1e3 * peer.per_image * limit, y[-1] - 0.6, f" goal: {limit:g}x {lib}", fontsize=7)
    lo = min(1e3 * c.times.q1 / c.n for c in comps)
    hi = max(1e3 * c.times.q3 / c.n for c in comps)
    ax.set_xlim(lo / 2, hi * 3)
    ax.set_ylim(-1, len(comps))
    ax.set_title(TITLES[res.key], fontsize=9)
    ax.grid(True, axis="x", which="major", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def versions() -> dict[str, str]:
    out = {}
    for mod, label in [("fsjax", "fsjax"), ("jax", "jax"), ("jaxlib", "jaxlib"), ("numpy", "numpy"),
                       ("scipy", "SciPy"), ("cv2", "OpenCV"), ("skimage", "scikit-image")]:
        try:
            out[label] = getattr(importlib.import_module(mod), "__version__", "?")
        except ImportError as e:
            out[label] = f"not installed ({e.__class__.__name__})"
    return out


def git_state() -> str:
    import subprocess

    try:
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--", "fsjax"],
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + (" + uncommitted changes in fsjax/ (" + ", ".join(
        ln[3:] for ln in dirty.splitlines()) + ")" if dirty else "")


# --------------------------------------------------------------------------- docs

def write_docs(results: list[Result], prof: dict | None, args, meta: dict) -> None:
    docs = ROOT / "docs"
    figs = docs / "figures"
    figs.mkdir(parents=True, exist_ok=True)
    for r in results:
        if r.comps:
            plot(r, figs / f"bench_insp_{r.key}.png")
    by = {r.key: r for r in results}
    mi, v = meta["machine"], meta["versions"]
    L: list[str] = []
    L += ["# Benchmarks: 2-D inspection", ""]
    L.append("Generated by `python benchmarks/bench_inspection.py --write-docs` "
             f"({'quick run' if args.quick else 'full run'}, {meta['date']}, fsjax at {meta['git']}). "
             "Do not edit by hand. Timing method and harness: `benchmarks/_harness.py` "
             "(see also [the filters benchmark](benchmarks.md)).")
    L += ["", "## Goals (issue 3)", ""]
    L.append("fsjax time per image divided by the peer's, for one image through `jax.jit(op)` and per image of "
             f"a `jax.jit(jax.vmap(op))` batch of {args.batch}. The goal for labelling is read both for the "
             "whole Otsu + labelling + areas workload and for labelling alone. The ratio range divides fsjax's "
             "quartiles by the peer's opposite quartiles (Q1/Q3 to Q3/Q1): where it straddles the limit, "
             "the verdict is within the noise of this shared machine.")
    L.append("")
    L += goals_markdown(results)
    L.append("")
    L += ["## Machine and libraries", ""]
    L.append(f"* CPU: {mi.get('cpu', '?')}, {mi.get('cores', '?')} cores, no GPU; memory {mi.get('memory', '?')}; "
             f"{mi.get('os', '')}; Python {mi.get('python', '')}.")
    L.append("* The machine is **shared** with other developers' test runs. Load average (1, 5, 15 min) at the "
             f"start: {_fmt_load(meta['load_start'])}, at the end: {_fmt_load(meta['load_end'])}; per workload "
             "in the table headings below (2 cores: a load above 2 means other work competed for the CPU, "
             "so absolute times are inflated and noisy; the round-robin order spreads that over all competitors "
             "alike, which keeps the ratios meaningful).")
    L.append("* Versions: " + ", ".join(f"{k} {val}" for k, val in v.items()) + ".")
    L.append(f"* Threads: OpenCV {meta['cv_threads']} threads; XLA CPU (default intra-op threading); "
             f"XLA_FLAGS {os.environ.get('XLA_FLAGS', '(unset)')}. SciPy and scikit-image are single-threaded. "
             "fsjax runs in float32 (JAX's default; x64 off).")
    L += ["", "## Workloads and inputs", ""]
    pr = by.get("pipeline")
    L.append(f"* **Blobs images** (pipeline, labelling, EDT): `skimage.data.binary_blobs(length={args.size}, "
             f"blob_size_fraction=0.02, volume_fraction=0.3, rng=1..{args.batch})`; image 1 is the single image, "
             f"all {args.batch} the batch. For the pipeline each mask becomes a grey image: 0.25 / 0.75, Gaussian blur sigma 1, "
             "Gaussian noise sd 0.05, clipped and quantised to k/255 (float32), so OpenCV's uint8 copy is exact"
             + (f"; Otsu level {pr.extra['otsu_level']:.4f}, {pr.extra['ref_count']} components in image 1"
                if pr and pr.extra else "") + ". Labelling and EDT take the binary mask itself.")
    L.append(f"* **Pipeline**: Otsu (256 bins) -> `x > level` -> 8-connected labels -> area of every label. "
             f"fsjax: `otsu` -> `label(connectivity=8, capacity={CAPACITY})` -> `jax.ops.segment_sum` of ones "
             "(also with `region_shape(columns=('area',))`); SciPy: `skimage.filters.threshold_otsu` (SciPy has "
             "no Otsu) -> `ndimage.label(structure=ones((3,3)))` -> `np.bincount`; scikit-image: the same with "
             "`measure.label(connectivity=2)`, also with `regionprops_table(properties=('area',))`; OpenCV: "
             "`convertScaleAbs` to uint8 -> `threshold(THRESH_OTSU)` -> `connectedComponentsWithStats("
             "connectivity=8)`. Accuracy: label count and the sorted multiset of areas against the SciPy "
             "pipeline.")
    L.append("* **Labelling alone**: the same bool mask; `ndimage.label`, `measure.label`, "
             "`cv2.connectedComponents(connectivity=8, CV_32S)`. Accuracy: same partition as SciPy (same "
             "background, one-to-one label correspondence), and whether the array is identical (same numbering).")
    L.append("* **EDT**: distance of each foreground pixel to the nearest background pixel. "
             "`scipy.ndimage.distance_transform_edt` (float64), `cv2.distanceTransform(DIST_L2, "
             "DIST_MASK_PRECISE)` (float32), `fsjax.ops.distance_transform` (float32). Accuracy: max |diff| "
             "against SciPy, and against SciPy's result rounded to float32 (0 means correctly rounded).")
    L.append(f"* **NCC**: {args.batch} `skimage.data` photographs ({', '.join(NCC_SOURCES[:args.batch])}; grey), "
             f"resized to {args.size}x{args.size} (bicubic) + noise sd 0.01; each with a {TPL}x{TPL} template "
             "cut at a random place + noise sd 0.02. `cv2.matchTemplate(TM_CCOEFF_NORMED)`, "
             "`skimage.feature.match_template` and `fsjax.ops.ncc_map`, all on the float32 arrays; output "
             f"{args.size - TPL + 1}x{args.size - TPL + 1}. Accuracy: max |diff| against OpenCV and against a "
             "float64 reference (scikit-image on float64 copies), and whether the maximum sits where the "
             "template was cut.")
    L.append("* **Shape matching**: `fsjax.synth._workpiece.alignment_scene()` (240x320, three rotated "
             "workpieces at sub-pixel poses, two decoys, textured background, illumination gradient) and "
             "`workpiece_template()` (56x72), `shape_locate` with its defaults (all angles). Accuracy against the "
             "scene's exact poses. SciPy and scikit-image have no rotation-invariant shape matcher; OpenCV's "
             "`GeneralizedHoughGuil` (generalized Hough transform on Canny edges, rotation and scale) is shown "
             "for scale: a different method, with results quantised to its accumulator (`dp` 2 px, 1 deg) and "
             "thresholds hand-tuned on this scene (a lower position threshold adds false detections).")
    L += ["", "## Method", ""]
    L.append("* One process; every competitor is a zero-argument callable that runs the workload on the same "
             "inputs and waits for the result (`jax.block_until_ready` for JAX; the JAX inputs are already "
             "device arrays). fsjax functions are `jax.jit`-compiled once; the batched row is "
             f"`jax.jit(jax.vmap(f))` over {args.batch} different images, its time divided by {args.batch}.")
    L.append(f"* Timing (`_harness.time_round_robin`): {args.warmup} untimed warm-up calls per competitor, then "
             f"{args.repeats} repeats **round-robin** (repeat r runs every competitor once, starting at a rotated "
             "position); GC off during a timed call; `time.perf_counter`. Tables give the median and the "
             "inter-quartile range per call, ms per image, and ratios of per-image medians to SciPy's and "
             "OpenCV's single-image rows.")
    L.append("* Compile time (fsjax only): `jax.jit(f).lower(x).compile()` on a fresh jit object, trace + lower + "
             "XLA compile, not included in the steady-state times.")
    L.append("* Peak MB, only comparable within a method: fsjax - XLA `memory_analysis()` temp + output bytes; "
             "numpy libraries - `tracemalloc` peak of one call (numpy arrays incl. outputs; misses scratch memory "
             "C/C++ code mallocs itself, which is large for OpenCV's and SciPy's internals).")
    L.append("* Accuracy is checked on every image the competitor processes (all 8 for the batched rows), "
             "before timing.")
    L += ["", "## Results", ""]
    for r in results:
        L += [f"### {TITLES[r.key]}", ""]
        L.append(f"Load average before / after timing: {_fmt_load(r.load_before)} / {_fmt_load(r.load_after)}.")
        L.append("")
        if r.comps:
            L += [markdown_table(r), ""]
            notes = [f"* {c.method}: {c.note}" for c in r.comps if c.note]
            if notes:
                L += notes + [""]
            L += [f"![{TITLES[r.key]}](figures/bench_insp_{r.key}.png)", ""]
        for m in r.missing:
            L.append(f"Not run: {m}.")
        if r.missing:
            L.append("")
    if prof:
        L += analysis(prof, results)
    (docs / "benchmarks_inspection.md").write_text("\n".join(L).rstrip() + "\n")
    log(f"wrote {docs / 'benchmarks_inspection.md'} and figures/bench_insp_*.png")


def _span(v: list[int]) -> str:
    return str(min(v)) if min(v) == max(v) else f"{min(v)}-{max(v)}"


def ncc_accuracy_note(r: Result | None) -> str:
    """A sentence on float32 accuracy of the NCC rows against float64, from the measured numbers."""
    if r is None or not r.extra.get("acc64"):
        return ""
    acc = {m: v for m, v in r.extra["acc64"].items()
           if not any(c.method == m and c.n > 1 for c in r.comps)}
    parts = [f"{m.split(' ')[0]} {_fmt(a)} overall, {_fmt(t)} on windows with sd >= {NCC_SD:g}"
             for m, (a, t) in acc.items()]
    return (" Accuracy against float64 (max |diff|): " + "; ".join(parts)
            + f" (such windows are {100 * r.extra['textured_fraction']:.0f} % of image 1). The errors of all three "
            "grow as the window's standard deviation falls, since the score divides by it and the float32 "
            "round-off of the sums does not shrink with it (the noise added to the inputs keeps every window's "
            f"sd above {r.extra['sd_min']:.4f} in image 1). scikit-image computes in float32 for a float32 input (its output is float32) "
            "and loses most.")


def analysis(p: dict, results: list[Result]) -> list[str]:
    """The 'where the time goes' section, with the numbers measured by ``profile``."""
    ms = {k: 1e3 * v for k, v in p.items() if isinstance(v, float)}
    S = p["size"]
    by = {r.key: r for r in results}
    st = {g["key"]: "goal reached" if g["single_x"] <= g["limit"] else "goal not reached"
          for g in goal_rows(results)}
    L = ["## Where the time goes (profile)", ""]
    L.append("Medians of back-to-back calls of each part, jitted separately, after the timed runs (so the parts "
             "need not add up exactly to the rows above, and they carry the same machine load).")
    L.append("")
    L.append("| part | ms |")
    L.append("|---|---|")
    for k, val in ms.items():
        L.append(f"| {k} | {val:.2f} |")
    rounds = p["label rounds"]
    L.append(f"| label: union-find rounds on the {len(rounds)} blobs masks | {', '.join(str(v) for v in rounds)} |")
    it = p.get("EDT envelope loop iterations (push, read)")
    if it:
        L.append(f"| EDT envelope: inner while-loop iterations (push, read; lanes in lock-step) | {it[0]}, {it[1]} |")
    L.append("")
    n_nodes = (S // 2) ** 2
    uf = ms.get("label union-find (block graph + while_loop)", float("nan"))
    per_round = uf / (max(rounds) + 1)
    gs = 3 * ms["gather, one int32 per 2x2 block (random indices)"] + ms["scatter-min, one int32 per 2x2 block (random indices)"]
    L.append(
        f"* **Labelling** ({st.get('label', 'no goal row')}). `fsjax.ops.label` is exact and data-parallel: the 2x2 blocks of the "
        f"image are the nodes of a graph ({n_nodes} nodes at {S}x{S}) and a Shiloach-Vishkin union-find "
        f"runs in a `lax.while_loop` to its fixed point ({_span(rounds)} rounds here plus the round "
        "that detects it). Every round touches every node, whatever the number of components: a neighbour "
        "minimum over 8 directions, one scatter-min and three gathers. The block graph plus the loop take "
        f"{uf:.1f} ms, about {per_round:.1f} ms per round, which is what one scatter-min and three gathers "
        f"over all nodes cost when measured alone on random indices ({gs:.1f} ms). The rest of `label` "
        f"({ms['fsjax label'] - uf:.1f} ms) is the exact raster-order ranking (which makes the labels "
        "identical to SciPy's) and the scatter of the labels back to pixels. SciPy, scikit-image and OpenCV "
        "label in one or two sequential raster passes with a small equivalence table, touching each pixel a "
        "couple of times: SciPy's whole labelling "
        f"({ms['SciPy ndi.label']:.1f} ms) costs as much as {ms['SciPy ndi.label'] / per_round:.1f} of fsjax's "
        "rounds. Getting within "
        "2x of SciPy on this CPU would need fewer rounds and cheaper ones at once (an untested idea: label "
        "small tiles locally first, then run the union-find on tile borders only).")
    L.append(
        f"* **Pipeline**: fsjax's Otsu costs {ms['fsjax otsu']:.1f} ms (scikit-image's "
        f"`threshold_otsu` {ms['skimage threshold_otsu']:.1f} ms), areas by `segment_sum` "
        f"{ms['fsjax segment_sum areas']:.1f} ms (numpy `bincount` {ms['np.bincount areas']:.1f} ms); "
        f"`region_shape(columns=('area',))` costs {ms['fsjax region_shape(area)']:.1f} ms at capacity "
        f"{CAPACITY}. So the pipeline's gap to SciPy is the labelling's gap, diluted by the two parts that are "
        "about as fast as SciPy's.")
    if "EDT parabola envelope (two scans with inner while_loops)" in ms and it:
        env = ms["EDT parabola envelope (two scans with inner while_loops)"]
        steps = 2 * S + it[0] + it[1]
        L.append(
            f"* **EDT** ({st.get('edt', 'no goal row')}): `distance_transform` ({ms['fsjax distance_transform']:.1f} ms) is "
            f"Felzenszwalb-Huttenlocher with the {S} lanes of one axis in lock-step. The 1-D pass (a "
            f"forward and a backward `lax.scan`) costs {ms['EDT 1-D pass (two scans)']:.1f} ms; the lower "
            f"envelope of parabolas {env:.1f} ms. The envelope is sequential along the other axis: a `lax.scan` "
            "that pushes each site, with an inner `while_loop` that pops the stack for as long as *any* lane "
            "still pops, and a read-out scan with a similar loop. That is "
            f"{2 * S} scan steps plus {it[0] + it[1]} inner iterations (counted by a NumPy re-enactment of "
            f"the lock-step algorithm), about {1e3 * env / steps:.0f} us per dependent step of {S}-lane "
            f"vector work. A trivial {S}-step `lax.scan` costs only "
            f"{ms['one trivial lax.scan over the rows']:.2f} ms, so the time is in the body of each step "
            "(several small kernels, including gathers from the stack arrays of all lanes), not in the loop "
            "machinery; the number of dependent steps is what a lane-parallel formulation cannot shorten. "
            "SciPy runs the same O(n) algorithm line by line in C.")
    r = by.get("ncc")
    L.append(
        f"* **NCC** ({st.get('ncc', 'no goal row')} on one image): `ncc_map` ({ms['fsjax ncc_map']:.1f} ms in the profile) is one "
        "FFT cross-correlation at the image size plus box sums of the window energies; the three FFTs alone "
        f"(two `rfft2` + one `irfft2` at {S}x{S}, XLA) cost {ms['XLA rfft2 x2 + irfft2 at image size, float32']:.1f} "
        f"ms (numpy.fft: {ms['numpy.fft rfft2 x2 + irfft2 at image size']:.1f} ms). OpenCV's `matchTemplate` "
        "correlates with a blocked DFT sized to the template and uses both cores." + ncc_accuracy_note(r))
    bat = []
    for key in ("pipeline", "label", "edt", "ncc"):
        rr = by.get(key)
        if not rr or not rr.comps:
            continue
        s1 = next((c for c in rr.comps if c.lib == "fsjax" and c.n == 1), None)
        sb = next((c for c in rr.comps if c.lib == "fsjax" and c.n > 1), None)
        if s1 and sb:
            bat.append(f"{key} {1e3 * sb.per_image:.1f} vs {1e3 * s1.per_image:.1f} ms")
    if bat:
        L.append(
            "* **Batching** (`jit(vmap)`, per image vs single image: " + "; ".join(bat) + f"). At {S}x{S} "
            "a batch amortises nothing that matters (one call's dispatch is negligible next to its work), "
            "while the batched programs stream batch-size times larger intermediates through the caches (see the peak MB "
            "column) and their data-dependent loops (union-find rounds, envelope pops) run until the slowest "
            "member is done: the lock-step envelope of 8 images pops as long as any of its lanes pops.")
    L.append("")
    return L


# --------------------------------------------------------------------------- main

def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="smoke run: 512x512, batch 2, 3 repeats, 1 warm-up")
    p.add_argument("--size", type=int, default=None, help=f"image side (default {SIZE}; 512 with --quick)")
    p.add_argument("--batch", type=int, default=None, help=f"batch for the vmap rows (default {BATCH}; 2 quick)")
    p.add_argument("--repeats", type=int, default=None, help="timed repeats (default 15; 3 with --quick)")
    p.add_argument("--warmup", type=int, default=None, help="untimed calls per competitor (default 2; 1 quick)")
    p.add_argument("--workloads", default=",".join(WORKLOADS), help="comma-separated subset of "
                   + ",".join(WORKLOADS))
    p.add_argument("--no-batch", action="store_true", help="skip the jit(vmap) batch rows")
    p.add_argument("--no-profile", action="store_true", help="skip the profile section")
    p.add_argument("--max-load", type=float, default=0.0,
                   help="before timing each workload, wait until the 1-min load is below this (0: don't wait)")
    p.add_argument("--max-wait", type=float, default=600.0, help="longest wait for --max-load, s")
    p.add_argument("--write-docs", action="store_true",
                   help="write docs/benchmarks_inspection.md and docs/figures/bench_insp_*.png")
    args = p.parse_args(argv)
    args.size = args.size or (512 if args.quick else SIZE)
    args.batch = args.batch or (2 if args.quick else BATCH)
    args.repeats = args.repeats or (3 if args.quick else 15)
    args.warmup = args.warmup if args.warmup is not None else (1 if args.quick else 2)
    wl = [w.strip() for w in args.workloads.split(",") if w.strip()]
    for w in wl:
        if w not in WORKLOADS:
            p.error(f"unknown workload {w!r}; choose from {', '.join(WORKLOADS)}")
    if args.size != SIZE:
        for k in ("pipeline", "label", "edt"):
            TITLES[k] = TITLES[k].replace("1024x1024", f"{args.size}x{args.size}")
        TITLES["ncc"] = TITLES["ncc"].replace("1024x1024", f"{args.size}x{args.size}")
    import cv2

    meta: dict[str, Any] = {"date": time.strftime("%Y-%m-%d %H:%M %Z"), "machine": machine_info(),
                            "versions": versions(), "load_start": load_average(), "git": git_state(),
                            "cv_threads": cv2.getNumThreads()}
    log(f"machine: {meta['machine']}\nversions: {meta['versions']}\nload: {meta['load_start']}\n"
        f"fsjax: {meta['git']}")
    batch = not args.no_batch
    masks = blobs_masks(args.batch, args.size)
    grey = blobs_grey(masks)
    imgs, tpls, pos = ncc_inputs(args.batch, args.size, TPL)
    builders = {
        "pipeline": lambda: build_pipeline(grey, batch),
        "label": lambda: build_label(masks, batch),
        "edt": lambda: build_edt(masks, batch),
        "ncc": lambda: build_ncc(imgs, tpls, pos, batch),
        "shape": build_shape,
    }
    results = [run_workload(w, builders[w], args.repeats, args.warmup, args) for w in wl]
    prof = None
    if not args.no_profile and {"pipeline", "label", "edt", "ncc"} <= set(wl):
        log("== profile")
        prof = profile(grey, masks, imgs, tpls, reps=3 if args.quick else 7)
        for k, val in prof.items():
            print(f"  {k}: {1e3 * val:.2f} ms" if isinstance(val, float) else f"  {k}: {val}")
    meta["load_end"] = load_average()
    print()
    for r in results:
        if r.comps:
            print(format_table(r))
        for m in r.missing:
            print(f"not run: {r.key}: {m}")
    print()
    print("Goals:\n" + goals_text(results))
    if args.write_docs:
        write_docs(results, prof, args, meta)
    return 0


if __name__ == "__main__":
    sys.exit(main())
