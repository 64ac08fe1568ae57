"""The ``fsjax`` command.

``fsjax ops [--family F] [--search TEXT] [--takes SORT] [--gives SORT]``
    list registered ops.
``fsjax run IN.png STAGE [STAGE ...] [-o OUT.png] [--color]``
    run a type-checked pipeline on an image file; prints the sort after each
    stage and a ``Feature`` result. A stage is ``name``, ``name:param=value,...``
    (named parameters) or ``name@a[,b]`` (knob values in [0, 1]).
``fsjax evolve --problem NAME [--gens G] [--pop P] [--seeds S] --out DIR``
    search a pipeline for a synthetic problem (denoise, binarize, edges, count):
    baselines first, then the GA per seed; writes ``DIR/champion.json`` (by op
    names and knobs), ``DIR/baselines.md`` and ``DIR/log.csv``.
``fsjax tour --out DIR [--quick] [--sections a,b] [--list]``
    the library's main job: a scored tour of what fsjax measures; writes
    ``DIR/report.md`` and figures; a running section prints a progress line every 15 s.
``fsjax fuzz --chains N --length L --seed S --out DIR`` / ``fsjax fuzz --replay FILE``
    the chain fuzzer (:mod:`fsjax.fuzz`): random typed chains run eager, under jit, vmap
    and grad (per-stage compiled programs reused across chains; ``--whole-chain F``: the
    fraction of chains also compiled whole, default 0.05; ``--workers N``: processes side
    by side, default ``min(2, CPU count)``); failures classified and minimised into
    ``DIR/report.md`` and JSON lines.

``fsjax sfm IMAGE_DIR --out DIR [--intrinsics fx,fy,cx,cy] [--ground-truth cameras.json]``
    structure from motion (:mod:`fsjax.sfm`): ``DIR/report.md``, ``DIR/sparse/*.txt`` (COLMAP
    text), ``DIR/points.ply``. The photographs must share one size (one camera): a folder of mixed
    sizes is refused, naming the odd files (exit 2). ``IMAGE_DIR`` may be a video file: frames chosen by accumulated
    rotation (``--rotation-deg``, ``--max-gap``; :mod:`fsjax.sfm.video`, needs the ``video`` extra).
``fsjax splat SFM_DIR --out DIR [--images IMAGE_DIR] [--width 192] [--steps N]``
    Gaussian splats trained on the photographs with the cameras of an ``fsjax sfm`` result
    (:mod:`fsjax.sfm.splat`; every 4th image held out): ``DIR/report.md`` (held-out PSNR/SSIM
    beside the untrained sparse points), ``DIR/splats.splat``, ``DIR/splats.ply``, ``DIR/viewer.html``.

``tour``, ``run``, ``evolve``, ``sfm`` and ``splat`` keep compiled programs in JAX's persistent compilation
cache (``fsjax.enable_compile_cache``: the user's cache directory, ``FSJAX_CACHE_DIR``
overrides it, ``FSJAX_CACHE_DIR=off`` disables it), so a second run skips compilation.
``fuzz`` does too for a run (not a replay), in ``--compile-cache DIR`` if given, and its
report says whether the cache was warm or cold at the start.

``tour`` compiles far more than it runs, so it asks XLA:CPU for its older loop emitters
(``XLA_FLAGS=--xla_cpu_use_fusion_emitters=false``, added to the environment before JAX starts its
backend, unless ``XLA_FLAGS`` already names that flag): the quick tour on a cold cache took 169 s
of CPU instead of 258 s and peaked at 1.22 GB instead of 1.71 GB, with the same report (every
figure equal; only timings differ). Not when ``XLA_FLAGS`` sets an optimisation level: the older
emitters at level 0 miscompile (``tools/repro_xla_emitters_level0.py``). Run time moves both ways
under the flag (a 1024 x 1024 Gaussian 2.8x slower, an opening 2x faster), so the library (but
its small fits, ``fsjax._linalg.jit_fast_compile``) and the other commands keep XLA's default;
``fuzz`` too, whose stage programs compile at level 0. ``XLA_FLAGS=--xla_cpu_use_fusion_emitters=true
fsjax tour`` restores the default.
"""

from __future__ import annotations

import argparse
import ast
import os
import sys
from typing import Any


def _value(text: str) -> Any:
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def parse_stage(text: str) -> Any:
    """Parse a command-line stage: ``name``, ``name:k=v,k2=v2`` or ``name@a[,b]``."""
    if "@" in text:
        name, knobs = text.split("@", 1)
        vals = [float(v) for v in knobs.split(",") if v]
        return (name, *vals)
    if ":" in text:
        name, rest = text.split(":", 1)
        params = {}
        for item in filter(None, rest.split(",")):
            if "=" not in item:
                raise SystemExit(f"fsjax run: stage {text!r}: expected param=value, got {item!r}")
            k, v = item.split("=", 1)
            params[k.strip()] = _value(v.strip())
        return (name, params)
    return text


def _fingerprint() -> str:
    """Size and mtime of every module of the installed package: changes when any op could have."""
    import hashlib
    from pathlib import Path

    h = hashlib.sha256()
    root = Path(__file__).resolve().parent
    for f in sorted(root.rglob("*.py")):
        st = f.stat()
        h.update(f"{f.relative_to(root)}:{st.st_size}:{st.st_mtime_ns};".encode())
    return h.hexdigest()[:24]


def _ops_table() -> list[dict]:
    """The op catalogue as plain records, from a cache keyed by the package's files.

    Listing needs every op family imported (JAX, all modules: seconds); the records are
    cached as ``fsjax-ops-<fingerprint>.json`` in the compile-cache directory
    (:func:`fsjax.compile_cache_dir`: ``FSJAX_CACHE_DIR``, else ``~/.cache/fsjax/xla``;
    ``FSJAX_CACHE_DIR=off`` disables it) and rebuilt whenever a module of the package
    changes, so a repeated ``fsjax ops`` does not load the library.
    """
    import json

    from ._cache import compile_cache_dir

    base = compile_cache_dir()  # FSJAX_CACHE_DIR=off: no cache, list from the live registry
    path = None if base is None else base / f"fsjax-ops-{_fingerprint()}.json"
    try:
        return json.loads(path.read_text())
    except (AttributeError, OSError, ValueError):
        pass
    import fsjax

    rows = [{"name": s.name, "family": s.family, "takes": [t.__name__ for t in s.takes], "gives": s.gives.__name__,
             "knobs": list(s.knobs), "summary": s.summary, "sig": s.signature_str()} for s in fsjax.list_ops()]
    if path is not None:
        try:
            base.mkdir(parents=True, exist_ok=True)
            for old in base.glob("fsjax-ops-*.json"):
                old.unlink()
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps(rows))
            tmp.replace(path)
        except OSError:  # a read-only cache directory: list without caching
            pass
    return rows


_SORT_NAMES = ("Image", "Color", "HSV", "Lab", "Region", "Labels", "Feature", "Contour", "Signal", "Volume",
               "Points", "Mesh", "Gaussians", "Camera", "Depth", "Match", "RegionProps", "Fit", "Edges1D")


def _cmd_ops(args: argparse.Namespace) -> int:
    rows = _ops_table()
    known = set(_SORT_NAMES) | {r["gives"] for r in rows} | {t for r in rows for t in r["takes"]}
    for name in (args.takes, args.gives):
        if name is not None and name not in known:
            raise SystemExit(f"fsjax ops: unknown sort {name!r}; sorts: {', '.join(sorted(known))}")
    fams = sorted({r["family"] for r in rows})
    if args.family is not None and args.family not in fams:
        raise ValueError(f"list_ops: unknown family {args.family!r}; known: {', '.join(fams)}")
    q = (args.search or "").lower()
    specs = [r for r in rows
             if (args.family is None or r["family"] == args.family)
             and (args.takes is None or r["takes"] == [args.takes])
             and (args.gives is None or r["gives"] == args.gives)
             and (not q or q in r["name"].lower() or q in r["family"].lower() or q in r["summary"].lower())]
    width = max((len(s["name"]) for s in specs), default=4)
    for s in specs:
        knobs = ", ".join(s["knobs"]) or "-"
        print(f"{s['name']:<{width}}  {s['family']:<11} {s['sig']:<28} knobs: {knobs:<22} {s['summary']}")
    fams = sorted({s["family"] for s in specs})
    print(f"\n{len(specs)} ops in {len(fams)} families")
    return 0


def _check_output(path: str, gives: type, bits: int) -> None:
    """Refuse an output the pipeline result cannot be written to, before anything runs."""
    import os

    import fsjax

    if gives is fsjax.Feature:
        raise SystemExit("fsjax run: the pipeline gives a Feature (a number, printed); -o needs an image result")
    if gives not in (fsjax.Image, fsjax.Color, fsjax.Region):
        raise SystemExit(f"fsjax run: the pipeline gives {gives.__name__}; -o writes Image, Color or Region only")
    if not path.lower().endswith(".png"):
        raise SystemExit(f"fsjax run: -o {path!r}: only PNG is written (lossless, 8 or 16 bit); use a .png name")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise SystemExit(f"fsjax run: -o {path!r}: the folder {folder!r} does not exist")
    if bits == 16 and gives is not fsjax.Image:
        raise SystemExit(f"fsjax run: --bits 16 writes grey Image results only; the pipeline gives {gives.__name__}")


def _cmd_run(args: argparse.Namespace) -> int:
    import fsjax
    from fsjax import io

    stages = [parse_stage(s) for s in args.stages]
    pipe = fsjax.pipeline(stages)
    if args.output:
        _check_output(args.output, pipe.gives, args.bits)
    want_color = args.color or pipe.takes is fsjax.Color
    x = io.read_image(args.input, as_grey=not want_color)
    print(f"input: {args.input} -> {type(x).__name__} {tuple(x.data.shape)}"
          + (f" ({x.conversion})" if getattr(x, "conversion", None) else ""))
    if not isinstance(x, pipe.takes):
        raise SystemExit(f"fsjax run: stage 1 takes {pipe.takes.__name__}, the file gives {type(x).__name__}")
    print(f"running {len(pipe)} stage(s) (each op compiles on its first call) ...", flush=True)
    import time

    import jax

    t0 = [time.perf_counter()]

    def progress(i, st, y):  # one line per finished stage, as it finishes (large images take a while)
        jax.block_until_ready(y)
        t = time.perf_counter()
        print(f"stage {i + 1}/{len(pipe)}: {st} -> {type(y).__name__}{_summary(y)} ({t - t0[0]:.1f} s)", flush=True)
        t0[0] = t

    outs = pipe.trace(x, on_stage=progress)
    y = outs[-1]
    if isinstance(y, fsjax.Feature):
        print(f"result: {float(y.value):.10g}{(' ' + y.unit) if y.unit else ''}")
    if args.output:
        if isinstance(y, fsjax.Feature):
            raise SystemExit("fsjax run: the result is a Feature (printed above); -o needs an image result")
        io.write_image(args.output, y, bit_depth=args.bits)
        print(f"wrote {args.output} ({args.bits}-bit)")
        if args.bits == 8 and "uint16" in str(getattr(x, "conversion", "")):
            print("note: the input was 16-bit; the result was written as 8-bit (--bits 16 keeps 16)")
    return 0


def _summary(y: Any) -> str:
    import numpy as np

    import fsjax

    if isinstance(y, (fsjax.Image, fsjax.Color)):
        d = np.asarray(y.data)
        return f" {d.shape} range [{d.min():.4g}, {d.max():.4g}]"
    if isinstance(y, fsjax.Region):
        d = np.asarray(y.data)
        return f" {d.shape} {int(d.sum())} px set"
    if isinstance(y, fsjax.Labels):
        return f" {tuple(y.data.shape)} {int(y.count)} labels"
    if isinstance(y, fsjax.Feature):
        return f" = {float(y.value):.6g}"
    return ""


def _cmd_evolve(args: argparse.Namespace) -> int:
    if not args.quiet:
        print(f"evolve: loading JAX and building the {args.problem!r} problem ...", flush=True)
    from .evolve.problems import make_problem
    from .evolve.runs import run_problem, write_run
    from .evolve.search import GAConfig

    vocab = [v.strip() for v in args.vocabulary.split(",") if v.strip()] if args.vocabulary else None
    problem = make_problem(args.problem, size=(args.size, args.size), n_train=args.n_train,
                           n_holdout=args.n_holdout, n_locked=args.n_train + args.n_holdout, n_stages=args.stages)
    cfg = GAConfig(pop=args.pop, gens=args.gens)
    if not args.quiet:
        print(f"evolve {args.problem}: {args.seeds} seed(s) x {args.gens} generations x {args.pop} individuals; "
              "measuring the baselines, then compiling the population program (one compile per skeleton, "
              "often 20-60 s on a laptop CPU) before the first generation ...", flush=True)
    report = run_problem(problem, seeds=range(args.seeds), cfg=cfg, vocabulary=vocab, progress=not args.quiet)
    paths = write_run(report, args.out)
    print(f"skeleton {report.skeleton}; compile {report.compile_seconds:.1f} s, total {report.seconds:.1f} s")
    print(report.table())
    best = report.best_seed().champion
    print("champion (best seed by train): " + " -> ".join(
        st["op"] + (f"(a={st['a']:.3f}" + (f", b={st['b']:.3f})" if st["b"] is not None else ")")
                    if st["a"] is not None else "") for st in best["stages"]))
    for k, p in paths.items():
        print(f"wrote {p} ({k})")
    return 0


def _cmd_tour(args: argparse.Namespace) -> int:
    from .tour import run_tour, section_names

    if args.list:
        print("\n".join(section_names()))
        return 0
    if not args.out:
        raise ValueError("argument '--out' is required (the directory for report.md and figures)")
    sections = [v.strip() for v in args.sections.split(",") if v.strip()] if args.sections else None
    run_tour(args.out, quick=args.quick, sections=sections)
    return 0


def _cmd_fuzz(args) -> int:
    from .fuzz._report import cli_main

    return cli_main(args)


def _cmd_sfm(args) -> int:
    from .sfm.run import run_folder

    intr = None
    if args.intrinsics:
        intr = [float(v) for v in args.intrinsics.split(",")]
        if len(intr) != 4:
            raise ValueError(f"argument '--intrinsics' must be fx,fy,cx,cy, got {args.intrinsics!r}")
    from .sfm.video import is_video, run_video

    if is_video(args.image_dir):  # a video: frames chosen by accumulated rotation (fsjax.sfm.video)
        rec, _ = run_video(args.image_dir, args.out, intrinsics=intr, threshold_deg=args.rotation_deg,
                           max_gap=args.max_gap or None, n_max=args.max_features, n_octaves=args.octaves, log=print)
        return 0 if rec.registered.sum() >= 2 else 1
    rec = run_folder(args.image_dir, args.out, intrinsics=intr, ground_truth=args.ground_truth,
                     n_max=args.max_features, n_octaves=args.octaves, log=print)
    return 0 if rec.registered.sum() >= 2 else 1


def _cmd_splat(args) -> int:
    from .sfm.splat import splat_from_sfm

    r = splat_from_sfm(args.sfm_dir, args.out, image_dir=args.images, width=args.width, iterations=args.steps,
                       max_splats=args.max_splats, seed=args.seed, log=print)
    if not r["beats_null"]:
        print("fsjax splat: the trained splats did NOT beat the null on the held-out views (see report.md)")
    return 0 if r["beats_null"] else 1


def _prefer_fast_compile() -> None:
    """XLA:CPU's older loop emitters for the compile-dominated tour (module docstring).

    Takes effect only if JAX's backend has not started in this process (the CLI imports no
    JAX before this); nothing is added when ``XLA_FLAGS`` names the flag or sets an
    optimisation level (the older emitters at level 0 miscompile).
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" not in flags and "xla_backend_optimization_level" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " --xla_cpu_use_fusion_emitters=false").strip()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="fsjax", description="Typed, jit-compiled vision operators in JAX.")
    sub = parser.add_subparsers(dest="cmd", required=True)

    p = sub.add_parser("ops", help="list registered ops")
    p.add_argument("--family")
    p.add_argument("--search")
    p.add_argument("--takes", help="input sort name, e.g. Image")
    p.add_argument("--gives", help="output sort name, e.g. Region")
    p.set_defaults(func=_cmd_ops)

    p = sub.add_parser("run", help="run a pipeline on an image file")
    p.add_argument("input")
    p.add_argument("stages", nargs="+", help="name | name:param=value,... | name@a[,b]")
    p.add_argument("-o", "--output", help="write the result to this PNG (checked before the pipeline runs)")
    p.add_argument("--bits", type=int, choices=(8, 16), default=8, help="bit depth of the -o PNG (16: grey only)")
    p.add_argument("--color", action="store_true", help="read the file as Color (default: grey)")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("evolve", help="evolve a pipeline for a synthetic problem; write champion, baselines, log")
    p.add_argument("--problem", required=True, choices=["denoise", "binarize", "edges", "count"])
    p.add_argument("--gens", type=int, default=40)
    p.add_argument("--pop", type=int, default=64)
    p.add_argument("--seeds", type=int, default=3, help="independent runs (seeds 0..S-1)")
    p.add_argument("--stages", type=int, default=6, help="stages of the search skeleton")
    p.add_argument("--size", type=int, default=64, help="image side in pixels")
    p.add_argument("--n-train", type=int, default=16)
    p.add_argument("--n-holdout", type=int, default=8)
    p.add_argument("--vocabulary", help="comma-separated op names (default: fsjax.evolve.DEFAULT_VOCABULARY)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--out", required=True)
    p.set_defaults(func=_cmd_evolve)

    p = sub.add_parser("tour", help="run the scored tour and write DIR/report.md")
    p.add_argument("--out", help="output directory (report.md and figures)")
    p.add_argument("--quick", action="store_true", help="smaller inputs (the form CI runs)")
    p.add_argument("--sections", help="comma-separated section names (default: all; see --list)")
    p.add_argument("--list", action="store_true", help="list the section names and exit")
    p.set_defaults(func=_cmd_tour)

    p = sub.add_parser("fuzz", help="chain fuzzer: random typed chains run eager/jit/vmap/grad; DIR/report.md")
    p.add_argument("--chains", type=int, default=200)
    p.add_argument("--length", type=int, default=6, help="maximum chain length")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--minutes", type=float, help="stop drawing new chains after this many minutes")
    p.add_argument("--no-grad", action="store_true", help="skip the grad way")
    p.add_argument("--whole-chain", type=float, default=None,
                   help="fraction of chains also compiled whole, jit(vmap(chain)) and grad (default 0.05; "
                        "every chain runs through per-stage compiled programs)")
    p.add_argument("--compile-cache", default=None,
                   help="persistent compile cache directory for a run (default: fsjax's, as FSJAX_CACHE_DIR "
                        "resolves it; 'off' disables); the report says whether it was warm or cold")
    p.add_argument("--workers", type=int, default=None,
                   help="processes running chains side by side (default: min(2, CPU count)); each covers its "
                        "share of the registry first, failures are minimised after")
    p.add_argument("--strict", action="store_true", help="exit 1 on SUSPECT/TYPEMISS/MISMATCH/SILENT_OVERFLOW/GRADNAN")
    p.add_argument("--replay", help="JSON-lines file of chains or failure records to run again")
    p.add_argument("--out", help="output directory (report.md, failures.jsonl, minimised.jsonl)")
    p.set_defaults(func=_cmd_fuzz)

    p = sub.add_parser("sfm", help="structure from motion on a folder of photographs or a video; DIR/report.md, COLMAP text, PLY")
    p.add_argument("image_dir", help="folder of .jpg/.png photographs of one size, or a video file (.mp4, .mov, ...)")
    p.add_argument("--out", required=True)
    p.add_argument("--intrinsics", help="fx,fy,cx,cy in pixels (pixel centres on integers); default: one focal length self-calibrated, principal point at the centre (image folders)")
    p.add_argument("--ground-truth", help="cameras.json to score against (as in ../shared/data/sfm)")
    p.add_argument("--max-features", type=int, default=4096, help="keypoint capacity per image")
    p.add_argument("--octaves", type=int, default=5, help="detector octaves (the first at twice the image size)")
    p.add_argument("--rotation-deg", type=float, default=10.0, help="video: keep a frame when the camera has turned this much")
    p.add_argument("--max-gap", type=int, default=30, help="video: keep a frame at least every this many frames (0: no limit)")
    p.set_defaults(func=_cmd_sfm)

    p = sub.add_parser("splat", help="Gaussian splats trained on the photographs of an sfm result; DIR/report.md, "
                                     ".splat, PLY, viewer")
    p.add_argument("sfm_dir", help="an `fsjax sfm` output (or any folder with a COLMAP text model in sparse/)")
    p.add_argument("--out", required=True)
    p.add_argument("--images", help="the photographs (default: SFM_DIR/images, else the folder fsjax sfm recorded)")
    p.add_argument("--width", type=int, default=192, help="training image width in pixels (height in proportion)")
    p.add_argument("--steps", type=int, default=3000, help="training steps (one view each)")
    p.add_argument("--max-splats", type=int, default=30000, help="splat capacity (densification stops there)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_splat)

    args = parser.parse_args(argv)
    if args.cmd == "tour":
        _prefer_fast_compile()
    if args.cmd in ("tour", "run", "evolve", "sfm", "splat"):
        # compiled programs persist across runs (FSJAX_CACHE_DIR overrides, =off disables)
        from ._cache import enable_compile_cache

        enable_compile_cache()
    try:
        return args.func(args)
    except (TypeError, ValueError, KeyError, FileNotFoundError, ImportError) as e:
        if isinstance(e, KeyError):
            e = str(e)
        print(f"fsjax {args.cmd}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
