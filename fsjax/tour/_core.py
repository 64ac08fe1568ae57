"""The tour's machinery: the :class:`Section` record, figure panels, the progress heartbeat,
the runner and the report writer. The sections themselves live in the family modules of
:mod:`fsjax.tour`; this module imports none of them.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import numpy as np

import fsjax


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


def run_sections(out_dir: str | Path, todo: Sequence[Callable[[Path, bool], Section]], *, quick: bool = False,
                 log=print, heartbeat_s: float = 15.0, blas_threads: int | None = 1) -> list[Section]:
    """Run the section functions ``todo`` in order, write figures and ``report.md`` into ``out_dir``.

    :func:`fsjax.tour.run_tour` resolves section names and calls this; the arguments are
    documented there.
    """
    if blas_threads is not None:
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=int(blas_threads)):
            return run_sections(out_dir, todo, quick=quick, log=log, heartbeat_s=heartbeat_s, blas_threads=None)
    global _HEARTBEAT
    jax.config.update("jax_enable_x64", True)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results: list[Section] = []
    t_all = time.perf_counter()
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
    write_report(out, results, total=total, quick=quick, log=log)
    return results


def write_report(out: Path, results: Sequence[Section], *, total: float, quick: bool, log=print) -> Path:
    """Write ``out/report.md``: the summary table, then each section's truth, rows, null and figure."""
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
    return out / "report.md"
