"""Attitude-feed faults against a device process (ground.testing.feed_faults): after each, the
device keeps serving and the next valid samples give an OK, correct solve."""

from ground.testing import feed_faults


def test_every_feed_fault_kind_is_survived_and_the_feed_recovers():
    # one round of each kind; the recovery bound is a hang guard here (bench_fuzz reports the
    # figure against its 2 s target)
    tally = feed_faults.run(seed=7, rounds=12, recovery_s=30.0, flood_recovery_s=30.0)
    assert tally.failures == 0, tally.notes
    assert tally.faults == 12 and tally.messages >= 24
    assert any(note.startswith("recovery to an OK solve after a single fault") for note in tally.notes)
