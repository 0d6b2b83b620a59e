"""The on-board catalog image: round trip, numpy views, and refusal of every corruption."""

import struct

import numpy as np
import pytest

from firmware_model.catalog.image_io import catalog_from_image, catalog_to_image
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.device.catalog_slot import catalog_slot_handler
from firmware_model.reference_frames import radec_to_vec
from protocol.catalog_image import (
    HEADER_SIZE,
    STAR_DTYPE,
    CatalogImageError,
    Reason,
    crc32,
    pack_image,
    parse_image,
)
from protocol.commands import SlotRejected


@pytest.fixture(scope="module")
def small_catalog(synthetic_catalog):
    return synthetic_catalog(40, dphi_star=2e-4)


@pytest.fixture(scope="module")
def image(small_catalog):
    return catalog_to_image(small_catalog, created_unix=1_700_000_000)


def _arrays(data):
    img = parse_image(data)
    return img.params, img.stars.copy(), img.pairs.copy(), img.hash_index.copy(), img.kvector.copy()


def _resign_header(raw: bytearray) -> bytes:
    raw[HEADER_SIZE - 4 : HEADER_SIZE] = struct.pack("<I", crc32(raw[: HEADER_SIZE - 4]))
    return bytes(raw)


def _code(data) -> Reason:
    with pytest.raises(CatalogImageError) as info:
        parse_image(data)
    return info.value.code


def test_round_trip_is_exact_and_uses_views(small_catalog, image):
    cat = catalog_from_image(image)
    assert cat.n_stars == small_catalog.n_stars and cat.n_pairs == small_catalog.n_pairs
    np.testing.assert_array_equal(cat.star_id, small_catalog.star_id)
    np.testing.assert_array_equal(cat.vec, small_catalog.vec)
    np.testing.assert_array_equal(cat.pair_phi, small_catalog.pair_phi)
    np.testing.assert_array_equal(cat.pair_i, small_catalog.pair_i)
    np.testing.assert_array_equal(cat.hash_index, small_catalog.hash_index)
    np.testing.assert_array_equal(cat.kvector, small_catalog.kvector)
    np.testing.assert_array_equal(cat.rg, small_catalog.rg.astype(np.float32))
    assert (cat.kv_m, cat.kv_q, cat.dphi_star) == (small_catalog.kv_m, small_catalog.kv_q, small_catalog.dphi_star)
    assert cat.meta["epoch"] == 2025.0 and cat.meta["source"] == "hipparcos"
    assert not cat.vec.flags.owndata and not cat.pair_phi.flags.owndata  # views into the buffer
    for phi in np.linspace(0.002, 0.29, 25):
        assert cat.hash_range(phi, 3e-3) == small_catalog.hash_range(phi, 3e-3)
        assert cat.kvector_range(phi, 3e-3) == small_catalog.kvector_range(phi, 3e-3)


def test_sections_are_aligned_and_counted(image):
    img = parse_image(image)
    assert img.total_size == len(image)
    assert all(e.offset % 8 == 0 for e in img.sections.values())
    assert img.sections["stars"].size == img.n_stars * STAR_DTYPE.itemsize


@pytest.mark.parametrize("cut", [0, 10, HEADER_SIZE - 1, HEADER_SIZE, HEADER_SIZE + 100, -8, -1])
def test_truncation_refused(image, cut):
    assert _code(image[:cut]) == Reason.TRUNCATED


def test_trailing_bytes_refused(image):
    assert _code(image + b"\0") == Reason.SIZE_MISMATCH


def test_every_single_bit_flip_refused(image):
    rng = np.random.default_rng(1)
    for pos in range(len(image)):
        bad = bytearray(image)
        bad[pos] ^= 1 << int(rng.integers(8))
        with pytest.raises(CatalogImageError):
            parse_image(bytes(bad))


def test_bad_magic_and_wrong_version(image):
    assert _code(b"XXXXXXXX" + image[8:]) == Reason.BAD_MAGIC
    raw = bytearray(image)
    raw[8:10] = struct.pack("<H", 2)
    assert _code(_resign_header(raw)) == Reason.BAD_VERSION


def test_header_crc_and_section_crc(image):
    raw = bytearray(image)
    raw[40] ^= 0x10  # epoch byte, header CRC not updated
    assert _code(bytes(raw)) == Reason.HEADER_CRC
    raw = bytearray(image)
    raw[HEADER_SIZE + 3] ^= 0x01  # star table
    assert _code(bytes(raw)) == Reason.SECTION_CRC


def test_bad_counts_and_section_table(image):
    raw = bytearray(image)
    n_stars = struct.unpack_from("<I", raw, 20)[0]
    struct.pack_into("<I", raw, 20, n_stars + 1)
    assert _code(_resign_header(raw)) == Reason.SECTION_SIZE
    raw = bytearray(image)
    struct.pack_into("<I", raw, 24, 10**6)  # n_pairs > n(n-1)/2
    assert _code(_resign_header(raw)) == Reason.COUNTS
    raw = bytearray(image)
    off = struct.unpack_from("<I", raw, 132)[0]  # stars section offset
    struct.pack_into("<I", raw, 132, off + 4)
    assert _code(_resign_header(raw)) == Reason.SECTION_BOUNDS


def _repack(image, mutate):
    params, stars, pairs, hash_index, kvector = _arrays(image)
    mutate(params, stars, pairs, hash_index, kvector)
    return pack_image(params, stars, pairs, hash_index, kvector)


def _nudge_angle(pairs):
    """Move one pair angle by 1e-7 rad without breaking the order."""
    k = int(np.flatnonzero(np.diff(pairs["phi"]) > 1e-6)[1])
    pairs["phi"][k] += 1e-7


def _set(arr, field, k, value):
    arr[field][k] = value


@pytest.mark.parametrize(
    "mutate, reason",
    [
        (lambda p, s, pr, h, k: _set(pr, "j", 0, 10_000), Reason.PAIR_INDEX),
        (lambda p, s, pr, h, k: _set(pr, "i", 0, pr["j"][0]), Reason.PAIR_INDEX),
        (lambda p, s, pr, h, k: pr.__setitem__(slice(0, 2), pr[1::-1].copy()), Reason.PAIR_ORDER),
        (lambda p, s, pr, h, k: _set(pr, "phi", len(pr) - 1, 0.31), Reason.PAIR_ORDER),
        (lambda p, s, pr, h, k: _nudge_angle(pr), Reason.PAIR_ANGLE),
        (lambda p, s, pr, h, k: s["vec"].__setitem__(3, s["vec"][3] * 1.001), Reason.STAR_VECTOR),
        (lambda p, s, pr, h, k: s["vec"].__setitem__(3, np.nan), Reason.STAR_VECTOR),
        (lambda p, s, pr, h, k: _set(s, "mag", 2, np.inf), Reason.STAR_VALUES),
        (lambda p, s, pr, h, k: _set(s, "rg", 2, -1.0), Reason.STAR_VALUES),
        (lambda p, s, pr, h, k: _set(s, "flags", 2, 9), Reason.STAR_VALUES),
        (lambda p, s, pr, h, k: h.__setitem__(5, h[5] + 1), Reason.HASH_INDEX),
        (lambda p, s, pr, h, k: k.__setitem__(7, k[7] + 1), Reason.KVECTOR),
        (lambda p, s, pr, h, k: setattr(p, "kv_q", p.kv_q + 1.0), Reason.KVECTOR),
        (lambda p, s, pr, h, k: setattr(p, "phi_min", p.phi_max), Reason.BAD_PARAMETERS),
        (lambda p, s, pr, h, k: setattr(p, "epoch", float("nan")), Reason.BAD_PARAMETERS),
    ],
)
def test_inconsistent_content_with_valid_crcs_refused(image, mutate, reason):
    assert _code(_repack(image, mutate)) == reason


def test_device_slot_handler_nacks_with_reason_code(image):
    handler = catalog_slot_handler()
    handler.validate(image)
    cat = handler.activate(image)
    assert cat.n_pairs > 0
    assert b'"n_stars": 40' in handler.info(image, cat)
    with pytest.raises(SlotRejected) as info:
        handler.validate(image[:-1])
    assert info.value.code == Reason.TRUNCATED


def test_verification_only_stars_round_trip_and_pairs_stay_among_pattern_stars():
    rng = np.random.default_rng(3)
    n, n_pattern = 40, 25
    cat = OnboardCatalog.build(
        np.arange(n),
        radec_to_vec(rng.uniform(0, 0.6, n), rng.uniform(-0.3, 0.3, n)),
        np.sort(rng.uniform(1, 6, n)),
        phi_min=1e-3,
        phi_max=0.3,
        n_h=32,
        meta={"epoch": 2025.0},
        n_pattern_stars=n_pattern,
    )
    assert cat.has_deep_stars and cat.n_pairs > 0 and max(cat.pair_j) < n_pattern
    assert cat.pattern_mag_limit == pytest.approx(float(cat.mag[n_pattern - 1]))
    back = catalog_from_image(catalog_to_image(cat, created_unix=0))
    assert back.n_pattern_stars == n_pattern and back.n_stars == n
    assert len(back.stars_within(cat.vec[n - 1], 1e-6)) == 0  # a verification-only star: not a pattern star
    assert list(back.stars_within(cat.vec[n - 1], 1e-6, deep=True)) == [n - 1]
    image = catalog_to_image(cat, created_unix=0)
    assert _code(_repack(image, lambda p, s, pr, h, k: _set(pr, "j", len(pr) - 1, n_pattern))) in (
        Reason.PAIR_INDEX,
        Reason.PAIR_ANGLE,
    )
    assert _code(_repack(image, lambda p, s, pr, h, k: setattr(p, "n_pattern_stars", n + 1))) == Reason.COUNTS


def test_an_image_without_verification_only_stars_says_zero(image, small_catalog):
    assert parse_image(image).params.n_pattern_stars == 0
    assert catalog_from_image(image).n_pattern_stars == small_catalog.n_stars
