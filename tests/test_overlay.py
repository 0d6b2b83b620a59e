"""The labelled overlay of a solve (``solve-file --overlay``, ground.analysis.frame_plot): colours
and shapes per kind, a legend whose counts are the record's, labels clear of each other (issue 30)."""

import numpy as np
import pytest
from conftest import required

from firmware_model.pipeline.raw_frame import Frame


@pytest.fixture(autouse=True)
def _matplotlib():
    """matplotlib is a [test] requirement: absent, these tests fail (conftest.required), never skip."""
    required("matplotlib")


def star(x, y, catalog_id=None, flux=100.0, body=None):
    return {"x": x, "y": y, "flux": flux, "catalog_id": catalog_id, "body": body}


def crowded_record():
    """Twelve identified stars within 60 px (the labels must spread out), three unmatched
    detections, a planet, a star at each corner; the record as solve-file's ``--json`` gives it."""
    rng = np.random.default_rng(3)
    stars = [star(150 + dx, 120 + dy, 1000 + k, 500 - k) for k, (dx, dy) in enumerate(rng.uniform(-30, 30, (12, 2)))]
    stars += [star(0.5, 0.5, 7), star(319, 0, 8), star(0, 239, 9), star(319, 239, 10)]
    stars += [star(60, 200), star(250, 60), star(155, 125)]
    stars.append(star(80, 60, body="jupiter", flux=900.0))
    return {
        "status": "OK",
        "ra_deg": 10.0,
        "dec_deg": 20.0,
        "roll_deg": 30.0,
        "n_detected": len(stars),
        "n_matched": 16,
        "stars": stars,
    }


def frame():
    rng = np.random.default_rng(0)
    return Frame(pixels=rng.poisson(50, (240, 320)).astype(np.uint16), pattern="MONO")


def test_overlay_counts_are_the_records_and_no_labels_collide(tmp_path):
    from ground.analysis.frame_plot import IDENTIFIED_COLOUR, overlay_figure, plot_identified
    from ground.optional import pyplot

    plt = pyplot()
    rec = crowded_record()
    fig, ax, drawn = overlay_figure(plt, frame(), rec)
    try:
        ids = sum(s["catalog_id"] is not None for s in rec["stars"])
        assert (drawn.identified, drawn.unmatched, drawn.planets) == (ids, 3, 1) and ids == rec["n_matched"]
        assert drawn.legend == ["identified (HIP n): 16", "unmatched detections: 3", "planets, moon: 1"]
        assert [t.get_text() for t in fig.legends[0].get_texts()] == drawn.legend
        assert "16 of 20 detections identified" in ax.get_title()
        boxes = drawn.label_boxes
        assert len(boxes) == 17  # 16 catalog numbers and the planet's name
        for i, a in enumerate(boxes):
            assert not any(a.overlaps(b) for b in boxes[i + 1 :]), i
        frame_box = ax.get_window_extent()
        assert all(frame_box.x0 <= b.x0 and b.x1 <= frame_box.x1 + 1 for b in boxes)
        assert all(frame_box.y0 <= b.y0 and b.y1 <= frame_box.y1 + 1 for b in boxes)
        labels = {t.get_text(): t.get_color() for t in ax.texts}
        assert labels["HIP 1000"] == IDENTIFIED_COLOUR and "Jupiter" in labels
    finally:
        plt.close(fig)
    png = plot_identified(frame(), rec, tmp_path / "o.png", label="HR")
    assert png.stat().st_size > 10_000


def test_a_device_record_says_it_lists_only_the_brightest():
    from ground.analysis.frame_plot import overlay_figure
    from ground.optional import pyplot

    plt = pyplot()
    rec = {**crowded_record(), "n_detected": 64, "n_matched": 40}
    fig, ax, drawn = overlay_figure(plt, frame(), rec)
    plt.close(fig)
    assert (
        "16 of 64 detections identified (the result lists the 20 brightest; 40 matched in the solve)" in ax.get_title()
    )
    assert drawn.identified == 16
