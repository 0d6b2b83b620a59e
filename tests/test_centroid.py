"""Centroid and colour fit: exact recovery without noise, analytic Jacobian, statistical
efficiency against truth, flags for saturation, edges, mono frames and hot pixels."""

import numpy as np
import pytest
from scipy.optimize import approx_fprime

from firmware_model.camera import CameraModel
from firmware_model.pipeline.centroid import FitParams, _WindowModel, fit_stars
from firmware_model.pipeline.detect import detect_stars
from firmware_model.pipeline.extract import extract_stars
from firmware_model.pipeline.raw_frame import Frame
from firmware_model.reference_frames import attitude_from_radec_roll
from ground.sim.sensor_sim import DetectorModel, Stars, random_star_field, render_frame
from protocol.star_flags import StarFlag

CAM = CameraModel.from_fov(480, 360, 2.0)
ATT = attitude_from_radec_roll(4.0, -0.2, 1.0)


def _stars(xs, ys, vmag, rg, bg):
    v = CAM.pixel_to_vector(np.asarray(xs, float), np.asarray(ys, float)) @ ATT
    n = len(xs)
    return Stars(np.arange(1, n + 1), v, np.broadcast_to(vmag, n), np.broadcast_to(rg, n), np.broadcast_to(bg, n))


def test_noise_free_exact_recovery():
    xs, ys = [100.3, 240.77, 380.5], [90.1, 200.45, 280.9]
    rg, bg = np.array([0.45, 1.0, 1.55]), np.array([0.3, 0.9, 1.3])
    stars = Stars([1, 2, 3], CAM.pixel_to_vector(xs, ys) @ ATT, [2.0, 2.5, 3.0], rg, bg)
    res = render_frame(stars, ATT, CAM, DetectorModel(pattern="GRBG"), seed=0)
    pixels = 100.0 + res.electrons / 1.6 + 10.0  # black 100 DN, 10 DN flat sky, no noise
    frame = Frame(pixels=pixels, pattern="GRBG", black_level=100, white_level=1e9)
    out = extract_stars(frame)
    order = np.argsort(out.x)
    assert len(out) == 3
    assert np.allclose(out.x[order], xs, atol=1e-4) and np.allclose(out.y[order], ys, atol=1e-4)
    assert np.allclose(out.rg[order], rg, rtol=1e-4) and np.allclose(out.bg[order], bg, rtol=1e-4)
    assert np.allclose(out.sigma, 1.0, atol=1e-4)


def test_analytic_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    rows, cols = [a.ravel().astype(float) for a in np.mgrid[10:19, 20:29]]
    chan = ((rows.astype(int) % 2) * 2 + cols.astype(int) % 2).clip(0, 2)
    wm = _WindowModel(rows, cols, chan, 3, 1.0 / rng.uniform(1, 3, len(rows)))
    p = np.array([24.3, 14.6, 1.2, 900.0, 1500.0, 700.0, 5.0, 6.0, 7.0])
    data = wm.model(p) + rng.normal(0, 2, len(rows))
    num = np.array([approx_fprime(p, lambda q, k=k: wm.residuals(q, data)[k], 1e-6) for k in range(len(rows))])
    assert np.allclose(wm.jacobian(p), num, rtol=1e-4, atol=1e-4)


def test_errors_match_predicted_covariance():
    """Pulls (error / predicted sigma) over many bright stars have unit spread."""
    ex, ey, erg, sx, srg = [], [], [], [], []
    for seed in range(4):
        stars = random_star_field(CAM, ATT, 12, vmag_range=(2.0, 3.5), seed=seed, min_separation_px=25)
        res = render_frame(stars, ATT, CAM, seed=100 + seed)
        out = extract_stars(res.frame)
        for t in res.truth["stars"]:
            d = np.hypot(out.x - t["x"], out.y - t["y"])
            j = int(np.argmin(d))
            assert d[j] < 0.5 and out.flags[j] == 0
            ex.append(out.x[j] - t["x"])
            ey.append(out.y[j] - t["y"])
            erg.append(out.rg[j] - t["rg"])
            sx.append(np.sqrt(out.cov_xy[j, 0, 0]))
            srg.append(np.sqrt(out.cov_colour[j, 0, 0]))
    ex, erg, sx, srg = map(np.asarray, (ex, erg, sx, srg))
    assert 0.75 < np.std(ex / sx) < 1.3 and 0.75 < np.std(erg / srg) < 1.3
    assert abs(np.mean(ex / sx)) < 0.4 and abs(np.mean(erg / srg)) < 0.4
    assert np.sqrt(np.mean(ex**2)) < 0.06  # px, bright stars


def test_mono_frame_single_amplitude_no_colour():
    res = render_frame(_stars([200.4], [150.7], 3.0, 0.8, 0.6), ATT, CAM, DetectorModel(pattern="MONO"), seed=1)
    out = extract_stars(res.frame)
    assert len(out) == 1 and np.isnan(out.rg[0]) and np.isnan(out.bg[0])
    assert out.flags[0] & StarFlag.NO_COLOUR and not out.flags[0] & StarFlag.FIT_FAILED
    assert np.hypot(out.x[0] - 200.4, out.y[0] - 150.7) < 0.05


def test_saturated_star_flagged_and_centred_from_wings():
    res = render_frame(_stars([240.3], [180.6], -1.0, 1.0, 1.0), ATT, CAM, seed=2)
    assert (res.frame.pixels >= 4095).sum() > 4
    out = extract_stars(res.frame)
    j = int(np.argmax(out.flux))
    assert out.flags[j] & StarFlag.SATURATED
    assert np.hypot(out.x[j] - 240.3, out.y[j] - 180.6) < 0.1


def test_edge_star_flagged():
    res = render_frame(_stars([1.2], [100.4], 2.0, 1.0, 1.0), ATT, CAM, seed=3)
    out = extract_stars(res.frame)
    assert len(out) == 1 and out.flags[0] & StarFlag.EDGE


def test_hot_pixel_inside_window_is_ignored():
    res = render_frame(_stars([200.0], [150.0], 3.0, 0.9, 0.7), ATT, CAM, DetectorModel(hot_pixel_fraction=0), seed=4)
    clean = extract_stars(res.frame)
    px = res.frame.pixels.copy()
    px[152, 203] = 3000  # hot pixel 3 px from the star
    hot = extract_stars(Frame(px, res.frame.pattern, res.frame.black_level, res.frame.white_level))
    assert len(hot) == 1
    assert abs(hot.x[0] - clean.x[0]) < 0.02 and abs(hot.rg[0] - clean.rg[0]) < 0.02


def test_unconverged_fit_falls_back_and_flags():
    res = render_frame(_stars([200.0], [150.0], 3.0, 1.0, 1.0), ATT, CAM, seed=5)
    det = detect_stars(res.frame)
    out = fit_stars(res.frame, det, FitParams(max_nfev=1))
    assert out.flags[0] & StarFlag.FIT_FAILED
    assert np.hypot(out.x[0] - 200.0, out.y[0] - 150.0) < 0.5  # centre-of-gravity fallback


def test_cog_method_is_coarser_than_the_fit_and_bad_method_rejected():
    stars = random_star_field(CAM, ATT, 12, vmag_range=(2.0, 3.0), seed=9, min_separation_px=25)
    res = render_frame(stars, ATT, CAM, seed=9)
    det = detect_stars(res.frame)
    lm, cog = fit_stars(res.frame, det), fit_stars(res.frame, det, FitParams(method="cog"))
    tx = np.array([t["x"] for t in res.truth["stars"]])
    ty = np.array([t["y"] for t in res.truth["stars"]])

    def rms(fit):
        d = np.hypot(fit.x[:, None] - tx[None], fit.y[:, None] - ty[None]).min(axis=1)
        return np.sqrt(np.mean(d**2))

    assert rms(lm) < 0.06 and rms(lm) < rms(cog) < 0.5
    assert np.all(np.isfinite(cog.rg)) and np.all(cog.flags & StarFlag.FIT_FAILED == 0)
    with pytest.raises(ValueError, match="unknown fit method"):
        fit_stars(res.frame, det, FitParams(method="gauss"))


def test_batched_windows_match_single_window_model():
    """The all-windows model, Jacobian and linear solve equal the one-window reference."""
    from firmware_model.pipeline.centroid import _Windows

    stars = random_star_field(CAM, ATT, 6, vmag_range=(2.0, 4.0), seed=11, min_separation_px=25)
    res = render_frame(stars, ATT, CAM, seed=11)
    det = detect_stars(res.frame)
    win = _Windows(res.frame, det, 4)
    rng = np.random.default_rng(1)
    n = len(det)
    p = np.column_stack(
        [
            det.x + rng.normal(0, 0.3, n),
            det.y + rng.normal(0, 0.3, n),
            rng.uniform(0.8, 1.3, n),
            rng.uniform(500, 2000, (n, 3)),
            rng.uniform(2, 8, (n, 3)),
        ]
    )
    r, jac, jfd = win.residuals(p, win.w), win.jacobian(p, win.w), win.jacobian_fd(p, win.w)
    lin = win.linear_solve(p[:, 0], p[:, 1], p[:, 2], win.w)
    for i in range(n):
        v = win.valid[i]
        rows = np.repeat(win.row_coords[i], win.side)[v]
        cols = np.tile(win.col_coords[i], win.side)[v]
        wm = _WindowModel(rows, cols, win.chan[i][v], 3, win.w[i][v])
        assert np.allclose(r[i][v], wm.residuals(p[i], win.data[i][v]), rtol=1e-10, atol=1e-10)
        assert np.allclose(jac[i][v], wm.jacobian(p[i]), rtol=1e-10, atol=1e-10)
        assert np.allclose(jfd[i][v], jac[i][v], rtol=1e-4, atol=1e-4)
        assert np.allclose(lin[i], wm.linear_solve(p[i, 0], p[i, 1], p[i, 2], win.data[i][v]), rtol=1e-8)
        assert np.all(r[i][~v] == 0) and np.all(jac[i][~v] == 0)


def test_compiled_levenberg_marquardt_matches_the_numpy_reference():
    from firmware_model.pipeline.centroid import _TOL, _levenberg_marquardt, _nb_levenberg_marquardt, _Windows

    for pattern in ("RGGB", "MONO"):
        stars = random_star_field(CAM, ATT, 12, vmag_range=(2.0, 7.0), seed=4, min_separation_px=15)
        frame = render_frame(stars, ATT, CAM, DetectorModel(pattern=pattern), seed=8).frame
        det = detect_stars(frame)
        win = _Windows(frame, det, 4)
        sig0 = np.full(len(det), 1.0)
        p0 = np.column_stack([det.x, det.y, sig0, win.linear_solve(det.x, det.y, sig0, win.w)])
        ref = _levenberg_marquardt(win, p0, win.w, FitParams())
        new = _nb_levenberg_marquardt(
            win.data, win.w, win.chan, win.nchan, win.row_coords, win.col_coords, p0, 60, _TOL
        )
        assert np.array_equal(ref[2], new[2]) and np.array_equal(ref[3], new[3])  # converged, started
        assert np.allclose(ref[0], new[0], rtol=1e-9, atol=1e-9) and np.allclose(ref[1], new[1], atol=1e-7)


def test_fit_stops_at_the_cap_with_the_same_stars(monkeypatch):
    import firmware_model.pipeline.extract as extract_mod
    from firmware_model.pipeline.detect import DetectParams
    from firmware_model.pipeline.extract import ExtractParams

    stars = random_star_field(CAM, ATT, 40, vmag_range=(2.0, 7.5), seed=9, min_separation_px=10)
    frame = render_frame(stars, ATT, CAM, DetectorModel(hot_pixel_fraction=2e-3), seed=2).frame
    params = ExtractParams(detect=DetectParams(max_candidates=12))
    calls = []
    real_fit = extract_mod.fit_stars
    monkeypatch.setattr(extract_mod, "fit_stars", lambda f, d, p: calls.append(len(d)) or real_fit(f, d, p))
    lazy = extract_stars(frame, params=params)
    n_lazy, calls[:] = sum(calls), []
    monkeypatch.setattr(extract_mod, "FIT_FIRST_FACTOR", 1000.0)
    full = extract_stars(frame, params=params)
    assert n_lazy < sum(calls)  # fewer candidates fitted
    assert len(lazy) == len(full) == 12
    assert np.array_equal(lazy.x, full.x) and np.array_equal(lazy.flags, full.flags)
