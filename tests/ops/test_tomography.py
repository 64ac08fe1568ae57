"""Tomography: conformance with scikit-image, a three-material phantom, nulls, centre of rotation, DRR/MIP."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage as ndi
from skimage.data import shepp_logan_phantom
from skimage.transform import iradon, radon, rescale

import fsjax
from fsjax import Camera, Image, Volume
from fsjax import ops as O
from fsjax.synth import CT_MATERIALS, ct_phantom, ct_sinogram

THETA = np.arange(180) * 1.0


@pytest.fixture(scope="module")
def shepp():
    return rescale(shepp_logan_phantom(), 0.24, anti_aliasing=True)  # 96 x 96


def test_radon_matches_skimage(shepp):
    for circle in (True, False):
        ref = radon(shepp, theta=THETA, circle=circle)
        got = np.asarray(O.radon_transform(Image(jnp.asarray(shepp)), n_angles=180, circle=circle).data)
        d = float(np.max(np.abs(ref - got)))
        print(f"radon vs skimage (circle={circle}): max |diff| = {d:.1e} (sinogram max {ref.max():.1f})")
        assert ref.shape == got.shape and d < 1e-10


@pytest.mark.parametrize("filt", ["ramp", "shepp-logan", "cosine"])
def test_fbp_matches_skimage(shepp, filt):
    for circle in (True, False):
        sino = radon(shepp, theta=THETA, circle=circle)
        ref = iradon(sino, theta=THETA, filter_name=filt, circle=circle)
        got = np.asarray(O.filtered_backprojection(Image(jnp.asarray(sino)), filter=filt, circle=circle).data)
        d = float(np.max(np.abs(ref - got)))
        print(f"FBP {filt} vs skimage iradon (circle={circle}): max |diff| = {d:.1e}")
        assert ref.shape == got.shape and d < 1e-9


def test_unfiltered_backprojection_is_twice_skimage_unfiltered(shepp):
    sino = radon(shepp, theta=THETA, circle=True)
    ref = iradon(sino, theta=THETA, filter_name=None, circle=True)
    got = np.asarray(O.backprojection(Image(jnp.asarray(sino)), circle=True).data)
    # skimage pads the detector with zeros and interpolates into them; fsjax stops at the last
    # bin: rays through the outermost half bin differ, by far less than 1e-6 of the peak
    d = float(np.max(np.abs(got - 2.0 * ref)))
    print(f"unfiltered BP vs 2 x skimage: max |diff| = {d:.1e} (peak {np.abs(got).max():.1f})")
    assert d < 1e-6 * np.abs(got).max()


SIZE, PX = 128, 0.75
VALS = np.array([0.0, CT_MATERIALS["water"], CT_MATERIALS["bone"], CT_MATERIALS["aluminium"]])


def _segment(rec):
    return np.digitize(rec, (VALS[1:] + VALS[:-1]) / 2)


def _scores(rec, mu, lab):
    seg = _segment(rec)
    dice = [2 * ((seg == k) & (lab == k)).sum() / ((seg == k).sum() + (lab == k).sum()) for k in (1, 2, 3)]
    err = [float((np.median(rec[ndi.binary_erosion(lab == k, iterations=2)]) - VALS[k]) / VALS[k] * 100)
           for k in (1, 2, 3)]
    return np.array(dice), np.array(err), float(np.sqrt(np.mean((rec - mu) ** 2)))


def _fbp_mu(sino, **kw):
    return np.asarray(O.filtered_backprojection(Image(jnp.asarray(sino)), circle=True, **kw).data) / (PX / 10.0)


def test_three_material_phantom_fbp_beats_nulls():
    mu, lab = ct_phantom(SIZE, PX)
    sino = ct_sinogram(180, SIZE, PX, photons=1e5, seed=0)
    rec = _fbp_mu(sino, filter="shepp-logan")
    dice, err, rmse = _scores(rec, mu, lab)
    print(f"CT phantom, FBP Shepp-Logan, 180 views, 1e5 photons: Dice water/bone/Al = "
          f"{dice.round(3).tolist()}, attenuation error % = {err.round(2).tolist()}, RMSE {rmse:.4f} /cm")
    assert np.all(dice >= 0.88) and np.all(np.abs(err) < 2.0)
    # null 1: 24 views
    rec24 = _fbp_mu(ct_sinogram(24, SIZE, PX, photons=1e5, seed=0), filter="shepp-logan")
    _, _, rmse24 = _scores(rec24, mu, lab)
    # null 2: unfiltered back-projection, given its best least-squares scale
    bp = np.asarray(O.backprojection(Image(jnp.asarray(sino)), circle=True).data)
    bp = bp * float((bp * mu).sum() / (bp * bp).sum())
    dice_bp, _, rmse_bp = _scores(bp, mu, lab)
    print(f"CT nulls: 24 views RMSE {rmse24:.4f} (x{rmse24 / rmse:.2f}), unfiltered RMSE {rmse_bp:.4f} "
          f"(x{rmse_bp / rmse:.2f}; Dice {dice_bp.round(3).tolist()})")
    assert rmse24 >= 1.8 * rmse and rmse_bp >= 1.8 * rmse


def test_rotation_center_to_a_hundredth_of_a_pixel():
    errs = []
    for k, off in enumerate((-2.37, 0.0, 0.41, 3.13)):
        sino = ct_sinogram(180, SIZE, PX, photons=1e5, seed=k, center_offset_px=off)
        c = float(O.rotation_center(Image(jnp.asarray(sino))).value)
        errs.append(c - (SIZE // 2 + off))
    errs = np.array(errs)
    print(f"rotation centre (noisy phantom, 4 offsets): errors {np.round(errs, 4).tolist()} px")
    assert np.max(np.abs(errs)) <= 0.01
    # null: assuming the nominal centre leaves the full offset
    assert np.max(np.abs([-2.37, 0.0, 0.41, 3.13])) > 100 * np.max(np.abs(errs))


def test_miscentred_scan_reconstructs_after_recentering():
    mu, lab = ct_phantom(SIZE, PX)
    off = 2.6
    sino = ct_sinogram(180, SIZE, PX, photons=None, center_offset_px=off)
    c = float(O.rotation_center(Image(jnp.asarray(sino))).value)
    shifted = ndi.shift(sino, (SIZE // 2 - c, 0), order=3, mode="constant")
    _, _, rmse_fixed = _scores(_fbp_mu(shifted), mu, lab)
    _, _, rmse_raw = _scores(_fbp_mu(sino), mu, lab)
    print(f"mis-centred scan (+{off} px): RMSE {rmse_raw:.4f} raw vs {rmse_fixed:.4f} after centring")
    assert rmse_fixed * 2 < rmse_raw


def test_rotation_center_fails_closed():
    sino = Image(jnp.zeros((16, 10)))
    assert np.isnan(float(O.rotation_center(sino).value))


def _cam(eye, target, w=21, h=17, f=30.0):
    R, t = fsjax.render.look_at(eye, target, up=[0.0, -1.0, 0.0])
    return Camera.from_intrinsics(f, f, (w - 1) / 2, (h - 1) / 2, width=w, height=h, R=R, t=t)


def test_drr_exact_for_a_linear_field_from_an_oblique_camera():
    D, H, W, sp = 8, 10, 12, (1.0, 0.8, 0.6)
    z, y, x = np.meshgrid(*(np.arange(n) for n in (D, H, W)), indexing="ij")
    X, Y, Z = (x - (W - 1) / 2) * sp[2], (y - (H - 1) / 2) * sp[1], (z - (D - 1) / 2) * sp[0]
    vol = Volume(jnp.asarray(1.0 + 0.1 * X - 0.05 * Y + 0.2 * Z), spacing=sp)
    cam = _cam([7.0, -4.0, -9.0], [0.3, 0.2, 0.1])
    img = np.asarray(O.volume_drr(vol, cam, n_samples=16).data)
    o, d = (np.asarray(a) for a in fsjax.render.pixel_rays(cam))
    lo, hi = (np.asarray(a) for a in fsjax.render.volume_box(vol))
    worst = 0.0
    for r, c in ((8, 10), (3, 4), (12, 15), (0, 0)):
        t1, t2 = (lo - o[r, c]) / d[r, c], (hi - o[r, c]) / d[r, c]
        a, b = max(np.minimum(t1, t2).max(), 0.0), np.maximum(t1, t2).min()
        if b <= a:
            truth = 0.0
        else:
            pa, pb = o[r, c] + a * d[r, c], o[r, c] + b * d[r, c]
            f = lambda p: 1.0 + 0.1 * p[0] - 0.05 * p[1] + 0.2 * p[2]  # noqa: E731
            truth = (b - a) * (f(pa) + f(pb)) / 2.0
        worst = max(worst, abs(img[r, c] - truth))
    print(f"DRR of a linear field, oblique camera: max |error| = {worst:.1e}")
    assert worst < 1e-9


def test_mip_finds_a_spike_where_it_projects():
    data = np.zeros((9, 9, 9))
    data[2, 6, 3] = 5.0
    vol = Volume(jnp.asarray(data), spacing=(1.0, 1.0, 1.0))
    cam = _cam([3.0, -2.0, -12.0], [0.0, 0.0, 0.0], w=41, h=41, f=60.0)
    img = np.asarray(O.volume_mip(vol, cam, n_samples=512).data)
    uv, _ = fsjax.render.project(cam, jnp.asarray([3 - 4.0, 6 - 4.0, 2 - 4.0]))
    r, c = np.unravel_index(np.argmax(img), img.shape)
    print(f"MIP spike: peak {img.max():.3f} (true 5) at ({r}, {c}); projection ({float(uv[1]):.2f}, {float(uv[0]):.2f})")
    assert abs(r - float(uv[1])) <= 1.0 and abs(c - float(uv[0])) <= 1.0 and img.max() > 4.0


def test_mip_and_drr_keep_the_samples_on_the_box_faces_under_jit():
    # ray samples are placed on the box between entry and exit; a compiled program rounded some of
    # the end samples (on the faces) outside the box, which dropped them: before the fix, MIP 11 %
    # and DRR 6 % off at some pixels of this scene under jit, against the eager call
    rng = np.random.default_rng(0)
    vol = Volume(jnp.asarray(rng.random((20, 24, 28))), spacing=(0.5, 0.4, 0.3))
    R, t = fsjax.render.look_at([1.0, 2.0, -15.0], [0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0])
    cam = Camera.from_intrinsics(60.0, 62.0, 15.5, 11.5, width=32, height=24, R=R, t=t)
    worst = {}
    for mode in ("mip", "drr"):
        e = np.asarray(fsjax.render.project_volume(vol, cam, mode=mode, n_samples=64).data)
        # compiled as a user's program is (the suite's XLA_FLAGS set LLVM level 0, which hid this)
        f = jax.jit(lambda v, cc, m=mode: fsjax.render.project_volume(v, cc, mode=m, n_samples=64))
        c = np.asarray(f.lower(vol, cam).compile(compiler_options={"xla_backend_optimization_level": 3})(vol, cam).data)
        worst[mode] = float(np.max(np.abs(e - c)) / np.max(e))
        assert (e > 0).sum() > 300
    # a bright layer of voxel centres on the entry face: the MIP is 5 wherever a ray starts on it
    data = np.zeros((7, 8, 9))
    data[0] = 5.0
    face = Volume(jnp.asarray(data), spacing=(0.5, 0.4, 0.3))
    cam2 = _cam([0.3, 0.2, -9.0], [0.0, 0.0, 0.0], w=23, h=19, f=40.0)
    mip = np.asarray(jax.jit(lambda v, cc: fsjax.render.project_volume(v, cc, mode="mip", n_samples=32))(face, cam2).data)
    hit = mip > 0
    print(f"project_volume eager vs jit: max rel. difference MIP {worst['mip']:.1e}, DRR {worst['drr']:.1e}; "
          f"face-layer MIP {mip[hit].min():.12f} on {hit.sum()} rays (true 5)")
    assert worst["mip"] < 1e-12 and worst["drr"] < 1e-12
    assert hit.sum() > 50 and np.allclose(mip[hit], 5.0, rtol=1e-12)


def test_bad_input():
    img = Image(jnp.ones((8, 10)))
    with pytest.raises(ValueError, match="radon_transform.*square"):
        O.radon_transform(img, circle=True)
    with pytest.raises(ValueError, match="radon_transform.*n_angles"):
        O.radon_transform(img, n_angles=0)
    with pytest.raises(ValueError, match="filtered_backprojection.*filter"):
        O.filtered_backprojection(img, filter="butterworth")
    with pytest.raises(ValueError, match="project_volume.*mode"):
        fsjax.render.project_volume(Volume(jnp.ones((3, 3, 3))), _cam([0.0, 0.0, -5.0], [0.0, 0.0, 0.0]), mode="avg")
    with pytest.raises(ValueError, match="volume_drr.*n_samples"):
        O.volume_drr(Volume(jnp.ones((3, 3, 3))), _cam([0.0, 0.0, -5.0], [0.0, 0.0, 0.0]), n_samples=1)
