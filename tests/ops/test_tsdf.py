"""TSDF fusion (``fsjax.ops.tsdf_fuse``): a sphere seen from six sides, fused and meshed."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fsjax


def _sphere_views(n_px=64, f=100.0, dist=4.0):
    """Analytic depth maps of the unit sphere from six cameras on the axes (ray-sphere hits)."""
    eyes = [(dist, 0, 0), (-dist, 0, 0), (0, dist, 0), (0, -dist, 0), (0, 0, dist), (0, 0, -dist)]
    ups = [(0, 0, 1)] * 4 + [(0, 1, 0)] * 2
    zs, cams = [], []
    for e, u in zip(eyes, ups):
        R, t = fsjax.render.look_at(jnp.asarray(e, float), jnp.zeros(3), up=jnp.asarray(u, float))
        cam = fsjax.Camera.from_intrinsics(f, f, (n_px - 1) / 2, (n_px - 1) / 2, width=n_px, height=n_px, R=R, t=t)
        o, d = (np.asarray(a) for a in fsjax.render.pixel_rays(cam))
        b = np.sum(o * d, -1)
        disc = b * b - (np.sum(o * o, -1) - 1.0)
        tt = -b - np.sqrt(np.maximum(disc, 0.0))
        zs.append(np.where(disc > 0, tt * (d @ np.asarray(R)[:, 2]), 0.0))
        cams.append(cam)
    return fsjax.DepthStack(jnp.asarray(np.stack(zs)), jax.tree.map(lambda *a: jnp.stack(a), *cams))


def test_sphere_from_six_views_within_a_tenth_of_a_voxel():
    sp = 0.1
    tsdf = fsjax.ops.tsdf_fuse(_sphere_views(), shape=(25, 25, 25), spacing=(sp, sp, sp),
                               origin=(-1.2, -1.2, -1.2), truncation=0.3)
    m = fsjax.ops.marching_cubes(tsdf, level=0.0)
    v = np.asarray(m.vertices)[np.asarray(m.vertex_valid)] - 1.2
    err = np.abs(np.linalg.norm(v, axis=1) - 1.0) / sp
    # the null: occupancy only (the sign of the fused volume, as space carving gives): the
    # surface then falls on edge midpoints, without the sub-voxel distance
    mo = fsjax.ops.marching_cubes(fsjax.Volume(jnp.sign(tsdf.data), spacing=(sp, sp, sp)), level=0.0)
    vo = np.asarray(mo.vertices)[np.asarray(mo.vertex_valid)] - 1.2
    null = np.abs(np.linalg.norm(vo, axis=1) - 1.0) / sp
    t = fsjax.ops.mesh_topology(m)
    print(f"unit sphere, 6 views 64x64, 25^3 voxels of 0.1: surface error median {np.median(err):.3f} "
          f"max {err.max():.3f} voxel (null, occupancy only: median {np.median(null):.3f}); "
          f"closed {bool(t.closed)}, components {int(t.components)}")
    assert np.median(err) <= 0.1 and np.median(err) < np.median(null)
    assert bool(t.closed) and bool(t.oriented) and int(t.components) == 1 and int(t.euler) == 2
    # without carving, the voxels outside every silhouette but inside the grid are unobserved;
    # those occluded by the sphere in one view are classified inside: a different, worse surface
    nc = fsjax.ops.tsdf_fuse(_sphere_views(), shape=(25, 25, 25), spacing=(sp, sp, sp),
                             origin=(-1.2, -1.2, -1.2), truncation=0.3, carve=False)
    assert int(jnp.sum(jnp.sign(nc.data) != jnp.sign(tsdf.data))) > 0


def test_single_wall_and_errors():
    cam = fsjax.Camera.from_intrinsics(20.0, 20.0, 7.5, 7.5, width=16, height=16)
    cams = jax.tree.map(lambda a: a[None], cam)
    wall = fsjax.DepthStack(jnp.full((1, 16, 16), 4.5), cams)
    v = fsjax.ops.tsdf_fuse(wall, shape=(8, 1, 1), truncation=2.0)
    assert np.allclose(np.asarray(v.data[:, 0, 0]), [-1, -1, -1, -0.75, -0.25, 0.25, 0.75, 1.0])
    # a wall with no return anywhere: carving sees empty space, no surface
    empty = fsjax.DepthStack(jnp.zeros((1, 16, 16)), cams)
    assert bool(jnp.all(fsjax.ops.tsdf_fuse(empty, shape=(8, 1, 1)).data == -1.0))
    with pytest.raises(ValueError, match="tsdf_fuse: argument 'truncation'"):
        fsjax.ops.tsdf_fuse(wall, truncation=0.0)
    with pytest.raises(TypeError, match="tsdf_fuse: argument 'depth' must be DepthStack"):
        fsjax.ops.tsdf_fuse(fsjax.Depth(jnp.full((16, 16), 4.5), cam))
    with pytest.raises(ValueError, match="one camera per view"):
        fsjax.DepthStack(jnp.zeros((2, 16, 16)), cams)


def test_grid_axes_follow_x_y_z():
    # a camera at the origin looking along +x at a wall at x = 4.5: the grid line must run along
    # x (voxel [0, 0, j] at x = j); a swapped axis puts the line beside the camera, unobserved
    R, t = fsjax.render.look_at(jnp.zeros(3), jnp.asarray([1.0, 0.0, 0.0]), up=jnp.asarray([0.0, 0.0, 1.0]))
    cam = fsjax.Camera.from_intrinsics(20.0, 20.0, 7.5, 7.5, width=16, height=16, R=R, t=t)
    wall = fsjax.DepthStack(jnp.full((1, 16, 16), 4.5), jax.tree.map(lambda a: a[None], cam))
    v = fsjax.ops.tsdf_fuse(wall, shape=(1, 1, 8), origin=(0.0, 0.0, 0.0), truncation=2.0)
    assert np.allclose(np.asarray(v.data[0, 0, :]), [-1, -1, -1, -0.75, -0.25, 0.25, 0.75, 1.0])


def test_one_sided_view_fill_holes_off_keeps_only_measured_surface():
    # the unit sphere seen by one camera (+x side). With hole filling (the default) the voxels
    # behind the visible cap that no view measured are classified inside, and the surface closes
    # over them far from the sphere (the null: a surface never measured). With fill_holes=False
    # they carry no data (-inf) and marching cubes makes only the measured cap.
    full = _sphere_views()
    one = fsjax.DepthStack(full.z[:1], jax.tree.map(lambda a: a[:1], full.camera))
    sp = 0.1
    kw = dict(shape=(25, 25, 25), spacing=(sp, sp, sp), origin=(-1.2, -1.2, -1.2), truncation=0.3)
    errs = {}
    for fill in (True, False):
        vol = fsjax.ops.tsdf_fuse(one, fill_holes=fill, **kw)
        assert bool(jnp.all(jnp.isfinite(vol.data))) == fill
        m = fsjax.ops.marching_cubes(vol, level=0.0)
        v = np.asarray(m.vertices)[np.asarray(m.vertex_valid)] - 1.2
        assert np.isfinite(v).all()
        errs[fill] = (np.abs(np.linalg.norm(v, axis=1) - 1.0) / sp, v, fsjax.ops.mesh_topology(m))
    e_fill, _, t_fill = errs[True]
    e_meas, v_meas, t_meas = errs[False]
    print(f"one view: filled surface max error {e_fill.max():.2f} voxel (closed {bool(t_fill.closed)}); "
          f"measured-only max {e_meas.max():.3f}, median {np.median(e_meas):.3f} voxel, "
          f"{int(t_meas.boundary_edges)} boundary edges")
    assert e_fill.max() > 3.0                    # the null invents surface voxels away from the sphere
    assert np.median(e_meas) <= 0.1 and e_meas.max() < 1.0
    assert v_meas[:, 0].min() > -0.05            # only the side the camera saw (x > 0)
    assert int(t_meas.boundary_edges) > 0 and not bool(t_meas.closed)
