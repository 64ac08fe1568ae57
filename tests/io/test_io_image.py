"""Image file I/O: PNG round trips (8- and 16-bit), recorded conversions, the
quantisation/clipping rule, sRGB decoding, and refusals."""

from __future__ import annotations

import sys

import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image as PILImage
from skimage import data

import fsjax
from fsjax import Color, Image, Region
from fsjax.io import read_image, write_image
from fsjax.ops.image._color import srgb_to_linear


@pytest.fixture(scope="module")
def camera8():
    return data.camera()[::4, ::4]  # uint8, real photo


def test_grey_png_round_trip(tmp_path, camera8):
    p = tmp_path / "cam.png"
    write_image(p, Image(camera8 / 255.0))
    img = read_image(p)
    assert isinstance(img, Image) and img.conversion == "uint8 / 255"
    d = float(np.max(np.abs(np.asarray(img.data) * 255.0 - camera8)))
    print(f"grey PNG round trip: max |diff| = {d:.2e} grey levels")
    assert d <= 1e-9
    # byte-exact against what Pillow itself stored
    assert np.array_equal(np.asarray(PILImage.open(p)), camera8)


def test_color_png_round_trip(tmp_path):
    rgb8 = data.astronaut()[::8, ::8]
    p = tmp_path / "astro.png"
    write_image(p, Color(rgb8 / 255.0))
    img = read_image(p)
    assert isinstance(img, Color) and img.conversion == "uint8 / 255"
    assert np.array_equal(np.round(np.asarray(img.data) * 255).astype(np.uint8), rgb8)


def test_16bit_png_read_and_bit_depth(tmp_path):
    a = (np.arange(20 * 30).reshape(20, 30) * 100 % 65536).astype(np.uint16)
    p = tmp_path / "g16.png"
    PILImage.fromarray(a).save(p)
    img = read_image(p)
    assert img.conversion == "uint16 / 65535"
    assert float(np.max(np.abs(np.asarray(img.data) - a / 65535.0))) <= 1e-15
    # a 12-bit sensor in 16-bit words
    b = (a % 4096).astype(np.uint16)
    PILImage.fromarray(b).save(p)
    img12 = read_image(p, bit_depth=12)
    assert img12.conversion == "uint16 / 4095" and float(np.max(img12.data)) <= 1.0
    assert float(np.max(np.abs(np.asarray(img12.data) - b / 4095.0))) <= 1e-15
    with pytest.raises(ValueError, match="bit_depth"):
        read_image(tmp_path / "g16.png", bit_depth=10)  # values up to 4095 exceed 10 bits


def test_16bit_write_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, (16, 24))
    p = tmp_path / "w16.png"
    write_image(p, Image(x), bit_depth=16)
    back = read_image(p)
    d = float(np.max(np.abs(np.asarray(back.data) - x)))
    print(f"16-bit write/read: max |diff| = {d:.2e} (bound 0.5/65535 = {0.5 / 65535:.2e})")
    assert back.conversion == "uint16 / 65535" and d <= 0.5 / 65535 + 1e-15


def test_16bit_colour_png_is_flagged(tmp_path):
    cv2 = pytest.importorskip("cv2")
    a = (np.arange(8 * 10 * 3).reshape(8, 10, 3) * 700).astype(np.uint16)
    p = tmp_path / "c16.png"
    cv2.imwrite(str(p), a[..., ::-1])
    img = read_image(p)
    assert isinstance(img, Color) and "16-bit colour" in img.conversion
    # 8-bit precision of the 16-bit value
    assert float(np.max(np.abs(np.asarray(img.data) - a / 65535.0))) <= 1 / 255


def test_quantisation_and_clipping_rule(tmp_path):
    x = np.array([[-0.2, 0.0, 0.5 / 255 - 1e-9, 0.5 / 255, 0.5, 1.0, 1.3]])
    p = tmp_path / "q.png"
    write_image(p, Image(x))
    got = np.asarray(PILImage.open(p)).ravel().tolist()
    assert got == [0, 0, 0, 1, 128, 255, 255]  # clip to [0, 1], then floor(v * 255 + 0.5)


def test_region_written_as_0_255(tmp_path):
    m = np.zeros((5, 6), bool)
    m[1:3, 2:5] = True
    p = tmp_path / "r.png"
    write_image(p, Region(m))
    assert np.array_equal(np.asarray(PILImage.open(p)), np.where(m, 255, 0))
    assert np.array_equal(np.asarray(read_image(p).data) == 1.0, m)


def test_linearize_records_and_decodes(tmp_path, camera8):
    p = tmp_path / "cam.png"
    PILImage.fromarray(camera8).save(p)
    img = read_image(p, linearize=True)
    assert img.conversion == "uint8 / 255; sRGB decoded"
    want = np.asarray(srgb_to_linear(camera8 / 255.0))
    assert float(np.max(np.abs(np.asarray(img.data) - want))) <= 1e-15
    # the sRGB curve: code value 128 is about 21.6 % linear light
    assert abs(float(srgb_to_linear(128 / 255)) - ((128 / 255 + 0.055) / 1.055) ** 2.4) < 1e-15


def test_write_srgb_then_read_linearized(tmp_path):
    x = np.linspace(0.0, 1.0, 64).reshape(8, 8)
    p = tmp_path / "lin.png"
    write_image(p, Image(x), srgb=True)
    back = np.asarray(read_image(p, linearize=True).data)
    d = float(np.max(np.abs(back - x)))
    # quantisation error of 0.5 code values times the largest slope of the sRGB decoding curve (~2.5)
    print(f"linear -> sRGB 8-bit -> linear: max |diff| = {d:.2e}")
    assert d <= 0.5 / 255 * 2.5
    raw = np.asarray(read_image(p).data)  # encoded values are brighter than linear ones in the mid-tones
    assert raw[4, 0] > x[4, 0] + 0.1


def test_as_grey_and_as_colour(tmp_path):
    rgb8 = data.astronaut()[::16, ::16]
    p = tmp_path / "c.png"
    PILImage.fromarray(rgb8).save(p)
    g = read_image(p, as_grey=True)
    assert isinstance(g, Image) and g.conversion == "uint8 / 255; grey = BT.709 luminance"
    want = (rgb8 / 255.0) @ np.array([0.2126, 0.7152, 0.0722])
    assert float(np.max(np.abs(np.asarray(g.data) - want))) <= 1e-15
    gl = read_image(p, as_grey=True, linearize=True)
    assert gl.conversion == "uint8 / 255; sRGB decoded; grey = BT.709 luminance"
    q = tmp_path / "g.png"
    PILImage.fromarray(rgb8[..., 0]).save(q)
    c = read_image(q, as_grey=False)
    assert isinstance(c, Color) and c.conversion.endswith("grey replicated to RGB")
    assert np.array_equal(np.asarray(c.data[..., 0]), np.asarray(c.data[..., 2]))


def test_rgba_and_palette_files(tmp_path):
    rgba = np.zeros((4, 4, 4), np.uint8)
    rgba[..., 0] = 200
    rgba[..., 3] = 128
    p = tmp_path / "a.png"
    PILImage.fromarray(rgba).save(p)
    img = read_image(p)
    assert isinstance(img, Color) and img.conversion == "uint8 / 255; alpha dropped"
    assert float(img.data[0, 0, 0]) == 200 / 255
    q = tmp_path / "p.png"
    PILImage.fromarray(rgba[..., :3]).convert("P").save(q)
    pal = read_image(q)
    assert isinstance(pal, Color) and "palette expanded" in pal.conversion


def test_read_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="read_image: no such file"):
        read_image(tmp_path / "missing.png")
    bad = tmp_path / "not_an_image.png"
    bad.write_bytes(b"this is not a png")
    with pytest.raises(ValueError, match="read_image: Pillow cannot decode"):
        read_image(bad)
    with pytest.raises(TypeError, match="as_grey"):
        read_image(bad, as_grey="yes")


def test_write_refuses_nan_and_bad_arguments(tmp_path):
    p = tmp_path / "x.png"
    with pytest.raises(ValueError, match="write_image: .*NaN"):
        write_image(p, Image(jnp.array([[0.1, jnp.nan]])))
    assert not p.exists()
    with pytest.raises(TypeError, match="write_image: argument 'img' must be Image, Color or Region, got HSV"):
        write_image(p, fsjax.HSV(jnp.zeros((2, 2, 3))))
    with pytest.raises(TypeError, match="got Labels"):
        write_image(p, fsjax.Labels(jnp.zeros((2, 2), jnp.int32), count=0))
    with pytest.raises(TypeError, match="got ndarray"):
        write_image(p, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="'.png'"):
        write_image(tmp_path / "x.jpg", Image(jnp.zeros((2, 2))))
    with pytest.raises(ValueError, match="batch"):
        write_image(p, Image(jnp.zeros((2, 3, 3))))
    with pytest.raises(ValueError, match="bit_depth"):
        write_image(p, Image(jnp.zeros((2, 2))), bit_depth=12)
    with pytest.raises(ValueError, match="bit_depth=16"):
        write_image(p, Color(jnp.zeros((2, 2, 3))), bit_depth=16)


def test_missing_pillow_names_the_package(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "PIL", None)
    with pytest.raises(ImportError, match="pillow"):
        write_image(tmp_path / "x.png", Image(jnp.zeros((2, 2))))
