"""Point-cloud and mesh file input/output: PLY, OBJ, STL, XYZ and PCD.

Libraries (the choice, stated once):

* **PLY** (ascii, binary little/big endian) through ``plyfile`` -- a small,
  maintained, numpy-based reader/writer of the full PLY grammar.
* **STL** (ascii and binary) through ``trimesh`` (``process=False``). Before
  ``trimesh`` parses a file, fsjax checks what it would silently accept: a
  binary STL whose size does not match its triangle count, an ascii STL
  without ``endsolid`` or with an unterminated facet.
* **OBJ** read and written by a small parser/writer of fsjax's own (``v`` and
  ``f`` lines, ``v/vt/vn`` and negative indices; 17 significant digits for
  float64), because ``trimesh``'s loader drops unreferenced vertices and
  renumbers the rest, and its exporter rounds to fixed decimals; a malformed line or an index out of range is an error
  naming the line. OBJ has no element counts: fsjax writes them in its first
  comment line and checks them on reading; in a foreign OBJ file, truncation at
  a line boundary (or inside the last number) cannot be detected.
* **XYZ** (plain text, one point per line: ``x y z`` or ``x y z nx ny nz``,
  ``#`` comments) through numpy.
* **PCD** (Point Cloud Library format v0.7, ``DATA ascii`` and ``DATA binary``)
  by a small reader/writer of fsjax's own, written from the format
  specification; ``binary_compressed`` is refused with a clear error.

Conventions:

* Coordinates are read as float64 and returned in the default float dtype
  (float64 when x64 is enabled, else float32). Files are written in float32
  unless the data are float64 (PLY ``double``, PCD ``SIZE 8``), so a float64
  cloud round-trips exactly.
* Colours: 8-bit file colours become ``value / 255`` *as stored* (no sRGB
  decoding, like :func:`fsjax.io.read_image` by default); writing quantises
  ``floor(c * 255 + 0.5)`` after clipping to ``[0, 1]``. Float colours in PLY
  are taken as they are.
* Only *valid* points (``Points.valid``) are written; only valid faces of a
  ``Mesh`` are written (with all its vertices). STL stores triangle soups: on
  reading, exactly equal vertex coordinates are merged, so a mesh written to
  STL comes back with the same triangles but possibly renumbered vertices.
  Polygons with more than three vertices (PLY, OBJ) are fan-triangulated.
* PCD points with a NaN coordinate (organised clouds) are returned as invalid
  slots with zero coordinates.
* Every failure raises ``ValueError`` (malformed, truncated, unsupported) or
  ``FileNotFoundError`` whose message names the function and the file.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..types import Mesh, Points

__all__ = ["read_points", "write_points", "read_mesh", "write_mesh"]

_POINT_FORMATS = ("ply", "pcd", "xyz", "obj", "stl")
_MESH_FORMATS = ("ply", "obj", "stl")
_XYZ_EXT = ("xyz", "txt", "pts")


class _Fail(Exception):
    """Internal: a reason, turned into ValueError(f'{fn}: cannot read {path}: {reason}')."""


def _format(fn: str, path: Path, fmt: str | None, allowed: tuple[str, ...]) -> str:
    if fmt is None:
        ext = path.suffix.lower().lstrip(".")
        fmt = "xyz" if ext in _XYZ_EXT else ext
    fmt = fmt.lower()
    if fmt not in allowed:
        raise ValueError(f"{fn}: unknown or unsupported format {fmt!r} for file {str(path)!r}; "
                         f"expected one of {', '.join(allowed)} (or pass format=...)")
    return fmt


def _float_dtype():
    return jnp.result_type(float)


# ---------------------------------------------------------------------------
# PLY (plyfile)
# ---------------------------------------------------------------------------


def _ply_read(path: Path, want_faces: bool):
    from plyfile import PlyData

    try:
        ply = PlyData.read(str(path))
    except Exception as e:  # plyfile raises its own parse errors
        raise _Fail(f"{type(e).__name__}: {e}") from e
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise _Fail("no 'vertex' element")
    v = ply["vertex"].data
    props = v.dtype.names or ()
    for c in "xyz":
        if c not in props:
            raise _Fail(f"vertex element has no '{c}' property")
    xyz = np.stack([np.asarray(v[c], np.float64) for c in "xyz"], axis=1)
    normals = None
    if all(c in props for c in ("nx", "ny", "nz")):
        normals = np.stack([np.asarray(v[c], np.float64) for c in ("nx", "ny", "nz")], axis=1)
    colors = None
    for trip in (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
        if all(c in props for c in trip):
            cols = [np.asarray(v[c]) for c in trip]
            if np.issubdtype(cols[0].dtype, np.integer):
                top = 255.0 if cols[0].dtype.itemsize == 1 else float(np.iinfo(cols[0].dtype).max)
                colors = np.stack(cols, axis=1).astype(np.float64) / top
            else:
                colors = np.stack(cols, axis=1).astype(np.float64)
            break
    faces = None
    if want_faces:
        if "face" not in names:
            raise _Fail("no 'face' element (a point cloud, not a mesh; use read_points)")
        fd = ply["face"].data
        key = next((k for k in ("vertex_indices", "vertex_index") if k in (fd.dtype.names or ())), None)
        if key is None:
            raise _Fail("face element has no 'vertex_indices' list")
        faces = _triangulate([np.asarray(f, np.int64) for f in fd[key]])
    return xyz, normals, colors, faces


def _ply_write(path: Path, xyz, normals, colors, faces, binary: bool):
    from plyfile import PlyData, PlyElement

    ftype = "f8" if xyz.dtype == np.float64 else "f4"
    fields = [("x", ftype), ("y", ftype), ("z", ftype)]
    if normals is not None:
        fields += [("nx", ftype), ("ny", ftype), ("nz", ftype)]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    arr = np.empty(len(xyz), dtype=fields)
    for i, c in enumerate("xyz"):
        arr[c] = xyz[:, i]
    if normals is not None:
        for i, c in enumerate(("nx", "ny", "nz")):
            arr[c] = normals[:, i]
    if colors is not None:
        q = _quantise(colors)
        for i, c in enumerate(("red", "green", "blue")):
            arr[c] = q[:, i]
    els = [PlyElement.describe(arr, "vertex")]
    if faces is not None:
        fa = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,))])
        fa["vertex_indices"] = faces
        els.append(PlyElement.describe(fa, "face"))
    PlyData(els, text=not binary).write(str(path))


def _triangulate(polys) -> np.ndarray:
    tris = []
    for p in polys:
        if len(p) < 3:
            raise _Fail(f"a face has {len(p)} vertices (need >= 3)")
        for i in range(1, len(p) - 1):
            tris.append((p[0], p[i], p[i + 1]))
    return np.asarray(tris, np.int64).reshape(-1, 3)


def _quantise(colors: np.ndarray) -> np.ndarray:
    return np.floor(np.clip(colors, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


# ---------------------------------------------------------------------------
# OBJ / STL (trimesh, after fsjax's own checks)
# ---------------------------------------------------------------------------

_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?(?:nan|inf)"


def _obj_read(path: Path):
    """Vertices and fan-triangulated faces of an OBJ file (``v`` and ``f`` lines; other lines ignored)."""
    verts: list[list[float]] = []
    polys: list[list[int]] = []
    declared = None
    with open(path, encoding="utf-8", errors="replace") as fh:
        for ln, line in enumerate(fh, 1):
            if ln == 1:
                hit = re.match(r"# written by fsjax: (\d+) vertices, (\d+) faces", line)
                declared = None if hit is None else (int(hit.group(1)), int(hit.group(2)))
            t = line.split("#", 1)[0].split()
            if not t:
                continue
            if t[0] == "v":
                if len(t) < 4 or not all(re.fullmatch(_NUM, x, re.I) for x in t[1:4]):
                    raise _Fail(f"line {ln}: malformed vertex {line.strip()!r} (truncated?)")
                verts.append([float(x) for x in t[1:4]])
            elif t[0] == "f":
                if len(t) < 4:
                    raise _Fail(f"line {ln}: a face needs >= 3 vertices, got {line.strip()!r} (truncated?)")
                poly = []
                for x in t[1:]:
                    head = x.split("/")[0]
                    if not re.fullmatch(r"-?\d+", head):
                        raise _Fail(f"line {ln}: malformed face index {x!r}")
                    i = int(head)
                    nv = len(verts)
                    if i == 0 or i > nv or -i > nv:
                        raise _Fail(f"line {ln}: face index {i} out of range (1..{nv} vertices so far)")
                    poly.append(i - 1 if i > 0 else nv + i)
                polys.append(poly)
    if not verts:
        raise _Fail("no vertices ('v' lines)")
    if declared is not None and declared != (len(verts), len(polys)):
        raise _Fail(f"the header declares {declared[0]} vertices and {declared[1]} faces, the file holds "
                    f"{len(verts)} and {len(polys)} (truncated?)")
    return np.asarray(verts, np.float64), _triangulate(polys)


def _stl_check(path: Path) -> None:
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(84)
    if len(head) < 84 and not head.lstrip().lower().startswith(b"solid"):
        raise _Fail(f"file too short for an STL ({size} bytes)")
    if len(head) >= 84:
        n = int(np.frombuffer(head[80:84], "<u4")[0])
        if size == 84 + 50 * n:
            if n == 0:
                raise _Fail("binary STL with 0 triangles")
            return  # consistent binary STL
    if head.lstrip().lower().startswith(b"solid"):
        with open(path, "rb") as fh:
            text = fh.read().decode("ascii", errors="replace")
        if "endsolid" not in text:
            raise _Fail("ascii STL without 'endsolid' (truncated?)")
        if text.count("facet normal") != text.count("endfacet") or text.count("endfacet") == 0:
            raise _Fail("ascii STL with unterminated or no facets (truncated?)")
        return
    n = int(np.frombuffer(head[80:84], "<u4")[0])
    raise _Fail(f"binary STL declares {n} triangles ({84 + 50 * n} bytes) but the file has {size} bytes "
                f"(truncated?)")


def _trimesh_read(path: Path, fmt: str):
    import trimesh

    if fmt == "obj":
        v, f = _obj_read(path)
        return v, None, None, f
    _stl_check(path)
    try:
        m = trimesh.load(str(path), file_type=fmt, process=False, force="mesh")
    except Exception as e:
        raise _Fail(f"{type(e).__name__}: {e}") from e
    v = np.asarray(m.vertices, np.float64)
    f = np.asarray(m.faces, np.int64).reshape(-1, 3)
    if fmt == "stl":  # merge exactly equal coordinates (STL is a triangle soup)
        v, inv = np.unique(v, axis=0, return_inverse=True)
        f = inv.reshape(-1)[f]
    return v, None, None, f


def _trimesh_write(path: Path, verts, faces, fmt: str, binary: bool):
    import trimesh

    if fmt == "obj":  # a plain writer: trimesh's exporter rounds to fixed decimals
        g = "%.17g" if verts.dtype == np.float64 else "%.9g"
        vl = "\n".join(f"v {g % a} {g % b} {g % c}" for a, b, c in verts.tolist())
        fl = "\n".join(f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces.tolist())
        with open(path, "w") as fh:
            fh.write(f"# written by fsjax: {len(verts)} vertices, {len(faces)} faces\n" + vl + "\n" + fl + "\n")
        return
    m = trimesh.Trimesh(vertices=verts, faces=faces, process=False)
    data = m.export(file_type="stl" if binary else "stl_ascii")
    mode = "wb" if isinstance(data, bytes) else "w"
    with open(path, mode) as fh:
        fh.write(data)


# ---------------------------------------------------------------------------
# XYZ (plain text)
# ---------------------------------------------------------------------------


def _xyz_read(path: Path):
    rows = []
    ncol = None
    with open(path, encoding="utf-8", errors="replace") as fh:
        for ln, line in enumerate(fh, 1):
            s = line.split("#", 1)[0].replace(",", " ").split()
            if not s:
                continue
            if ncol is None:
                ncol = len(s)
                if ncol not in (3, 6):
                    raise _Fail(f"line {ln}: expected 3 (x y z) or 6 (x y z nx ny nz) columns, got {ncol}")
            elif len(s) != ncol:
                raise _Fail(f"line {ln}: {len(s)} columns where the file has {ncol} (truncated?)")
            try:
                rows.append([float(x) for x in s])
            except ValueError as e:
                raise _Fail(f"line {ln}: not a number: {line.strip()!r}") from e
    if not rows:
        raise _Fail("no points")
    a = np.asarray(rows, np.float64)
    return a[:, :3], (a[:, 3:6] if ncol == 6 else None), None


def _xyz_write(path: Path, xyz, normals):
    a = xyz if normals is None else np.concatenate([xyz, normals], axis=1)
    fmt = "%.17g" if a.dtype == np.float64 else "%.9g"
    np.savetxt(path, a, fmt=fmt)


# ---------------------------------------------------------------------------
# PCD v0.7 (own reader / writer)
# ---------------------------------------------------------------------------

_PCD_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")


def _pcd_read(path: Path):
    raw = path.read_bytes()
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        nl = raw.find(b"\n", pos)
        if nl < 0:
            raise _Fail("header ends before the DATA line (truncated?)")
        line = raw[pos:nl].decode("ascii", errors="replace").strip()
        pos = nl + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        key = key.upper()
        if key not in _PCD_KEYS:
            raise _Fail(f"unknown header line {line!r}")
        header[key] = vals
        if key == "DATA":
            break
    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT", "DATA"):
        if key not in header:
            raise _Fail(f"header has no {key} line")
    fields = header["FIELDS"]
    try:
        sizes = [int(s) for s in header["SIZE"]]
        counts = [int(s) for s in header.get("COUNT", ["1"] * len(fields))]
        width, height = int(header["WIDTH"][0]), int(header["HEIGHT"][0])
        npts = int(header["POINTS"][0]) if "POINTS" in header else width * height
    except (ValueError, IndexError) as e:
        raise _Fail(f"malformed header: {e}") from e
    types = [t.upper() for t in header["TYPE"]]
    if not (len(sizes) == len(types) == len(counts) == len(fields)):
        raise _Fail("FIELDS, SIZE, TYPE and COUNT have different lengths")
    if npts != width * height:
        raise _Fail(f"POINTS {npts} != WIDTH x HEIGHT = {width * height}")
    kind = {"F": "f", "U": "u", "I": "i"}
    dt = []
    for f, s, t, c in zip(fields, sizes, types, counts):
        if t not in kind or s not in (1, 2, 4, 8):
            raise _Fail(f"field {f!r}: unsupported TYPE {t} / SIZE {s}")
        dt.append((f if f != "_" else f"_pad{len(dt)}", f"<{kind[t]}{s}", (c,) if c > 1 else ()))
    dtype = np.dtype(dt)
    mode = header["DATA"][0].lower() if header["DATA"] else ""
    if mode == "binary":
        need = npts * dtype.itemsize
        body = raw[pos:]
        if len(body) < need:
            raise _Fail(f"binary data has {len(body)} bytes, {need} needed for {npts} points (truncated)")
        rec = np.frombuffer(body[:need], dtype=dtype)
    elif mode == "ascii":
        lines = [ln for ln in raw[pos:].decode("ascii", errors="replace").splitlines() if ln.strip()]
        if len(lines) < npts:
            raise _Fail(f"ascii data has {len(lines)} lines, {npts} points declared (truncated)")
        ncol = sum(counts)
        try:
            vals = np.array([ln.split() for ln in lines[:npts]], dtype=object)
            if vals.ndim != 2 or vals.shape[1] != ncol:
                raise ValueError("ragged rows")
        except ValueError as e:
            raise _Fail(f"ascii data rows do not all have {ncol} values (truncated?)") from e
        rec = np.empty(npts, dtype=dtype)
        col = 0
        for (name, t, shp), c in zip(dt, counts):
            try:
                block = vals[:, col:col + c].astype(np.float64 if t[1] == "f" else np.int64)
            except ValueError as e:
                raise _Fail(f"field {name!r}: not a number ({e})") from e
            rec[name] = block.reshape((npts,) + shp).astype(t)
            col += c
    elif mode == "binary_compressed":
        raise _Fail("DATA binary_compressed is not supported (re-save as binary or ascii)")
    else:
        raise _Fail(f"unknown DATA mode {mode!r}")
    names = dtype.names
    for c in "xyz":
        if c not in names:
            raise _Fail(f"no '{c}' field")
    xyz = np.stack([rec[c].astype(np.float64) for c in "xyz"], axis=1)
    normals = None
    if all(c in names for c in ("normal_x", "normal_y", "normal_z")):
        normals = np.stack([rec[c].astype(np.float64) for c in ("normal_x", "normal_y", "normal_z")], axis=1)
    colors = None
    for c in ("rgb", "rgba"):
        if c in names:
            packed = np.ascontiguousarray(rec[c])
            if packed.dtype.itemsize != 4:
                raise _Fail(f"field {c!r} must have SIZE 4")
            u = packed.view("<u4")
            colors = np.stack([(u >> 16) & 255, (u >> 8) & 255, u & 255], axis=1).astype(np.float64) / 255.0
            break
    return xyz, normals, colors


def _pcd_write(path: Path, xyz, normals, colors, binary: bool):
    n = len(xyz)
    s = 8 if xyz.dtype == np.float64 else 4
    ft = f"<f{s}"
    fields = ["x", "y", "z"]
    dt = [("x", ft), ("y", ft), ("z", ft)]
    if normals is not None:
        fields += ["normal_x", "normal_y", "normal_z"]
        dt += [(f, ft) for f in fields[3:6]]
    if colors is not None:
        fields.append("rgb")
        dt.append(("rgb", "<u4"))
    rec = np.empty(n, dtype=dt)
    for i, c in enumerate("xyz"):
        rec[c] = xyz[:, i]
    if normals is not None:
        for i, c in enumerate(("normal_x", "normal_y", "normal_z")):
            rec[c] = normals[:, i]
    if colors is not None:
        q = _quantise(colors).astype(np.uint32)
        rec["rgb"] = (q[:, 0] << 16) | (q[:, 1] << 8) | q[:, 2]
    sizes = [str(s)] * (len(fields) - (colors is not None)) + (["4"] if colors is not None else [])
    types = ["F"] * (len(fields) - (colors is not None)) + (["U"] if colors is not None else [])
    head = ("# .PCD v0.7 - Point Cloud Data file format (written by fsjax)\nVERSION 0.7\n"
            f"FIELDS {' '.join(fields)}\nSIZE {' '.join(sizes)}\nTYPE {' '.join(types)}\n"
            f"COUNT {' '.join(['1'] * len(fields))}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
            f"POINTS {n}\nDATA {'binary' if binary else 'ascii'}\n")
    with open(path, "wb") as fh:
        fh.write(head.encode("ascii"))
        if binary:
            fh.write(rec.tobytes())
        else:
            ffmt = "%.17g" if s == 8 else "%.9g"
            fmts = [ffmt] * (len(fields) - (colors is not None)) + (["%d"] if colors is not None else [])
            cols = [rec[f].astype(np.float64 if f != "rgb" else np.int64) for f in fields]
            body = "\n".join(" ".join(f % v for f, v in zip(fmts, row)) for row in zip(*cols))
            fh.write((body + "\n").encode("ascii"))


# ---------------------------------------------------------------------------
# Public functions
# ---------------------------------------------------------------------------


def _existing(fn: str, path: Any) -> Path:
    p = Path(os.fspath(path))
    if not p.is_file():
        raise FileNotFoundError(f"{fn}: file {str(p)!r} not found")
    return p


def read_points(path: str | os.PathLike, *, format: str | None = None) -> Points:
    """Read a point cloud (PLY, PCD, XYZ; the vertices of an OBJ or STL mesh) into ``Points``.

    Args:
      path: the file; the format comes from the extension (``.ply``, ``.pcd``,
        ``.xyz``/``.txt``/``.pts``, ``.obj``, ``.stl``) unless ``format`` is given.
      format: one of ``"ply"``, ``"pcd"``, ``"xyz"``, ``"obj"``, ``"stl"``.

    Returns:
      ``Points`` with every slot valid (PCD NaN points: invalid, zeroed), and
      ``normals``/``colors`` when the file holds them (colours ``value / 255``).

    Raises:
      FileNotFoundError, or ValueError naming ``read_points``, the file and the
      reason (unknown format, malformed or truncated data).

    Example:
      >>> import tempfile, os, numpy as np
      >>> from fsjax.io import read_points, write_points
      >>> from fsjax import Points
      >>> p = Points(np.array([[0.0, 1.0, 2.0], [3.0, 4.0, 5.5]]))
      >>> path = os.path.join(tempfile.mkdtemp(), "two.pcd")
      >>> write_points(path, p)
      >>> q = read_points(path)
      >>> float(np.abs(np.asarray(q.xyz) - np.asarray(p.xyz)).max())
      0.0
    """
    fn = "read_points"
    p = _existing(fn, path)
    fmt = _format(fn, p, format, _POINT_FORMATS)
    try:
        if fmt == "ply":
            xyz, normals, colors, _ = _ply_read(p, want_faces=False)
        elif fmt == "pcd":
            xyz, normals, colors = _pcd_read(p)
        elif fmt == "xyz":
            xyz, normals, colors = _xyz_read(p)
        else:
            xyz, normals, colors, _ = _trimesh_read(p, fmt)
    except _Fail as e:
        raise ValueError(f"{fn}: cannot read {fmt.upper()} file {str(p)!r}: {e}") from e
    if len(xyz) == 0:
        raise ValueError(f"{fn}: {fmt.upper()} file {str(p)!r} holds no points")
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any() and fmt != "pcd":
        raise ValueError(f"{fn}: {fmt.upper()} file {str(p)!r} has {int(bad.sum())} point(s) with NaN/inf "
                         f"coordinates")
    xyz = np.where(bad[:, None], 0.0, xyz)
    dt = _float_dtype()

    def fix(a):
        return None if a is None else jnp.asarray(np.where(np.isfinite(a), a, 0.0), dt)

    try:
        return Points(jnp.asarray(xyz, dt), valid=jnp.asarray(~bad), normals=fix(normals), colors=fix(colors))
    except (TypeError, ValueError) as e:
        raise ValueError(f"{fn}: {fmt.upper()} file {str(p)!r}: {e}") from e


def write_points(path: str | os.PathLike, points: Points, *, format: str | None = None,
                 binary: bool = True) -> None:
    """Write the valid points of a ``Points`` (with normals and colours) to PLY, PCD or XYZ.

    Args:
      path: destination; the format comes from the extension unless given.
      points: a single (unbatched) ``Points``.
      format: ``"ply"``, ``"pcd"`` or ``"xyz"``.
      binary: PLY/PCD binary (default) or ascii. XYZ is always text (17
        significant digits for float64: exact round trip).

    Example:
      >>> import tempfile, os, numpy as np
      >>> from fsjax.io import read_points, write_points
      >>> from fsjax import Points
      >>> p = Points(np.array([[0.5, 1.0, 2.0], [9.0, 9.0, 9.0]]), valid=np.array([True, False]))
      >>> path = os.path.join(tempfile.mkdtemp(), "one.ply")
      >>> write_points(path, p, binary=False)
      >>> read_points(path).xyz.shape
      (1, 3)
    """
    fn = "write_points"
    if not isinstance(points, Points):
        raise TypeError(f"{fn}: argument 'points' must be a Points, got {type(points).__name__}")
    if points.xyz.ndim != 2:
        raise ValueError(f"{fn}: argument 'points' must be a single cloud (N, 3), got {points.xyz.shape}")
    p = Path(os.fspath(path))
    fmt = _format(fn, p, format, ("ply", "pcd", "xyz"))
    keep = np.asarray(points.valid)
    xyz = np.asarray(points.xyz)[keep]
    normals = None if points.normals is None else np.asarray(points.normals)[keep]
    colors = None if points.colors is None else np.asarray(points.colors)[keep]
    if not np.isfinite(xyz).all():
        raise ValueError(f"{fn}: argument 'points' has NaN/inf coordinates among valid points")
    if xyz.dtype not in (np.float32, np.float64):
        xyz = xyz.astype(np.float64)
    try:
        if fmt == "ply":
            _ply_write(p, xyz, normals, colors, None, binary)
        elif fmt == "pcd":
            _pcd_write(p, xyz, normals, colors, binary)
        else:
            _xyz_write(p, xyz, normals)
    except OSError as e:
        raise ValueError(f"{fn}: cannot write {str(p)!r}: {e}") from e


def read_mesh(path: str | os.PathLike, *, format: str | None = None) -> Mesh:
    """Read a triangle mesh (PLY, OBJ, STL) into a ``Mesh``.

    Args:
      path: the file; the format comes from the extension unless given.
      format: ``"ply"``, ``"obj"`` or ``"stl"``.

    Returns:
      ``Mesh`` with int32 faces (polygons fan-triangulated; STL vertices merged
      where coordinates are exactly equal).

    Raises:
      FileNotFoundError, or ValueError naming ``read_mesh``, the file and the
      reason (unknown format, no faces, an index out of range, truncation).

    Example:
      >>> import tempfile, os, numpy as np
      >>> from fsjax.io import read_mesh, write_mesh
      >>> from fsjax import Mesh
      >>> m = Mesh(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]))
      >>> path = os.path.join(tempfile.mkdtemp(), "tri.obj")
      >>> write_mesh(path, m)
      >>> r = read_mesh(path)
      >>> r.faces.tolist(), float(np.asarray(r.vertices).sum())
      ([[0, 1, 2]], 2.0)
    """
    fn = "read_mesh"
    p = _existing(fn, path)
    fmt = _format(fn, p, format, _MESH_FORMATS)
    try:
        if fmt == "ply":
            v, _, _, f = _ply_read(p, want_faces=True)
        else:
            v, _, _, f = _trimesh_read(p, fmt)
        if len(f) == 0:
            raise _Fail("no faces")
        if f.min() < 0 or f.max() >= len(v):
            raise _Fail(f"face indices span [{f.min()}, {f.max()}] but there are {len(v)} vertices")
        if not np.isfinite(v).all():
            raise _Fail("NaN/inf vertex coordinates")
    except _Fail as e:
        raise ValueError(f"{fn}: cannot read {fmt.upper()} file {str(p)!r}: {e}") from e
    return Mesh(jnp.asarray(v, _float_dtype()), jnp.asarray(f.astype(np.int32)))


def write_mesh(path: str | os.PathLike, mesh: Mesh, *, format: str | None = None, binary: bool = True) -> None:
    """Write the valid faces of a ``Mesh`` (and all its vertices) to PLY, OBJ or STL.

    Args:
      path: destination; the format comes from the extension unless given.
      mesh: a single (unbatched) ``Mesh``.
      format: ``"ply"``, ``"obj"`` or ``"stl"``.
      binary: PLY/STL binary (default) or ascii; OBJ is always text.

    Example:
      >>> import tempfile, os, numpy as np
      >>> from fsjax.io import read_mesh, write_mesh
      >>> from fsjax import Mesh
      >>> m = Mesh(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]),
      ...          np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
      >>> path = os.path.join(tempfile.mkdtemp(), "tet.stl")
      >>> write_mesh(path, m)
      >>> read_mesh(path).faces.shape
      (4, 3)
    """
    fn = "write_mesh"
    if not isinstance(mesh, Mesh):
        raise TypeError(f"{fn}: argument 'mesh' must be a Mesh, got {type(mesh).__name__}")
    if mesh.vertices.ndim != 2:
        raise ValueError(f"{fn}: argument 'mesh' must be a single mesh, got vertices {mesh.vertices.shape}")
    p = Path(os.fspath(path))
    fmt = _format(fn, p, format, _MESH_FORMATS)
    v = np.asarray(mesh.vertices)
    if v.dtype not in (np.float32, np.float64):
        v = v.astype(np.float64)
    f = np.asarray(mesh.faces)[np.asarray(mesh.face_valid)].astype(np.int64)
    if not np.isfinite(v).all():
        raise ValueError(f"{fn}: argument 'mesh' has NaN/inf vertex coordinates")
    try:
        if fmt == "ply":
            _ply_write(p, v, None, None, f, binary)
        else:
            _trimesh_write(p, v, f, fmt, binary)
    except OSError as e:
        raise ValueError(f"{fn}: cannot write {str(p)!r}: {e}") from e
