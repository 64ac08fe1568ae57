"""Geometry: contours, point clouds, meshes, Gaussian splats, cameras and depth maps.

Camera convention: OpenCV (x right, y down, z forward); poses are ``world_from_camera``.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._base import Sort, _as_array, is_concrete

__all__ = ["Contour", "Points", "Mesh", "Gaussians", "Camera", "Depth", "DepthStack", "PointValues", "PointLabels",
           "StructuredLightRig"]


class Contour(Sort):
    """Fixed-capacity polyline(s), ``points`` ``(*batch, N, 2)`` as sub-pixel ``(row, col)``.

    ``valid`` marks used slots; ``truncated`` is True when the capacity was
    exceeded. ``closed`` tells whether the valid points form a closed curve.
    """

    _array_field = "points"

    points: Float[Array, "*batch N 2"]
    valid: Bool[Array, "*batch N"]
    truncated: Bool[Array, "*batch"]
    closed: bool = eqx.field(static=True, default=False)

    def __init__(self, points: Any, valid: Any = None, truncated: Any = False, closed: bool = False):
        self.points = _as_array(points, sort="Contour", field="points", kind="float", min_ndim=2, trailing=(2,))
        if valid is None:
            valid = jnp.ones(self.points.shape[:-1], dtype=bool)
        self.valid = _as_array(valid, sort="Contour", field="valid", kind="bool", min_ndim=1)
        if self.valid.shape != self.points.shape[:-1]:
            raise ValueError(
                f"Contour(valid=...): shape {self.valid.shape} does not match points {self.points.shape[:-1]}"
            )
        self.truncated = jnp.asarray(truncated, dtype=bool)
        self.closed = bool(closed)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.points.shape[:-2])


class Points(Sort):
    """Fixed-capacity point set: ``xyz`` ``(*batch, N, 3)``, ``valid`` ``(*batch, N)``.

    Optional ``normals`` ``(*batch, N, 3)`` (unit length) and ``colors``
    ``(*batch, N, 3)`` linear RGB. ``truncated`` flags lost points.
    """

    _array_field = "xyz"

    xyz: Float[Array, "*batch N 3"]
    valid: Bool[Array, "*batch N"]
    normals: Float[Array, "*batch N 3"] | None
    colors: Float[Array, "*batch N 3"] | None
    truncated: Bool[Array, "*batch"]
    _float_fields = ("xyz", "normals", "colors")

    def __init__(self, xyz: Any, valid: Any = None, normals: Any = None, colors: Any = None, truncated: Any = False):
        self.xyz = _as_array(xyz, sort="Points", field="xyz", kind="float", min_ndim=2, trailing=(3,))
        if valid is None:
            valid = jnp.ones(self.xyz.shape[:-1], dtype=bool)
        self.valid = _as_array(valid, sort="Points", field="valid", kind="bool", min_ndim=1)
        if self.valid.shape != self.xyz.shape[:-1]:
            raise ValueError(f"Points(valid=...): shape {self.valid.shape} does not match xyz {self.xyz.shape[:-1]}")
        self.normals = None if normals is None else _as_array(
            normals, sort="Points", field="normals", kind="float", min_ndim=2, trailing=(3,))
        self.colors = None if colors is None else _as_array(
            colors, sort="Points", field="colors", kind="float", min_ndim=2, trailing=(3,))
        for name in ("normals", "colors"):
            v = getattr(self, name)
            if v is not None and v.shape != self.xyz.shape:
                raise ValueError(f"Points({name}=...): shape {v.shape} does not match xyz {self.xyz.shape}")
        self.truncated = jnp.asarray(truncated, dtype=bool)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.xyz.shape[:-2])


class Mesh(Sort):
    """Triangle mesh: ``vertices`` ``(V, 3)``, ``faces`` ``(F, 3)`` int32, outward winding.

    ``vertex_valid``/``face_valid`` mark used slots of fixed capacities.
    """

    vertices: Float[Array, "*batch V 3"]
    faces: Int[Array, "*batch F 3"]
    vertex_valid: Bool[Array, "*batch V"]
    face_valid: Bool[Array, "*batch F"]
    truncated: Bool[Array, "*batch"]
    _float_fields = ("vertices",)

    def __init__(self, vertices: Any, faces: Any, vertex_valid: Any = None, face_valid: Any = None,
                 truncated: Any = False):
        self.vertices = _as_array(vertices, sort="Mesh", field="vertices", kind="float", min_ndim=2, trailing=(3,))
        self.faces = _as_array(faces, sort="Mesh", field="faces", kind="int", min_ndim=2, trailing=(3,))
        if vertex_valid is None:
            vertex_valid = jnp.ones(self.vertices.shape[:-1], dtype=bool)
        if face_valid is None:
            face_valid = jnp.ones(self.faces.shape[:-1], dtype=bool)
        self.vertex_valid = _as_array(vertex_valid, sort="Mesh", field="vertex_valid", kind="bool", min_ndim=1)
        self.face_valid = _as_array(face_valid, sort="Mesh", field="face_valid", kind="bool", min_ndim=1)
        if is_concrete(self.faces) and self.faces.size:
            nv = self.vertices.shape[-2]
            f = np.asarray(self.faces)
            if int(f.min()) < 0 or int(f.max()) >= nv:
                raise ValueError(
                    f"Mesh(faces=...): indices must be in [0, {nv - 1}], got range "
                    f"[{int(f.min())}, {int(f.max())}]"
                )
        self.truncated = jnp.asarray(truncated, dtype=bool)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.vertices.shape[:-2])


class Gaussians(Sort):
    """3-D Gaussian splats in the 3DGS parameterisation (Kerbl et al. 2023).

    ``means`` ``(N, 3)``; ``log_scales`` ``(N, 3)``; ``quats`` ``(N, 4)`` as
    ``(w, x, y, z)`` (normalised at use; a zero-length quaternion is an error);
    ``opacity_logits`` ``(N,)``; ``colors`` ``(N, K, 3)`` spherical-harmonic
    coefficients (``K = 1`` is a plain colour); ``valid`` ``(N,)``.
    """

    means: Float[Array, "*batch N 3"]
    log_scales: Float[Array, "*batch N 3"]
    quats: Float[Array, "*batch N 4"]
    opacity_logits: Float[Array, "*batch N"]
    colors: Float[Array, "*batch N K 3"]
    valid: Bool[Array, "*batch N"]
    _float_fields = ("means", "log_scales", "quats", "opacity_logits", "colors")

    def __init__(self, means: Any, log_scales: Any, quats: Any, opacity_logits: Any, colors: Any, valid: Any = None):
        self.means = _as_array(means, sort="Gaussians", field="means", kind="float", min_ndim=2, trailing=(3,))
        self.log_scales = _as_array(log_scales, sort="Gaussians", field="log_scales", kind="float", min_ndim=2,
                                    trailing=(3,))
        self.quats = _as_array(quats, sort="Gaussians", field="quats", kind="float", min_ndim=2, trailing=(4,))
        self.opacity_logits = _as_array(opacity_logits, sort="Gaussians", field="opacity_logits", kind="float",
                                        min_ndim=1)
        colors = jnp.asarray(colors)
        if colors.ndim == self.means.ndim:
            colors = colors[..., None, :]
        self.colors = _as_array(colors, sort="Gaussians", field="colors", kind="float", min_ndim=3, trailing=(3,))
        if valid is None:
            valid = jnp.ones(self.means.shape[:-1], dtype=bool)
        self.valid = _as_array(valid, sort="Gaussians", field="valid", kind="bool", min_ndim=1)
        n = self.means.shape[:-1]
        for name, arr, tail in (("log_scales", self.log_scales, 1), ("quats", self.quats, 1),
                                ("opacity_logits", self.opacity_logits, 0), ("colors", self.colors, 2),
                                ("valid", self.valid, 0)):
            lead = arr.shape[: arr.ndim - tail]
            if lead != n:
                raise ValueError(f"Gaussians({name}=...): leading shape {lead} does not match means {n}")
        if is_concrete(self.quats) and is_concrete(self.valid):
            norms = np.linalg.norm(np.asarray(self.quats), axis=-1)
            if bool(np.any((norms == 0) & np.asarray(self.valid))):
                raise ValueError("Gaussians(quats=...): a zero-length quaternion is not a rotation")

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.means.shape[:-2])


class Camera(Sort):
    """Pinhole camera, OpenCV convention.

    ``K`` ``(3, 3)`` intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels;
    ``dist`` ``(5,)`` Brown-Conrady ``(k1, k2, p1, p2, k3)``; ``R`` ``(3, 3)`` and
    ``t`` ``(3,)`` give the pose ``world_from_camera`` (a camera-frame point ``p``
    maps to ``R @ p + t`` in the world). ``width``/``height`` in pixels (static).
    Camera frame: x right, y down, z forward.
    """

    K: Float[Array, "*batch 3 3"]
    dist: Float[Array, "*batch 5"]
    R: Float[Array, "*batch 3 3"]
    t: Float[Array, "*batch 3"]
    width: int = eqx.field(static=True, default=0)
    height: int = eqx.field(static=True, default=0)
    _float_fields = ("K", "dist", "R", "t")

    def __init__(self, K: Any, *, width: int, height: int, dist: Any = None, R: Any = None, t: Any = None):
        self.K = _as_array(K, sort="Camera", field="K", kind="float", min_ndim=2, trailing=(3, 3))
        batch = self.K.shape[:-2]
        dt = self.K.dtype
        self.dist = _as_array(jnp.zeros(batch + (5,), dt) if dist is None else dist, sort="Camera",
                              field="dist", kind="float", min_ndim=1, trailing=(5,))
        self.R = _as_array(jnp.broadcast_to(jnp.eye(3, dtype=dt), batch + (3, 3)) if R is None else R,
                           sort="Camera", field="R", kind="float", min_ndim=2, trailing=(3, 3))
        self.t = _as_array(jnp.zeros(batch + (3,), dt) if t is None else t, sort="Camera", field="t",
                           kind="float", min_ndim=1, trailing=(3,))
        if int(width) <= 0 or int(height) <= 0:
            raise ValueError(f"Camera(width=..., height=...): must be positive, got {width} x {height}")
        self.width = int(width)
        self.height = int(height)

    @classmethod
    def from_intrinsics(cls, fx: float, fy: float, cx: float, cy: float, *, width: int, height: int,
                        **kw: Any) -> Camera:
        """Camera from focal lengths and principal point (pixels)."""
        K = jnp.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return cls(K, width=width, height=height, **kw)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.K.shape[:-2])


class Depth(Sort):
    """Depth map ``z`` ``(*batch, H, W)`` along the optical axis, with its ``camera``.

    0 or NaN means "no return"; NaN is therefore allowed in ``z``.
    """

    _array_field = "z"

    z: Float[Array, "*batch H W"]
    camera: Camera
    _float_fields = ()

    def __init__(self, z: Any, camera: Camera):
        self.z = _as_array(z, sort="Depth", field="z", kind="float", min_ndim=2, spatial=2)
        if not isinstance(camera, Camera):
            raise TypeError(f"Depth(camera=...): expected a Camera, got {type(camera).__name__}")
        self.camera = camera

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.z.shape[:-2])


class DepthStack(Sort):
    """``V`` depth maps of one scene, ``z`` ``(*batch, V, H, W)``, each with its camera.

    ``camera`` is a :class:`Camera` batched ``(*batch, V)`` (stack the views' cameras with
    ``jax.tree.map(lambda *a: jnp.stack(a), *cameras)``); all views share one image size.
    0 or NaN in ``z`` means "no return". The input of multi-view fusion (``tsdf_fuse``).
    """

    _array_field = "z"

    z: Float[Array, "*batch V H W"]
    camera: Camera
    _float_fields = ()

    def __init__(self, z: Any, camera: Camera):
        self.z = _as_array(z, sort="DepthStack", field="z", kind="float", min_ndim=3)
        if not isinstance(camera, Camera):
            raise TypeError(f"DepthStack(camera=...): expected a Camera, got {type(camera).__name__}")
        if tuple(camera.batch_shape) != tuple(self.z.shape[:-2]):
            raise ValueError(f"DepthStack(camera=...): camera batch shape {camera.batch_shape} must equal the "
                             f"stack's leading shape {tuple(self.z.shape[:-2])} (one camera per view)")
        if (camera.height, camera.width) != tuple(self.z.shape[-2:]):
            raise ValueError(f"DepthStack: depth maps {tuple(self.z.shape[-2:])} do not match the camera's "
                             f"image size {camera.height} x {camera.width}")
        self.camera = camera

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.z.shape[:-3])


# ---------------------------------------------------------------------------
# per-point results of the point-cloud families; the structured-light camera/projector pair
# ---------------------------------------------------------------------------


class PointValues(Sort):
    """Per-point values of a cloud: ``values`` ``(*batch, N, C)`` with named columns.

    ``names`` (static) names the ``C`` columns; ``valid`` ``(*batch, N)`` is the
    cloud's mask (invalid rows hold NaN). ``pv["curvedness"]`` returns a column.
    """

    values: Float[Array, "*batch N C"]
    valid: Bool[Array, "*batch N"]
    names: tuple[str, ...] = eqx.field(static=True, default=())
    _float_fields = ()  # NaN marks a value that could not be measured

    def __init__(self, values: Any, names: tuple[str, ...], valid: Any = None):
        self.values = _as_array(values, sort="PointValues", field="values", kind="float", min_ndim=2)
        self.names = tuple(str(n) for n in names)
        if len(self.names) != self.values.shape[-1]:
            raise ValueError(f"PointValues(names=...): {len(self.names)} names for {self.values.shape[-1]} columns")
        if valid is None:
            valid = jnp.ones(self.values.shape[:-1], dtype=bool)
        self.valid = _as_array(valid, sort="PointValues", field="valid", kind="bool", min_ndim=1)
        if self.valid.shape != self.values.shape[:-1]:
            raise ValueError(f"PointValues(valid=...): shape {self.valid.shape} does not match values "
                             f"{self.values.shape[:-1]}")

    def __getitem__(self, name: str) -> Array:
        if name not in self.names:
            raise KeyError(f"PointValues: no column {name!r}; columns: {', '.join(self.names)}")
        return self.values[..., self.names.index(name)]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.values.shape[:-2])


class PointLabels(Sort):
    """Per-point cluster labels: ``labels`` ``(*batch, N)`` int32, 0 = none, ``1..count``.

    ``valid`` is the cloud's mask, ``count`` the number of clusters,
    ``truncated`` True when the cluster capacity or a neighbour capacity was
    exceeded.
    """

    labels: Int[Array, "*batch N"]
    valid: Bool[Array, "*batch N"]
    count: Int[Array, "*batch"]
    truncated: Bool[Array, "*batch"]

    def __init__(self, labels: Any, valid: Any = None, count: Any = None, truncated: Any = False):
        self.labels = _as_array(labels, sort="PointLabels", field="labels", kind="int", min_ndim=1)
        if valid is None:
            valid = jnp.ones(self.labels.shape, dtype=bool)
        self.valid = _as_array(valid, sort="PointLabels", field="valid", kind="bool", min_ndim=1)
        if self.valid.shape != self.labels.shape:
            raise ValueError(f"PointLabels(valid=...): shape {self.valid.shape} does not match labels "
                             f"{self.labels.shape}")
        if count is None:
            count = np.max(np.asarray(self.labels), axis=-1, initial=0)
        self.count = jnp.asarray(count, dtype=jnp.int32)
        self.truncated = jnp.asarray(truncated, dtype=bool)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.labels.shape[:-1])


class StructuredLightRig(Sort):
    """A capturing ``camera`` and a ``projector`` (both :class:`fsjax.Camera`, OpenCV frame)."""

    camera: Camera
    projector: Camera
    _float_fields = ()

    def __init__(self, camera: Camera, projector: Camera):
        for name, c in (("camera", camera), ("projector", projector)):
            if not isinstance(c, Camera):
                raise TypeError(f"StructuredLightRig({name}=...): expected a Camera, got {type(c).__name__}")
        self.camera, self.projector = camera, projector

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return self.camera.batch_shape
