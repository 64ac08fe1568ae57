"""3-D file I/O: round trips for PLY, OBJ, STL, XYZ, PCD; clear errors on truncated/malformed files."""

import os

import numpy as np
import pytest

from fsjax import Mesh, Points
from fsjax.data import mesh_arrays
from fsjax.io.mesh import read_mesh, read_points, write_mesh, write_points
from fsjax.synth._pool import icosphere


def _cloud(n=500, seed=0):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(n, 3)) * [1.0, 2.0, 0.001] + [1e3, -2.0, 0.0]  # mixed magnitudes
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    col = rng.integers(0, 256, size=(n, 3)) / 255.0
    return xyz, nrm, col


@pytest.mark.parametrize("fmt,binary", [("ply", True), ("ply", False), ("pcd", True), ("pcd", False),
                                        ("xyz", False)])
def test_points_round_trip(tmp_path, fmt, binary):
    xyz, nrm, col = _cloud()
    valid = np.ones(len(xyz), bool)
    valid[::7] = False
    p = Points(xyz, valid=valid, normals=nrm, colors=None if fmt == "xyz" else col)
    path = tmp_path / f"cloud.{fmt}"
    write_points(path, p, binary=binary)
    q = read_points(path)
    assert q.xyz.shape == (valid.sum(), 3) and bool(np.all(np.asarray(q.valid)))
    err = float(np.abs(np.asarray(q.xyz) - xyz[valid]).max())
    nerr = float(np.abs(np.asarray(q.normals) - nrm[valid]).max())
    assert err == 0.0 and nerr == 0.0  # float64 written as double / 17 digits: exact
    if fmt != "xyz":
        np.testing.assert_array_equal(np.asarray(q.colors), col[valid])  # k / 255 is exact
    else:
        assert q.colors is None
    print(f"{fmt} ({'binary' if binary else 'ascii'}) points round trip: max |dxyz| = {err:.1e}, "
          f"{os.path.getsize(path)} bytes")


def test_points_round_trip_float32(tmp_path):
    xyz = _cloud()[0].astype(np.float32)
    for fmt in ("ply", "pcd", "xyz"):
        path = tmp_path / f"f32.{fmt}"
        write_points(path, Points(xyz.astype(np.float64).astype(np.float32)), binary=True)
        q = np.asarray(read_points(path).xyz)
        np.testing.assert_array_equal(q.astype(np.float32), xyz)  # float32 values survive exactly


@pytest.mark.parametrize("fmt,binary", [("ply", True), ("ply", False), ("obj", False), ("stl", True),
                                        ("stl", False)])
def test_mesh_round_trip_bunny(tmp_path, fmt, binary):
    v, f = mesh_arrays("bunny")
    path = tmp_path / f"bunny.{fmt}"
    write_mesh(path, Mesh(v, f), binary=binary)
    m = read_mesh(path)
    rv, rf = np.asarray(m.vertices), np.asarray(m.faces)
    if fmt == "stl":
        # triangle soup (float32 in STL; the bunny's coordinates are float32 values): the same
        # triangles, vertices merged where exactly equal
        np.testing.assert_array_equal(rv[rf], v[f])
        assert len(rv) == len(np.unique(v[np.unique(f)], axis=0))
    else:
        np.testing.assert_array_equal(rv, v)
        np.testing.assert_array_equal(rf, f)
    print(f"{fmt} ({'binary' if binary else 'ascii'}) bunny round trip exact: {len(rv)} vertices, "
          f"{len(rf)} faces")


def test_mesh_polygons_and_points_from_mesh(tmp_path):
    # a quad and a pentagon are fan-triangulated; OBJ v/vt/vn and negative indices
    obj = tmp_path / "poly.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0.5 1.5 0\nvt 0 0\n"
                   "f 1/1/1 2/1/1 3/1/1 4/1/1\nf -5 -4 -3 -2 -1\n")
    m = read_mesh(obj)
    assert np.asarray(m.faces).tolist() == [[0, 1, 2], [0, 2, 3], [0, 1, 2], [0, 2, 3], [0, 3, 4]]
    v, f = icosphere(2)
    write_mesh(tmp_path / "ico.ply", Mesh(v, f))
    p = read_points(tmp_path / "ico.ply")
    np.testing.assert_array_equal(np.asarray(p.xyz), v)


def test_pcd_pcl_style_and_nan(tmp_path):
    # a PCL-style file: rgb packed into a float32 field, an organised cloud with NaN points
    rgb = np.array([(255 << 16) | (128 << 8) | 1, 0, (1 << 16) | (2 << 8) | 3], "<u4")
    head = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
            "WIDTH 3\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA binary\n")
    rec = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4")])
    rec["x"] = [1, np.nan, 3]
    rec["y"] = [0.5, np.nan, -1]
    rec["rgb"] = rgb.view("<f4")
    path = tmp_path / "pcl.pcd"
    path.write_bytes(head.encode() + rec.tobytes())
    p = read_points(path)
    assert np.asarray(p.valid).tolist() == [True, False, True]
    np.testing.assert_array_equal(np.asarray(p.xyz), [[1, 0.5, 0], [0, 0, 0], [3, -1, 0]])
    np.testing.assert_allclose(np.asarray(p.colors)[[0, 2]] * 255, [[255, 128, 1], [1, 2, 3]])


def _truncate(path, frac):
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * frac)])


@pytest.mark.parametrize("fmt,binary", [("ply", True), ("ply", False), ("pcd", True), ("pcd", False),
                                        ("xyz", False)])
def test_truncated_points_raise(tmp_path, fmt, binary):
    xyz, nrm, _ = _cloud(200)
    path = tmp_path / f"t.{fmt}"
    write_points(path, Points(xyz, normals=nrm), binary=binary)
    _truncate(path, 0.6037)  # cuts inside a record / a line
    with pytest.raises(ValueError, match=r"read_points: .*" + str(path.name)):
        read_points(path)


@pytest.mark.parametrize("fmt,binary", [("ply", True), ("ply", False), ("obj", False), ("stl", True),
                                        ("stl", False)])
def test_truncated_mesh_raise(tmp_path, fmt, binary):
    v, f = icosphere(2)
    path = tmp_path / f"t.{fmt}"
    write_mesh(path, Mesh(v, f), binary=binary)
    _truncate(path, 0.8037)
    with pytest.raises(ValueError, match=r"read_mesh: .*" + str(path.name)):
        read_mesh(path)


def test_malformed_and_unknown(tmp_path):
    bad_obj = tmp_path / "bad.obj"
    bad_obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n")
    with pytest.raises(ValueError, match=r"read_mesh: .*bad\.obj.*line 4: face index 4 out of range"):
        read_mesh(bad_obj)
    bad_xyz = tmp_path / "bad.xyz"
    bad_xyz.write_text("0 0 0\n1 2 three\n")
    with pytest.raises(ValueError, match=r"read_points: .*bad\.xyz.*line 2: not a number"):
        read_points(bad_xyz)
    cloud_ply = tmp_path / "cloud.ply"
    write_points(cloud_ply, Points(np.zeros((3, 3))))
    with pytest.raises(ValueError, match=r"read_mesh: .*cloud\.ply.*no 'face' element"):
        read_mesh(cloud_ply)
    comp = tmp_path / "c.pcd"
    comp.write_text("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\n"
                    "POINTS 1\nDATA binary_compressed\n")
    with pytest.raises(ValueError, match=r"read_points: .*c\.pcd.*binary_compressed"):
        read_points(comp)
    garbage = tmp_path / "g.ply"
    garbage.write_bytes(b"\x00\x01garbage")
    with pytest.raises(ValueError, match=r"read_points: .*g\.ply"):
        read_points(garbage)
    with pytest.raises(ValueError, match=r"read_points: unknown or unsupported format 'las'.*x\.las"):
        (tmp_path / "x.las").write_text("")
        read_points(tmp_path / "x.las")
    with pytest.raises(ValueError, match=r"write_mesh: unknown or unsupported format 'pcd'"):
        write_mesh(tmp_path / "m.pcd", Mesh(*icosphere(0)))
    with pytest.raises(FileNotFoundError, match=r"read_mesh: file .*nope\.stl.* not found"):
        read_mesh(tmp_path / "nope.stl")
    with pytest.raises(TypeError, match="write_points: argument 'points'"):
        write_points(tmp_path / "p.ply", np.zeros((3, 3)))
