"""Frame container, serialisation, readers and writers (DNG round trip through rawpy)."""

import numpy as np
import pytest

from firmware_model.pipeline.frame_readers import FrameReadError, read_frame
from firmware_model.pipeline.raw_frame import BLUE, GREEN, RED, Frame, frame_from_bytes, frame_to_bytes, pattern_codes
from ground.sim.frame_writer import write_dng, write_frame
from protocol import frame_blob
from protocol.crc import CRC32_RESIDUE, crc32


def _frame(pattern="RGGB", shape=(48, 64), seed=0):
    rng = np.random.default_rng(seed)
    return Frame(
        pixels=rng.integers(0, 4096, shape, dtype=np.uint16),
        pattern=pattern,
        black_level=(64, 65, 66, 67) if pattern != "MONO" else 64,
        white_level=4095,
        exposure_s=0.1,
        timestamp="2026-11-22T01:00:00+00:00",
        site={"lat_deg": 52.1, "lon_deg": 4.4, "height_m": 3.0},
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


def test_two_frames_of_one_camera_have_different_blob_crcs_and_version_1_is_still_read():
    """A version-1 blob ended with its own CRC-32, so every blob had the whole-file CRC-32
    0x2144DF1C and an upload resumed another frame's bytes; version 2 keeps it in the header."""
    a, b = _frame("RGGB"), _frame("RGGB")
    b.pixels[0, 0] += 1
    blob_a, blob_b = frame_to_bytes(a), frame_to_bytes(b)
    assert crc32(blob_a) != crc32(blob_b) and CRC32_RESIDUE not in (crc32(blob_a), crc32(blob_b))
    header = bytearray(blob_a)
    header[30] ^= 1  # the white level, in the header: covered by the CRC-32 too
    with pytest.raises(ValueError, match="CRC"):
        frame_from_bytes(bytes(header))
    v1_head = np.frombuffer(blob_a, frame_blob.V1_HEADER_DTYPE, 1).copy()
    v1_head["version"] = 1
    body = v1_head.tobytes() + blob_a[frame_blob.HEADER_SIZE :]
    v1 = body + crc32(body).to_bytes(4, "little")
    assert crc32(v1) == CRC32_RESIDUE  # what made version 1 unfit as a transfer's identity
    assert np.array_equal(frame_from_bytes(v1).pixels, a.pixels)


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
        ("missing.dng", "no such file"),
        ("empty.dng", "empty"),
        ("text.fits", "not a recognised"),
        ("junk.cr2", "not a readable raw"),
        ("trunc.dng", "raw"),
        ("odd.npy", "even dimensions"),
        ("pat.npy", "unknown CFA pattern"),
    ]:
        with pytest.raises(FrameReadError, match=msg):
            read_frame(tmp_path / name)


def test_a_header_claiming_a_huge_image_is_refused_before_allocating(tmp_path):
    """A damaged TIFF whose width reads 2**20 (a 464 GiB request before) and a FITS header whose
    NAXIS promise more bytes than the file holds: refused from the header alone."""
    import struct

    import tifffile

    tifffile.imwrite(tmp_path / "big.tiff", np.zeros((48, 64), np.uint16))
    data = bytearray((tmp_path / "big.tiff").read_bytes())
    ifd = struct.unpack_from("<I", data, 4)[0]
    for k in range(struct.unpack_from("<H", data, ifd)[0]):
        entry = ifd + 2 + 12 * k
        if struct.unpack_from("<H", data, entry)[0] in (256, 257):  # ImageWidth, ImageLength
            struct.pack_into("<I", data, entry + 8, 1 << 20)
    (tmp_path / "big.tiff").write_bytes(bytes(data))
    with pytest.raises(FrameReadError, match="header claims"):
        read_frame(tmp_path / "big.tiff")
    good = write_frame(_frame(), tmp_path / "g.fits").read_bytes()
    (tmp_path / "cut.fits").write_bytes(good[: len(good) // 2])
    with pytest.raises(FrameReadError):
        read_frame(tmp_path / "cut.fits")


def test_image_bombs_are_refused_from_their_headers_in_every_reader(tmp_path):
    """Issue 29: a PNG and a 335-byte JPEG claiming 13 000 x 13 000 px were decoded (790 MB, up to
    88 s of solve); a .npy header claiming 16 384**2 float64 was read whole. Each is refused from
    its header, at once, with one line."""
    import io
    import struct
    import zlib

    from PIL import Image

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", 13000, 13000, 8, 0, 0, 0, 0)  # 8-bit grey
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 13001 * 64))
    (tmp_path / "bomb.png").write_bytes(png + chunk(b"IEND", b""))
    buf = io.BytesIO()
    Image.new("L", (8, 8)).save(buf, "JPEG")
    jpeg = bytearray(buf.getvalue())
    sof = jpeg.index(b"\xff\xc0")  # baseline frame header: length, precision, height, width
    struct.pack_into(">HH", jpeg, sof + 5, 13000, 13000)
    (tmp_path / "bomb.jpg").write_bytes(bytes(jpeg))
    header = np.lib.format.header_data_from_array_1_0(np.zeros((2, 2)))
    header["shape"] = (16384, 16384)
    with open(tmp_path / "bomb.npy", "wb") as f:
        np.lib.format.write_array_header_1_0(f, header)
        f.write(b"\0" * 4096)
    for name in ("bomb.png", "bomb.jpg", "bomb.npy"):
        with pytest.raises(FrameReadError) as err:
            read_frame(tmp_path / name)
        message = str(err.value)
        assert message.count(str(tmp_path / name)) == 1 and "\n" not in message
        assert "header claims a 13000 x 13000 image" in message or "header claims a 16384 x 16384" in message


def test_a_tiff_sample_format_without_a_numpy_type_is_named(tmp_path):
    """40-bit samples: tifffile reads no dtype for them; the reader says so (it once failed on
    ``None.itemsize``)."""
    import tifffile

    tifffile.imwrite(tmp_path / "odd.tiff", np.zeros((4, 4), np.uint16))
    with tifffile.TiffFile(tmp_path / "odd.tiff", mode="r+") as tif:
        tif.pages.first.tags["BitsPerSample"].overwrite(40)
    with pytest.raises(FrameReadError, match="TIFF sample format not supported"):
        read_frame(tmp_path / "odd.tiff")


@pytest.mark.parametrize("suffix", [".dng", ".fits", ".npy"])
def test_damaged_frame_files_raise_only_frame_read_error(tmp_path, suffix):
    """Seeded damage (cuts, header bytes, scattered bytes, large numbers in the header) of each
    format: every read ends in FrameReadError or a frame, never another exception; a cut file is
    refused unless only padding was cut (then its pixels are the original's), and a damaged file
    that reads is a frame of the original size (pixel bytes and tags such as the CFA pattern
    carry no check in these formats; a garbage shape never comes out)."""
    import random
    import struct

    original = _frame()
    good = write_frame(original, tmp_path / f"g{suffix}").read_bytes()
    if suffix == ".npy":  # the sidecar of the frame fields goes with every damaged copy
        (tmp_path / "f.json").write_bytes((tmp_path / "g.json").read_bytes())
    rng = random.Random(suffix)
    refused = 0
    for trial in range(120):
        d = bytearray(good)
        if trial % 4 == 0:
            d = d[: rng.randrange(1, len(d))]
        elif trial % 4 == 1:
            for _ in range(rng.randrange(1, 8)):
                d[rng.randrange(min(len(d), 512))] = rng.randrange(256)
        elif trial % 4 == 2:
            for _ in range(rng.randrange(1, 20)):
                d[rng.randrange(len(d))] = rng.randrange(256)
        else:
            for _ in range(3):
                i = rng.randrange(min(len(d) - 4, 400))
                d[i : i + 4] = struct.pack("<I", rng.choice([0xFFFFFFFF, 100_000, 1 << 20]))
        (tmp_path / f"f{suffix}").write_bytes(bytes(d))
        try:
            frame = read_frame(tmp_path / f"f{suffix}")
        except FrameReadError:
            refused += 1
            continue
        assert frame.pixels.shape == original.pixels.shape, trial
        if trial % 4 == 0:  # a cut that left every pixel (FITS pads to 2880-byte blocks)
            assert np.array_equal(frame.pixels, original.pixels), f"trial {trial}: cut to {len(d)} of {len(good)} bytes"
    assert refused >= 20


# ------------------------------------------------------------------ PNG / JPEG (Pillow)
def _rgb_planes(h, w):
    """An (h, w, 3) uint8 image whose R, G, B planes differ everywhere (R = 10+r, G = 100+c, B = 200+r+c)."""
    r, c = np.mgrid[0:h, 0:w]
    return np.stack([10 + r, 100 + c, 200 + (r + c) % 50], axis=-1).astype(np.uint8)


def _check_rggb(f, rgb, atol=0):
    h, w = f.height, f.width
    assert f.pattern == "RGGB" and f.metadata["demosaiced"] is True
    assert f.black_level == (0.0,) * 4 and f.white_level == 255
    px = f.pixels.astype(int)
    rgb = rgb.astype(int)
    np.testing.assert_allclose(px[0::2, 0::2], rgb[0:h:2, 0:w:2, 0], atol=atol)
    np.testing.assert_allclose(px[0::2, 1::2], rgb[0:h:2, 1:w:2, 1], atol=atol)
    np.testing.assert_allclose(px[1::2, 0::2], rgb[1:h:2, 0:w:2, 1], atol=atol)
    np.testing.assert_allclose(px[1::2, 1::2], rgb[1:h:2, 1:w:2, 2], atol=atol)


def test_png_rgb_remosaiced_to_rggb(tmp_path):
    from PIL import Image

    rgb = _rgb_planes(6, 8)
    Image.fromarray(rgb, "RGB").save(tmp_path / "c.png")
    f = read_frame(tmp_path / "c.png")
    assert (f.width, f.height) == (8, 6) and f.pixels.dtype == np.uint8
    _check_rggb(f, rgb)
    assert f.metadata["source_mode"] == "RGB" and f.metadata["source_size"] == [8, 6]
    assert f.metadata["source_format"] == "PNG" and "cropped_px" not in f.metadata
    assert f.timestamp is None and f.exposure_s is None
    assert f.channel_map()[0, 0] == RED and f.channel_map()[1, 1] == BLUE


def test_jpeg_rgb_remosaiced_to_rggb(tmp_path):
    from PIL import Image

    # flat 8x8 blocks of one colour each survive JPEG (4:4:4, q=100) within a few DN
    rgb = np.zeros((16, 24, 3), np.uint8)
    rgb[:, :8] = (200, 40, 90)
    rgb[:, 8:16] = (30, 180, 60)
    rgb[:, 16:] = (70, 90, 220)
    Image.fromarray(rgb, "RGB").save(tmp_path / "c.jpg", quality=100, subsampling=0)
    f = read_frame(tmp_path / "c.jpg")
    assert (f.width, f.height) == (24, 16) and f.metadata["source_format"] == "JPEG"
    _check_rggb(f, rgb, atol=4)


def test_png_rgba_drops_alpha_and_odd_size_is_cropped(tmp_path):
    from PIL import Image

    rgb = _rgb_planes(7, 9)
    rgba = np.concatenate([rgb, np.full((7, 9, 1), 17, np.uint8)], axis=-1)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "a.png")
    f = read_frame(tmp_path / "a.png")
    assert (f.width, f.height) == (8, 6)
    assert f.metadata["cropped_px"] == [1, 1] and f.metadata["source_size"] == [9, 7]
    assert f.metadata["source_mode"] == "RGBA"
    _check_rggb(f, rgb)  # alpha (17) never appears: every value is a colour plane's
    Image.fromarray(rgb[:, :8], "RGB").save(tmp_path / "o.png")  # odd height only
    g = read_frame(tmp_path / "o.png")
    assert (g.width, g.height) == (8, 6) and g.metadata["cropped_px"] == [0, 1]


def test_greyscale_png_is_mono(tmp_path):
    from PIL import Image

    grey8 = (np.arange(5 * 7).reshape(5, 7) * 7).astype(np.uint8)
    Image.fromarray(grey8, "L").save(tmp_path / "g8.png")
    f = read_frame(tmp_path / "g8.png")
    assert f.is_mono and np.array_equal(f.pixels, grey8) and f.white_level == 255
    assert (f.width, f.height) == (7, 5) and "cropped_px" not in f.metadata  # MONO needs no even size
    assert f.metadata["demosaiced"] is False and f.metadata["source_mode"] == "L"
    grey16 = (np.arange(6 * 4).reshape(6, 4) * 2700).astype(np.uint16)
    Image.fromarray(grey16).save(tmp_path / "g16.png")
    g = read_frame(tmp_path / "g16.png")
    assert g.is_mono and g.pixels.dtype == np.uint16 and np.array_equal(g.pixels, grey16)
    assert g.white_level == 65535 and g.metadata["source_mode"].startswith("I;16")


def test_jpeg_exif_timestamp_and_exposure(tmp_path):
    from PIL import Image

    rgb = _rgb_planes(8, 8)
    exif = Image.Exif()
    exif[271], exif[272] = "Canon", "Canon EOS Test"
    sub = exif.get_ifd(0x8769)
    sub[36867] = "2021:03:26 00:46:16"  # DateTimeOriginal
    sub[37521] = "25"  # SubsecTimeOriginal
    sub[33434] = 0.5  # ExposureTime
    Image.fromarray(rgb, "RGB").save(tmp_path / "e.jpg", exif=exif, quality=95)
    f = read_frame(tmp_path / "e.jpg")
    assert f.timestamp == "2021-03-26T00:46:16.250000Z" and f.exposure_s == pytest.approx(0.5)
    assert f.metadata["timestamp_utc_assumed"] is True
    assert f.metadata["timestamp_source"] == "EXIF DateTimeOriginal"
    assert f.metadata["exif_camera"] == "Canon EOS Test"
    # an offset tag turns the local clock time into UTC
    sub[36881] = "+02:00"  # OffsetTimeOriginal
    Image.fromarray(rgb, "RGB").save(tmp_path / "o.png", exif=exif)
    g = read_frame(tmp_path / "o.png")
    assert g.timestamp == "2021-03-25T22:46:16.250000Z"
    assert g.metadata["timestamp_utc_assumed"] is False and g.metadata["exif_time_offset"] == "+02:00"


def test_bad_png_and_jpeg_files(tmp_path):
    from PIL import Image

    (tmp_path / "garbage.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4)
    (tmp_path / "garbage.jpg").write_bytes(b"\xff\xd8\xff" + b"\x00" * 500)
    (tmp_path / "text.png").write_text("hello, I am not a PNG\n")
    Image.fromarray(_rgb_planes(64, 64), "RGB").save(tmp_path / "g.png")
    good = (tmp_path / "g.png").read_bytes()
    (tmp_path / "trunc.png").write_bytes(good[: len(good) // 2])
    Image.fromarray(_rgb_planes(64, 64), "RGB").save(tmp_path / "g.jpg")
    good = (tmp_path / "g.jpg").read_bytes()
    (tmp_path / "trunc.jpg").write_bytes(good[: len(good) // 2])
    Image.fromarray(_rgb_planes(1, 5), "RGB").save(tmp_path / "thin.png")
    for name, msg in [
        ("garbage.png", "not a readable PNG/JPEG"),
        ("garbage.jpg", "not a readable PNG/JPEG"),
        ("text.png", "not a recognised"),
        ("trunc.png", "not a readable PNG/JPEG"),
        ("trunc.jpg", "not a readable PNG/JPEG"),
        ("thin.png", "too small"),
    ]:
        with pytest.raises(FrameReadError, match=msg) as info:
            read_frame(tmp_path / name)
        text = str(info.value)
        assert "\n" not in text and text.startswith(str(tmp_path / name)), text
        exc = info.value  # no chained traceback behind the one-line reason
        assert exc.__cause__ is None and (exc.__context__ is None or exc.__suppress_context__), name


def test_frame_files_takes_png_and_jpeg(tmp_path):
    from firmware_model.pipeline.frame_readers import frame_files

    for name in ("a.png", "b.JPG", "c.jpeg", "d.json", "e.txt"):
        (tmp_path / name).write_bytes(b"x")
    assert [p.name for p in frame_files(tmp_path)] == ["a.png", "b.JPG", "c.jpeg"]


def test_shared_real_colour_frames(shared_data):
    import json

    from conftest import require_shared

    from firmware_model.pipeline.frame_readers import frame_files

    folder = require_shared(shared_data / "frames" / "colour-real")  # a skip, or under CI=true a failure
    ref = json.loads((folder / "reference_pointing.json").read_text())
    paths = frame_files(folder)
    assert sorted(p.name for p in paths) == sorted(ref)
    for p in paths:
        f = read_frame(p)
        w, h = ref[p.name]["size_px"]
        assert f.metadata["source_size"] == [w, h] and f.metadata["source_mode"] == ref[p.name]["mode"]
        assert (f.width, f.height) == (w - w % 2, h - h % 2) and f.pattern == "RGGB"
        assert f.white_level == 255 and f.pixels.max() > f.pixels.min()
    exif = read_frame(folder / "img_7660.png")
    assert exif.exposure_s == pytest.approx(10.0) and exif.timestamp == "2021-03-26T00:46:16.870000Z"
    from astropy.time import Time

    assert Time(exif.timestamp, scale="utc").isot == "2021-03-26T00:46:16.870"  # the planets module parses it
