"""``st16-ground frame render / inspect`` end to end on small frames."""

import json

import numpy as np

from ground.cli.main import main


def test_render_then_inspect_json_and_plot(tmp_path, capsys):
    out = tmp_path / "f.dng"
    args = [
        "frame",
        "render",
        "--out",
        str(out),
        "--width",
        "640",
        "--height",
        "480",
        "--fov",
        "2.5",
        "--random",
        "8",
        "--mag-range",
        "2",
        "4",
        "--seed",
        "5",
        "--cosmics",
        "3",
    ]
    assert main(args) == 0
    truth = json.loads((tmp_path / "f.truth.json").read_text())
    assert len(truth["stars"]) == 8 and len(truth["attitude_quaternion"]) == 4
    capsys.readouterr()
    assert main(["--json", "frame", "inspect", str(out), "--plot", str(tmp_path / "o.png")]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["n_stars"] == 8 and set(rep["timings_ms"]) >= {"detect_ms", "fit_ms", "total_ms"}
    for s in rep["stars"]:
        assert s["truth"] is not None and np.hypot(s["truth"]["dx"], s["truth"]["dy"]) < 0.3
        assert {"x", "y", "rg", "bg", "flags", "reduced_chi2"} <= set(s)
    assert (tmp_path / "o.png").stat().st_size > 10_000


def test_inspect_text_and_bad_file(tmp_path, capsys):
    out = tmp_path / "m.fits"
    assert (
        main(
            [
                "frame",
                "render",
                "--out",
                str(out),
                "--width",
                "320",
                "--height",
                "240",
                "--pattern",
                "MONO",
                "--random",
                "4",
                "--mag-range",
                "2",
                "3",
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert main(["frame", "inspect", str(out)]) == 0
    text = capsys.readouterr().out
    assert "MONO" in text and "NO_COLOUR" in text and "timings ms" in text
    bad = tmp_path / "junk.dng"
    bad.write_bytes(b"not a raw file at all")
    assert main(["frame", "inspect", str(bad)]) == 2
    assert "not a readable raw" in capsys.readouterr().err


def test_render_from_catalog_image(tmp_path):
    from firmware_model.camera import CameraModel
    from firmware_model.catalog.image_io import catalog_to_image
    from firmware_model.catalog.onboard import OnboardCatalog
    from firmware_model.reference_frames import attitude_from_radec_roll, quat_to_matrix

    rng = np.random.default_rng(2)
    cam = CameraModel.from_fov(640, 480, 2.5)
    a = attitude_from_radec_roll(*np.radians([10.0, 20.0, 30.0]))
    v_in = cam.pixel_to_vector(rng.uniform(20, 620, 12), rng.uniform(20, 460, 12)) @ a
    v_out = rng.normal(size=(50, 3))
    v_out /= np.linalg.norm(v_out, axis=1, keepdims=True)
    vec = np.vstack([v_in, v_out])
    ids = np.arange(1000, 1000 + len(vec))
    cat = OnboardCatalog.build(
        ids,
        vec,
        rng.uniform(2, 4, len(vec)),
        rng.uniform(0.4, 1.4, len(vec)),
        rng.uniform(0.3, 1.2, len(vec)),
        phi_min=1e-4,
        phi_max=0.2,
        meta={"epoch": 2000.0},
    )
    (tmp_path / "cat.bin").write_bytes(catalog_to_image(cat, created_unix=0))
    out = tmp_path / "c.fits"
    assert (
        main(
            [
                "frame",
                "render",
                "--out",
                str(out),
                "--catalog",
                str(tmp_path / "cat.bin"),
                "--width",
                "640",
                "--height",
                "480",
                "--fov",
                "2.5",
                "--ra",
                "10",
                "--dec",
                "20",
                "--roll",
                "30",
            ]
        )
        == 0
    )
    truth = json.loads((tmp_path / "c.truth.json").read_text())
    assert np.allclose(quat_to_matrix(truth["attitude_quaternion"]), a, atol=1e-12)
    got = {s["id"]: (s["x"], s["y"]) for s in truth["stars"]}
    inside = [i for i, v in zip(ids, vec) if cam.in_frame(*cam.vector_to_pixel(a @ v))[0]]
    assert sorted(got) == sorted(inside) and len(inside) >= 12
    for i in inside:
        x, y = cam.vector_to_pixel(a @ vec[i - 1000])
        assert np.hypot(got[i][0] - x[0], got[i][1] - y[0]) < 1e-3  # float32 catalog vectors
