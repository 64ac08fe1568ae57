"""Chain generation: the sort graph, the input pool, random type-correct chains.

A chain is plain data (JSON-able), so a failure can be written as one line and replayed::

    {"input": {"sort": "Image", "kind": "scene", "size": [16, 16], "dtype": "float64", "variant": 0},
     "stages": [{"op": "gaussian", "a": 0.31, "b": null, "params": {}, "slot": 0}, ...]}

``slot`` is the position of the chain's running value among the inputs of a multi-input op;
the other inputs come from the pool (built at the running value's raster size, next variant).
"""

from __future__ import annotations

import dataclasses
import math
import random
from collections.abc import Sequence
from typing import Any

__all__ = ["Chain", "DrawState", "Stage", "SortGraph", "IMAGE_KINDS", "KNOB_STEPS", "build_input", "generate_chain"]

# Image inputs of the pool: kind -> (weight, default size). Sizes are few on purpose: every
# new shape compiles every primitive again.
IMAGE_KINDS: dict[str, tuple[float, tuple[int, int] | None]] = {
    "scene": (4.0, None),        # the standard scene (fsjax.synth.standard_input), size drawn from SIZES
    "photo": (1.5, (16, 16)),    # skimage.data.camera, block-averaged (a real photograph)
    "constant": (1.0, (16, 16)),
    "spike": (1.0, (16, 16)),    # a single bright pixel on black
    "large": (1.0, (16, 16)),    # the scene times 1e6 (very large values)
    "tiny": (0.4, (1, 1)),       # edge sizes: rarer than before (every new shape compiles again)
    "odd": (0.6, (3, 5)),
    "nan": (0.3, (16, 16)),      # all-NaN: must be refused at the door
}
try:  # scikit-image is not a core dependency: without it the pool has no photograph
    import skimage as _skimage  # noqa: F401
except ImportError:
    del IMAGE_KINDS["photo"]
SIZES: tuple[tuple[int, int], ...] = ((16, 16), (15, 17))
# the canonical size most chains use (its programs repeat), and the odd size now and then
SIZE_WEIGHTS: tuple[float, ...] = (0.85, 0.15)
DTYPES: tuple[str, ...] = ("float64", "float32")
RASTER_KINDS = ("scene", "constant", "empty")  # other raster sorts (Color, Region, Labels, ...)
# sorts whose "constant" variant is a meaningful input (a flat raster, volume or profile);
# others (points, meshes, cameras, contours) always come as the pool's scene
RASTER_SORTS = frozenset({"Color", "HSV", "Lab", "Region", "Labels", "Depth", "Volume", "Signal"})


@dataclasses.dataclass(frozen=True)
class Stage:
    op: str
    a: float | None = None
    b: float | None = None
    params: tuple[tuple[str, Any], ...] = ()
    slot: int = 0

    def to_json(self) -> dict:
        return {"op": self.op, "a": self.a, "b": self.b, "params": dict(self.params), "slot": self.slot}

    @classmethod
    def from_json(cls, d: dict) -> Stage:
        return cls(d["op"], d.get("a"), d.get("b"), tuple(sorted((d.get("params") or {}).items())),
                   int(d.get("slot", 0)))


@dataclasses.dataclass(frozen=True)
class Chain:
    """A fuzz chain: an input description and stages (plain data)."""

    input: tuple[tuple[str, Any], ...]
    stages: tuple[Stage, ...]

    @property
    def inp(self) -> dict:
        return dict(self.input)

    def to_json(self) -> dict:
        return {"input": self.inp, "stages": [s.to_json() for s in self.stages]}

    @classmethod
    def from_json(cls, d: dict) -> Chain:
        inp = dict(d["input"])
        if "size" in inp:
            inp["size"] = tuple(inp["size"])
        return cls(tuple(sorted(inp.items())), tuple(Stage.from_json(s) for s in d["stages"]))

    def replace(self, **kw) -> Chain:
        return dataclasses.replace(self, **kw)

    def with_input(self, **kw) -> Chain:
        inp = self.inp
        inp.update(kw)
        return self.replace(input=tuple(sorted(inp.items())))

    def describe(self) -> str:
        i = self.inp
        size = "x".join(map(str, i["size"]))
        head = f"{i['sort']}[{i['kind']} {size} {i['dtype']}]"
        parts = []
        for s in self.stages:
            k = ",".join(f"{v:.2f}" for v in (s.a, s.b) if v is not None)
            p = ",".join(f"{n}={v}" for n, v in s.params)
            parts.append(s.op + (f"@{k}" if k else "") + (f":{p}" if p else "") + (f"#{s.slot}" if s.slot else ""))
        return " -> ".join([head, *parts])


# ---------------------------------------------------------------------------
# Input pool
# ---------------------------------------------------------------------------


def _photo(variant: int, size: tuple[int, int]):
    import numpy as np

    try:
        from skimage import data as skdata
    except ImportError:  # the pool drops "photo" without scikit-image; a replayed chain may still ask
        raise RuntimeError("fsjax fuzz: the 'photo' input needs scikit-image (pip install scikit-image)") from None

    img = skdata.camera().astype(np.float64) / 255.0  # 512 x 512
    h, w = size
    img = img[: (512 // h) * h, : (512 // w) * w].reshape(h, 512 // h, w, 512 // w).mean(axis=(1, 3))
    return img[:, ::-1].copy() if variant % 2 else img


def _image_array(kind: str, variant: int, size: tuple[int, int]):
    import numpy as np

    from fsjax.synth import standard_scene

    h, w = size
    if kind in ("scene", "odd"):
        return standard_scene(variant % 2, size)[0]
    if kind == "photo":
        return _photo(variant, size)
    if kind == "constant":
        return np.full(size, 0.5 if variant % 2 == 0 else 0.3)
    if kind == "tiny":
        return np.full(size, 0.5 if variant % 2 == 0 else 0.2)
    if kind == "spike":
        a = np.zeros(size)
        a[(h // 3 + variant) % h, (w // 2 + 2 * variant) % w] = 1.0
        return a
    if kind == "large":
        return standard_scene(variant % 2, size)[0] * 1e6
    if kind == "nan":
        return np.full(size, np.nan)
    raise ValueError(f"fuzz: unknown image kind {kind!r}")


def _cast(x, dtype: str):
    import jax
    import jax.numpy as jnp

    def c(v):
        if hasattr(v, "dtype") and jnp.issubdtype(v.dtype, jnp.floating) and v.dtype != dtype:
            return jnp.asarray(v, dtype=dtype)
        return v

    return jax.tree_util.tree_map(c, x)


def build_input(sort: type, kind: str, size: tuple[int, int], dtype: str, variant: int = 0):
    """One pool input: ``sort`` of ``kind`` at ``size`` (raster sorts) in ``dtype``."""
    import jax.numpy as jnp

    from fsjax.registry import list_ops
    from fsjax.synth import standard_input
    from fsjax.types import Image, Region

    list_ops()  # op families register the pool builders of the sorts they introduce
    size = tuple(size)
    if sort is Image:
        return Image(jnp.asarray(_image_array(kind, variant, size), dtype=dtype))
    if kind == "empty" and sort is Region:
        import numpy as np

        return Region(jnp.asarray(np.zeros(size, bool)))
    x = standard_input(sort, variant % 2, size=size)
    if kind == "constant":
        import jax

        def flat(v):
            if hasattr(v, "dtype") and jnp.issubdtype(v.dtype, jnp.floating) and v.ndim >= 2:
                return jnp.full_like(v, 0.5 if variant % 2 == 0 else 0.3)
            return v

        x = jax.tree_util.tree_map(flat, x)
    return _cast(x, dtype)


def raster_size(x) -> tuple[int, int] | None:
    """``(H, W)`` of a raster sort (by its main array), else ``None``."""
    arr = getattr(x, "data", None)
    if arr is None or getattr(arr, "ndim", 0) < 2:
        return None
    if arr.ndim >= 3 and arr.shape[-1] == 3 and type(x).__name__ in ("Color", "HSV", "Lab"):
        return tuple(arr.shape[-3:-1])
    return tuple(arr.shape[-2:])


def float_dtype(x) -> str | None:
    import jax
    import jax.numpy as jnp

    for v in jax.tree_util.tree_leaves(x):
        if hasattr(v, "dtype") and jnp.issubdtype(v.dtype, jnp.floating):
            return str(v.dtype)
    return None


def extra_input(sort: type, like, dtype: str, variant: int):
    """A pool input of ``sort`` to fill another slot of a multi-input op fed with ``like``."""
    size = raster_size(like) or SIZES[0]
    x = build_input(sort, "scene", size, dtype, variant)
    sp = getattr(like, "spacing", None)
    if sort.__name__ == "Volume" and type(like).__name__ == "Volume" and sp is not None and sp != x.spacing:
        # the ops that take two volumes need one spacing (ncc3d, lk_translation3d, ...): the pool's
        # second volume takes the running one's, so they are not refused for a mismatch alone
        x = sort(x.data, spacing=tuple(sp))
    return x


# ---------------------------------------------------------------------------
# The sort graph
# ---------------------------------------------------------------------------


class SortGraph:
    """Which ops can take which sorts, and which sorts are reachable from the pool.

    ``pool``: sorts the pool can build. ``reachable``: the fixed point of
    "a sort is reachable when the pool builds it or an op whose every input is
    reachable (the chain slot) or pool-buildable (other slots) gives it".
    """

    def __init__(self, specs: Sequence[Any], pool: set[type]):
        self.specs = {s.name: s for s in specs}
        self.pool = set(pool)
        reach = set(self.pool)
        changed = True
        while changed:
            changed = False
            for s in specs:
                if s.gives in reach:
                    continue
                if any(self._slot_ok(s, i, reach) for i in range(len(s.takes))):
                    reach.add(s.gives)
                    changed = True
        self.reachable = reach

    def _slot_ok(self, spec, slot: int, reach: set[type]) -> bool:
        if not any(issubclass(r, spec.takes[slot]) for r in reach):
            return False
        return all(any(issubclass(p, t) for p in self.pool) for j, t in enumerate(spec.takes) if j != slot)

    def candidates(self, sort: type) -> list:
        """``(spec, slot)`` for every op slot that can take the running value of ``sort`` (cached)."""
        memo = self.__dict__.setdefault("_cands", {})
        if sort not in memo:
            memo[sort] = [(s, i) for s in self.specs.values() for i in self.slots_for(s, sort)]
        return memo[sort]

    def slots_for(self, spec, sort: type) -> list[int]:
        """Slots of ``spec`` that can take the running value of ``sort`` (others from the pool)."""
        out = []
        for i, t in enumerate(spec.takes):
            if issubclass(sort, t) and all(any(issubclass(p, u) for p in self.pool)
                                           for j, u in enumerate(spec.takes) if j != i):
                out.append(i)
        return out

    def sorts_after(self, sort_name: str, stages) -> type:
        """The running sort after ``stages`` applied to an input of sort ``sort_name``."""
        cur = next(t for t in self.pool if t.__name__ == sort_name)
        for st in stages:
            cur = self.specs[st.op].gives
        return cur

    def runnable(self, spec) -> bool:
        return any(self._slot_ok(spec, i, self.reachable) for i in range(len(spec.takes)))

    def why_unreachable(self, spec) -> str:
        missing = [t.__name__ for t in spec.takes if not any(issubclass(r, t) for r in self.reachable)]
        if missing:
            return f"no reachable input sort ({', '.join(missing)})"
        nopool = [t.__name__ for t in spec.takes if not any(issubclass(p, t) for p in self.pool)]
        return f"second input sort has no pool builder ({', '.join(nopool)})"


# knob values on a grid of 1 / KNOB_STEPS: a concrete value that sizes a kernel compiles the
# eager primitives again, so few values let the eager way's compiled primitives repeat (the
# traced ways take knobs as traced arguments: their programs do not depend on the value)
KNOB_STEPS = 10


def _draw_knob(rng: random.Random) -> float:
    r = rng.random()
    if r < 0.1:
        return 0.0
    if r < 0.2:
        return 1.0
    return round(round(rng.random() * KNOB_STEPS) / KNOB_STEPS, 4)


def _draw_params(spec, rng: random.Random) -> tuple[tuple[str, Any], ...]:
    # named parameters that are not knob-mapped: the spec gives only their defaults; a bool's
    # other value is legal by its type, so bools are flipped now and then, and a ``capacity``
    # is set small now and then. Other types (str choices, tuples, other ints) stay at their
    # default: their legal values are not in the spec.
    out = []
    for name, default in spec.params.items():
        if name in spec.knobs:
            continue
        if isinstance(default, bool) and rng.random() < 0.2:
            out.append((name, not default))
        elif name == "capacity" and isinstance(default, int) and rng.random() < 0.3:
            # fixed capacities: a small one makes overflow happen (it must be flagged)
            out.append((name, rng.choice([1, 2, 4])))
    return tuple(out)


def _weighted(rng: random.Random, items: list, weights: list[float]):
    total = sum(weights)
    r = rng.random() * total
    for it, w in zip(items, weights):
        r -= w
        if r <= 0:
            return it
    return items[-1]


def _input_for(sort: type, rng: random.Random, canonical: bool = False) -> dict:
    """An input description for ``sort``: kind, size and dtype drawn. ``canonical``: the
    coverage phase's input, at the canonical size ``SIZES[0]`` (edge sizes left out)."""
    from fsjax.types import Image

    dtype = rng.choice(DTYPES)
    size_w = [1.0] if canonical else list(SIZE_WEIGHTS)
    if sort is Image:
        kinds = [k for k in IMAGE_KINDS if not canonical or IMAGE_KINDS[k][1] in (None, SIZES[0])]
        kind = _weighted(rng, kinds, [IMAGE_KINDS[k][0] for k in kinds])
        size = IMAGE_KINDS[kind][1] or _weighted(rng, list(SIZES[: len(size_w)]), size_w)
    else:
        kind = _weighted(rng, list(RASTER_KINDS), [4.0, 1.0, 0.5])
        size = _weighted(rng, list(SIZES[: len(size_w)]), size_w)
        if (kind == "empty" and sort.__name__ != "Region") or sort.__name__ not in RASTER_SORTS:
            kind = "scene"
    return {"sort": sort.__name__, "kind": kind, "size": tuple(size), "dtype": dtype, "variant": 0}


# After every op has been drawn once (the coverage phase), ops are drawn WITH replacement:
# a chain then starts, with probability ``PREFIX_REUSE``, from an earlier chain's input and
# a prefix of its stages (knob values included: its eager results, stage programs and grad
# programs all exist), and is extended with new stages; an op whose (op, running sort,
# input size, dtype) was drawn before weighs ``SEEN_WEIGHT`` times an unseen one (its
# compiled programs very likely exist). Least-used-first drawing stays for the unseen.
PREFIX_REUSE = 0.6
SEEN_WEIGHT = 4.0   # a seen combination against an unseen one, when the two-level draw is off
# The reuse phase draws each stage in two levels: with probability ``NEW_COMBO_RATE`` among the
# candidates whose (op, running sort, input size, dtype) was not drawn before (new programs to
# compile), otherwise among those drawn before (their programs exist). A one-level weighting
# (``SEEN_WEIGHT`` x) cannot bound the compiles: the unseen candidates are many, so their summed
# weight won (80 % of reuse-phase chains compiled something in the fourth full run). ``None``:
# the one-level weighting.
NEW_COMBO_RATE: float | None = 0.05
HISTORY = 400   # earlier chains a prefix is drawn from (the most recent)
COVERAGE_USED_WEIGHT = 0.02   # coverage phase: an op drawn before, against 1 for one not drawn yet


@dataclasses.dataclass
class DrawState:
    """What the generator remembers across chains of one run: op uses, the (op, sort, size,
    dtype) combinations drawn (their programs were compiled), and recent chains (prefixes to
    extend). ``generate_chain`` updates it."""

    uses: dict[str, int] = dataclasses.field(default_factory=dict)
    seen: set = dataclasses.field(default_factory=set)
    history: list = dataclasses.field(default_factory=list)
    covered: bool = False   # every drawable op drawn at least once: the reuse phase
    drawn: dict = dataclasses.field(default_factory=dict)   # combination -> stages drawn for it (knobs, params)
    cover: frozenset | None = None   # the ops the coverage phase must draw (None: every drawable op);
    # a worker of a parallel run covers its share of the registry (fsjax.fuzz.fuzz(workers=...))
    emitted: set = dataclasses.field(default_factory=set)   # chains drawn so far (exact repeats are redrawn)
    repeats: int = 0   # chains that are exact repeats all the same (REPEAT_REDRAWS draws were all repeats)


# An exact repeat of a chain drawn before (the same input, stages, knob values and parameters) tests
# nothing new: the runner takes its results from the earlier chain's prefix and it costs ~0 s, so
# it only inflated the chain count (the fifth full run: 59 of its 359 chains). The generator draws
# again, up to this many times.
REPEAT_REDRAWS = 20


def generate_chain(graph: SortGraph, rng: random.Random, max_length: int, uses: dict[str, int] | DrawState,
                   ) -> Chain:
    """One random type-correct chain; with a :class:`DrawState`, not an exact repeat of a chain
    drawn before in the run (drawn again up to ``REPEAT_REDRAWS`` times; ``state.repeats`` counts
    the repeats left).

    ``uses``: a :class:`DrawState` (or, as before, a bare dict of op uses: then every chain is
    drawn least-used-first, the coverage phase only). While some drawable op has not been
    drawn (the coverage phase), an op not drawn yet weighs 1 and one drawn ``u`` times
    ``COVERAGE_USED_WEIGHT / (1 + u)^2``, on the canonical input size (with a bare dict:
    ``1 / (1 + u)^2``, every size). After that (the reuse phase) a chain extends an earlier chain's prefix with
    probability ``PREFIX_REUSE``, and combinations drawn before weigh ``SEEN_WEIGHT`` times
    more (see the module constants).
    """
    if not isinstance(uses, DrawState):
        return _draw_chain(graph, rng, max_length, uses)
    state = uses
    for _ in range(REPEAT_REDRAWS):
        chain = _draw_chain(graph, rng, max_length, state)
        if chain not in state.emitted:
            break
    else:
        state.repeats += 1
    state.emitted.add(chain)
    state.history.append(chain)
    del state.history[:-HISTORY]
    if not state.covered:
        drawable = graph.__dict__.setdefault("_drawable", [n for n, s in graph.specs.items() if graph.runnable(s)])
        state.covered = all(state.uses.get(n, 0) for n in drawable if state.cover is None or n in state.cover)
    return chain


def _draw_chain(graph: SortGraph, rng: random.Random, max_length: int, uses: dict[str, int] | DrawState) -> Chain:
    state = uses if isinstance(uses, DrawState) else None
    uses = state.uses if state is not None else uses
    reuse = state is not None and state.covered

    def pick(items: list, keys: list, weights: list[float]):
        # the reuse phase's two-level draw (NEW_COMBO_RATE): seen combinations, else new ones
        if reuse and NEW_COMBO_RATE is not None:
            seen = [k in state.seen for k in keys]
            old = [it for it, sn in zip(items, seen) if sn]
            new = [it for it, sn in zip(items, seen) if not sn]
            if old and (not new or rng.random() >= NEW_COMBO_RATE):
                return old[rng.randrange(len(old))]
            return new[rng.randrange(len(new))]
        return _weighted(rng, items, weights)

    def w(name: str, sort: type | None = None, inp: dict | None = None) -> float:
        base = 1.0 / (1.0 + uses.get(name, 0)) ** 2
        if state is not None and not reuse:   # the coverage phase: an op not drawn yet first
            if state.cover is not None and name not in state.cover and not uses.get(name):
                # another worker's share (or outside a bounded run's share): only a bridge
                # between sorts, not drawn for its own sake (it compiles everything new)
                return COVERAGE_USED_WEIGHT ** 2
            return 1.0 if not uses.get(name) else COVERAGE_USED_WEIGHT * base
        if not reuse:
            return base
        # the reuse phase: with replacement, combinations drawn before (compiled) preferred
        return SEEN_WEIGHT if (name, sort.__name__, inp["size"], inp["dtype"]) in state.seen else 1.0

    length = rng.randint(1, max_length)
    stages: list[Stage] = []
    cur = None
    inp = None
    if reuse and state.history and length > 1 and rng.random() < PREFIX_REUSE:
        prev = state.history[rng.randrange(len(state.history))]
        k = rng.randint(1, min(length - 1, len(prev.stages)))
        inp = prev.inp
        stages = list(prev.stages[:k])
        cur = graph.sorts_after(inp["sort"], stages)
    if not stages:
        # first stage: any op with a slot the pool feeds directly
        firsts = [(s, i, p) for p in sorted(graph.pool, key=lambda t: t.__name__) for s, i in graph.candidates(p)]
        # the coverage phase draws canonical inputs only; the reuse phase other sizes and the edge
        # inputs at the rate of new combinations (every new shape compiles every program again)
        canonical = state is not None and (not reuse or (NEW_COMBO_RATE is not None and rng.random() >= NEW_COMBO_RATE))
        sort_in = {}
        fw = []
        for s, _, p in firsts:
            if p not in sort_in:
                sort_in[p] = _input_for(p, rng, canonical=canonical)
            fw.append(w(s.name, p, sort_in[p]))
        fkeys = [(s.name, p.__name__, sort_in[p]["size"], sort_in[p]["dtype"]) for s, _, p in firsts]
        spec, slot, psort = pick(firsts, fkeys, fw)
        inp = sort_in[psort]
    for k in range(len(stages), length):
        if k > 0:
            cands = graph.candidates(cur)
            if not cands:
                break
            spec, slot = pick(cands, [(s.name, cur.__name__, inp["size"], inp["dtype"]) for s, _ in cands],
                              [w(s.name, cur, inp) for s, _ in cands])
        combo = (spec.name, (cur or psort).__name__, inp["size"], inp["dtype"])
        earlier = state.drawn.get(combo) if state is not None else None
        if reuse and NEW_COMBO_RATE is not None and earlier and rng.random() >= NEW_COMBO_RATE:
            # knob values and parameters drawn before for this combination: a knob that sizes an
            # array (a kernel, a crop) gives the shapes, so the eager primitives and every later
            # stage's programs exist; new values at the rate of new combinations
            stages.append(dataclasses.replace(earlier[rng.randrange(len(earlier))], slot=slot))
        else:
            knobs = [_draw_knob(rng) if rng.random() < 0.85 else None for _ in spec.knobs]
            a = knobs[0] if knobs else None
            b = knobs[1] if len(knobs) > 1 else None
            stages.append(Stage(spec.name, a, b, _draw_params(spec, rng), slot))
            if state is not None and len(state.drawn.setdefault(combo, [])) < 8:
                state.drawn[combo].append(stages[-1])
        uses[spec.name] = uses.get(spec.name, 0) + 1
        if state is not None:
            state.seen.add(combo)
        cur = spec.gives
    return Chain(tuple(sorted(inp.items())), tuple(stages))


def knob_values(chain: Chain) -> list[tuple[float, float]]:
    """The knob array of a chain (``None`` -> 0.5 placeholder, never read)."""
    return [(0.5 if s.a is None else s.a, 0.5 if s.b is None else s.b) for s in chain.stages]


def is_finite_number(v) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)
