"""The truth of a rendered frame and a solve scored against it: ``Truth`` (the attitude and the
stars' pixels that ``NAME.truth.json`` holds beside a frame, ``frame_writer.write_rendered``) and
:func:`score`, shared by ``replay``, the benches and the rendered availability run."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass

import numpy as np

from firmware_model.pipeline.raw_frame import Frame
from firmware_model.reference_frames import quat_to_matrix, rotation_angle
from ground.link.solve_report import matched_stars
from ground.sim.frame_writer import truth_path_for

_log = logging.getLogger(__name__)

CORRECT_DEG = 0.1  #: attitude error bound of a correct solve (peer_solvers.md section 5)
MATCH_RADIUS_PX = 2.0  #: detection <-> truth association radius


@dataclass(frozen=True)
class Truth:
    q_icrs_to_sensor: np.ndarray
    star_id: np.ndarray
    x: np.ndarray
    y: np.ndarray

    @classmethod
    def for_frame(cls, frame_path, frame: Frame | None = None, warn=None) -> Truth | None:
        """The truth beside a rendered frame (``NAME.truth.json``), or None: absent, unreadable, or
        (with ``frame``) written for another frame (its camera size or render seed differ). The
        last two are said through ``warn`` (default: one line on stderr): the frame is then not
        scored, and nothing else is lost."""
        path = truth_path_for(frame_path)
        if not path.is_file():
            return None
        say = warn or (lambda msg: _log.warning("st16-ground: %s", msg))
        try:
            data = json.loads(path.read_text())
            stars = data.get("stars", [])
            truth = cls(
                np.asarray(data["attitude_quaternion"], dtype=float).reshape(4),
                np.array([s["id"] for s in stars], dtype=np.int64),
                np.array([s["x"] for s in stars], dtype=float),
                np.array([s["y"] for s in stars], dtype=float),
            )
            camera, seed = data.get("camera") or {}, data.get("seed")
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            say(f"{path.name} is not a readable truth file ({type(exc).__name__}: {exc}); frame not scored")
            return None
        if frame is not None:
            size = (camera.get("width"), camera.get("height"))
            frame_seed = (frame.metadata or {}).get("seed")
            if (None not in size and size != (frame.width, frame.height)) or (
                seed is not None and frame_seed is not None and int(seed) != int(frame_seed)
            ):
                say(
                    f"{path.name} describes another frame ({size[0]} x {size[1]}, seed {seed}; the frame is "
                    f"{frame.width} x {frame.height}, seed {frame_seed}); frame not scored"
                )
                return None
        return truth

    def stars_near(self, x: float, y: float) -> set[int]:
        """Ids of truth stars within MATCH_RADIUS_PX (a blend may hold several)."""
        if not len(self.x):
            return set()
        return {int(i) for i in self.star_id[np.hypot(self.x - x, self.y - y) <= MATCH_RADIUS_PX]}


def score(record: dict, truth: Truth | None) -> dict:
    """Outcome, attitude error (deg) and wrong-id count of a solve record."""
    if record.get("q_icrs_to_sensor") is None:
        return {"outcome": "no_match"}
    if truth is None:
        return {"outcome": "unscored"}
    err = np.degrees(rotation_angle(quat_to_matrix(record["q_icrs_to_sensor"]), quat_to_matrix(truth.q_icrs_to_sensor)))
    wrong = 0
    for s in matched_stars(record):
        near = truth.stars_near(s["x"], s["y"])
        wrong += int(bool(near) and s["catalog_id"] not in near)
    outcome = "correct" if err <= CORRECT_DEG and wrong == 0 else "wrong"
    return {"outcome": outcome, "attitude_error_deg": float(err), "wrong_ids": wrong}
