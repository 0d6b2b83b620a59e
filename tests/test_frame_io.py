"""Frame container, serialisation, readers and writers (DNG round trip through rawpy)."""

import numpy as np
import pytest

from firmware_model.frame import Frame, frame_from_bytes, frame_to_bytes, pattern_codes, RED, GREEN, BLUE
from firmware_model.frame_io import FrameReadError, read_frame
from ground.frame_writer import write_dng, write_frame


def _frame(pattern="RGGB", shape=(48, 64), seed=0):
    rng = np.random.default_rng(seed)
    return Frame(
        pixels=rng.integers(0, 4096, shape, dtype=np.uint16), pattern=pattern,
        black_level=(64, 65, 66, 67) if pattern != "MONO" else 64, white_level=4095, exposure_s=0.1,
        timestamp="2026-11-22T01:00:00+00:00", site={"lat_deg": 52.1, "lon_deg": 4.4, "height_m": 3.0},
        camera={"width": shape[1], "height": shape[0], "f": 1000.0, "cx": 31.5, "cy": 23.5},
        metadata={"note": "test"},
    )


def test_pattern_codes_and_maps():
    assert pattern_codes("rggb").tolist() == [[RED, GREEN], [GREEN, BLUE]]
    assert pattern_codes("GBRG").tolist() == [[GREEN, BLUE], [RED, GREEN]]
    f = _frame("BGGR", (4, 6))
    assert f.channel_map()[1, 1] == RED and f.channel_map()[0, 0] == BLUE
    assert f.black_map()[1, 0] == 66 and f.black_map()[3, 5] == 67


@pytest.mark.parametrize(
    "kwargs, msg",
    [
        ({"pattern": "RGBW"}, "unknown CFA pattern"),
        ({"pixels": np.zeros((5, 8), np.uint16)}, "even dimensions"),
        ({"pixels": np.full((4, 4), np.nan)}, "non-finite"),
        ({"pixels": np.zeros(16)}, "2-D"),
        ({"white_level": 10, "black_level": 64}, "white level"),
        ({"black_level": (1, 2, 3)}, "black_level"),
    ],
)
def test_frame_rejects_bad_input(kwargs, msg):
    base = {"pixels": np.zeros((4, 4), np.uint16), "pattern": "RGGB"}
    with pytest.raises(ValueError, match=msg):
        Frame(**{**base, **kwargs})


@pytest.mark.parametrize("pattern", ["RGGB", "MONO"])
def test_bytes_round_trip_and_corruption(pattern):
    f = _frame(pattern)
    blob = frame_to_bytes(f)
    g = frame_from_bytes(blob)
    assert np.array_equal(g.pixels, f.pixels) and g.pattern == f.pattern
    assert g.black_level == f.black_level and g.exposure_s == pytest.approx(0.1)
    assert g.camera == f.camera and g.site == f.site and g.timestamp == f.timestamp
    bad = bytearray(blob)
    bad[100] ^= 1
    with pytest.raises(ValueError, match="CRC"):
        frame_from_bytes(bytes(bad))
    with pytest.raises(ValueError, match="bytes"):
        frame_from_bytes(blob[:-10])


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG", "MONO"])
def test_dng_round_trip_bit_exact(tmp_path, pattern):
    import rawpy

    f = _frame(pattern)
    path = write_dng(f, tmp_path / "f.dng")
    with rawpy.imread(str(path)) as raw:
        assert np.array_equal(raw.raw_image_visible, f.pixels)
        assert raw.white_level == 4095
    g = read_frame(path)
    assert np.array_equal(g.pixels, f.pixels)
    assert g.pattern == pattern
    assert g.black_level == f.black_level
    assert g.white_level == 4095 and g.exposure_s == pytest.approx(0.1)
    assert g.camera == f.camera and g.timestamp == f.timestamp


@pytest.mark.parametrize("pattern", ["GRBG", "MONO"])
def test_fits_and_npy_round_trip(tmp_path, pattern):
    f = _frame(pattern)
    for name in ("f.fits", "f.npy"):
        g = read_frame(write_frame(f, tmp_path / name))
        assert np.array_equal(g.pixels, f.pixels) and g.pattern == pattern, name
        assert g.black_level == f.black_level and g.white_level == 4095
        assert g.exposure_s == pytest.approx(0.1) and g.site == f.site
        assert g.camera["f"] == 1000.0


def test_fits_bayer_offset(tmp_path):
    from astropy.io import fits

    hdu = fits.PrimaryHDU(np.zeros((4, 4), np.uint16))
    hdu.header["BAYERPAT"] = "RGGB"
    hdu.header["XBAYROFF"] = 1
    hdu.writeto(tmp_path / "o.fits")
    assert read_frame(tmp_path / "o.fits").pattern == "GRBG"


def test_tiff_mono(tmp_path):
    import tifffile

    data = np.arange(12 * 10, dtype=np.uint16).reshape(12, 10)
    tifffile.imwrite(tmp_path / "m.tiff", data)
    f = read_frame(tmp_path / "m.tiff")
    assert f.is_mono and np.array_equal(f.pixels, data) and f.white_level == 65535


def test_shared_real_mono_frames(shared_data):
    paths = sorted((shared_data / "frames" / "tetra3-mono").glob("*.tiff"))
    assert paths
    for p in paths:
        f = read_frame(p)
        assert (f.width, f.height) == (1024, 768) and f.is_mono
        assert f.pixels.dtype == np.uint16 and f.pixels.max() > f.pixels.min()


def test_bad_files(tmp_path):
    (tmp_path / "empty.dng").write_bytes(b"")
    (tmp_path / "text.fits").write_text("hello, I am not an image\n")
    (tmp_path / "junk.cr2").write_bytes(b"\x00" * 4000)
    good = write_dng(_frame("RGGB", (64, 64)), tmp_path / "g.dng").read_bytes()
    (tmp_path / "trunc.dng").write_bytes(good[: len(good) // 3])
    np.save(tmp_path / "odd.npy", np.zeros((5, 6), np.uint16))
    (tmp_path / "odd.json").write_text('{"pattern": "RGGB"}')
    np.save(tmp_path / "pat.npy", np.zeros((4, 4), np.uint16))
    (tmp_path / "pat.json").write_text('{"pattern": "XYZW"}')
    for name, msg in [
        ("missing.dng", "no such file"), ("empty.dng", "empty"), ("text.fits", "not a recognised"),
        ("junk.cr2", "not a readable raw"), ("trunc.dng", "raw"), ("odd.npy", "even dimensions"),
        ("pat.npy", "unknown CFA pattern"),
    ]:
        with pytest.raises(FrameReadError, match=msg):
            read_frame(tmp_path / name)
