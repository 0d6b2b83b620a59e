"""The command line's contract (docs/cli.md, docs/bad_input.md; issue 30): every refusal is one
line on stderr with the exit code of its class (``ground.cli.main.EXIT_CODES``), never a
traceback; under ``--json`` stdout is exactly one JSON document, a failure's included; every
command names its output ``-o/--output``. Run in-process; the link cases against a device served
on a pty. No case solves a real frame: each shows its contract on the cheapest input."""

import json
import re

import numpy as np
import pytest

from ground.cli.main import build_parser, main


def run(argv: list[str], capsys) -> tuple[int, str, list[str]]:
    """(exit code, stdout, stderr lines) of ``st16-ground ARGV`` in-process."""
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's refusals
        code = int(exc.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err.strip().splitlines()


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    from firmware_model.pipeline.raw_frame import Frame
    from ground.sim.frame_writer import write_frame

    d = tmp_path_factory.mktemp("contract")
    write_frame(Frame(np.zeros((48, 64), np.uint16), "MONO", white_level=4095), d / "f.npy")
    (d / "baddir").mkdir()
    (d / "empty").mkdir()
    (d / "one").mkdir()
    write_frame(Frame(np.zeros((48, 64), np.uint16), "MONO", white_level=4095), d / "one" / "f.npy")
    (d / "held").mkdir()
    (d / "held" / "results.jsonl").write_text('{"frame": "a.dng", "status": "OK"}\n')
    (d / "cat.st16cat").write_text("x")
    (d / "params.json").write_text('{"max_seeds": 50}')
    assert main(["frame", "render", "--random", "8", "--width", "160", "--height", "120", "-o", str(d / "F.npy")]) == 0
    truth = json.loads((d / "F.truth.json").read_text())
    for star in truth["stars"]:
        del star["y"]
    (d / "noy").mkdir()
    (d / "noy" / "F.npy").write_bytes((d / "F.npy").read_bytes())
    (d / "noy" / "F.truth.json").write_text(json.dumps(truth))
    return d


# (argv with {d} for the files, exit code, the one stderr line (regex), or None: no stderr line)
OFFLINE_CASES = [
    (
        ["solve-file", "{d}/f.npy", "--fov-deg", "120"],
        2,
        r"^st16-ground: field-of-view hint 120 deg is outside 1-90 deg$",
    ),
    (["solve-file", "{d}/f.npy", "--fov-deg", "179"], 2, r"hint 179 deg is outside 1-90 deg$"),
    (["solve-file", "{d}/f.npy", "--fov-range", "10", "150"], 2, r"high end 150 deg is outside 1-90 deg$"),
    (
        ["solve", "--offline", "--frame", "{d}/f.npy", "--catalog", "{d}/cat.st16cat", "--pinhole-fov-deg", "150"],
        2,
        r"^st16-ground: --pinhole-fov-deg 150 deg is outside 1-90 deg$",
    ),
    (  # a hint everywhere: where nothing is searched it is refused, naming the camera's option
        ["solve", "--offline", "--frame", "{d}/f.npy", "--catalog", "{d}/cat.st16cat", "--fov-deg", "11.4"],
        2,
        r"argument --fov-deg: --fov-deg is a field-of-view hint .* give --pinhole-fov-deg 11.4 .*usage",
    ),
    (
        ["--port", "nosuch://x", "ping"],
        2,
        r"^st16-ground: --port nosuch://x: invalid URL, protocol 'nosuch' not known$",
    ),
    (
        ["frame", "inspect", "{d}/noy/F.npy"],
        0,
        r"^st16-ground: F.truth.json is not a readable truth file \(KeyError: 'y'\); ignored$",
    ),
    (
        ["frame", "inspect", "{d}/noy/F.npy", "--truth", "{d}/noy/F.truth.json"],
        2,
        r"--truth .*: not a readable truth file \(KeyError: 'y'\)$",
    ),
    (["replay", "{d}/nodir", "--offline", "--catalog", "{d}/cat.st16cat"], 2, r"nodir: no such directory$"),
    (["replay", "{d}/empty", "--offline"], 2, r"^st16-ground: .*empty: no frame files .*in the directory$"),
    (["solve-file", "{d}/baddir"], 2, r"^st16-ground: .*baddir: a directory, not a frame file$"),
    (
        ["solve-file", "{d}/f.npy", "--wcs", "{d}/cat.st16cat/x.wcs"],
        2,
        r"argument --wcs: .*cat.st16cat is a file, not a directory",
    ),
    (
        ["solve-file", "{d}/f.npy", "--fov-deg", "abc"],
        2,
        r"^st16-ground solve-file: error: argument --fov-deg: .*\(st16-ground solve-file --help: usage\)$",
    ),
    (["catalog", "colours", "--qe", "{d}/nope.csv", "-o", "{d}/c.png"], 2, r"nope.csv"),
]


@pytest.mark.parametrize("as_json", [False, True], ids=["text", "json"])
@pytest.mark.parametrize(
    "argv,code,line", OFFLINE_CASES, ids=lambda v: " ".join(v)[:60] if isinstance(v, list) else None
)
def test_each_refusal_is_one_line_its_exit_code_and_json_under_json(files, capsys, argv, code, line, as_json):
    args = [a.format(d=files) for a in argv]
    rc, out, err = run((["--json"] if as_json else []) + args, capsys)
    assert rc == code, (rc, err)
    assert len(err) == 1 and re.search(line, err[0]) and "Traceback" not in err[0], err
    if as_json:
        doc = json.loads(out)  # exactly one document, the failure's included
        assert rc == 0 or doc["exit_code"] == rc


def test_link_cases(served_device, files, capsys):
    d, port = files, served_device
    # a missing input and an --out that already holds results: usage or input, 2
    for argv, line in (
        (["replay", f"{d}/nodir"], r"^st16-ground: .*nodir: no such directory$"),
        (["replay", f"{d}/f.npy"], r"f.npy: not a directory$"),
        (["replay", f"{d}/one", "-o", f"{d}/held"], r"already holds 1 frame result\(s\): --resume continues"),
        (["replay", f"{d}/empty"], r"^st16-ground: .*empty: no frame files .*in the directory$"),
        (["solve", "--frame", f"{d}/nope.dng"], r"^st16-ground: \S*nope.dng: no such file$"),
    ):
        rc, out, err = run(["--port", port, *argv], capsys)
        assert rc == 2 and len(err) == 1 and re.search(line, err[0]), (argv, rc, err)
    # a result with no attitude (NO_CATALOG) exits 3, as a solve with none
    assert run(["--port", port, "init"], capsys)[0] == 0
    for argv in (["go", "--wait"], ["result"]):
        rc, out, err = run(["--port", port, *argv], capsys)
        assert rc == 3 and "NO_CATALOG" in out and err == [], (argv, rc, err)
        rc, out, _ = run(["--port", port, "--json", *argv], capsys)
        assert rc == 3 and json.loads(out)["status"] == "NO_CATALOG"
    # replay and params upload: text without --json, one JSON document with it
    for argv in (["replay", f"{d}/one", "-o", f"{d}/r1"], ["params", "upload", f"{d}/params.json"]):
        rc, out, err = run(["--port", port, *argv], capsys)
        assert rc == 0 and err == [] and not out.startswith("{"), out
        with pytest.raises(json.JSONDecodeError):
            json.loads(out)
    rc, out, _ = run(["--port", port, "--json", "replay", f"{d}/one", "-o", f"{d}/r2"], capsys)
    assert rc == 0 and json.loads(out)["frames"] == 1
    rc, out, _ = run(["--port", port, "--json", "params", "upload", f"{d}/params.json"], capsys)
    assert rc == 0 and json.loads(out)["slot"] == 2


def test_solve_file_json_is_one_document_with_the_files_written(files, capsys, monkeypatch):
    """``--json solve-file F --wcs W --overlay O``: the files are named inside the one document
    (they used to follow it as ``wcs: ...`` and ``overlay: ...`` lines)."""
    import ground.analysis.frame_plot as frame_plot
    import ground.cli.solve as solve_cli
    from ground.solver import Solve

    record = {"status": "NO_MATCH", "q_icrs_to_sensor": None, "reason": "test", "timings_s": {}}

    class Solver:
        catalog = None

        def solve(self, frame, say=None):
            return Solve(dict(record))

    monkeypatch.setattr(solve_cli, "offline_solver", lambda args, search: Solver())
    monkeypatch.setattr(frame_plot, "plot_identified", lambda frame, rec, path, label: path)
    argv = ["solve-file", f"{files}/f.npy", "--wcs", f"{files}/x.wcs", "--overlay", f"{files}/x.png"]
    rc, out, err = run(["--json", *argv], capsys)
    doc = json.loads(out)
    assert rc == 3 and doc["status"] == "NO_MATCH"
    assert doc["written"] == {"wcs": None, "overlay": {"path": f"{files}/x.png"}}
    assert len(err) == 1 and "--wcs" in err[0] and "not written" in err[0], err  # no attitude: no WCS, said once
    rc, out, err = run(argv, capsys)
    assert rc == 3 and out.strip().endswith(f"overlay: {files}/x.png")


def test_hil_demo_says_why_it_failed(tmp_path, capsys, monkeypatch):
    import ground.hil.run as hil

    summary = {
        "updates": 57,
        "pointing_error_deg_first": 4.003,
        "pointing_error_deg_last": 0.648,
        "acquisition_s": 0.5,
        "last_fix_age_s": 0.2,
    }
    monkeypatch.setattr(hil, "run_hil", lambda *a, **kw: dict(summary))
    argv = ["hil", "demo", "--duration", "10", "--dynamics", "standin", "--out", str(tmp_path)]
    rc, out, err = run(argv, capsys)
    assert rc == 1 and err == [
        "st16-ground: hil demo failed: final pointing error 0.648 deg is over the 0.05 deg pass mark"
    ]
    rc, out, err = run(["--json", *argv], capsys)
    assert rc == 1 and json.loads(out)["pointing_error_deg_last"] == 0.648 and len(err) == 1
    summary["pointing_error_deg_last"] = 0.01
    assert run(argv, capsys)[0] == 0
    summary["last_fix_age_s"] = 30.0  # a run that ends on the gyro alone fails, whatever its error
    rc, out, err = run(argv, capsys)
    assert rc == 1 and err == [
        "st16-ground: hil demo failed: the flight side's last tracker fix is 30.0 s old at the end, over 5 s"
    ]


@pytest.mark.parametrize(
    "argv,dest",
    [
        (["catalog", "build"], "output"),
        (["catalog", "colours"], "plot"),
        (["colour", "fit", "r.jsonl", "--catalog", "c"], "output"),
        (["frame", "render"], "out"),
        (["replay", "d"], "out"),
        (["solve"], "out"),
        (["sim", "colour"], "out"),
        (["demo"], "out"),
        (["hil", "demo"], "out"),
        (["camera", "calibrate", "f.dng", "--catalog", "c"], "output"),
        (["export", "xtce"], "output"),
    ],
)
def test_every_output_is_dash_o_or_dash_dash_output_and_old_spellings_still_work(argv, dest, tmp_path):
    """docs/cli.md "Outputs": ``-o/--output`` everywhere; ``--out`` and ``--plot`` kept as aliases."""
    parser = build_parser()
    target = str(tmp_path / "x.out")
    spellings = ["-o", "--output"] + [
        old for old in ("--out", "--plot") if old in _options(parser, argv) and dest in ("out", "plot")
    ]
    for option in spellings:
        assert str(getattr(parser.parse_args([*argv, option, target]), dest)) == target, option


def _options(parser, argv) -> set[str]:
    """The option strings of the subcommand ``argv`` names."""
    import argparse

    node = parser
    for word in argv:
        subs = [a for a in node._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs or word not in subs[0].choices:
            break
        node = subs[0].choices[word]
    return {s for a in node._actions for s in a.option_strings}


def test_a_cut_device_reason_ends_at_a_whole_word_and_says_so():
    from ground.cli.link import mark_cut_reason
    from protocol.result import EXT_REASON_BYTES

    full = "12 stars (coverage 0.45, chance 1e-05 at search attempt 3) with optics fitted to a search-chosen pattern"
    cut = mark_cut_reason({"reason": full.encode()[:EXT_REASON_BYTES].decode()})
    assert cut["reason_cut"] and cut["reason"].endswith(" ...") and "search-chosen )" not in cut["reason"]
    assert mark_cut_reason({"reason": "no catalog"}) == {"reason": "no catalog"}


def test_the_field_of_view_range_is_stated_once():
    help_text = build_parser()._subparsers._group_actions[0].choices["solve-file"].format_help()
    assert help_text.count("(1-90)") == 2  # --fov-deg and --fov-range, from the one constant


def test_json_is_one_document_from_database_frame_render_and_learn_colours(
    files, capsys, monkeypatch, tmp_path, synthetic_catalog
):
    """``--json`` in the commands that used to print plain lines: the document is all of stdout."""
    from firmware_model.catalog.image_io import catalog_to_image
    from ground.catalog import sky_database
    from protocol.catalog_image import parse_image

    db_file = tmp_path / "sky.npz"
    db_file.write_bytes(b"x" * 10)
    meta = {"version": 2, "patterns": 7, "stars": 5, "faintest_mag": 8.0, "fov_deg": [5, 60], "build_s": 0.1}
    fake = sky_database.SkyDatabase(index=None, mag=np.zeros(5), star_id=np.zeros(5), meta=meta, path=db_file)
    monkeypatch.setattr(sky_database, "load", lambda path: fake)
    monkeypatch.setattr(sky_database, "build", lambda progress=False: fake)
    monkeypatch.setattr(sky_database, "save", lambda db, path: None)
    for argv, member in (
        (["database", "info", "--database", str(db_file)], {}),
        (["database", "build", "--database", str(db_file)], {"built": False}),
        (["database", "build", "--database", str(db_file), "--force"], {"built": True}),
    ):
        rc, out, err = run(["--json", *argv], capsys)
        doc = json.loads(out)
        assert rc == 0 and err == [] and doc["patterns"] == 7 and doc["bytes"] == 10, (argv, out, err)
        assert all(doc[k] == v for k, v in member.items()), doc

    rc, out, _ = run(
        [
            "--json",
            "frame",
            "render",
            "--random",
            "4",
            "--width",
            "64",
            "--height",
            "48",
            "-o",
            str(tmp_path / "G.npy"),
        ],
        capsys,
    )
    assert rc == 0 and json.loads(out)["frame"] == str(tmp_path / "G.npy")

    image = catalog_to_image(synthetic_catalog(30), created_unix=1_700_000_000)
    (tmp_path / "cat.st16cat").write_bytes(image)
    stars = [
        {
            "catalog_id": int(s["star_id"]),
            "rg": float(s["rg"]) * 1.1,
            "bg": float(s["bg"]) * 1.1,
            "rg_sigma": 0.01,
            "bg_sigma": 0.01,
            "saturated": False,
            "body": None,
        }
        for s in parse_image(image).stars[:5]
    ]
    (tmp_path / "results.jsonl").write_text(3 * (json.dumps({"status": "OK", "stars": stars}) + "\n"))
    argv = ["catalog", "learn-colours", str(tmp_path), "--catalog", str(tmp_path / "cat.st16cat")]
    rc, out, err = run(["--json", *argv, "-o", str(tmp_path / "new.st16cat")], capsys)
    doc = json.loads(out)
    assert rc == 0 and doc["stars_updated"] == 5 and err == []
    assert doc["written"] == {"image": str(tmp_path / "new.st16cat"), "report": None, "plot": None}
    rc, out, err = run(["--json", *argv, "--min-obs", "4", "-o", str(tmp_path / "no.st16cat")], capsys)
    assert rc == 1 and json.loads(out)["written"]["image"] is None and len(err) == 1


def test_demo_and_warm_up_json_is_one_document_and_the_steps_go_to_stderr(tmp_path, capsys, monkeypatch):
    """``demo`` and ``warm-up`` (their work stubbed): under ``--json`` the steps' lines are on stderr
    and stdout is the document; in text the demo's summary line, which .ci/run reads, and without
    matplotlib it says the plots were skipped and why."""
    import ground.cli.demo as demo
    import ground.cli.end_to_end as end_to_end
    from ground.catalog import sky_database

    def fake_demo(out, n_frames, seed, progress):
        print("st16 demo: output folder ...")
        rows = [
            {
                "frame": "frame_00_rggb.dng",
                "method": "lis",
                "status": "OK",
                "matched": 12,
                "error_arcsec": 1.5,
                "device_ms": 80.0,
                "exchange_s": 0.4,
            }
        ]
        return {
            "output": str(out),
            "frames": 1,
            "counts": {"correct": 1, "wrong": 0, "no_match": 0},
            "results": rows,
            "written": {"log": f"{out}/results.jsonl", "plots": []},
        }

    monkeypatch.setattr(demo, "_kernels", lambda progress: {"seconds": 0.4, "cache": None})
    monkeypatch.setattr(end_to_end, "run_demo", fake_demo)
    rc, out, err = run(["--json", "demo", "-o", str(tmp_path)], capsys)
    doc = json.loads(out)
    assert rc == 0 and doc["counts"]["correct"] == 1 and doc["kernels"]["seconds"] == 0.4
    assert err[0].startswith("kernels: ready in 0.4 s") and err[1] == "st16 demo: output folder ..."
    rc, out, err = run(["demo", "-o", str(tmp_path)], capsys)
    last = out.strip().splitlines()[-1]
    assert rc == 0 and err == [] and last.startswith("1 of 1 frames solved correctly (wrong 0, no match 0); log ")
    assert last.endswith(end_to_end.NO_PLOTS), last

    class Db:
        meta = {"version": 2, "patterns": 7, "stars": 5, "faintest_mag": 8.0, "fov_deg": [5, 60], "build_s": 0.1}
        path = None

        def summary(self):
            return "sky database: 7 patterns"

    monkeypatch.setattr(sky_database, "sky_database", lambda progress=False: Db())
    rc, out, err = run(["--json", "warm-up"], capsys)
    assert rc == 0 and json.loads(out)["database"]["patterns"] == 7 and err[0].startswith("kernels: ready")
    rc, out, err = run(["warm-up"], capsys)
    assert rc == 0 and out.splitlines() == [
        "kernels: ready in 0.4 s (numba's cache: beside the modules, in __pycache__)",
        "sky database: 7 patterns",
    ]
