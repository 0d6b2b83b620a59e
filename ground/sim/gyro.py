"""The flight side's gyro (docs/hil.md "The flight side"): a seeded rate-integrating gyro model
measuring the true body rate with a bias, angle random walk, rate random walk and scale factor.

Per step of ``dt`` s, per axis (IEEE Std 952 error terms, the discrete form of Farrenkopf's model):

* ``b_k+1 = b_k + rrw * sqrt(dt) * n1`` (rate random walk, rad/s/sqrt(s));
* ``w_meas = (1 + sf) * w_true + b + arw / sqrt(dt) * n2`` (angle random walk, rad/sqrt(s); the
  mean rate over the step), ``n1, n2`` standard normal, ``sf`` a fixed scale-factor error drawn
  once per axis, ``b_0`` drawn once per axis (the turn-on bias).

Defaults (:data:`DEFAULT`): the class of a tactical-grade fibre-optic gyro such as Northrop
Grumman's LN-200, whose datasheet gives gyro bias repeatability 1-10 deg/h, angle random walk
0.04-0.1 deg/sqrt(h) and scale-factor stability 100 ppm (1 sigma). We take the best of each
range: a turn-on bias of 1 deg/h, 0.07 deg/sqrt(h), 100 ppm. The rate random walk is not on that
datasheet: 0.1 deg/h/sqrt(h) is **our assumption**, in the range quoted for that class.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numpy only when a gyro runs: the CLI's help reads the defaults here
    import numpy as np

DEG_PER_H = math.radians(1.0) / 3600.0  #: rad/s
DEG_PER_SQRT_H = math.radians(1.0) / 60.0  #: rad/sqrt(s)

#: Each parameter's (name, unit scale, largest accepted value in its unit): out of range is refused.
LIMITS = {
    "bias_deg_h": 3600.0,  #: 1 deg/s: a gyro worse than that is not an attitude gyro
    "arw_deg_rt_h": 100.0,
    "rrw_deg_h_rt_h": 1000.0,
    "sf_ppm": 1e5,  #: 10 %
}

#: how each parameter is named to a user: ``st16-ground hil demo``'s option and the unit
SHOWN = {
    "bias_deg_h": ("--gyro-bias", "deg/h"),
    "arw_deg_rt_h": ("--gyro-arw", "deg/sqrt(h)"),
    "rrw_deg_h_rt_h": ("--gyro-rrw", "deg/h/sqrt(h)"),
    "sf_ppm": ("--gyro-sf", "ppm"),
}


@dataclass(frozen=True)
class GyroSpec:
    """A gyro class: ``bias_deg_h`` the 1-sigma turn-on bias per axis, ``arw_deg_rt_h`` angle
    random walk, ``rrw_deg_h_rt_h`` rate random walk, ``sf_ppm`` the 1-sigma scale-factor error."""

    bias_deg_h: float = 1.0
    arw_deg_rt_h: float = 0.07
    rrw_deg_h_rt_h: float = 0.1
    sf_ppm: float = 100.0

    def problems(self) -> list[str]:
        """Why this spec is refused (empty when fine), one phrase each."""
        out = []
        for name, hi in LIMITS.items():
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.0 <= v <= hi):
                option, unit = SHOWN[name]
                out.append(f"{option} {v:g} {unit} outside [0, {hi:g}]")
        return out

    @property
    def arw(self) -> float:
        """rad/sqrt(s)"""
        return self.arw_deg_rt_h * DEG_PER_SQRT_H

    @property
    def rrw(self) -> float:
        """rad/s/sqrt(s)"""
        return self.rrw_deg_h_rt_h * DEG_PER_H / 60.0


DEFAULT = GyroSpec()


class Gyro:
    """The seeded gyro of the module docstring; :meth:`measure` once per step."""

    def __init__(self, spec: GyroSpec = DEFAULT, seed: int = 0):
        problems = spec.problems()
        if problems:
            raise ValueError("; ".join(problems))
        import numpy as np

        self.spec = spec
        self.rng = np.random.default_rng(seed)
        self.bias = self.rng.normal(0.0, spec.bias_deg_h * DEG_PER_H, 3)
        self.sf = self.rng.normal(0.0, spec.sf_ppm * 1e-6, 3)

    def measure(self, w_true, dt: float) -> np.ndarray:
        """The mean rate (rad/s, body axes) the gyro reports over a step of ``dt`` s."""
        import numpy as np

        w = (1.0 + self.sf) * np.asarray(w_true, dtype=float) + self.bias
        w = w + self.rng.normal(0.0, self.spec.arw / math.sqrt(dt), 3)
        self.bias = self.bias + self.rng.normal(0.0, self.spec.rrw * math.sqrt(dt), 3)
        return w
