"""Learned star colours: the Bayesian update, gathering from solve records, the
re-signed catalog image and the ``catalog learn-colours`` command."""

import json

import numpy as np
import pytest

from firmware_model.catalog.image_io import catalog_from_image, catalog_to_image
from ground.calibration.learned_colours import Observations, learn_colours, observations_from_records
from protocol.catalog_image import CatalogImageError, parse_image, with_star_colours

IDS = np.array([11, 22, 33, 44])
RG = np.array([0.6, 0.8, 1.0, 1.2])
BG = np.array([1.2, 1.0, 0.8, 0.6])


def _obs(star, rg, bg, sigma=0.03):
    n = len(rg)
    return Observations(
        np.full(n, star), np.asarray(rg, float), np.asarray(bg, float), np.full(n, sigma), np.full(n, sigma)
    )


def _concat(*parts):
    return Observations(
        *(np.concatenate([getattr(p, f) for p in parts]) for f in ("star_id", "rg", "bg", "sigma_rg", "sigma_bg"))
    )


def test_known_bias_recovered_within_posterior_sigma():
    rng = np.random.default_rng(1)
    true = (RG[1] * 1.12, BG[1] * 0.9)  # the catalog model is 12 % / -10 % off
    obs = _obs(22, true[0] + 0.03 * rng.standard_normal(40), true[1] + 0.03 * rng.standard_normal(40))
    out = learn_colours(IDS, RG, BG, obs, sigma_scale=1.0)
    (s,) = out.stars
    assert s.updated and s.n_used == 40 and s.n_rejected == 0
    for k in range(2):
        assert abs(s.learned[k] - true[k]) < 3 * s.sigma[k]
        assert s.sigma[k] < 0.03 / np.sqrt(40) * 1.01  # the data dominate a 5 % prior
        assert abs(s.shift_sigma[k]) > 10
    assert out.rg[1] == np.float32(s.learned[0]) and out.bg[1] == np.float32(s.learned[1])
    assert np.array_equal(out.rg[[0, 2, 3]], RG[[0, 2, 3]].astype(np.float32))  # unobserved stars unchanged
    assert out.reason is None and out.summary()["stars_updated"] == 1


def test_prior_pulls_towards_the_catalog_with_few_noisy_observations():
    obs = _obs(33, [1.3, 1.3, 1.3], [0.8, 0.8, 0.8], sigma=0.5)
    (s,) = learn_colours(IDS, RG, BG, obs, sigma_scale=1.0).stars
    w_prior, w_data = 1 / (0.05 * 1.0) ** 2, 3 / 0.5**2
    assert s.learned[0] == pytest.approx((w_prior * 1.0 + w_data * 1.3) / (w_prior + w_data), rel=1e-6)
    assert s.sigma[0] == pytest.approx((w_prior + w_data) ** -0.5)


def test_outliers_rejected():
    rng = np.random.default_rng(2)
    good = _obs(11, 0.65 + 0.02 * rng.standard_normal(20), 1.25 + 0.02 * rng.standard_normal(20), 0.02)
    wrong = _obs(11, [1.2, 0.2, 1.0], [0.6, 2.0, 0.7], 0.02)  # mismatches: another star's colours
    (s,) = learn_colours(IDS, RG, BG, _concat(good, wrong), sigma_scale=1.0).stars
    assert s.n_rejected == 3 and s.n_used == 20
    assert abs(s.learned[0] - 0.65) < 3 * s.sigma[0] and abs(s.learned[1] - 1.25) < 3 * s.sigma[1]


def test_weights_respected():
    obs = _concat(_obs(44, [1.3] * 3, [0.6] * 3, 0.01), _obs(44, [1.1] * 3, [0.6] * 3, 0.1))
    (s,) = learn_colours(IDS, RG, BG, obs, prior_rel=1e6, sigma_scale=1.0, clip=100).stars
    assert s.learned[0] == pytest.approx((1.3 * 100**2 + 1.1 * 10**2) / (100**2 + 10**2), rel=1e-5)


def test_too_few_observations_change_nothing_and_say_why():
    obs = _concat(_obs(11, [0.7, 0.7], [1.1, 1.1]), _obs(22, [0.9], [1.0]))
    out = learn_colours(IDS, RG, BG, obs)
    assert not out.updated
    assert np.array_equal(out.rg, RG.astype(np.float32)) and np.array_equal(out.bg, BG.astype(np.float32))
    assert out.reason == (
        "no star has 3 usable observations (3 over 2 stars, at most 2 per star): catalog colours unchanged"
    )
    assert "\n" not in out.reason and out.summary()["unchanged"] == out.reason
    assert learn_colours(IDS, RG, BG, Observations.from_rows([])).reason.startswith("no matched observations")


def test_invalid_and_unknown_observations_counted_not_used():
    obs = Observations.from_rows([(99, 1, 1, 0.1, 0.1), (11, np.nan, 1, 0.1, 0.1), (11, 1, 1, 0, 0.1)])
    out = learn_colours(IDS, RG, BG, obs)
    assert (out.n_unknown_id, out.n_invalid, out.stars) == (1, 2, [])
    assert out.reason.startswith("none of 3 observations usable")


def test_run_sigma_scale_inflates_underestimated_sigmas():
    rng = np.random.default_rng(3)
    obs = _concat(
        *(
            _obs(s, r + 0.06 * rng.standard_normal(30), b + 0.06 * rng.standard_normal(30), 0.02)
            for s, r, b in zip(IDS, RG, BG)
        )
    )
    out = learn_colours(IDS, RG, BG, obs)
    assert 2.4 < out.sigma_scale < 3.6  # true noise 0.06 against a claimed 0.02
    assert sum(s.n_rejected for s in out.stars) <= 3


def test_bad_settings_refused():
    with pytest.raises(ValueError, match="min_obs"):
        learn_colours(IDS, RG, BG, Observations.from_rows([]), min_obs=0)
    with pytest.raises(ValueError, match="differ in length"):
        learn_colours(IDS, RG[:2], BG, Observations.from_rows([]))


def _record(status, stars):
    return {"status": status, "stars": stars}


def test_observations_from_records_take_confident_matched_unsaturated_stars():
    star = {
        "catalog_id": 11,
        "rg": 0.6,
        "bg": 1.2,
        "rg_sigma": 0.02,
        "bg_sigma": 0.04,
        "saturated": False,
        "body": None,
    }
    recs = [
        _record("OK", [star, {**star, "catalog_id": None}, {**star, "saturated": True}, {**star, "body": "mars"}]),
        _record("LOW_CONFIDENCE", [star]),
        _record("OK", [{k: v for k, v in star.items() if "sigma" not in k}]),  # an older log
    ]
    obs = observations_from_records(recs)
    assert len(obs) == 2 and obs.usable().tolist() == [True, False]
    obs = observations_from_records(recs, default_sigma=(0.05, 0.05))
    assert obs.usable().all() and obs.sigma_rg.tolist() == [0.02, 0.05]
    beta = (2.0, 0.0, 0.0, 1.0, 0.1, 0.0)
    obs = observations_from_records(recs[:1], beta=beta)
    assert obs.rg[0] == pytest.approx(1.3) and obs.sigma_rg[0] == pytest.approx(0.04) and obs.bg[0] == 1.2


@pytest.fixture(scope="module")
def image(synthetic_catalog):
    return catalog_to_image(synthetic_catalog(30), created_unix=1_700_000_000)


def test_image_with_new_colours_is_re_signed_and_changes_only_colours(image):
    old = parse_image(image)
    rg, bg = old.stars["rg"].copy(), old.stars["bg"].copy()
    rg[3], bg[7] = 0.5, 1.5
    new = with_star_colours(image, rg, bg)
    img = parse_image(new)
    assert img.stars["rg"][3] == np.float32(0.5) and img.stars["bg"][7] == np.float32(1.5)
    diff = np.flatnonzero(np.frombuffer(image, np.uint8) != np.frombuffer(new, np.uint8))
    stars = old.sections["stars"]
    inside = (diff >= stars.offset) & (diff < stars.offset + stars.size)
    assert np.all(inside | (diff < 192))  # only star records and the header's CRCs change
    for f in ("star_id", "vec", "mag", "flags"):
        assert np.array_equal(img.stars[f], old.stars[f])
    assert catalog_from_image(new).n_pairs == old.n_pairs
    with pytest.raises(CatalogImageError, match="STAR_VALUES"):
        with_star_colours(image, -rg, bg)
    with pytest.raises(ValueError, match="need 30"):
        with_star_colours(image, rg[:5], bg)


def _write_log(path, image, n_per_star, scale=1.1, seed=5):
    """A results log whose matched stars show each catalog colour times ``scale`` (+ noise)."""
    rng = np.random.default_rng(seed)
    stars = parse_image(image).stars
    with open(path, "w") as fh:
        for _ in range(n_per_star):
            recs = [
                {
                    "catalog_id": int(s["star_id"]),
                    "rg": float(s["rg"]) * scale + 0.01 * rng.standard_normal(),
                    "bg": float(s["bg"]) * scale + 0.01 * rng.standard_normal(),
                    "rg_sigma": 0.01,
                    "bg_sigma": 0.01,
                    "saturated": False,
                    "body": None,
                }
                for s in stars[:5]
            ]
            fh.write(json.dumps({"status": "OK", "stars": recs}) + "\n")


def test_cli_learns_writes_the_image_report_and_plot(tmp_path, image, capsys):
    from ground.cli.main import main

    (tmp_path / "cat.st16cat").write_bytes(image)
    _write_log(tmp_path / "results.jsonl", image, 6)
    out, report, plot = tmp_path / "learned.st16cat", tmp_path / "report.json", tmp_path / "learned.png"
    argv = ["catalog", "learn-colours", str(tmp_path), "--catalog", str(tmp_path / "cat.st16cat"), "-o", str(out)]
    assert main([*argv, "--report", str(report), "--plot", str(plot)]) == 0
    text = capsys.readouterr().out
    assert "stars_updated: 5" in text and f"wrote {out}" in text
    new, old = parse_image(out.read_bytes()).stars, parse_image(image).stars
    assert np.allclose(new["rg"][:5], old["rg"][:5] * 1.1, rtol=0.02)
    assert np.array_equal(new["rg"][5:], old["rg"][5:])
    rep = json.loads(report.read_text())
    assert rep["stars_updated"] == 5 and len(rep["stars"]) == 5 and rep["stars"][0]["n_used"] == 6
    assert plot.stat().st_size > 0


def test_cli_with_too_few_observations_writes_nothing_and_says_why(tmp_path, image, capsys):
    from ground.cli.main import main

    (tmp_path / "cat.st16cat").write_bytes(image)
    _write_log(tmp_path / "results.jsonl", image, 2)
    out = tmp_path / "learned.st16cat"
    rc = main(
        [
            "catalog",
            "learn-colours",
            str(tmp_path / "results.jsonl"),
            "--catalog",
            str(tmp_path / "cat.st16cat"),
            "-o",
            str(out),
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and not out.exists()
    assert err == [
        "st16-ground catalog: learn-colours: no star has 3 usable observations (10 over 5 stars, at most 2 per star): "
        "catalog colours unchanged; no image written"
    ]


def test_cli_bad_inputs_are_one_line(tmp_path, image, capsys):
    from ground.cli.main import main

    (tmp_path / "cat.st16cat").write_bytes(image[:100])
    _write_log(tmp_path / "results.jsonl", image, 3)
    assert main(["catalog", "learn-colours", str(tmp_path / "none"), "--catalog", str(tmp_path / "cat.st16cat")]) == 2
    assert main(["catalog", "learn-colours", str(tmp_path), "--catalog", str(tmp_path / "cat.st16cat")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "no results log" in err[0] and "TRUNCATED" in err[1]


def test_cli_defaults_are_the_module_defaults():
    from ground.calibration import learned_colours as lc
    from ground.cli.main import build_parser

    args = build_parser().parse_args(["catalog", "learn-colours", "r", "--catalog", "c"])
    assert (args.prior_rel, args.clip, args.min_obs) == (lc.PRIOR_REL, lc.CLIP, lc.MIN_OBS)


# --------------------------------------------------------------------------- the verified partial upload


def _recoloured(image, scale=1.05, rows=slice(0, 4)):
    stars = parse_image(image).stars
    rg, bg = stars["rg"].copy(), stars["bg"].copy()
    rg[rows] *= scale
    bg[rows] /= scale
    return with_star_colours(image, rg, bg)


def test_patch_carries_only_the_changed_bytes_and_checks_both_crcs(image):
    from protocol.catalog_patch import PatchError, PatchReason, apply_patch, diff_ranges, make_patch

    new = _recoloured(image)
    patch = make_patch(image, new)
    assert apply_patch(image, patch) == new
    assert len(patch) < 200 and len(diff_ranges(image, new)) <= 4 + 3  # 4 star records + header CRC fields
    for base, bad, code in (
        (new, patch, PatchReason.BASE_MISMATCH),  # made for another image
        (image, patch[:-1], PatchReason.NOT_A_PATCH),
        (image, patch + b"\0", PatchReason.NOT_A_PATCH),
        (image, b"ST16CAT\0" + patch[8:], PatchReason.NOT_A_PATCH),
        (image, patch[:16] + bytes(4) + patch[20:], PatchReason.RESULT_CRC),  # result CRC field altered
    ):
        with pytest.raises(PatchError) as info:
            apply_patch(base, bad)
        assert info.value.code == code
    far = bytearray(patch)
    far[24:28] = (len(image) - 2).to_bytes(4, "little")  # first range's offset past the end
    with pytest.raises(PatchError, match="RANGE"):
        apply_patch(image, bytes(far))


@pytest.fixture
def device_port(tmp_path):
    """(state directory, pty path) of an in-process device with the catalog validator on slot 0."""
    import threading

    from firmware_model.device.catalog_slot import catalog_slot_handler
    from firmware_model.device.device import Device
    from firmware_model.device.link import PtyLink, serve
    from firmware_model.device.slots import SlotStore

    running = []

    def start():
        device = Device(store=SlotStore(tmp_path / "state"), slots={0: catalog_slot_handler()})
        link, stop = PtyLink(), threading.Event()
        thread = threading.Thread(target=serve, args=(device, link, stop), daemon=True)
        thread.start()
        running.append((link, stop, thread))
        return device, link.path

    def stop_all():
        while running:
            link, stop, thread = running.pop()
            stop.set()
            thread.join(2)
            link.close()

    yield start, stop_all
    stop_all()


@pytest.mark.parametrize("as_json", [False, True], ids=["text", "json"])
def test_learned_colours_patch_the_device_catalog_verified_and_persisted(tmp_path, image, device_port, capsys, as_json):
    from ground.cli.main import main
    from protocol.crc import crc32

    start, stop = device_port
    device, port = start()
    (tmp_path / "cat.st16cat").write_bytes(image)
    _write_log(tmp_path / "results.jsonl", image, 4)
    assert main(["--port", port, "catalog", "upload", str(tmp_path / "cat.st16cat")]) == 0
    capsys.readouterr()
    out = tmp_path / "learned.st16cat"
    argv = ["--port", port, "catalog", "learn-colours", str(tmp_path), "--catalog", str(tmp_path / "cat.st16cat")]
    assert main(["--json"] * as_json + [*argv, "-o", str(out), "--upload"]) == 0
    text = capsys.readouterr().out
    if as_json:  # one document: the report, what was written and the patch sent
        doc = json.loads(text)
        assert doc["written"]["image"] == str(out) and doc["patch"]["verified"] and doc["stars_updated"] == 5
    else:
        assert "verified" in text
    new = out.read_bytes()
    assert device._objects[0].rg[0] == parse_image(new).stars["rg"][0]
    stop()
    device, port = start()  # restart: the patched catalog was persisted whole
    assert device.transfers.store.active(0) == new and crc32(device.transfers.store.active(0)) == crc32(new)
    # the same learning again: the device no longer holds the image it was learned for
    assert main([*argv, "-o", str(tmp_path / "again.st16cat"), "--upload"]) == 2
    assert "not " in capsys.readouterr().err
    assert main(["--json", *argv, "-o", str(tmp_path / "again.st16cat"), "--upload"]) == 2
    assert json.loads(capsys.readouterr().out)["exit_code"] == 2  # the error's document alone, not the report too


def test_a_bad_or_interrupted_patch_leaves_the_old_catalog(tmp_path, image, device_port):
    from ground.link.client import Client, Nack
    from protocol.catalog_image import Reason
    from protocol.catalog_patch import PatchReason, make_patch
    from protocol.commands import Slot
    from protocol.crc import crc32

    start, stop = device_port
    device, port = start()
    new = _recoloured(image)
    with Client(port) as c:
        with pytest.raises(Nack) as info:  # nothing to patch yet
            c.upload(Slot.CATALOG_PATCH, make_patch(image, new), progress=False)
        assert info.value.reason == PatchReason.NO_BASE
        c.upload(Slot.CATALOG, image, progress=False)
        unsigned = bytearray(new)
        unsigned[-1] ^= 1  # padding changed under a consistent patch: the result fails the data CRC
        for patch, reason in (
            (make_patch(new, _recoloured(new)), PatchReason.BASE_MISMATCH),
            (make_patch(image, bytes(unsigned)), Reason.DATA_CRC),
        ):
            with pytest.raises(Nack) as info:
                c.upload(Slot.CATALOG_PATCH, patch, progress=False)
            assert info.value.reason == reason
            assert c.slot_info(Slot.CATALOG).crc32 == crc32(image)
        patch = make_patch(image, new)  # interrupted: BEGIN and half the data, then the device goes away
        c.xfer_begin(Slot.CATALOG_PATCH, len(patch), crc32(patch))
        c.xfer_data(Slot.CATALOG_PATCH, 0, patch[: len(patch) // 2])
    stop()
    device, port = start()
    assert device.transfers.store.active(0) == image and device._objects[0].rg[0] == parse_image(image).stars["rg"][0]
    with Client(port) as c:  # the rest of the patch, then COMMIT: applied whole
        report = c.upload(Slot.CATALOG_PATCH, patch, progress=False)
        assert report.resumed_from == len(patch) // 2
        assert c.slot_info(Slot.CATALOG).crc32 == crc32(new)
