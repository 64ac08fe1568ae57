"""``fsjax tour``: a scored tour of what fsjax measures.

Each section builds a scene with a known answer, measures it with fsjax, and
measures the *null* (doing nothing, or the naive method) on the same data. The
report states the ground truth, the fsjax figure, the null figure and whether
fsjax beat the null; each section writes a PNG. Runs in float64.

Sections are plain functions returning :class:`Section`; other capabilities add
their own by appending to :data:`SECTIONS`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import fsjax
from fsjax import Image, Region
from fsjax import ops as O
from fsjax.synth import standard_scene


@dataclasses.dataclass
class Section:
    title: str
    truth: str
    rows: list[tuple[str, str]]  # (method, figure)
    fsjax_figure: str
    null_figure: str
    beats_null: bool
    figure: str | None = None
    notes: str = ""
    seconds: float = 0.0
    cpu_seconds: float = 0.0  # process CPU time (all threads): comparable on a shared machine
    peak_mb: float | None = None  # the process's peak resident memory once this section ended


def _to_u8(a: np.ndarray, signed: bool = False) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.dtype == bool or signed:
        pass
    if signed:
        m = max(float(np.max(np.abs(a))), 1e-12)
        a = 0.5 + 0.5 * a / m
    else:
        lo, hi = float(np.min(a)), float(np.max(a))
        a = (a - lo) / (hi - lo) if hi > lo else np.zeros_like(a)
    return (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)


def _panel(path: Path, images: list[np.ndarray], labels: list[str], signed: tuple[int, ...] = ()) -> str:
    from PIL import Image as PILImage
    from PIL import ImageDraw

    tiles = [_to_u8(np.asarray(im, dtype=float), i in signed) for i, im in enumerate(images)]
    h = max(t.shape[0] for t in tiles)
    gap, top = 6, 16
    w = sum(t.shape[1] for t in tiles) + gap * (len(tiles) + 1)
    canvas = PILImage.new("L", (w, h + top + gap), 255)
    draw = ImageDraw.Draw(canvas)
    x = gap
    for t, lab in zip(tiles, labels):
        canvas.paste(PILImage.fromarray(t), (x, top))
        draw.text((x, 2), lab, fill=0)
        x += t.shape[1] + gap
    canvas.save(path)
    return path.name


def _psnr(x, ref) -> float:
    return float(O.psnr(Image(jnp.asarray(x)), Image(jnp.asarray(ref))).value)


# ---------------------------------------------------------------------------
# sections
# ---------------------------------------------------------------------------


def denoise(out: Path, quick: bool) -> Section:
    size = (96, 128) if quick else (192, 256)
    clean, _ = standard_scene(0, size, noise=0.0)
    rng = np.random.default_rng(7)
    sigma_n = 0.08
    noisy = clean + sigma_n * rng.standard_normal(size)
    img = Image(jnp.asarray(noisy))
    # knob sweep of the Gaussian, one compiled vmap over 24 knob values
    a = jnp.linspace(0.0, 1.0, 24)
    t0 = time.perf_counter()
    sweep = jax.jit(jax.vmap(lambda u: fsjax.apply(img, "gaussian", a=u).data))(a)
    sweep.block_until_ready()
    t_sweep = time.perf_counter() - t0
    ps = [_psnr(s, clean) for s in sweep]
    best = int(np.argmax(ps))
    sig_best = float(fsjax.get_op("gaussian").knobs["sigma"].to_param(float(a[best])))
    outs = {
        f"gaussian (best of knob sweep, sigma={sig_best:.2f})": np.asarray(sweep[best]),
        "median r=2": O.median(img, radius=2).data,
        "bilateral (1.5 px, 0.2)": O.bilateral(img, sigma_spatial=1.5, sigma_range=0.2).data,
        "guided (r=3, eps=0.01)": O.guided_filter(img, radius=3, eps=0.01).data,
        "perona_malik (kappa 0.1, 20 it)": O.perona_malik(img, kappa=0.1, iterations=20).data,
    }
    null = _psnr(noisy, clean)
    rows = [("null: noisy input", f"{null:.2f} dB")]
    rows += [(k, f"{_psnr(v, clean):.2f} dB") for k, v in outs.items()]
    best_name, best_val = max(((k, _psnr(v, clean)) for k, v in outs.items()), key=lambda kv: kv[1])
    fig = _panel(out / "denoise.png", [clean, noisy] + [np.asarray(v) for v in outs.values()],
                 ["clean", "noisy", "gauss", "median", "bilateral", "guided", "perona-malik"])
    return Section(
        title="Denoising a scene with known clean image",
        truth=f"clean piecewise-constant scene {size[0]}x{size[1]}, additive Gaussian noise sigma={sigma_n}",
        rows=rows,
        fsjax_figure=f"best: {best_name} {best_val:.2f} dB",
        null_figure=f"{null:.2f} dB (do nothing)",
        beats_null=all(_psnr(v, clean) > null for v in outs.values()),
        figure=fig,
        notes=f"the 24-value Gaussian knob sweep ran as one vmapped call ({t_sweep:.2f} s incl. compile).",
    )


def _disc_image(size, centre, radius, blur=1.0, noise=0.01, seed=3):
    h, w = size
    rr, cc = np.mgrid[0:h, 0:w].astype(float)
    # 8x8 supersampled anti-aliased disc
    ss = 8
    off = (np.arange(ss) + 0.5) / ss - 0.5
    acc = np.zeros(size)
    for dy in off:
        for dx in off:
            acc += ((rr + dy - centre[0]) ** 2 + (cc + dx - centre[1]) ** 2) <= radius**2
    img = 0.2 + 0.6 * acc / ss**2
    img = np.asarray(O.gaussian(Image(jnp.asarray(img)), sigma=blur).data)
    return img + noise * np.random.default_rng(seed).standard_normal(size)


def edges(out: Path, quick: bool) -> Section:
    size = (96, 96) if quick else (160, 160)
    centre, radius = (size[0] / 2 - 0.3, size[1] / 2 + 0.4), size[0] * 0.3
    img = _disc_image(size, centre, radius)
    rr, cc = np.mgrid[0 : size[0], 0 : size[1]].astype(float)
    dist = np.abs(np.hypot(rr - centre[0], cc - centre[1]) - radius)
    can = np.asarray(O.canny(Image(jnp.asarray(img)), sigma=1.5).data)
    mag = O.sobel_amp(Image(jnp.asarray(img)))
    naive = np.asarray(O.otsu(mag).data)  # null: threshold the gradient magnitude, no NMS
    d_can, d_naive = float(dist[can].mean()), float(dist[naive].mean())
    n_can, n_naive = int(can.sum()), int(naive.sum())
    perimeter = 2 * math.pi * radius
    fig = _panel(out / "edges.png", [img, np.asarray(mag.data), naive, can],
                 ["disc", "sobel_amp", "null: otsu(|grad|)", "canny"])
    return Section(
        title="Edge location on a disc of known radius",
        truth=f"anti-aliased disc, radius {radius:.2f} px, centre ({centre[0]:.2f}, {centre[1]:.2f}), blur 1 px, noise 0.01",
        rows=[("canny sigma=1.5: mean distance to true circle", f"{d_can:.3f} px ({n_can} px, perimeter {perimeter:.0f})"),
              ("null: Otsu on Sobel magnitude", f"{d_naive:.3f} px ({n_naive} px)")],
        fsjax_figure=f"{d_can:.3f} px",
        null_figure=f"{d_naive:.3f} px",
        beats_null=d_can < d_naive,
        figure=fig,
    )


def thresholds(out: Path, quick: bool) -> Section:
    size = (96, 128) if quick else (192, 256)
    h, w = size
    rng = np.random.default_rng(11)
    rr, cc = np.mgrid[0:h, 0:w].astype(float)
    truth = np.zeros(size, bool)
    for _ in range(14):
        r0, c0, rad = rng.uniform(10, h - 10), rng.uniform(10, w - 10), rng.uniform(4, 9)
        truth |= (rr - r0) ** 2 + (cc - c0) ** 2 <= rad**2
    ramp = 0.15 + 0.55 * cc / (w - 1)  # strong illumination gradient
    img = np.clip(ramp + 0.25 * truth + 0.02 * rng.standard_normal(size), 0, 1)
    im = Image(jnp.asarray(img))

    def err(m):
        return float(np.mean(np.asarray(m.data) != truth))

    methods = {
        "fixed 0.5 (null)": O.threshold(im, lo=0.5, hi=1.0),
        "otsu (global)": O.otsu(im),
        "sauvola r=15": O.sauvola(im, radius=15, k=0.1),
        "local_mean r=15": O.local_mean(im, radius=15, offset=-0.05),
        "dyn_threshold r=15": O.dyn_threshold(im, radius=15, offset=0.05),
    }
    errs = {k: err(v) for k, v in methods.items()}
    null = errs["fixed 0.5 (null)"]
    local_best = min(errs[k] for k in ("sauvola r=15", "local_mean r=15", "dyn_threshold r=15"))
    fig = _panel(out / "thresholds.png", [img, truth] + [np.asarray(v.data) for v in methods.values()],
                 ["ramp+objects", "truth", "fixed", "otsu", "sauvola", "local_mean", "dyn_thr"])
    return Section(
        title="Segmentation under an illumination ramp",
        truth="14 discs of contrast 0.25 on a ramp 0.15..0.70, noise 0.02; pixel error rate vs the true mask",
        rows=[(k, f"{100 * v:.2f} % pixels wrong") for k, v in errs.items()],
        fsjax_figure=f"best local method {100 * local_best:.2f} %",
        null_figure=f"fixed threshold {100 * null:.2f} %, global Otsu {100 * errs['otsu (global)']:.2f} %",
        beats_null=local_best < min(null, errs["otsu (global)"]),
        figure=fig,
    )


def salt_removal(out: Path, quick: bool) -> Section:
    size = (96, 128) if quick else (192, 256)
    _, masks = standard_scene(0, size, noise=0.0)
    truth = masks["disc"] | masks["rect"]
    rng = np.random.default_rng(5)
    noisy = truth | (rng.random(size) < 0.03)
    opened = np.asarray(O.region_open(Region(jnp.asarray(noisy)), radius=1.5).data)
    e_null, e = float(np.mean(noisy != truth)), float(np.mean(opened != truth))
    fig = _panel(out / "salt.png", [truth, noisy, opened], ["truth", "3% salt", "region_open r=1.5"])
    return Section(
        title="Removing salt noise from a mask with an opening",
        truth="disc + rectangle mask; 3 % of pixels set at random",
        rows=[("null: noisy mask", f"{100 * e_null:.3f} % pixels wrong"),
              ("region_open (disk r=1.5)", f"{100 * e:.3f} % pixels wrong")],
        fsjax_figure=f"{100 * e:.3f} %",
        null_figure=f"{100 * e_null:.3f} %",
        beats_null=e < e_null,
        figure=fig,
    )


def noise_level(out: Path, quick: bool) -> Section:
    size = (128, 128) if quick else (256, 256)
    clean, _ = standard_scene(1, size, noise=0.0)
    clean = np.asarray(O.gaussian(Image(jnp.asarray(clean)), sigma=1.0).data)
    rows, worst, worst_null = [], 0.0, 0.0
    rng = np.random.default_rng(2)
    # noise gain of the residual filter (delta - G): sqrt(sum((delta - g)^2)), measured on an impulse
    delta = np.zeros((21, 21))
    delta[10, 10] = 1.0
    g = np.asarray(O.gaussian(Image(jnp.asarray(delta)), sigma=1.0).data)
    gain = float(np.sqrt(np.sum((delta - g) ** 2)))
    for s in (0.005, 0.01, 0.02, 0.05):
        noisy = Image(jnp.asarray(clean + s * rng.standard_normal(size)))
        est = float(O.noise_sigma(noisy).value)
        # null: the naive estimate, std of the high-pass residual (image minus its Gaussian blur)
        resid = np.asarray(noisy.data) - np.asarray(O.gaussian(noisy, sigma=1.0).data)
        naive = float(np.std(resid)) / gain
        rel, rel_n = abs(est - s) / s, abs(naive - s) / s
        worst, worst_null = max(worst, rel), max(worst_null, rel_n)
        rows.append((f"true sigma {s}", f"noise_sigma {est:.4f} ({100 * rel:.1f} %), naive {naive:.4f} ({100 * rel_n:.1f} %)"))
    fig = _panel(out / "noise.png", [clean, clean + 0.05 * rng.standard_normal(size)], ["clean", "sigma 0.05"])
    return Section(
        title="Estimating the noise level of an image",
        truth="smooth scene plus Gaussian noise of known sigma",
        rows=rows,
        fsjax_figure=f"worst relative error {100 * worst:.1f} %",
        null_figure=f"naive residual std: worst {100 * worst_null:.1f} %",
        beats_null=worst < worst_null,
        figure=fig,
        notes="the naive estimate is the std of (image - Gaussian(image, 1 px)), corrected for the noise the blur removes; "
              "it is biased upwards by scene edges.",
    )


def lowpass_gain(out: Path, quick: bool) -> Section:
    n = 128
    rr, cc = np.mgrid[0:n, 0:n].astype(float)
    f_lo, f_hi, fc = 4 / n, 24 / n, 0.08
    lo = np.sin(2 * np.pi * f_lo * cc)
    hi = np.sin(2 * np.pi * f_hi * rr)
    img = Image(jnp.asarray(0.5 + 0.2 * lo + 0.2 * hi))
    y = np.asarray(O.gaussian_lowpass(img, cutoff=fc).data) - 0.5
    g_lo = float(np.sum(y * lo) / np.sum(lo * lo)) / 0.2
    g_hi = float(np.sum(y * hi) / np.sum(hi * hi)) / 0.2
    a_lo = math.exp(-(f_lo**2) / (2 * fc**2))
    a_hi = math.exp(-(f_hi**2) / (2 * fc**2))
    err = max(abs(g_lo - a_lo), abs(g_hi - a_hi))
    fig = _panel(out / "lowpass.png", [np.asarray(img.data), y + 0.5], ["two sinusoids", "gaussian_lowpass"])
    return Section(
        title="Frequency response of the Gaussian low-pass",
        truth=f"sinusoids at {f_lo:.4f} and {f_hi:.4f} cycles/px; analytic gain exp(-f^2 / 2 fc^2), fc = {fc}",
        rows=[(f"gain at {f_lo:.4f}", f"{g_lo:.6f} (analytic {a_lo:.6f})"),
              (f"gain at {f_hi:.4f}", f"{g_hi:.6f} (analytic {a_hi:.6f})"),
              ("null: unfiltered", "gain 1.000000 at both")],
        fsjax_figure=f"max gain error {err:.1e}",
        null_figure=f"gain error of doing nothing at {f_hi:.4f}: {abs(1 - a_hi):.3f}",
        beats_null=err < abs(1 - a_hi),
        figure=fig,
    )


def sharpness_ranking(out: Path, quick: bool) -> Section:
    size = (96, 128) if quick else (192, 256)
    clean, _ = standard_scene(0, size, noise=0.0)
    im = Image(jnp.asarray(clean))
    sigmas = [0.0, 0.5, 1.0, 1.5, 2.0, 3.0]
    imgs = [im if s == 0 else O.gaussian(im, sigma=s) for s in sigmas]
    sh = [float(O.sharpness(x).value) for x in imgs]
    sd = [float(O.std(x).value) for x in imgs]
    mono = all(a > b for a, b in zip(sh, sh[1:]))
    rel_sh = sh[-1] / sh[0]
    rel_sd = sd[-1] / sd[0]
    fig = _panel(out / "sharpness.png", [np.asarray(x.data) for x in imgs], [f"blur {s}" for s in sigmas])
    return Section(
        title="Focus measure: sharpness falls with blur",
        truth=f"the same scene blurred with sigma {sigmas} px (known ordering)",
        rows=[(f"blur {s}", f"sharpness {a:.3e}, std {b:.4f}") for s, a, b in zip(sigmas, sh, sd)],
        fsjax_figure=f"strictly decreasing: {mono}; sharpest/blurriest ratio {1 / rel_sh:.1f}x",
        null_figure=f"null focus measure (grey std) changes only {1 / rel_sd:.2f}x",
        beats_null=mono and (1 / rel_sh) > (1 / rel_sd),
        figure=fig,
    )


def pipeline_compile(out: Path, quick: bool) -> Section:
    size = (96, 128) if quick else (192, 256)
    imgs = [standard_scene(v % 2, size)[0] for v in range(16)]
    batch = Image(jnp.asarray(np.stack(imgs)))
    p = fsjax.pipeline(["gaussian", "sobel_amp", "otsu"])
    f = jax.jit(jax.vmap(lambda x, k: p._run(x, k), in_axes=(0, None)))
    knobs = jnp.array([[0.3, 0.0], [0.0, 0.0], [0.0, 0.0]])
    t0 = time.perf_counter()
    jax.block_until_ready(f(batch, knobs))
    t_first = time.perf_counter() - t0
    reps = []
    for _ in range(5):
        t0 = time.perf_counter()
        jax.block_until_ready(f(batch, knobs))
        reps.append(time.perf_counter() - t0)
    steady = float(np.median(reps))
    single = [p(Image(jnp.asarray(x)), knobs) for x in imgs]
    batched = f(batch, knobs)
    agree = all(np.array_equal(np.asarray(batched.data[i]), np.asarray(s.data)) for i, s in enumerate(single))
    try:
        fsjax.pipeline(["otsu", "sobel_amp"])
        refused = "NOT refused"
    except fsjax.PipelineTypeError as e:
        refused = f"refused before tracing: {e}"
    return Section(
        title="One compiled pipeline over a batch",
        truth="gaussian -> sobel_amp -> otsu on 16 images; the vmapped batch must equal 16 separate calls",
        rows=[("first call (compile + run)", f"{t_first:.3f} s"), ("steady state, 16 images", f"{steady * 1e3:.1f} ms"),
              ("batch equals separate calls", str(agree)), ("['otsu', 'sobel_amp']", refused)],
        fsjax_figure=f"{steady / 16 * 1e3:.2f} ms per image steady state, identical to separate calls: {agree}",
        null_figure="a mistyped chain fails at construction, before compilation",
        beats_null=agree and refused.startswith("refused"),
    )


SECTIONS: list[Callable[[Path, bool], Section]] = [
    denoise, edges, thresholds, salt_removal, noise_level, lowpass_gain, sharpness_ranking, pipeline_compile,
]


def all_sections() -> list[Callable[[Path, bool], Section]]:
    """Every tour section: the 2-D basics here, then inspection and metrology scenes."""
    import importlib

    out = list(SECTIONS)
    for name in _TOUR_MODULES:
        out += importlib.import_module(f"fsjax.{name}").SECTIONS
    return out


#: tour modules after the 2-D basics, in report order
_TOUR_MODULES = ("tour_inspection", "tour_metrology", "tour_points", "tour_registration", "tour_render",
                 "tour_measure3d", "tour_tomography", "tour_calibration", "tour_splat", "tour_evolve")


class _Heartbeat:
    """Prints what a running tour section is doing every ``every`` seconds, so a long section
    (compiling, fitting) is never mistaken for a hang. Sections name their current step with
    :func:`step`; the heartbeat line shows it with the elapsed time."""

    def __init__(self, every: float = 15.0, stream=None):
        import sys
        import threading

        self.every = every
        self.stream = stream if stream is not None else sys.stdout
        self.label = ""
        self.section = ""
        self.printed = False
        self.t0 = self.last = time.perf_counter()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self._stop.wait(min(1.0, self.every)):
            now = time.perf_counter()
            if self.section and now - self.last >= self.every:
                self.last = now
                what = f": {self.label}" if self.label else ""
                print(("" if self.printed else "\n") + f"    ... {self.section} still running ({now - self.t0:.0f} s){what}",
                      file=self.stream, flush=True)
                self.printed = True

    def start(self, section: str):
        self.section, self.label, self.printed = section, "", False
        self.t0 = self.last = time.perf_counter()
        if not self._thread.is_alive():
            self._thread.start()

    def stop(self):
        self._stop.set()


_HEARTBEAT: _Heartbeat | None = None


def _peak_rss_mb() -> float | None:
    """Peak resident memory of this process in MB (None where the platform does not say)."""
    try:
        import resource
        import sys

        r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return r / 1e6 if sys.platform == "darwin" else r / 1e3  # bytes on macOS, KiB on Linux
    except (ImportError, OSError):
        return None


def step(label: str) -> None:
    """Name what the running tour section is doing (shown by the progress heartbeat)."""
    if _HEARTBEAT is not None:
        _HEARTBEAT.label = label


def section_names() -> list[str]:
    """The names of every tour section, in report order (``fsjax tour --sections`` takes these)."""
    return [fn.__name__ for fn in all_sections()]


def run_tour(out_dir: str | Path, *, quick: bool = False, sections=None, log=print,
             heartbeat_s: float = 15.0, blas_threads: int | None = 1) -> list[Section]:
    """Run every section, write figures and ``report.md`` into ``out_dir``; return the sections.

    Args:
        out_dir: output directory (created).
        quick: smaller inputs (the form ``.ci/run`` and the tests use).
        sections: the section functions to run, or their names (see :func:`section_names`);
            ``None`` runs them all.
        log: ``print`` for the console progress lines, or a callable taking a section name.
        heartbeat_s: while a section runs, a line on stdout every this many seconds says it
            is still running and what it is doing (0 disables).
        blas_threads: OpenBLAS/LAPACK threads while the tour runs (numpy, scipy and jaxlib's CPU
            linear algebra), restored afterwards; ``None`` leaves the library default. The tour's
            matrices are small: with a thread per core, OpenBLAS spin-waits between calls and, on a
            machine with other work, one compiled 14-view ``calibrate_camera`` call took 2-3 s of
            CPU instead of 0.07 s (measured; results identical).
    """
    if blas_threads is not None:
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=int(blas_threads)):
            return run_tour(out_dir, quick=quick, sections=sections, log=log, heartbeat_s=heartbeat_s,
                            blas_threads=None)
    global _HEARTBEAT
    jax.config.update("jax_enable_x64", True)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results: list[Section] = []
    t_all = time.perf_counter()
    todo = all_sections() if sections is None else sections
    if any(isinstance(fn, str) for fn in todo):
        by_name = {fn.__name__: fn for fn in all_sections()}
        unknown = [fn for fn in todo if isinstance(fn, str) and fn not in by_name]
        if unknown:
            raise ValueError(f"run_tour: unknown section(s) {unknown}; known: {sorted(by_name)}")
        todo = [by_name[fn] if isinstance(fn, str) else fn for fn in todo]
    hb = _Heartbeat(heartbeat_s) if heartbeat_s > 0 and log is print else None
    _HEARTBEAT = hb
    try:
        for i, fn in enumerate(todo):
            t0, c0 = time.perf_counter(), time.process_time()
            log(f"[{i + 1}/{len(todo)}] {fn.__name__} ...", end="", flush=True) if log is print else log(fn.__name__)
            if hb is not None:
                hb.start(fn.__name__)
            sec = fn(out, quick)
            sec.seconds = time.perf_counter() - t0
            sec.cpu_seconds = time.process_time() - c0
            sec.peak_mb = _peak_rss_mb()
            if hb is not None:
                hb.section = ""
            results.append(sec)
            # compiled programs of one section are rarely reused by the next; releasing them keeps
            # the tour's resident memory bounded (the persistent cache, when on, keeps them on disk)
            jax.clear_caches()
            if log is print:
                lead = f"    {fn.__name__}:" if hb is not None and hb.printed else ""
                mem = f", peak {sec.peak_mb:.0f} MB" if sec.peak_mb else ""
                print(f"{lead} {sec.seconds:.1f} s (CPU {sec.cpu_seconds:.1f} s{mem}), beats null: {sec.beats_null}",
                      flush=True)
    finally:
        if hb is not None:
            hb.stop()
        _HEARTBEAT = None
    total = time.perf_counter() - t_all
    peak_mb = _peak_rss_mb()
    lines = [
        "# fsjax tour",
        "",
        f"fsjax {fsjax.__version__}, jax {jax.__version__}, backend {jax.default_backend()}, float64; "
        f"{len(fsjax.list_ops())} ops in {len(fsjax.families())} families. Total {total:.1f} s"
        + (" (quick mode)" if quick else "") + (f", peak resident memory {peak_mb:.0f} MB." if peak_mb else "."),
        "",
        "Each section: the ground truth, the fsjax figure, and the null (doing nothing or the naive method) on the same data.",
        "",
        "| section | fsjax | null | beats null |",
        "|---|---|---|---|",
    ]
    for s in results:
        lines.append(f"| {s.title} | {s.fsjax_figure} | {s.null_figure} | {'yes' if s.beats_null else '**no**'} |")
    for s in results:
        lines += ["", f"## {s.title}", "", f"Ground truth: {s.truth}.", "", "| method | figure |", "|---|---|"]
        lines += [f"| {m} | {v} |" for m, v in s.rows]
        lines += ["", f"fsjax: {s.fsjax_figure}. Null: {s.null_figure}. Beats the null: {'yes' if s.beats_null else 'NO'}."]
        if s.notes:
            lines += ["", s.notes]
        if s.figure:
            lines += ["", f"![{s.title}]({s.figure})"]
        lines += ["", f"_{s.seconds:.1f} s (CPU {s.cpu_seconds:.1f} s)"
                  + (f"; peak memory so far {s.peak_mb:.0f} MB_" if s.peak_mb else "_")]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    if log is print:
        print(f"wrote {out / 'report.md'} ({total:.1f} s" + (f", peak memory {peak_mb:.0f} MB)" if peak_mb else ")"))
    return results
