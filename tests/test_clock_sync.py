"""The ground's TIME correlation (ground.link.clock_sync): the fit recovers a clock's offset and
drift from polls of which some were delayed, and maps device time tags back to host time."""

import numpy as np

from ground.link.clock_sync import fit, latch_estimate


def test_the_fit_recovers_offset_and_drift_and_ignores_delayed_polls():
    rng = np.random.default_rng(4)
    host = np.sort(rng.uniform(100.0, 120.0, 200))
    rtt = rng.uniform(0.0004, 0.0006, 200)
    delayed = rng.random(200) < 0.3
    rtt[delayed] += rng.uniform(0.002, 0.02, delayed.sum())  # the reply waited: the latch is earlier
    latched = host - np.where(delayed, rtt / 3, 0.0)  # host: each exchange's midpoint
    device = 7.0 + (latched - 100.0) * (1 + 50e-6)
    m = fit(host, device, rtt)
    assert abs(m.drift_ppm - 50.0) < 0.1 and m.polls == 50
    good = ~delayed
    assert np.abs([m.to_host(d) - h for d, h in zip(device[good], host[good])]).max() < 2e-6


def test_a_paced_latch_is_the_send_time_plus_the_frame_on_the_line():
    assert latch_estimate(10.0, 10.2) == 10.1
    assert latch_estimate(10.0, 10.2, baud=115200) == 10.0 + 7 * 10 / 115200  # C0 0E 11 93 crc crc C0
