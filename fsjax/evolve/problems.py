"""Search problems: synthetic scenes with exact ground truth, and user input/target pairs.

A :class:`Problem` holds three disjoint splits (``train`` for selection,
``holdout`` tracked during the run but never used for selection, ``locked``
scored once at the end), the per-image metric (higher is better), the sort the
pipeline must produce, a default skeleton, the hand-written pipeline and the
"identity" null.

Synthetic problems (:func:`make_problem`) draw image ``i`` of a split from
``numpy.random.default_rng((problem, split, seed, i))``: deterministic, and the
three splits come from disjoint seed streams (a test checks that no image
repeats across splits). Images are ``(H, W)`` float in ``[0, 1]``; pixel
centres on integer indices; shapes are sampled at pixel centres, so the truth
is exact (no anti-aliasing).

============ ============================================ =============== =====================
problem      scene                                        target          metric (per image)
============ ============================================ =============== =====================
``denoise``  discs and rectangles on a smooth ramp,        clean image     PSNR, dB (peak 1)
             Gaussian noise sd 0.1 (clipped to [0, 1])
``binarize`` bright discs/ellipses under an illumination   object mask     IoU
             ramp, noise sd 0.06
``edges``    piecewise-constant discs and rectangles,      label borders   F1, 1 px tolerance
             blur sd 1 px, noise sd 0.04
``count``    1-9 separated discs 0.3 above a ramp           number of discs 1 / (1 + abs error)
             (0.1-0.6), noise sd 0.08
============ ============================================ =============== =====================

"identity" null per problem: ``denoise``: the noisy input itself; the other
problems need a ``Region``, so the null is the fixed global threshold at 0.5
(``threshold`` with ``lo = 0.5``), followed by ``count_obj`` for ``count``.
"""

from __future__ import annotations

import dataclasses
import zlib
from collections.abc import Callable, Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np
from scipy import ndimage as ndi

from ..types import Feature, Image, Region
from .genome import Skeleton, type_skeleton

__all__ = ["Split", "Problem", "make_problem", "problem_from_pairs", "PROBLEMS", "METRICS", "METRIC_FLOOR"]

PROBLEMS = ("denoise", "binarize", "edges", "count")


# ---------------------------------------------------------------------------
# metrics (per image, JAX, higher is better)
# ---------------------------------------------------------------------------


def psnr(pred, target):
    """PSNR in dB for peak value 1: ``10 log10(1 / mse)``; capped at 100 dB for an exact match."""
    mse = jnp.mean((pred - target) ** 2)
    safe = jnp.where(mse > 1e-10, mse, 1.0)
    return jnp.where(mse > 1e-10, -10.0 * jnp.log10(safe), 100.0)


def iou(pred, target):
    """Intersection over union of two masks; 1 when both are empty."""
    pred, target = pred.astype(bool), target.astype(bool)
    inter = jnp.sum(pred & target)
    union = jnp.sum(pred | target)
    return jnp.where(union > 0, inter / jnp.where(union > 0, union, 1), 1.0).astype(jnp.result_type(float))


def _dilate3(m):
    p = jnp.pad(m, 1)
    h, w = m.shape
    out = m
    for dr in range(3):
        for dc in range(3):
            out = out | p[dr:dr + h, dc:dc + w]
    return out


def f1_tol1(pred, target):
    """F1 of edge masks with a 1-pixel (3 x 3) matching tolerance.

    precision = predicted pixels within 1 px of a true edge / predicted pixels;
    recall = true pixels within 1 px of a predicted edge / true pixels; F1 = 2PR / (P + R)
    (0 when either is 0; 1 when both masks are empty).
    """
    pred, target = pred.astype(bool), target.astype(bool)
    npred, ntrue = jnp.sum(pred), jnp.sum(target)
    tp_p = jnp.sum(pred & _dilate3(target))
    tp_r = jnp.sum(target & _dilate3(pred))
    p = jnp.where(npred > 0, tp_p / jnp.where(npred > 0, npred, 1), 0.0)
    r = jnp.where(ntrue > 0, tp_r / jnp.where(ntrue > 0, ntrue, 1), 0.0)
    s = p + r
    f = jnp.where(s > 0, 2 * p * r / jnp.where(s > 0, s, 1.0), 0.0)
    return jnp.where((npred == 0) & (ntrue == 0), 1.0, f).astype(jnp.result_type(float))


def count_score(pred, target):
    """``1 / (1 + |pred - target|)`` for a predicted count."""
    return 1.0 / (1.0 + jnp.abs(pred - target))


METRICS: dict[str, Callable] = {"psnr": psnr, "iou": iou, "f1": f1_tol1, "count": count_score}
#: Fitness of a non-finite result, per metric (the worst value).
METRIC_FLOOR: dict[str, float] = {"psnr": 0.0, "iou": 0.0, "f1": 0.0, "count": 0.0}
_METRIC_GIVES: dict[str, type] = {"psnr": Image, "iou": Region, "f1": Region, "count": Feature}


# ---------------------------------------------------------------------------
# problem records
# ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Split:
    """Inputs ``(N, H, W)`` float and targets (``(N, H, W)`` or ``(N,)``) of one split."""

    inputs: np.ndarray
    targets: np.ndarray

    def __len__(self) -> int:
        return int(self.inputs.shape[0])


@dataclasses.dataclass(frozen=True)
class Problem:
    """A search problem (see the module docstring)."""

    name: str
    metric: str
    gives: type
    train: Split
    holdout: Split
    locked: Split
    hand: tuple[Any, ...]  # fsjax.pipeline stages
    null: tuple[Any, ...]  # "identity" baseline stages (empty: the input itself)
    single_sorts: tuple[type, ...]  # skeleton of the best-single-op baseline
    default_sorts: tuple[type, ...]  # default search skeleton

    @property
    def metric_fn(self) -> Callable:
        return METRICS[self.metric]

    @property
    def floor(self) -> float:
        return METRIC_FLOOR[self.metric]

    def skeleton(self, vocabulary: Sequence[str] | None = None, sorts: Sequence[type] | None = None) -> Skeleton:
        return type_skeleton(self.default_sorts if sorts is None else sorts, vocabulary)

    def split(self, name: str) -> Split:
        if name not in ("train", "holdout", "locked"):
            raise ValueError(f"Problem.split: unknown split {name!r}; use 'train', 'holdout' or 'locked'")
        return getattr(self, name)


def _sorts_for(gives: type, n_stages: int) -> tuple[type, ...]:
    """Default skeleton: Image stages, then Region stages (and a final count stage)."""
    if gives is Image:
        return (Image,) * (n_stages + 1)
    if gives is Region:
        n_img = max(1, (n_stages - 1) // 2 + (n_stages - 1) % 2)
        return (Image,) * (n_img + 1) + (Region,) * (n_stages - n_img)
    n_img = max(1, (n_stages - 1) // 2)
    return (Image,) * (n_img + 1) + (Region,) * (n_stages - n_img - 1) + (Feature,)


# ---------------------------------------------------------------------------
# synthetic scenes
# ---------------------------------------------------------------------------


def _rng(problem: str, split: str, seed: int, i: int) -> np.random.Generator:
    return np.random.default_rng([zlib.crc32(problem.encode()), zlib.crc32(split.encode()), seed, i])


def _ramp(rng, h, w, lo, hi):
    rr, cc = np.mgrid[0:h, 0:w] / max(h, w)
    ang = rng.uniform(0, 2 * np.pi)
    t = np.cos(ang) * rr + np.sin(ang) * cc
    t = (t - t.min()) / max(t.max() - t.min(), 1e-12)
    return lo + (hi - lo) * t


def _shapes(rng, h, w, n):
    """Label image with ``n`` random discs/rectangles (later shapes on top)."""
    lab = np.zeros((h, w), np.int32)
    rr, cc = np.mgrid[0:h, 0:w]
    for k in range(1, n + 1):
        if rng.uniform() < 0.5:
            r0, c0 = rng.uniform(0.15, 0.85, 2) * (h, w)
            rad = rng.uniform(0.08, 0.2) * min(h, w)
            m = (rr - r0) ** 2 + (cc - c0) ** 2 <= rad**2
        else:
            r0, c0 = rng.integers(0, h - 6), rng.integers(0, w - 6)
            m = (rr >= r0) & (rr < r0 + rng.integers(5, h // 2)) & (cc >= c0) & (cc < c0 + rng.integers(5, w // 2))
        lab[m] = k
    return lab


def _denoise(rng, h, w):
    lab = _shapes(rng, h, w, rng.integers(3, 7))
    levels = rng.uniform(0.15, 0.85, lab.max() + 1)
    clean = np.where(lab > 0, levels[lab], _ramp(rng, h, w, 0.25, 0.6))
    noisy = np.clip(clean + rng.normal(0, 0.1, (h, w)), 0.0, 1.0)
    return noisy, clean


def _binarize(rng, h, w):
    rr, cc = np.mgrid[0:h, 0:w]
    mask = np.zeros((h, w), bool)
    for _ in range(rng.integers(2, 6)):
        r0, c0 = rng.uniform(0.1, 0.9, 2) * (h, w)
        a, b = rng.uniform(0.06, 0.16, 2) * min(h, w)
        t = rng.uniform(0, np.pi)
        u = (rr - r0) * np.cos(t) + (cc - c0) * np.sin(t)
        v = -(rr - r0) * np.sin(t) + (cc - c0) * np.cos(t)
        mask |= (u / a) ** 2 + (v / b) ** 2 <= 1.0
    bg = _ramp(rng, h, w, 0.1, 0.55)
    img = np.where(mask, bg + rng.uniform(0.25, 0.35), bg) + rng.normal(0, 0.06, (h, w))
    return np.clip(img, 0.0, 1.0), mask


def _edges(rng, h, w):
    lab = _shapes(rng, h, w, rng.integers(2, 5))
    levels = rng.uniform(0.1, 0.9, lab.max() + 1)
    levels[1:] = np.where(np.abs(levels[1:] - levels[0]) < 0.2, levels[1:] + 0.35, levels[1:]) % 1.0
    img = ndi.gaussian_filter(levels[lab], 1.0, mode="reflect") + rng.normal(0, 0.04, (h, w))
    p = np.pad(lab, 1, mode="edge")
    border = ((p[1:-1, 1:-1] != p[:-2, 1:-1]) | (p[1:-1, 1:-1] != p[2:, 1:-1])
              | (p[1:-1, 1:-1] != p[1:-1, :-2]) | (p[1:-1, 1:-1] != p[1:-1, 2:]))
    return np.clip(img, 0.0, 1.0), border


def _count(rng, h, w):
    rr, cc = np.mgrid[0:h, 0:w]
    n_want = int(rng.integers(1, 10))
    centres, radii = [], []
    for _ in range(200):
        if len(centres) == n_want:
            break
        rad = rng.uniform(0.05, 0.09) * min(h, w)
        c = rng.uniform(rad + 1, np.array([h, w]) - rad - 1)
        if all(np.hypot(*(c - c2)) > rad + r2 + 3 for c2, r2 in zip(centres, radii)):
            centres.append(c)
            radii.append(rad)
    mask = np.zeros((h, w), bool)
    for (r0, c0), rad in zip(centres, radii):
        mask |= (rr - r0) ** 2 + (cc - c0) ** 2 <= rad**2
    n = ndi.label(mask, structure=np.ones((3, 3)))[1]  # the truth, exactly as sampled
    bg = _ramp(rng, h, w, 0.1, 0.6)
    img = np.where(mask, bg + 0.3, bg) + rng.normal(0, 0.08, (h, w))
    return np.clip(img, 0.0, 1.0), float(n)


_GEN = {"denoise": _denoise, "binarize": _binarize, "edges": _edges, "count": _count}
_METRIC_OF = {"denoise": "psnr", "binarize": "iou", "edges": "f1", "count": "count"}
_HAND: dict[str, tuple] = {
    # hand-written pipelines (what a person would try first), knobs in [0, 1]
    "denoise": (("guided_filter", {"eps": 0.01, "radius": 2}), ("gaussian", {"sigma": 0.7})),
    "binarize": (("gaussian", {"sigma": 1.0}), ("local_mean", {"radius": 12, "offset": -0.08}),
                 ("region_open", {"radius": 1})),
    "edges": (("canny", {"sigma": 1.0, "high_threshold": 0.05}),),
    "count": (("gaussian", {"sigma": 1.0}), ("top_hat", {"radius": 8}), ("otsu"),
              ("remove_small", {"min_area": 5.0}), ("count_obj")),
}
_NULL: dict[str, tuple] = {
    "denoise": (),
    "binarize": (("threshold", {"lo": 0.5}),),
    "edges": (("threshold", {"lo": 0.5}),),
    "count": (("threshold", {"lo": 0.5}), "count_obj"),
}


def _build(name: str, split: str, seed: int, n: int, size: tuple[int, int]) -> Split:
    xs, ts = [], []
    for i in range(n):
        x, t = _GEN[name](_rng(name, split, seed, i), *size)
        xs.append(x)
        ts.append(t)
    return Split(np.stack(xs).astype(np.float64), np.asarray(np.stack(ts)))


def make_problem(name: str, *, n_train: int = 16, n_holdout: int = 8, n_locked: int = 16,
                 size: tuple[int, int] = (64, 64), seed: int = 0, n_stages: int = 6) -> Problem:
    """A synthetic problem with exact ground truth and three disjoint splits.

    Args:
      name: one of :data:`PROBLEMS`.
      n_train, n_holdout, n_locked: images per split (each >= 1).
      size: image shape ``(H, W)``, each >= 24.
      seed: data seed (the splits differ for every seed and never share an image).
      n_stages: stages of the default search skeleton (>= 2; >= 3 for ``count``).
    """
    if name not in _GEN:
        raise ValueError(f"make_problem: unknown problem {name!r}; choose one of {', '.join(PROBLEMS)}")
    for k, v in (("n_train", n_train), ("n_holdout", n_holdout), ("n_locked", n_locked)):
        if int(v) < 1:
            raise ValueError(f"make_problem: {k} must be >= 1, got {v}")
    if len(size) != 2 or min(size) < 24:
        raise ValueError(f"make_problem: size must be (H, W) with both >= 24, got {size}")
    metric = _METRIC_OF[name]
    gives = _METRIC_GIVES[metric]
    if n_stages < (3 if gives is Feature else 2):
        raise ValueError(f"make_problem: n_stages too small for {name!r}: {n_stages}")
    size = (int(size[0]), int(size[1]))
    return Problem(
        name=name, metric=metric, gives=gives,
        train=_build(name, "train", seed, n_train, size),
        holdout=_build(name, "holdout", seed, n_holdout, size),
        locked=_build(name, "locked", seed, n_locked, size),
        hand=_HAND[name], null=_NULL[name],
        single_sorts=(Image, Image) if gives is Image else (Image, Region) + ((Feature,) if gives is Feature else ()),
        default_sorts=_sorts_for(gives, n_stages),
    )


def problem_from_pairs(inputs: Any, targets: Any, metric: str, *, name: str = "user",
                       fractions: tuple[float, float, float] = (0.5, 0.25, 0.25), seed: int = 0,
                       n_stages: int = 4, hand: Sequence[Any] = (), null: Sequence[Any] | None = None) -> Problem:
    """A problem from the user's own input/target pairs.

    The pairs are shuffled with ``seed`` and cut into train / holdout / locked by
    ``fractions``; every split must get at least one pair.

    Args:
      inputs: ``(N, H, W)`` grey images, finite, in ``[0, 1]``.
      targets: ``(N, H, W)`` clean images (``"psnr"``), masks (``"iou"``, ``"f1"``), or
        ``(N,)`` counts (``"count"``).
      metric: one of ``"psnr"``, ``"iou"``, ``"f1"``, ``"count"``.
      hand: a hand-written pipeline (stage list) for the baseline table; required before a run.
      null: the "identity" baseline's stages (default as for the synthetic problems).

    Raises:
      ValueError: unknown metric, inputs/targets differing in count or shape, non-finite
        or out-of-range inputs, or a split that would be empty.
    """
    if metric not in METRICS:
        raise ValueError(f"problem_from_pairs: unknown metric {metric!r}; choose one of {', '.join(METRICS)}")
    x = np.asarray(inputs, dtype=np.float64)
    t = np.asarray(targets)
    if x.ndim != 3:
        raise ValueError(f"problem_from_pairs: inputs must be (N, H, W), got shape {x.shape}")
    if t.shape[:1] != x.shape[:1]:
        raise ValueError(f"problem_from_pairs: {x.shape[0]} inputs but {t.shape[0] if t.ndim else 0} targets; "
                         f"inputs and targets must pair one to one")
    want = x.shape[:1] if metric == "count" else x.shape
    if t.shape != want:
        raise ValueError(f"problem_from_pairs: metric {metric!r} needs targets of shape {want}, got {t.shape}")
    if not np.all(np.isfinite(x)) or x.min() < 0 or x.max() > 1:
        raise ValueError("problem_from_pairs: inputs must be finite and in [0, 1]")
    if len(fractions) != 3 or any(f <= 0 for f in fractions):
        raise ValueError(f"problem_from_pairs: fractions must be three positive numbers, got {fractions}")
    n = x.shape[0]
    fr = np.asarray(fractions, float) / float(sum(fractions))
    n_hold, n_lock = int(np.floor(n * fr[1])), int(np.floor(n * fr[2]))
    n_train = n - n_hold - n_lock
    if min(n_train, n_hold, n_lock) < 1:
        raise ValueError(f"problem_from_pairs: {n} pairs are too few for three disjoint splits with fractions "
                         f"{tuple(fractions)} (train {n_train}, holdout {n_hold}, locked {n_lock}); every split "
                         f"needs at least one pair")
    perm = np.random.default_rng(seed).permutation(n)
    parts = np.split(perm, [n_train, n_train + n_hold])
    gives = _METRIC_GIVES[metric]
    if metric in ("iou", "f1"):
        t = t.astype(bool)
    splits = [Split(x[p], t[p].astype(np.float64) if metric in ("psnr", "count") else t[p]) for p in parts]
    if null is None:
        null = () if gives is Image else (("threshold", {"lo": 0.5}),) + (("count_obj",) if gives is Feature else ())
    return Problem(
        name=name, metric=metric, gives=gives, train=splits[0], holdout=splits[1], locked=splits[2],
        hand=tuple(hand), null=tuple(null),
        single_sorts=(Image, Image) if gives is Image else (Image, Region) + ((Feature,) if gives is Feature else ()),
        default_sorts=_sorts_for(gives, n_stages),
    )
