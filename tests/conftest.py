"""Shared fixtures: the read-only data in ../shared (skipped cleanly when absent)."""

import threading
from pathlib import Path

import pytest
from hypothesis import settings

# Property tests check behaviour, not speed: no per-example deadline (the machine is shared).
settings.register_profile("project", deadline=None)
settings.load_profile("project")

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture
def served_device():
    """Path of a pty served by an in-process default Device (stopped after the test)."""
    from firmware_model.device.device import Device
    from firmware_model.device.link import PtyLink, serve

    link, stop = PtyLink(), threading.Event()
    thread = threading.Thread(target=serve, args=(Device(), link, stop), daemon=True)
    thread.start()
    yield link.path
    stop.set()
    thread.join(2)
    link.close()


@pytest.fixture(scope="session")
def synthetic_catalog():
    """``build(n, **kw)``: an ``OnboardCatalog`` of ``n`` random stars (rng seed 7) in a 0.6 x 0.6 rad
    patch, ids from 100, with colours (B-V lookup); ``kw`` adds build settings (``dphi_star``)."""
    import numpy as np

    from firmware_model.catalog.onboard import OnboardCatalog
    from firmware_model.reference_frames import radec_to_vec

    def build(n: int, **kw):
        rng = np.random.default_rng(7)
        return OnboardCatalog.build(
            np.arange(100, 100 + n),
            radec_to_vec(rng.uniform(0, 0.6, n), rng.uniform(-0.3, 0.3, n)),
            rng.uniform(1, 5, n),
            rng.uniform(0.7, 1.3, n),
            rng.uniform(0.6, 1.1, n),
            phi_min=1e-3,
            phi_max=0.3,
            n_h=32,
            meta={"epoch": 2025.0, "source": "hipparcos", "colour_source": np.full(n, 2)},
            **kw,
        )

    return build


@pytest.fixture(scope="session")
def shared_data() -> Path:
    path = SHARED / "data"
    if not path.is_dir():
        pytest.skip("../shared/data is absent")
    return path
