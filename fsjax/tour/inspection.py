"""Inspection scenes measured with fsjax ops: surface defects and particle counting.

Two ground-truth scenes from :mod:`fsjax.synth` (issue 3, "Ground-truth
scenes" 1 and 4), the recipes that measure them (pipelines of registered
fsjax ops, each compiled once with ``jax.jit``), their scoring against the
truth, and the ``fsjax tour`` sections (:data:`SECTIONS`) that print the
figures beside the null.

Surface defects (:func:`fsjax.synth.surface_defects`):

1. Background: the surface without its defects is estimated by a *median*
   filter. The ``median`` op caps its radius at 5 px (an 11 x 11 window), far
   smaller than a dent, so the median runs on a downsampled copy: ``resize``
   by ``1/factor`` with anti-aliasing (default 8: 512 -> 64 px), ``median``
   of radius ``radius`` (default 3, a 7 x 7 window = 56 x 56 px of the
   original), ``resize`` back (bilinear). Defects cover a small fraction of
   any window, so the median ignores them; the illumination varies slowly and
   survives the down/up-sampling.
2. Difference: the image smoothed by ``gaussian`` (``sigma`` 1 px, tames the
   texture) minus the background: ``abs_diff`` for detection, ``sub_images``
   (offset 0.5) as the signed grey image measured under each region.
3. Blobs: ``hysteresis`` on ``|difference|`` (seeds above ``high`` grow
   within ``low``: dark and bright defects alike), ``label`` (8-connected),
   ``region_props`` (area, centroid, inertia axes, mean signed difference).
4. Rule (:func:`classify_defects`), per region of area >= ``min_area`` (smaller
   ones are noise and not reported): polarity = sign of the mean difference;
   elongation = major / minor axis of the inertia ellipse;
   ``scratch`` = dark and elongation >= 4; ``dent`` = dark, elongation < 2 and
   area >= 100 px; ``particle`` = bright, elongation < 2 and area < 150 px;
   anything else is ``unknown`` (reported, counted as a wrong type).

Null: the same chain with the background replaced by one global grey level
(the image median), i.e. a global two-sided threshold without background
estimation; and a plain global Otsu threshold of the raw image.

Scoring (:func:`score_defects`): a true defect is *detected* when exactly one
reported region overlaps its footprint and that region overlaps no other
defect; a reported region that overlaps no footprint is a *false positive*.

Particle counting (:func:`fsjax.synth.particle_scene`): ``otsu``,
then ``watershed_split`` (distance-transform h-maxima markers, watershed of
the negated distance) and ``region_props`` centroids; the null is ``label``
of the same mask (touching pairs stay merged). Each disc is matched to the
label under its true centre; the count must be exact, the matching a
bijection, every centroid within 1 px of the drawn centre.
"""

from __future__ import annotations

import functools
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from fsjax import Image, Labels, RegionProps
from fsjax import ops as O
from fsjax.synth import particle_scene, surface_defects

from ._core import Section, _panel

__all__ = [
    "DEFECT_TYPES",
    "defect_background",
    "detect_defects",
    "classify_defects",
    "score_defects",
    "inspect_surface",
    "count_particles",
    "score_particles",
    "SECTIONS",
]

#: Codes returned by :func:`classify_defects`: 0 = no region / ignored (noise).
DEFECT_TYPES = ("none", "scratch", "dent", "particle", "unknown")
_COLUMNS = ("area", "centroid_row", "centroid_col", "major_axis_length", "minor_axis_length",
            "eccentricity", "mean_intensity")

# the feature rule (see the module docstring)
SCRATCH_ELONGATION = 4.0
ROUND_ELONGATION = 2.0
DENT_MIN_AREA = 100.0
PARTICLE_MAX_AREA = 150.0


# ---------------------------------------------------------------------------
# surface defects
# ---------------------------------------------------------------------------


@functools.cache
def _background_fn(shape: tuple[int, int], factor: int, radius: int):
    small = (max(1, shape[0] // factor), max(1, shape[1] // factor))

    def run(img: Image) -> Image:
        low = O.resize(img, shape=small, antialias=True)
        return O.resize(O.median(low, radius=radius), shape=shape)

    return jax.jit(run)


def defect_background(img: Image, *, factor: int = 8, radius: int = 3) -> Image:
    """Background (defect-free surface) estimate: a median filter on a ``1/factor`` copy.

    ``resize`` down by ``factor`` (anti-aliased), ``median`` of ``radius`` (the op's
    cap is 5), ``resize`` back to the input shape (bilinear). The effective window
    is ``(2 radius + 1) factor`` px of the original image.
    """
    shape = tuple(int(s) for s in img.data.shape[-2:])
    return _background_fn(shape, int(factor), int(radius))(img)


def classify_defects(props: RegionProps, *, min_area: float = 8.0):
    """Defect type codes (indices into :data:`DEFECT_TYPES`) for each table row, by the feature rule.

    ``props`` must hold ``area``, ``major_axis_length``, ``minor_axis_length`` and
    ``mean_intensity`` measured on the signed difference (offset 0.5). Invalid rows
    and regions below ``min_area`` get 0. Jittable.
    """
    area = props["area"]
    major, minor = props["major_axis_length"], props["minor_axis_length"]
    safe = jnp.where(minor > 0, minor, 1.0)
    elong = jnp.where(minor > 0, major / safe, jnp.inf)
    dark = props["mean_intensity"] < 0.5
    scratch = dark & (elong >= SCRATCH_ELONGATION)
    dent = dark & (elong < ROUND_ELONGATION) & (area >= DENT_MIN_AREA)
    particle = ~dark & (elong < ROUND_ELONGATION) & (area < PARTICLE_MAX_AREA)
    code = jnp.where(scratch, 1, jnp.where(dent, 2, jnp.where(particle, 3, 4)))
    keep = props.valid & (area >= min_area)
    return jnp.where(keep, code, 0).astype(jnp.int32)


@functools.cache
def _detect_fn(sigma: float, low: float, high: float, min_area: float, capacity: int):
    def run(img: Image, background: Image):
        sm = O.gaussian(img, sigma=sigma)
        region = O.hysteresis(O.abs_diff(sm, background), low=low, high=high)
        labels = O.label(region, capacity=capacity)
        signed = O.sub_images(sm, background, offset=0.5)
        props = O.region_props(labels, signed, capacity=capacity, columns=_COLUMNS)
        return labels, props, classify_defects(props, min_area=min_area)

    return jax.jit(run)


def detect_defects(img: Image, background: Image, *, sigma: float = 1.0, low: float = 0.03,
                   high: float = 0.05, min_area: float = 8.0, capacity: int = 64):
    """Blob analysis of ``gaussian(img) - background``: returns ``(labels, props, codes)``.

    ``hysteresis(|difference|, low, high)`` -> ``label`` -> ``region_props`` on the
    signed difference -> :func:`classify_defects`. Compiled once per parameter set.
    """
    return _detect_fn(float(sigma), float(low), float(high), float(min_area), int(capacity))(img, background)


def score_defects(labels: np.ndarray, codes: np.ndarray, defects) -> dict:
    """Score reported regions (``codes > 0``) against the true defect footprints.

    Returns a dict: ``reported`` regions, ``detected`` (defects overlapped by
    exactly one region that overlaps no other defect), ``false_positives``
    (reported regions overlapping no defect), ``typed`` (detected defects whose
    region got the true type), ``assigned`` (per defect: the type given, or
    ``"missed"``/``"merged"``/``"split"``), ``region_of`` (label per defect or 0).
    """
    labels = np.asarray(labels)
    codes = np.asarray(codes)
    rep = [k + 1 for k in range(codes.shape[0]) if codes[k] > 0]
    ov = np.zeros((len(rep), len(defects)), bool)
    for a, k in enumerate(rep):
        reg = labels == k
        for i, d in enumerate(defects):
            ov[a, i] = bool((reg & d.mask).any())
    detected, typed, assigned, region_of = 0, 0, [], []
    for i, d in enumerate(defects):
        hits = np.nonzero(ov[:, i])[0]
        if len(hits) == 0:
            assigned.append("missed")
            region_of.append(0)
        elif len(hits) > 1:
            assigned.append("split")
            region_of.append(0)
        elif ov[hits[0]].sum() > 1:
            assigned.append("merged")
            region_of.append(0)
        else:
            k = rep[hits[0]]
            kind = DEFECT_TYPES[int(codes[k - 1])]
            detected += 1
            typed += kind == d.kind
            assigned.append(kind)
            region_of.append(k)
    fp = int((~ov.any(1)).sum()) if len(rep) else 0
    return dict(reported=len(rep), detected=detected, false_positives=fp, typed=typed,
                assigned=assigned, region_of=region_of)


def inspect_surface(image, defects, *, otsu_null: bool = True, **kw) -> dict:
    """Run the defect recipe and its nulls on one scene; return scores and intermediates.

    ``otsu_null=False`` skips the global-Otsu null (saves its compilation).
    """
    img = Image(jnp.asarray(image))
    bg = defect_background(img)
    labels, props, codes = detect_defects(img, bg, **kw)
    flat = Image(jnp.full(img.data.shape, jnp.median(img.data), img.data.dtype))
    n_labels, n_props, n_codes = detect_defects(img, flat, **kw)
    out = {}
    if otsu_null:
        otsu = O.otsu(img)
        o_lab = O.label(otsu, capacity=1024)
        o_codes = np.where(np.arange(1, 1025) <= int(o_lab.count), 4, 0)  # every region reported, untyped
        out = dict(otsu=np.asarray(otsu.data), otsu_score=score_defects(o_lab.data, o_codes, defects),
                   otsu_truncated=bool(o_lab.truncated))
    return dict(
        background=np.asarray(bg.data),
        labels=np.asarray(labels.data),
        props=props,
        codes=np.asarray(codes),
        score=score_defects(labels.data, codes, defects),
        null_labels=np.asarray(n_labels.data),
        null_score=score_defects(n_labels.data, n_codes, defects),
        **out,
    )


# ---------------------------------------------------------------------------
# particle counting
# ---------------------------------------------------------------------------


@functools.cache
def _particles_fn(capacity: int):
    def run(img: Image, h):
        region = O.otsu(img)
        merged = O.label(region, capacity=capacity)
        split = O.watershed_split(region, h=h)
        cols = ("area", "centroid_row", "centroid_col")
        return (region, merged, split, O.region_props(split, img, capacity=capacity, columns=cols),
                O.region_props(merged, img, capacity=capacity, columns=cols))

    return jax.jit(run)


def count_particles(img: Image, *, h: float = 0.75, capacity: int = 128):
    """Otsu mask, its plain labelling (null), its ``watershed_split`` and both centroid tables.

    Returns ``(region, merged, split, split_props, merged_props)``. ``h`` is the
    dome height of the distance-map markers (px, traced: one compilation for all
    values); 0.75 also separates pairs whose smaller disc rises less than 1 px
    above the neck (radius 5 against 9).
    """
    return _particles_fn(int(capacity))(img, jnp.asarray(h, img.data.dtype))


def score_particles(labels: Labels, props: RegionProps, truth: dict) -> dict:
    """Match each true disc to the label under its centre; centroid errors in px.

    ``bijective`` is True when every disc lands on a label and no two discs share
    one; ``errors`` are the distances from each disc's centre to its label's
    centroid (a shared label gives the merged blob's centroid).
    """
    lab = np.asarray(labels.data)
    c = np.rint(truth["centres"]).astype(int)
    ids = lab[c[:, 0], c[:, 1]]
    cen = np.stack([np.asarray(props["centroid_row"]), np.asarray(props["centroid_col"])], 1)
    got = np.where(ids[:, None] > 0, cen[np.maximum(ids, 1) - 1], np.nan)
    err = np.hypot(*(got - truth["centres"]).T)
    paired = sorted(i for p in truth["pairs"] for i in p)
    return dict(count=int(labels.count), bijective=bool((ids > 0).all() and len(set(ids.tolist())) == len(ids)),
                errors=err, max_error=float(np.nanmax(err)), mean_error=float(np.nanmean(err)),
                max_error_pairs=float(np.nanmax(err[paired])) if paired else 0.0,
                max_error_isolated=float(np.nanmax(np.delete(err, paired))))


# ---------------------------------------------------------------------------
# tour sections
# ---------------------------------------------------------------------------


def _label_view(lab: np.ndarray) -> np.ndarray:
    """Label image for display: background 0, labels spread over grey levels 0.3..1."""
    lab = np.asarray(lab)
    return np.where(lab > 0, 0.3 + 0.7 * ((lab * 0.6180339887) % 1.0), 0.0)


def _fmt_score(s: dict, n: int) -> str:
    return (f"{s['detected']}/{n} detected, {s['false_positives']} false positives, "
            f"{s['typed']}/{n} typed ({s['reported']} regions)")


def surface_defects_section(out: Path, quick: bool) -> Section:
    """Scene 1: 3 scratches, 2 dents, 1 particle on brushed metal; median background + blob rule.

    Quick mode keeps the scene (the time is compilation, not pixels) and skips
    the global-Otsu null.
    """
    size = (512, 512)
    image, defects = surface_defects(size, seed=0)
    t0 = time.perf_counter()
    r = inspect_surface(image, defects, otsu_null=not quick)
    t_first = time.perf_counter() - t0
    img = Image(jnp.asarray(image))
    t0 = time.perf_counter()
    jax.block_until_ready(detect_defects(img, defect_background(img)))
    t_steady = time.perf_counter() - t0
    s, sn = r["score"], r["null_score"]
    n = len(defects)
    props, labels = r["props"], r["labels"]
    rows = []
    for i, d in enumerate(defects):
        k = s["region_of"][i]
        if k:
            el = float(props["major_axis_length"][k - 1] / props["minor_axis_length"][k - 1])
            extra = (f"area {float(props['area'][k - 1]):.0f} px, elongation {el:.1f}, "
                     f"mean diff {float(props['mean_intensity'][k - 1]) - 0.5:+.3f}")
        else:
            extra = "no single region"
        rows.append((f"{d.kind} at ({d.centre[0]:.0f}, {d.centre[1]:.0f}), contrast {d.contrast:+.3f}",
                     f"-> {s['assigned'][i]} ({extra})"))
    rows += [("fsjax: median background (1/8 size, r=3) + hysteresis(abs diff, 0.03, 0.05) + rule", _fmt_score(s, n)),
             ("null: same chain, flat background (global median level)", _fmt_score(sn, n))]
    null_fig = f"global level: {_fmt_score(sn, n)}"
    if "otsu_score" in r:
        so = r["otsu_score"]
        rows.append(("null: global Otsu on the raw image", f"{so['detected']}/{n} detected, "
                     f"{so['false_positives']} false positives ({so['reported']} regions)"))
        null_fig += f"; global Otsu: {so['detected']}/{n} detected, {so['false_positives']} false positives"
    ok = s["detected"] == n and s["false_positives"] == 0 and s["typed"] == n
    null_ok = sn["detected"] == n and sn["false_positives"] == 0 and sn["typed"] == n
    diff = image - r["background"]
    truth = np.zeros(size, bool)
    for d in defects:
        truth |= d.mask
    fig = _panel(out / "surface_defects.png",
                 [image, r["background"], diff, truth, _label_view(labels), _label_view(r["null_labels"])],
                 ["surface", "median background", "difference", "true footprints", "fsjax regions",
                  "null: flat background"], signed=(2,))
    return Section(
        title="Surface defects: scratches, dents and a particle on brushed metal",
        truth=(f"{size[0]}x{size[1]} brushed texture (std 0.012) on illumination 0.28..0.62, noise 0.004; "
               f"3 dark scratches, 2 soft dark dents, 1 bright particle; footprints |defect| >= peak/4"),
        rows=rows,
        fsjax_figure=_fmt_score(s, n),
        null_figure=null_fig,
        beats_null=ok and not null_ok,
        figure=fig,
        notes=("The median op caps its radius at 5 px, so the background median runs on a 1/8 copy "
               "(anti-aliased resize, 7x7 median = 56x56 px window, bilinear resize back). "
               f"First call incl. compilation {t_first:.1f} s; steady state (background + detection) "
               f"{1e3 * t_steady:.0f} ms."),
    )


def particle_count_section(out: Path, quick: bool) -> Section:
    """Scene 4: 60 particles with 6 touching pairs; watershed split vs plain labelling."""
    image, truth = particle_scene((256, 256), seed=0)  # same scene in quick mode (small already)
    img = Image(jnp.asarray(image))
    t0 = time.perf_counter()
    region, merged, split, sp, mp = count_particles(img)
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(count_particles(img))
    t_steady = time.perf_counter() - t0
    s = score_particles(split, sp, truth)
    m = score_particles(merged, mp, truth)
    n = truth["n_particles"]
    rows = [
        ("truth", f"{n} particles, {len(truth['pairs'])} touching pairs, {truth['n_components']} blobs"),
        ("null: otsu + label", f"count {m['count']}; centroid error max {m['max_error']:.2f} px "
                               f"(merged pairs give the blob's centroid)"),
        ("fsjax: otsu + watershed_split (h=0.75)", f"count {s['count']}, one label per particle: {s['bijective']}"),
        ("centroid error (region_props), all particles", f"max {s['max_error']:.3f} px, mean {s['mean_error']:.3f} px"),
        ("centroid error, the 12 particles of touching pairs", f"max {s['max_error_pairs']:.3f} px"),
        ("centroid error, isolated particles", f"max {s['max_error_isolated']:.3f} px"),
    ]
    ok = s["count"] == n and s["bijective"] and s["max_error"] <= 1.0
    fig = _panel(out / "particle_count.png",
                 [image, np.asarray(region.data), _label_view(np.asarray(merged.data)),
                  _label_view(np.asarray(split.data))],
                 ["particles", "otsu", f"null: label ({m['count']})", f"watershed_split ({s['count']})"])
    return Section(
        title="Particle counting: touching pairs split by the distance-map watershed",
        truth=(f"{n} discs, radius 5..9 px, grey 0.45..0.9 on 0.15, blur 0.7 px, noise 0.02; "
               f"{len(truth['pairs'])} pairs overlap by 1 px, the rest >= 4.5 px apart"),
        rows=rows,
        fsjax_figure=f"{s['count']}/{n}, centroids within {s['max_error']:.2f} px",
        null_figure=f"{m['count']}/{n} (touching pairs merged)",
        beats_null=ok and m["count"] != n,
        figure=fig,
        notes=(f"First call incl. compilation {t_first:.1f} s; steady state {1e3 * t_steady:.0f} ms "
               "(threshold, labelling, split and both centroid tables)."),
    )


SECTIONS = [surface_defects_section, particle_count_section]
