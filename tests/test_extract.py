"""extract_stars fits only what its result needs: a pass that only measures the PSF fits the
brightest candidates until enough are measurable, and the kept pass is fitted to the cap, with the
same stars as fitting every pass to the cap."""

import numpy as np
from open_loop_sky import POINTINGS, render

import firmware_model.pipeline.extract as extract_mod
from firmware_model.camera import CameraModel
from firmware_model.pipeline.extract import (
    FIT_FIRST_FACTOR,
    PSF_FIT_FIRST_FACTOR,
    PSF_SAMPLE_STARS,
    ExtractParams,
    _Pass,
    extract_stars,
)

#: A field wide enough for more stars than the candidate cap.
WIDE = CameraModel.from_horizontal_fov(1024, 768, 25.0)


def _fitted_per_call(monkeypatch) -> list[int]:
    sizes: list[int] = []
    fit = extract_mod.fit_stars

    def counted(frame, det, params):
        sizes.append(len(det))
        return fit(frame, det, params)

    monkeypatch.setattr(extract_mod, "fit_stars", counted)
    return sizes


def test_a_pass_that_only_measures_the_psf_fits_few_candidates(monkeypatch):
    _, r = render(WIDE, POINTINGS[1], psf_sigma=1.6)  # the 1 px start is off: two passes
    cap = ExtractParams().detect.max_candidates
    sizes = _fitted_per_call(monkeypatch)
    stars = extract_stars(r.frame, WIDE)
    assert stars.psf_passes == 2 and len(stars) == cap
    first_pass = int(np.ceil(PSF_FIT_FIRST_FACTOR * PSF_SAMPLE_STARS))
    assert first_pass < FIT_FIRST_FACTOR * cap
    fitted = [n for n in sizes if n]
    # the first pass measures the PSF on one small chunk; the kept one is fitted to the cap
    assert fitted[0] == first_pass and sum(fitted[1:]) >= cap, fitted


def test_fitting_only_what_is_needed_keeps_the_same_stars(monkeypatch):
    _, r = render(WIDE, POINTINGS[1], psf_sigma=1.6)
    fast = extract_stars(r.frame, WIDE)
    monkeypatch.setattr(_Pass, "fit_for_psf", lambda p, likely_kept: p.fit_to_cap())  # every pass fitted to the cap
    full = extract_stars(r.frame, WIDE)
    assert fast.psf_passes == full.psf_passes and fast.reason == full.reason
    for name in ("x", "y", "flux", "rg", "cov_xy", "sigma", "flags"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(full, name), err_msg=name)
