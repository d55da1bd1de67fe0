"""Fits from photographs: target and mask files (PNG 8/16-bit, TIFF, OpenEXR, JPEG, .npy) read
as linear radiance, reduced to one channel, their one-line errors, and the exposure (gain)
unknowns.

Every file is written by the test itself, where possible by another library than the reader
(OpenImageIO): Pillow for 8-bit and 16-bit grey PNG and JPEG, tifffile for TIFF, a few lines of
zlib for 16-bit colour PNG (which Pillow cannot write, nor read without dropping to 8 bits);
OpenEXR files by OpenImageIO itself, the only EXR writer installed.  The fits run on a cheap
analytic two-view model; one end-to-end `difffog fit` runs the splat on a 16×16 view."""

import dataclasses
import json
import struct
import zlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tifffile
from PIL import Image

import difffog as df
from difffog import DifffogError, IdentifiabilityWarning
from difffog.fit._images import LUMINANCE, load_mask, load_target, srgb_to_linear

from helpers import ToyLight

RNG = np.random.default_rng(16)
#: linear radiance in [0, 1] (6 rows, 7 columns), with both ends of the sRGB curve's pieces
L = RNG.uniform(0.0, 1.0, (6, 7))
L[0, :4] = [0.0, 0.002, 0.0031308, 1.0]
RGB = RNG.uniform(0.0, 1.0, (6, 7, 3))


def linear_to_srgb(x):
    """The sRGB transfer function (IEC 61966-2-1), linear [0, 1] to encoded [0, 1]: what an
    8-bit file stores, as code value / 255."""
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4)
                    - 0.055)


def write_png(path, a):
    """A PNG of uint8 or uint16 pixels (H, W) or (H, W, 1-4 channels), written from the PNG
    specification: signature, IHDR, one zlib-compressed IDAT of unfiltered rows, IEND."""
    a = np.asarray(a)
    a = a[..., None] if a.ndim == 2 else a
    h, w, c = a.shape
    kind = {1: 0, 2: 4, 3: 2, 4: 6}[c]  # grey, grey + alpha, RGB, RGBA
    rows = a.astype(f">u{a.dtype.itemsize}").reshape(h, -1).view(np.uint8).reshape(h, -1)
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rows], axis=1).tobytes()

    def chunk(tag, data):
        return (struct.pack(">I", len(data)) + tag + data
                + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF))

    ihdr = struct.pack(">IIBBBBB", w, h, 8 * a.dtype.itemsize, kind, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw))
                     + chunk(b"IEND", b""))


def write_exr(path, a, pixel_type):
    import OpenImageIO as oiio

    a = np.asarray(a)
    a = a[..., None] if a.ndim == 2 else a  # (OpenImageIO would take a 2-D array as (W, H))
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(a.shape[1], a.shape[0], a.shape[2], pixel_type))
    assert out.write_image(np.ascontiguousarray(a))
    out.close()


def luminance(rgb):
    return rgb @ np.asarray(LUMINANCE)


# ------------------------------------------------------------------ transfer and formats
def test_srgb_decoding_is_the_exact_iec_61966_2_1_inverse():
    v = np.linspace(0.0, 1.0, 1001)
    lin = srgb_to_linear(v)
    low = v <= 0.04045
    np.testing.assert_allclose(lin[low], v[low] / 12.92, rtol=1e-15)
    np.testing.assert_allclose(lin[~low], ((v[~low] + 0.055) / 1.055) ** 2.4, rtol=1e-15)
    assert srgb_to_linear(0.0) == 0.0 and srgb_to_linear(1.0) == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_allclose(linear_to_srgb(lin), v, atol=1e-12)  # the pair are inverses


def test_8bit_png_is_srgb_decoded_within_half_a_code_value(tmp_path):
    """An 8-bit file stores round(255·sRGB(L)); the loader returns sRGB⁻¹(code / 255) exactly,
    which is L within the quantization: half a code value (0.5/255) in the encoded domain."""
    code = np.round(255 * linear_to_srgb(L)).astype(np.uint8)
    Image.fromarray(code).save(tmp_path / "t.png")
    img, info = load_target(tmp_path / "t.png")
    assert img.dtype == np.float64 and img.shape == (6, 7)
    np.testing.assert_allclose(img, srgb_to_linear(code / 255.0), rtol=1e-15, atol=0)
    assert np.abs(linear_to_srgb(img) - linear_to_srgb(L)).max() <= 0.5 / 255 + 1e-12
    assert (info["format"], info["dtype"], info["transfer"], info["channel"]) == (
        "png", "uint8", "srgb", "grey")
    # transfer="linear": code / 255 as it is
    img, info = load_target(tmp_path / "t.png", transfer="linear")
    np.testing.assert_allclose(img, code / 255.0, rtol=1e-15)
    assert info["transfer"] == "linear"


def test_16bit_png_is_linear_within_half_a_code_value(tmp_path):
    code = np.round(65535 * L).astype(np.uint16)
    Image.fromarray(code).save(tmp_path / "t.png")  # Pillow's 16-bit grey ("I;16")
    img, info = load_target(tmp_path / "t.png")
    assert (info["dtype"], info["transfer"]) == ("uint16", "linear")
    np.testing.assert_allclose(img, code / 65535.0, rtol=1e-15)
    assert np.abs(img - L).max() <= 0.5 / 65535 + 1e-15
    # a 16-bit file the user says is sRGB-encoded
    img, info = load_target(tmp_path / "t.png", transfer="srgb")
    np.testing.assert_allclose(img, srgb_to_linear(code / 65535.0), rtol=1e-15)
    assert info["transfer"] == "srgb"


def test_16bit_colour_png_keeps_16_bits_and_reduces_by_luminance_or_a_channel(tmp_path):
    code = np.round(65535 * RGB).astype(np.uint16)
    write_png(tmp_path / "t.png", code)
    lin = code / 65535.0
    img, info = load_target(tmp_path / "t.png")
    assert (info["dtype"], info["channel"], info["channels"]) == ("uint16", "luminance",
                                                                  ["R", "G", "B"])
    np.testing.assert_allclose(img, luminance(lin), rtol=1e-14)
    assert np.abs(img - luminance(RGB)).max() <= 0.5 / 65535 + 1e-15
    for i, ch in enumerate("rgb"):
        np.testing.assert_allclose(load_target(tmp_path / "t.png", channel=ch)[0], lin[..., i],
                                   rtol=1e-15)


def test_8bit_colour_is_linearised_before_it_is_reduced(tmp_path):
    """Luminance is a weighted sum of *linear* R, G, B: decoding after the sum would be wrong
    by up to several percent for saturated colours."""
    code = np.round(255 * linear_to_srgb(RGB)).astype(np.uint8)
    Image.fromarray(code).save(tmp_path / "t.png")
    img, _ = load_target(tmp_path / "t.png")
    right = luminance(srgb_to_linear(code / 255.0))
    np.testing.assert_allclose(img, right, rtol=1e-14)
    assert np.abs(srgb_to_linear(luminance(code / 255.0)) - right).max() > 1e-2
    g, _ = load_target(tmp_path / "t.png", channel="g")
    np.testing.assert_allclose(g, srgb_to_linear(code[..., 1] / 255.0), rtol=1e-15)


def test_float_and_16bit_tiff_are_linear_as_stored(tmp_path):
    f = RGB.astype(np.float32)
    tifffile.imwrite(tmp_path / "f.tif", f, photometric="rgb")
    img, info = load_target(tmp_path / "f.tif")
    assert (info["format"], info["dtype"], info["transfer"]) == ("tiff", "float32", "linear")
    np.testing.assert_allclose(img, luminance(f.astype(np.float64)), rtol=1e-14)
    np.testing.assert_array_equal(load_target(tmp_path / "f.tif", channel="b")[0], f[..., 2])
    code = np.round(65535 * L).astype(np.uint16)
    tifffile.imwrite(tmp_path / "i.tif", code)
    img, info = load_target(tmp_path / "i.tif")
    assert (info["dtype"], info["transfer"]) == ("uint16", "linear")
    np.testing.assert_allclose(img, code / 65535.0, rtol=1e-15)


@pytest.mark.parametrize("pixel_type,dtype", [("half", np.float16), ("float", np.float32)])
def test_exr_half_and_float_are_linear_as_stored(tmp_path, pixel_type, dtype):
    """Radiance above 1 (a bright sky) survives; half floats round to 11 significant bits."""
    hdr = (RGB * 40.0).astype(dtype)
    write_exr(tmp_path / "t.exr", hdr, pixel_type)
    img, info = load_target(tmp_path / "t.exr", channel="r")
    assert (info["format"], info["dtype"], info["transfer"]) == ("openexr", np.dtype(dtype).name,
                                                                 "linear")
    np.testing.assert_array_equal(img, hdr[..., 0].astype(np.float64))
    rel = 2.0 ** -11 if dtype == np.float16 else 2.0 ** -24
    np.testing.assert_allclose(img, 40.0 * RGB[..., 0], rtol=rel)
    np.testing.assert_allclose(load_target(tmp_path / "t.exr")[0],
                               luminance(hdr.astype(np.float64)), rtol=1e-14)


def test_alpha_is_dropped_from_a_target_and_is_the_mask_of_its_file(tmp_path):
    """Colour values are read as stored (not premultiplied by alpha); the file's own alpha is
    its mask: 1 where alpha is nonzero."""
    code = np.round(255 * linear_to_srgb(RGB)).astype(np.uint8)
    alpha = np.full((6, 7), 255, np.uint8)
    alpha[:2] = 0
    alpha[2] = 100
    Image.fromarray(np.dstack([code, alpha])).save(tmp_path / "t.png")
    img, info = load_target(tmp_path / "t.png")
    assert info["alpha"] == "dropped" and info["channels"] == ["R", "G", "B", "A"]
    np.testing.assert_allclose(img, luminance(srgb_to_linear(code / 255.0)), rtol=1e-14)
    np.testing.assert_array_equal(load_mask(tmp_path / "t.png"), (alpha > 0).astype(float))


def test_mask_files_use_nonzero_pixels(tmp_path):
    m = np.zeros((6, 7), np.uint8)
    m[1:4, 2:6] = 255
    m[5, 0] = 1  # any nonzero code value is "use"
    Image.fromarray(m).save(tmp_path / "m.png")
    np.testing.assert_array_equal(load_mask(tmp_path / "m.png"), (m > 0).astype(float))
    Image.fromarray(np.dstack([m, m, 0 * m])).save(tmp_path / "rgb.png")
    np.testing.assert_array_equal(load_mask(tmp_path / "rgb.png"), (m > 0).astype(float))
    w = RNG.uniform(0, 2, (6, 7))
    np.save(tmp_path / "w.npy", w)  # .npy: weights as stored
    np.testing.assert_array_equal(load_mask(tmp_path / "w.npy"), w)


def test_npy_and_jpeg_targets(tmp_path):
    np.save(tmp_path / "t.npy", L)
    img, info = load_target(tmp_path / "t.npy")
    np.testing.assert_array_equal(img, L)
    assert (info["format"], info["transfer"]) == ("NumPy", "linear")
    np.save(tmp_path / "rgb.npy", RGB)
    np.testing.assert_allclose(load_target(tmp_path / "rgb.npy")[0], luminance(RGB), rtol=1e-14)
    # a flat grey JPEG decodes to its code value exactly
    Image.fromarray(np.full((8, 8), 128, np.uint8)).save(tmp_path / "g.jpg", quality=95)
    img, info = load_target(tmp_path / "g.jpg")
    assert (info["format"], info["transfer"]) == ("jpeg", "srgb")
    np.testing.assert_allclose(img, srgb_to_linear(128 / 255.0), rtol=1e-15)


# ------------------------------------------------------------------ one-line errors
def _files(d):
    """Broken and unusable files, by name."""
    (d / "junk.png").write_bytes(b"this is not a PNG")
    (d / "x.bmp").write_bytes(b"BM")
    np.save(d / "five.npy", np.ones((6, 7, 5)))
    tifffile.imwrite(d / "five.tif", np.ones((6, 7, 5), np.float32), photometric="minisblack",
                     planarconfig="contig")
    tifffile.imwrite(d / "i32.tif", np.ones((6, 7), np.int32))
    tifffile.imwrite(d / "rot.tif", np.ones((6, 7), np.uint16),
                     extratags=[(274, "H", 1, 6, True)])  # EXIF/TIFF orientation: rotated 90°
    nan = RGB.astype(np.float32)
    nan[2, 3, 1] = np.nan
    nan[4, 1] = np.inf
    tifffile.imwrite(d / "nan.tif", nan, photometric="rgb")
    neg = L.astype(np.float32)
    neg[1, 2] = -0.5
    neg[3, 3] = -0.25
    write_exr(d / "neg.exr", neg, "float")
    Image.fromarray((255 * L).astype(np.uint8)).save(d / "grey.png")
    np.save(d / "grey.npy", L)


@pytest.mark.parametrize("name,kw,needle", [
    ("missing.png", {}, "missing.png: no such file"),
    ("x.bmp", {}, "unknown image format '.bmp'; supported: .npy (linear radiance), .png"),
    ("junk.png", {}, "junk.png: cannot read it as PNG"),
    ("five.npy", {}, "5 channels (?, ?, ?, ?, ?); supported: 1 (grey) or 3 (R, G, B)"),
    ("five.tif", {}, "5 channels (R, G, B, channel3, channel4); supported: 1 (grey) or 3"),
    ("i32.tif", {}, "pixels of type int32; supported: 8- or 16-bit"),
    ("rot.tif", {}, "stored rotated or mirrored (orientation tag 6); save it upright"),
    ("nan.tif", {}, "non-finite values (NaN or infinite) in its luminance image: 2 pixels, "
                    "the first at row 2, column 3; replace them or mask them out"),
    ("neg.exr", {}, "negative values in its image: 2 pixels, the first at row 1, column 2 "
                    "(-0.5); radiance is >= 0: clip them at 0 or mask them out"),
    ("grey.png", {"channel": "r"}, "a grey image (Y) has no channel 'r'; use channel "
                                   "'luminance'"),
    ("grey.png", {"channel": "red"}, "channel 'red': choose 'luminance'"),
    ("grey.png", {"transfer": "gamma"}, "transfer 'gamma': choose 'auto'"),
    ("grey.npy", {"transfer": "srgb"}, "a .npy target holds linear radiance as stored"),
])
def test_bad_files_get_one_line_errors(tmp_path, name, kw, needle):
    _files(tmp_path)
    with pytest.raises(DifffogError) as e:
        load_target(tmp_path / name, **kw)
    msg = str(e.value)
    assert needle in msg and "\n" not in msg, msg


def test_masked_out_pixels_are_not_checked(tmp_path):
    _files(tmp_path)
    mask = np.ones((6, 7))
    mask[2, 3] = mask[4, 1] = 0
    img, _ = load_target(tmp_path / "nan.tif", mask=mask)
    assert np.isfinite(img[mask > 0]).all()
    with pytest.raises(DifffogError, match=r"its mask is \(3, 2\) pixels \(width, height\), "
                                           r"the image \(7, 6\)"):
        load_target(tmp_path / "nan.tif", mask=np.ones((2, 3)))


# ------------------------------------------------------------------ a cheap two-view model
class LitToy(df.AbstractForwardModel):
    """Two views, linear in the lights like the renderer (sun F, sky S) and not in the fog:
    top = F·(1 − e^(−ζa)) + S·b·e^(−γ), oblique = F·ζ·c + S·d.  No light solve."""

    scene: df.Scene = eqx.field(static=True)
    cameras: tuple = eqx.field(static=True)
    a: jax.Array
    b: jax.Array
    c: jax.Array
    d: jax.Array

    def __init__(self):
        scene = df.load_scene("fog-balls")
        cams = tuple(dataclasses.replace(c, resolution=r)
                     for c, r in zip(scene.cameras, [(7, 6), (5, 4)]))
        self.scene = scene.replace(cameras=cams)
        self.cameras = cams
        y, x = np.mgrid[0:6, 0:7] / 5.0
        q, p = np.mgrid[0:4, 0:5] / 3.0
        self.a, self.b, self.c, self.d = (jnp.asarray(v, jnp.float32) for v in (
            0.5 + x, 1.0 + np.sin(3 * y), np.exp(-p) * (1 + q), 1.0 + p * q))

    def light(self, params):
        return ToyLight(result=jnp.asarray(df.RESULTS.successful, jnp.int32),
                        iterations=jnp.asarray(1, jnp.int32),
                        error_estimate=jnp.asarray(0.0, params.scattering.dtype))

    def images_from(self, light, p):
        F, S = p.sun_irradiance, p.sky_radiance
        return {"top": F * (1 - jnp.exp(-p.scattering * self.a))
                + S * self.b * jnp.exp(-p.absorption),
                "oblique": F * p.scattering * self.c + S * self.d}

    def check(self, params):
        return None

    def settings(self):
        return {"solver": "toy", "resolution": 0}


@pytest.fixture(scope="module")
def toy():
    return LitToy()


def _render(toy, **values):
    p = toy.params()
    for k, v in values.items():
        p = df.set_param(p, toy.scene, k, v)
    return {k: np.asarray(v, np.float64) for k, v in toy(p).items()}


TRUTH = {"fog.scattering": 1.5, "fog.absorption": 0.4}


@pytest.mark.parametrize("init", [None, 1.0])
def test_a_global_exposure_is_recovered_with_the_fog(toy, init):
    """Targets at 1.3 × the model's images: the fit finds the gain (and ζ, γ) to 1e-3.  Without
    an initial value the exposure starts at the least-squares gain of the first render."""
    targets = {k: 1.3 * v for k, v in _render(toy, **TRUTH).items()}
    start = {"fog.scattering": 1.0, "fog.absorption": 0.6, "exposure": init}
    res = df.fit(toy.scene, targets, start, forward=toy, rtol=1e-7, atol=1e-7)
    assert res.converged, res.message
    assert res.estimates["exposure"] == pytest.approx(1.3, rel=1e-3)
    for p, v in TRUTH.items():
        assert res.estimates[p] == pytest.approx(v, rel=1e-3), p
    if init is None:  # the least-squares gain at ζ = 1, γ = 0.6
        y = np.concatenate([v.ravel() for v in _render(toy, **{"fog.scattering": 1.0,
                                                              "fog.absorption": 0.6}).values()])
        t = np.concatenate([v.ravel() for v in targets.values()])
        assert res.initial["exposure"] == pytest.approx(y @ t / (y @ y), rel=1e-5)
    else:
        assert res.initial["exposure"] == 1.0
    assert 0 < res.stderr["exposure"] < 1e-3 and "exposure" in res.to_json()["stderr"]


def test_per_camera_exposures_are_recovered(toy):
    clean = _render(toy, **{"fog.scattering": 1.5})
    targets = {"top": 1.3 * clean["top"], "oblique": 0.6 * clean["oblique"]}
    res = df.fit(toy.scene, targets, {"fog.scattering": 1.2, "camera.top.exposure": None,
                                      "camera.oblique.exposure": None}, forward=toy,
                 rtol=1e-7, atol=1e-7)
    assert res.converged, res.message
    assert res.estimates["camera.top.exposure"] == pytest.approx(1.3, rel=1e-3)
    assert res.estimates["camera.oblique.exposure"] == pytest.approx(0.6, rel=1e-3)
    assert res.estimates["fog.scattering"] == pytest.approx(1.5, rel=1e-3)


def test_an_exposure_with_both_lights_is_not_identifiable_and_warns(toy):
    """The images are linear in (sun, sky): a gain on them equals scaling both lights."""
    targets = _render(toy, **TRUTH)
    with pytest.warns(IdentifiabilityWarning, match="near-singular|correlated"):
        res = df.fit(toy.scene, targets, {"exposure": 1.2, "sun.irradiance": None,
                                          "sky.radiance": None}, forward=toy)
    assert res.warnings


@pytest.mark.parametrize("unknowns,needle", [
    (["camera.side.exposure"], "unknown 'camera.side.exposure': camera 'side' has no target "
                               "(the targets' cameras: top, oblique)"),
    (["exposur"], "and the images' gains: exposure, camera.top.exposure, "
                  "camera.oblique.exposure. Did you mean 'exposure'?"),
    ({"exposure": (2.0, 3.0, 5.0)}, "unknown 'exposure': the initial value 2 lies outside"),
])
def test_bad_exposures_get_one_line_errors(toy, unknowns, needle):
    with pytest.raises(DifffogError) as e:
        df.fit(toy.scene, _render(toy), unknowns, forward=toy)
    assert needle in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_a_fit_reads_target_and_mask_files_and_records_them(toy, tmp_path):
    clean = _render(toy, **{"fog.scattering": 1.5})
    gain = 0.9 / clean["top"].max()  # the photo's scale: the brightest pixel at 90%
    code = np.round(65535 * gain * clean["top"]).astype(np.uint16)
    write_png(tmp_path / "top.png", np.dstack([code] * 3))  # a grey scene in a colour file
    mask = np.full((6, 7), 255, np.uint8)
    mask[0] = 0
    Image.fromarray(mask).save(tmp_path / "top_mask.png")
    res = df.fit(toy.scene, {"top": str(tmp_path / "top.png")}, ["exposure", "fog.scattering"],
                 forward=toy, weights={"top": tmp_path / "top_mask.png"}, channel="g",
                 rtol=1e-7, atol=1e-7)
    assert res.converged, res.message
    assert res.estimates["exposure"] == pytest.approx(gain, rel=1e-3)
    assert res.estimates["fog.scattering"] == pytest.approx(1.5, rel=1e-3)
    rec = json.loads(json.dumps(res.to_json()))
    assert rec["target_files"]["top"] == {
        "path": str(tmp_path / "top.png"), "format": "png", "dtype": "uint16",
        "transfer": "linear", "channel": "g", "channels": ["R", "G", "B"], "alpha": None,
        "size": [7, 6]}
    assert rec["mask_files"] == {"top": str(tmp_path / "top_mask.png")}
    assert "target top: " in str(res)
    # a photo of the wrong size: both sizes and the fixes
    Image.fromarray(np.zeros((4, 5), np.uint8)).save(tmp_path / "small.png")
    with pytest.raises(DifffogError, match=r"target 'top' \(.*small.png\): the image is 5x4 "
                                           r"pixels \(width x height\) but camera 'top' is "
                                           r"7x6; resize \(or crop\) the image to 7x6, or set"):
        df.fit(toy.scene, {"top": str(tmp_path / "small.png")}, ["exposure"], forward=toy)


# ------------------------------------------------------------------ the command line
# slow: the default suite's 12-minute budget on 2 cores (stop 56);
# by default the files are read (the tests above), a fit reads target files
# (test_a_fit_reads_target_and_mask_files...) and recovers an exposure (test_a_global_exposure...)
@pytest.mark.slow
def test_cli_fits_the_exposure_of_a_16bit_png(tmp_path, capsys):
    """`difffog fit --target top=photo.png --unknown exposure` end to end: the splat on
    cloud-plane's top view at 1/8 size (16×16), its own render scaled to a 16-bit PNG at the
    camera's 128×128 pixels (the brightest pixel at 90%).  The exposure starts at the
    least-squares gain of the first render, exact here, and the fit confirms it in one step
    (the toy fits above move it from 1).  ~10 s, most of it compiling the render and the step."""
    from difffog.cli import main
    from difffog.fit._driver import make_model

    scene = df.load_scene("cloud-plane")
    fwd = make_model(scene, "splat", cameras=["top"], resolution=8, downsample=8)
    clean = np.kron(np.asarray(fwd(fwd.params())["top"], np.float64), np.ones((8, 8)))
    gain = 0.9 / clean.max()
    write_png(tmp_path / "photo.png", np.round(65535 * gain * clean).astype(np.uint16))
    out = tmp_path / "fit"
    argv = ["fit", "cloud-plane", "--solver", "splat", "-N", "8", "--downsample", "8",
            "--target", f"top={tmp_path / 'photo.png'}", "--unknown", "exposure",
            "--out", str(out), "-q"]
    assert main(argv) == 0, capsys.readouterr()
    rep = json.loads((out / "fit.json").read_text())
    assert rep["converged"]
    # the fit at N = 8 finds the gain of its own render; the estimate is that fit corrected
    # to N = 16 (--model-error refine, the default), off by the model error it states
    assert rep["fitted"]["exposure"] == pytest.approx(gain, rel=1e-3)
    assert rep["initial"]["exposure"] == pytest.approx(gain, rel=1e-3)
    assert 0 < rep["stderr"]["exposure"] < 1e-3 * gain  # 16-bit quantization: tiny
    assert abs(rep["estimates"]["exposure"] - gain) == pytest.approx(
        rep["model_error_parts"]["exposure"]["lattice"], rel=1e-3)
    assert rep["model_error"]["exposure"] >= rep["model_error_parts"]["exposure"]["lattice"]
    assert rep["target_files"]["top"] == {
        "path": str(tmp_path / "photo.png"), "format": "png", "dtype": "uint16",
        "transfer": "linear", "channel": "grey", "channels": ["Y"], "alpha": None,
        "size": [128, 128]}
    assert rep["targets"] == {"top": str(tmp_path / "photo.png")}
