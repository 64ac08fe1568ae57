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
    ``DIR/report.md`` and figures; a running section reports progress on stderr.

``tour``, ``run`` and ``evolve`` keep compiled programs in JAX's persistent compilation
cache (``fsjax.enable_compile_cache``: the user's cache directory, ``FSJAX_CACHE_DIR``
overrides it, ``FSJAX_CACHE_DIR=off`` disables it), so a second run skips compilation.
"""

from __future__ import annotations

import argparse
import ast
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


def _cmd_ops(args: argparse.Namespace) -> int:
    import fsjax

    def sort(name):
        if name is None:
            return None
        cls = getattr(fsjax, name, None)
        if not (isinstance(cls, type) and issubclass(cls, fsjax.Sort)):
            raise SystemExit(f"fsjax ops: unknown sort {name!r}")
        return cls

    specs = fsjax.list_ops(family=args.family, takes=sort(args.takes), gives=sort(args.gives), search=args.search)
    width = max((len(s.name) for s in specs), default=4)
    for s in specs:
        knobs = ", ".join(f"{k}" for k in s.knobs) or "-"
        print(f"{s.name:<{width}}  {s.family:<11} {s.signature_str():<28} knobs: {knobs:<22} {s.summary}")
    fams = sorted({s.family for s in specs})
    print(f"\n{len(specs)} ops in {len(fams)} families")
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    import fsjax
    from fsjax import io

    stages = [parse_stage(s) for s in args.stages]
    pipe = fsjax.pipeline(stages)
    want_color = args.color or pipe.takes is fsjax.Color
    x = io.read_image(args.input, as_grey=not want_color)
    print(f"input: {args.input} -> {type(x).__name__} {tuple(x.data.shape)}"
          + (f" ({x.conversion})" if getattr(x, "conversion", None) else ""))
    if not isinstance(x, pipe.takes):
        raise SystemExit(f"fsjax run: stage 1 takes {pipe.takes.__name__}, the file gives {type(x).__name__}")
    outs = pipe.trace(x)
    for i, (st, y) in enumerate(zip(pipe.stages, outs)):
        print(f"stage {i + 1}: {st} -> {type(y).__name__}{_summary(y)}")
    y = outs[-1]
    if isinstance(y, fsjax.Feature):
        print(f"result: {float(y.value):.10g}{(' ' + y.unit) if y.unit else ''}")
    if args.output:
        if isinstance(y, fsjax.Feature):
            raise SystemExit("fsjax run: the result is a Feature (printed above); -o needs an image result")
        io.write_image(args.output, y)
        print(f"wrote {args.output}")
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
    from .evolve.problems import make_problem
    from .evolve.runs import run_problem, write_run
    from .evolve.search import GAConfig

    vocab = [v.strip() for v in args.vocabulary.split(",") if v.strip()] if args.vocabulary else None
    problem = make_problem(args.problem, size=(args.size, args.size), n_train=args.n_train,
                           n_holdout=args.n_holdout, n_locked=args.n_train + args.n_holdout, n_stages=args.stages)
    cfg = GAConfig(pop=args.pop, gens=args.gens)
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
    p.add_argument("-o", "--output")
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

    args = parser.parse_args(argv)
    if args.cmd in ("tour", "run", "evolve"):
        # compiled programs persist across runs (FSJAX_CACHE_DIR overrides, =off disables)
        from ._cache import enable_compile_cache

        enable_compile_cache()
    try:
        return args.func(args)
    except (TypeError, ValueError, KeyError, FileNotFoundError) as e:
        if isinstance(e, KeyError):
            e = str(e)
        print(f"fsjax {args.cmd}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
