"""Genomes, stage vocabularies and type skeletons, all derived from the registry.

A *type skeleton* is the sequence of sorts a pipeline passes through, e.g.
``Image -> Image -> Image -> Region -> Region`` (four stages). Stage ``s`` maps
sort ``sorts[s]`` to ``sorts[s + 1]``; its *vocabulary* is every registered
one-input op of the search vocabulary whose ``takes`` is exactly
``(sorts[s],)`` and whose ``gives`` is ``sorts[s + 1]``, sorted by name, with
the identity (index 0) in front when the two sorts are equal. A newly
registered op therefore joins the search space by being named in the
vocabulary, with no other change.

A *genome* of a skeleton with ``S`` stages is two arrays: ``ops`` ``(S,)``
int32, the op index within each stage's vocabulary, and ``knobs`` ``(S, 2)``
float in ``[0, 1]`` (knobs ``a``, ``b`` of the stage's op, mapped to physical
units by the op's knob spec; rows of ops with fewer knobs are carried but
unused). A population is the same with a leading axis ``P``.

Decoding is deterministic (index -> name through the sorted vocabulary) and
champions are *stored by op name* (:func:`champion_record`); re-encoding a
stored champion (:func:`encode`) looks the names up again, so adding an op to
the registry, which shifts indices, never silently rewrites a stored champion;
a stored op that left the vocabulary is an error naming the stage and op.

The default vocabulary (:data:`DEFAULT_VOCABULARY`) is an explicit list of
2-D ops of the filter, morphology, point, edge, frequency, threshold, binary
and label families: ``Image -> Image``, ``Image -> Region``, ``Region ->
Region`` and ``Region -> Feature`` (``count_obj``). It leaves out ops whose
batch of 16 images of 64 x 64 took more than about 30 ms (median, rank and
percentile filters with a traced radius: ~150 ms; ``fill_holes``: ~120 ms;
Perona-Malik: ~85 ms) or whose output shape differs from the input
(``resize``), and the geometry family (a warp of the whole image is not a
processing step for these problems). Ops that other families register later
(3-D points, rendering) do not enter a search unless named, so they neither
change a skeleton's vocabulary nor its compile time.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..registry import OpSpec, get_op
from ..types import Feature, Image, Region, Sort

__all__ = [
    "IDENTITY",
    "DEFAULT_VOCABULARY",
    "Skeleton",
    "type_skeleton",
    "enumerate_skeletons",
    "stage_vocabulary",
    "random_population",
    "decode",
    "champion_record",
    "encode",
    "pipeline_stages",
]

IDENTITY = "identity"

#: The default search vocabulary (op names). See the module docstring for what it leaves out and why.
DEFAULT_VOCABULARY: tuple[str, ...] = (
    # Image -> Image
    "gaussian", "box_filter", "guided_filter", "bilateral", "unsharp_mask",
    "gaussian_lowpass", "gaussian_highpass",
    "erosion", "dilation", "opening", "closing", "top_hat",
    "sobel_amp", "log", "gamma", "normalize", "invert",
    # Image -> Region
    "threshold", "otsu", "triangle", "local_mean", "hysteresis", "canny",
    # Region -> Region
    "region_open", "region_close", "region_erode", "region_dilate", "boundary",
    "remove_small", "region_not",
    # Region -> Feature
    "count_obj",
)

#: Sorts a stage state may have; each is carried between stages as one array.
STATE_SORTS: dict[type, str] = {Image: "data", Region: "data", Feature: "value"}


def _vocab_specs(vocabulary: Sequence[str] | None) -> list[OpSpec]:
    names = DEFAULT_VOCABULARY if vocabulary is None else tuple(vocabulary)
    if isinstance(vocabulary, str):
        raise TypeError("vocabulary: expected a sequence of op names, got a single str")
    specs = []
    for n in names:
        if n == IDENTITY:
            continue
        s = get_op(n)  # unknown names raise UnknownOpError with suggestions
        if not s.linear:
            raise ValueError(f"vocabulary: op {n!r} takes {len(s.takes)} inputs; stages take one-input ops only")
        specs.append(s)
    return specs


def stage_vocabulary(takes: type, gives: type, vocabulary: Sequence[str] | None = None) -> tuple[str, ...]:
    """Op names that fit one stage ``takes -> gives`` (identity first when the sorts are equal).

    Args:
      takes, gives: sort classes of the stage's input and output.
      vocabulary: op names searched (``None``: :data:`DEFAULT_VOCABULARY`).

    Returns:
      A tuple of names; position = op index in the genome. Empty when nothing fits.
    """
    fit = sorted({s.name for s in _vocab_specs(vocabulary) if s.takes == (takes,) and s.gives is gives})
    return ((IDENTITY,) if takes is gives else ()) + tuple(fit)


@dataclasses.dataclass(frozen=True)
class Skeleton:
    """A type skeleton: sorts ``(S + 1,)`` and the vocabulary of each of the ``S`` stages."""

    sorts: tuple[type, ...]
    vocabs: tuple[tuple[str, ...], ...]

    @property
    def n_stages(self) -> int:
        return len(self.vocabs)

    @property
    def takes(self) -> type:
        return self.sorts[0]

    @property
    def gives(self) -> type:
        return self.sorts[-1]

    @property
    def sizes(self) -> np.ndarray:
        """Vocabulary size of each stage, ``(S,)`` int."""
        return np.array([len(v) for v in self.vocabs], dtype=np.int32)

    def segments(self) -> list[tuple[int, int]]:
        """Maximal runs ``[start, stop)`` of consecutive stages with the same vocabulary."""
        out, start = [], 0
        for s in range(1, self.n_stages + 1):
            if s == self.n_stages or self.vocabs[s] != self.vocabs[start]:
                out.append((start, s))
                start = s
        return out

    def describe(self) -> str:
        return " -> ".join(t.__name__ for t in self.sorts)

    def __str__(self) -> str:
        return f"Skeleton({self.describe()}; vocabulary sizes {self.sizes.tolist()})"


def type_skeleton(sorts: Sequence[type], vocabulary: Sequence[str] | None = None) -> Skeleton:
    """Build a :class:`Skeleton` from its sorts, checking every stage has a vocabulary.

    Args:
      sorts: ``S + 1`` sort classes (input, then the output of each stage); each must be
        one of ``Image``, ``Region``, ``Feature`` (the sorts carried as one array).
      vocabulary: op names searched (``None``: :data:`DEFAULT_VOCABULARY`).

    Raises:
      ValueError: fewer than two sorts, a sort that cannot be a stage state, or a stage
        whose vocabulary is empty (named by its 1-based number and signature).
    """
    sorts = tuple(sorts)
    if len(sorts) < 2:
        raise ValueError(f"type_skeleton: need at least 2 sorts (input and one stage), got {len(sorts)}")
    for t in sorts:
        if t not in STATE_SORTS:
            raise ValueError(f"type_skeleton: sort {getattr(t, '__name__', t)!r} cannot be a stage state; "
                             f"supported: {', '.join(c.__name__ for c in STATE_SORTS)}")
    vocabs = []
    for s in range(len(sorts) - 1):
        v = stage_vocabulary(sorts[s], sorts[s + 1], vocabulary)
        if not v:
            raise ValueError(f"type_skeleton: stage {s + 1} ({sorts[s].__name__} -> {sorts[s + 1].__name__}) has an "
                             f"empty vocabulary: no op of the search vocabulary takes {sorts[s].__name__} and "
                             f"gives {sorts[s + 1].__name__}")
        vocabs.append(v)
    return Skeleton(sorts, tuple(vocabs))


def enumerate_skeletons(takes: type, gives: type, n_stages: int,
                        vocabulary: Sequence[str] | None = None) -> list[Skeleton]:
    """Every skeleton of ``n_stages`` stages from ``takes`` to ``gives`` whose stages all have ops."""
    if n_stages < 1:
        raise ValueError(f"enumerate_skeletons: n_stages must be >= 1, got {n_stages}")
    states = list(STATE_SORTS)
    paths: list[tuple[type, ...]] = [(takes,)]
    for _ in range(n_stages):
        paths = [p + (t,) for p in paths for t in states if stage_vocabulary(p[-1], t, vocabulary)]
    return [type_skeleton(p, vocabulary) for p in paths if p[-1] is gives]


def random_population(rng: np.random.Generator, sk: Skeleton, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` uniform random genomes: ops ``(n, S)`` int32, knobs ``(n, S, 2)`` float64 in ``[0, 1]``."""
    ops = np.stack([rng.integers(0, k, size=n) for k in sk.sizes], axis=1).astype(np.int32)
    knobs = rng.uniform(0.0, 1.0, size=(n, sk.n_stages, 2))
    return ops, knobs


def decode(sk: Skeleton, ops: Any, knobs: Any) -> list[dict[str, Any]]:
    """One genome as a list of stage dicts ``{op, a, b, params}`` (identity stages included).

    ``a``/``b`` are ``None`` for knobs the op does not have; ``params`` holds the physical
    parameter values the knobs map to.
    """
    ops = np.asarray(ops)
    knobs = np.asarray(knobs, dtype=float)
    if ops.shape != (sk.n_stages,) or knobs.shape != (sk.n_stages, 2):
        raise ValueError(f"decode: expected ops ({sk.n_stages},) and knobs ({sk.n_stages}, 2), "
                         f"got {ops.shape} and {knobs.shape}")
    out = []
    for s, (i, row) in enumerate(zip(ops, knobs)):
        if not 0 <= int(i) < len(sk.vocabs[s]):
            raise ValueError(f"decode: stage {s + 1} op index {int(i)} outside its vocabulary of {len(sk.vocabs[s])}")
        name = sk.vocabs[s][int(i)]
        if name == IDENTITY:
            out.append({"op": IDENTITY, "a": None, "b": None, "params": {}})
            continue
        spec = get_op(name)
        nk = len(spec.knobs)
        a = float(row[0]) if nk >= 1 else None
        b = float(row[1]) if nk >= 2 else None
        params = {k: float(v) for k, v in spec.knob_params(a, b, strict=True).items()}
        out.append({"op": name, "a": a, "b": b, "params": params})
    return out


def pipeline_stages(stages: Sequence[dict[str, Any]]) -> list[Any]:
    """Stage dicts -> the stage list :func:`fsjax.pipeline` takes (identity stages dropped)."""
    out = []
    for st in stages:
        if st["op"] == IDENTITY:
            continue
        ks = [v for v in (st.get("a"), st.get("b")) if v is not None]
        out.append((st["op"], *ks) if ks else st["op"])
    return out


def champion_record(sk: Skeleton, ops: Any, knobs: Any, **extra: Any) -> dict[str, Any]:
    """A JSON-ready record of a genome *by op name*: skeleton sorts, stages, plus ``extra`` fields."""
    return {"skeleton": [t.__name__ for t in sk.sorts], "stages": decode(sk, ops, knobs), **extra}


def encode(sk: Skeleton, record: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Genome arrays of a stored record (by op name) in skeleton ``sk``'s current vocabulary.

    Raises:
      ValueError: the record's skeleton differs from ``sk``, or a stored op is not in its
        stage's vocabulary any more (named with the stage number).
    """
    names = [t.__name__ for t in sk.sorts]
    if list(record["skeleton"]) != names:
        raise ValueError(f"encode: record skeleton {record['skeleton']} differs from {names}")
    ops = np.zeros(sk.n_stages, dtype=np.int32)
    knobs = np.full((sk.n_stages, 2), 0.5)
    for s, st in enumerate(record["stages"]):
        if st["op"] not in sk.vocabs[s]:
            raise ValueError(f"encode: stage {s + 1}: op {st['op']!r} is not in the stage's vocabulary "
                             f"({', '.join(sk.vocabs[s])})")
        ops[s] = sk.vocabs[s].index(st["op"])
        for j, key in enumerate(("a", "b")):
            v = st.get(key)
            if v is not None:
                if not (math.isfinite(v) and 0.0 <= v <= 1.0):
                    raise ValueError(f"encode: stage {s + 1} knob {key!r} must be in [0, 1], got {v}")
                knobs[s, j] = v
    return ops, knobs


def is_state_sort(t: type) -> bool:
    """True for the sorts a stage state can have (:data:`STATE_SORTS`)."""
    return isinstance(t, type) and issubclass(t, Sort) and t in STATE_SORTS


def __getattr__(name):
    if name == "skeleton":  # renamed: fsjax.ops.skeleton is the morphological skeleton
        from ..types.results import deprecated_name

        deprecated_name("fsjax.evolve.skeleton", "fsjax.evolve.type_skeleton")
        return type_skeleton
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
