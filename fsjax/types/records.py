"""Measurement records: a measured number, matches (2-D and 3-D), region properties, 2-D fits, 1-D edges.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._base import Sort, _as_array
from .results import reason_code, reason_message

__all__ = ["Feature", "Match", "Match3D", "RegionProps", "NamedParams", "Fit", "Edges1D", "MeshTopology"]


class NamedParams(eqx.Module):
    """Mixin: a parameter vector ``params (..., P)`` whose columns ``names`` (static) name.

    ``rec["r"]`` returns the column ``r`` (batched records: shape ``(*batch,)``); an unknown
    name raises ``KeyError`` listing the parameters. Used by :class:`Fit`,
    :class:`fsjax.fit.Fit3D` and :class:`fsjax.fit.RansacResult`.
    """

    def __getitem__(self, name: str) -> Array:
        names = self.names
        if name not in names:
            raise KeyError(f"{type(self).__name__}: no parameter {name!r}; parameters: {', '.join(names)}")
        return self.params[..., names.index(name)]


class Feature(Sort):
    """One measured number, shape ``(*batch,)``; ``unit`` names its unit (static)."""

    _array_field = "value"

    value: Float[Array, "*batch"]
    unit: str = eqx.field(static=True, default="")
    _float_fields = ()  # a measured NaN is a legitimate "could not measure"

    def __init__(self, value: Any, unit: str = ""):
        self.value = _as_array(value, sort="Feature", field="value", kind="float", min_ndim=0)
        self.unit = unit

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.value.shape)

    def __float__(self) -> float:
        return float(self.value)


class Match(Sort):
    """Found instances of a model, fixed capacity ``K``.

    Per instance: sub-pixel ``row``/``col`` of the model's reference point in the
    image, ``angle_deg`` (counter-clockwise as seen on screen, i.e. rotating the
    +col axis towards -row), ``scale``, ``score`` (method-specific, higher is
    better), ``valid``. Valid instances come first, sorted by descending score;
    ``truncated`` is True when more instances passed the acceptance test than
    the capacity holds. Unused slots carry no meaning (the matching ops fill
    them with zeros and scale 1): always read ``valid``.
    """

    row: Float[Array, "*batch K"]
    col: Float[Array, "*batch K"]
    angle_deg: Float[Array, "*batch K"]
    scale: Float[Array, "*batch K"]
    score: Float[Array, "*batch K"]
    valid: Bool[Array, "*batch K"]
    truncated: Bool[Array, "*batch"]
    _float_fields = ()  # unused slots are not checked

    def __init__(self, row: Any, col: Any, score: Any, valid: Any = None, angle_deg: Any = None,
                 scale: Any = None, truncated: Any = False):
        self.row = _as_array(row, sort="Match", field="row", kind="float", min_ndim=1)
        shape = self.row.shape
        dt = self.row.dtype
        self.col = _as_array(col, sort="Match", field="col", kind="float", min_ndim=1)
        self.score = _as_array(score, sort="Match", field="score", kind="float", min_ndim=1)
        self.angle_deg = _as_array(jnp.zeros(shape, dt) if angle_deg is None else angle_deg, sort="Match",
                                   field="angle_deg", kind="float", min_ndim=1)
        self.scale = _as_array(jnp.ones(shape, dt) if scale is None else scale, sort="Match", field="scale",
                               kind="float", min_ndim=1)
        self.valid = _as_array(jnp.ones(shape, bool) if valid is None else valid, sort="Match", field="valid",
                               kind="bool", min_ndim=1)
        for name in ("col", "score", "angle_deg", "scale", "valid"):
            if getattr(self, name).shape != shape:
                raise ValueError(f"Match({name}=...): shape {getattr(self, name).shape} does not match row {shape}")
        self.truncated = jnp.asarray(truncated, dtype=bool)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.row.shape[:-1])


class Match3D(Sort):
    """One found instance of a 3-D template: a similarity pose, a score, ``valid`` and a ``reason``.

    The pose maps template coordinates to scene coordinates,
    ``scene = scale * R @ p + t``, with ``p`` and ``t`` in the physical units of the grids
    as ``(x, y, z)`` (voxel ``[k, i, j]`` of a ``Volume`` sits at ``(j dx, i dy, k dz)``; a
    point cloud or mesh brought onto a grid keeps that placement). ``R`` ``(*batch, 3, 3)``
    is a proper rotation (``det = +1``), ``scale`` the isotropic scale (1 for rigid
    methods), ``score`` the method's own similarity (higher is better; the op states its
    range). ``valid`` False means the method did not find the template (or its answer is
    ambiguous); then ``R``, ``t``, ``scale`` hold NaN and ``reason`` says why, as a code of
    :class:`fsjax.types.RESULTS` (``not_found``, ``degenerate``, ``invalid_input``,
    ``max_iterations``; ``ok`` when valid). ``iterations`` counts the refinement steps (0
    for closed-form methods). ``m.message`` reads the reason; ``m.apply(p)`` maps template
    points ``(..., 3)`` into the scene.
    """

    R: Float[Array, "*batch 3 3"]
    t: Float[Array, "*batch 3"]
    scale: Float[Array, "*batch"]
    score: Float[Array, "*batch"]
    valid: Bool[Array, "*batch"]
    reason: Int[Array, "*batch"]
    iterations: Int[Array, "*batch"]
    _float_fields = ()  # an invalid match holds NaN by design

    def __init__(self, R: Any, t: Any, score: Any, valid: Any, reason: Any, scale: Any = None,
                 iterations: Any = 0):
        self.R = _as_array(R, sort="Match3D", field="R", kind="float", min_ndim=2, trailing=(3, 3))
        batch, dt = self.R.shape[:-2], self.R.dtype
        self.t = _as_array(t, sort="Match3D", field="t", kind="float", min_ndim=1, trailing=(3,))
        if self.t.shape[:-1] != batch:
            raise ValueError(f"Match3D(t=...): batch shape {self.t.shape[:-1]} does not match R {batch}")
        self.score = jnp.broadcast_to(jnp.asarray(score, dt), batch)
        self.scale = jnp.broadcast_to(jnp.asarray(1.0 if scale is None else scale, dt), batch)
        self.valid = jnp.broadcast_to(_as_array(valid, sort="Match3D", field="valid", kind="bool", min_ndim=0),
                                      batch)
        self.reason = jnp.broadcast_to(_as_array(reason, sort="Match3D", field="reason", kind="int", min_ndim=0),
                                       batch)
        self.iterations = jnp.broadcast_to(jnp.asarray(iterations, jnp.int32), batch)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.R.shape[:-2])

    @property
    def message(self) -> Any:
        """Text of ``reason`` (concrete records; an array of texts when batched)."""
        return reason_message(self.reason)

    def apply(self, p: Any) -> Array:
        """Template points ``p (..., 3)`` mapped into the scene: ``scale R p + t``."""
        p = jnp.asarray(p)
        return self.scale[..., None] * jnp.einsum("...ij,...j->...i", self.R, p) + self.t


class RegionProps(Sort):
    """Per-label measurements, fixed capacity ``K``: a table ``(K, F)`` with named columns.

    ``names`` (static) names the ``F`` columns (e.g. ``"area"``,
    ``"centroid_row"``); ``label`` gives the label id of each row (row ``k``
    describes label ``k + 1``); ``valid`` marks labels that exist; ``truncated``
    says labels beyond the capacity were not measured. Invalid rows hold NaN.
    ``props["area"]`` returns a column.
    """

    table: Float[Array, "*batch K F"]
    label: Int[Array, "*batch K"]
    valid: Bool[Array, "*batch K"]
    truncated: Bool[Array, "*batch"]
    names: tuple[str, ...] = eqx.field(static=True, default=())
    _float_fields = ()

    def __init__(self, table: Any, names: tuple[str, ...], valid: Any, label: Any = None, truncated: Any = False):
        self.table = _as_array(table, sort="RegionProps", field="table", kind="float", min_ndim=2)
        self.names = tuple(str(n) for n in names)
        if len(self.names) != self.table.shape[-1]:
            raise ValueError(
                f"RegionProps(names=...): {len(self.names)} names for {self.table.shape[-1]} columns"
            )
        if len(set(self.names)) != len(self.names):
            raise ValueError("RegionProps(names=...): column names must be unique")
        self.valid = _as_array(valid, sort="RegionProps", field="valid", kind="bool", min_ndim=1)
        if self.valid.shape != self.table.shape[:-1]:
            raise ValueError(f"RegionProps(valid=...): shape {self.valid.shape} does not match table rows "
                             f"{self.table.shape[:-1]}")
        if label is None:
            label = jnp.broadcast_to(jnp.arange(1, self.table.shape[-2] + 1, dtype=jnp.int32), self.valid.shape)
        self.label = _as_array(label, sort="RegionProps", field="label", kind="int", min_ndim=1)
        self.truncated = jnp.asarray(truncated, dtype=bool)

    def __getitem__(self, name: str) -> Array:
        if name not in self.names:
            raise KeyError(f"RegionProps: no column {name!r}; columns: {', '.join(self.names)}")
        return self.table[..., self.names.index(name)]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.table.shape[:-2])


class Fit(NamedParams, Sort):
    """Result record of a geometric fit: named parameters plus diagnostics.

    ``kind`` (static) names the model (``"line"``, ``"circle"``, ``"ellipse"``,
    ...), ``names`` (static) its parameters, in units stated by the op.
    ``rms`` is the residual RMS, ``iterations`` the solver steps, ``converged``
    False (with NaN parameters) when the fit failed or was degenerate, and
    ``n_used`` the number of points that entered the final fit. ``reason`` (int32)
    says why not, in the codes of :class:`fsjax.types.RESULTS` shared with every fit
    (``too_few``, ``degenerate``, ``max_iterations``, ``invalid_input`` for a truncated
    input or an out-of-range traced knob, ``unsupported_model`` for points that do not
    support a circle / ellipse); ``message`` gives its text (docs/results.md).
    """

    params: Float[Array, "*batch P"]
    rms: Float[Array, "*batch"]
    iterations: Int[Array, "*batch"]
    converged: Bool[Array, "*batch"]
    n_used: Int[Array, "*batch"]
    reason: Int[Array, "*batch"]
    kind: str = eqx.field(static=True, default="")
    names: tuple[str, ...] = eqx.field(static=True, default=())
    _float_fields = ()

    def __init__(self, params: Any, names: tuple[str, ...], kind: str, rms: Any, converged: Any,
                 iterations: Any = 0, n_used: Any = 0, reason: Any = None):
        self.params = _as_array(params, sort="Fit", field="params", kind="float", min_ndim=1)
        self.names = tuple(str(n) for n in names)
        if len(self.names) != self.params.shape[-1]:
            raise ValueError(f"Fit(names=...): {len(self.names)} names for {self.params.shape[-1]} parameters")
        self.kind = str(kind)
        self.rms = jnp.asarray(rms, dtype=self.params.dtype)
        self.converged = jnp.asarray(converged, dtype=bool)
        self.iterations = jnp.asarray(iterations, dtype=jnp.int32)
        self.n_used = jnp.asarray(n_used, dtype=jnp.int32)
        if reason is None:  # no cause given: ok, or the generic failure
            reason = jnp.where(self.converged, reason_code("ok"), reason_code("degenerate"))
        self.reason = jnp.broadcast_to(jnp.asarray(reason, dtype=jnp.int32), self.converged.shape)

    @property
    def message(self) -> Any:
        """The text of ``reason`` (``str``; an array of ``str`` for a batched record)."""
        return reason_message(self.reason)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.params.shape[:-1])


class Edges1D(Sort):
    """Edges found along a 1-D measure profile (calipers), fixed capacity ``K``.

    ``pos`` is the sub-pixel position along the profile in pixels from its start;
    ``row``/``col`` the image position; ``amplitude`` the signed derivative at the
    edge (positive = dark-to-light along the profile); ``width`` the distance to
    the paired edge for edge pairs (0 for single edges from ``measure_pos`` and for
    unused slots: read ``valid`` and the op that made it). Valid edges come first
    in profile order; ``truncated`` flags lost edges.
    """

    pos: Float[Array, "*batch K"]
    row: Float[Array, "*batch K"]
    col: Float[Array, "*batch K"]
    amplitude: Float[Array, "*batch K"]
    width: Float[Array, "*batch K"]
    valid: Bool[Array, "*batch K"]
    truncated: Bool[Array, "*batch"]
    _float_fields = ()

    def __init__(self, pos: Any, row: Any, col: Any, amplitude: Any, valid: Any, width: Any = None,
                 truncated: Any = False):
        self.pos = _as_array(pos, sort="Edges1D", field="pos", kind="float", min_ndim=1)
        shape, dt = self.pos.shape, self.pos.dtype
        self.row = _as_array(row, sort="Edges1D", field="row", kind="float", min_ndim=1)
        self.col = _as_array(col, sort="Edges1D", field="col", kind="float", min_ndim=1)
        self.amplitude = _as_array(amplitude, sort="Edges1D", field="amplitude", kind="float", min_ndim=1)
        self.width = _as_array(jnp.zeros(shape, dt) if width is None else width, sort="Edges1D",
                               field="width", kind="float", min_ndim=1)
        self.valid = _as_array(valid, sort="Edges1D", field="valid", kind="bool", min_ndim=1)
        for name in ("row", "col", "amplitude", "width", "valid"):
            if getattr(self, name).shape != shape:
                raise ValueError(f"Edges1D({name}=...): shape {getattr(self, name).shape} does not match pos {shape}")
        self.truncated = jnp.asarray(truncated, dtype=bool)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.pos.shape[:-1])


class MeshTopology(Sort):
    """Counts that say whether a triangle mesh is a closed, consistently oriented surface.

    Per mesh (shape ``(*batch,)``, int32): ``vertices`` (used by a valid face), ``faces``
    (valid), ``edges`` (distinct undirected), ``boundary_edges`` (used by one face),
    ``nonmanifold_edges`` (used by three or more), ``flipped_edges`` (used by two faces in the
    same direction: a winding flip between them), ``components`` (connected through shared
    vertices) and ``euler`` (``V - E + F``; 2 per closed genus-0 component).
    ``closed`` / ``oriented`` / ``manifold`` read them as booleans.
    """

    vertices: Int[Array, "*batch"]
    faces: Int[Array, "*batch"]
    edges: Int[Array, "*batch"]
    boundary_edges: Int[Array, "*batch"]
    nonmanifold_edges: Int[Array, "*batch"]
    flipped_edges: Int[Array, "*batch"]
    components: Int[Array, "*batch"]
    euler: Int[Array, "*batch"]
    _float_fields = ()

    def __init__(self, vertices: Any, faces: Any, edges: Any, boundary_edges: Any, nonmanifold_edges: Any,
                 flipped_edges: Any, components: Any, euler: Any):
        for name, v in (("vertices", vertices), ("faces", faces), ("edges", edges),
                        ("boundary_edges", boundary_edges), ("nonmanifold_edges", nonmanifold_edges),
                        ("flipped_edges", flipped_edges), ("components", components), ("euler", euler)):
            setattr(self, name, _as_array(v, sort="MeshTopology", field=name, kind="int", min_ndim=0))

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.faces.shape)

    @property
    def manifold(self) -> Array:
        """Every edge used by at most two faces."""
        return self.nonmanifold_edges == 0

    @property
    def closed(self) -> Array:
        """Every edge used by exactly two faces (a watertight surface)."""
        return (self.boundary_edges == 0) & (self.nonmanifold_edges == 0)

    @property
    def oriented(self) -> Array:
        """No two faces traverse a shared edge in the same direction."""
        return self.flipped_edges == 0
