"""SLIP encoder and streaming decoder, including hypothesis properties on arbitrary splits."""

from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import slip


def test_escape_examples():
    assert slip.encode(bytes.fromhex("0E118DC00010")) == bytes.fromhex("C00E118DDBDC0010C0")
    assert slip.encode(b"\xdb") == bytes.fromhex("C0DBDDC0")
    assert slip.unescape(bytes.fromhex("DBDCDBDD")) == b"\xc0\xdb"


def _decode_all(stream: bytes, cuts: list[int], max_frame: int = 8192):
    dec = slip.Decoder(max_frame)
    events, prev = [], 0
    for cut in sorted(c % (len(stream) + 1) for c in cuts) + [len(stream)]:
        events += dec.feed(stream[prev:cut])
        prev = max(prev, cut)
    return events


@given(st.lists(st.binary(min_size=1, max_size=300), max_size=8), st.lists(st.integers(0, 10_000), max_size=20))
def test_frames_survive_any_split(frames, cuts):
    stream = b"".join(slip.encode(f) for f in frames)
    events = _decode_all(stream, cuts)
    assert [e.data for e in events] == frames


def test_idle_fends_are_not_frames():
    assert slip.Decoder().feed(b"\xc0\xc0\xc0\xc0") == []


def test_bad_escape_is_a_framing_error_and_next_frame_survives():
    dec = slip.Decoder()
    events = dec.feed(b"\xc0\x0e\x11\xdb\x41\x80\xc0" + slip.encode(b"ok!!!"))
    assert isinstance(events[0], slip.FramingError) and "0x41" in events[0].reason
    assert events[1] == slip.Frame(b"ok!!!")
    events = dec.feed(b"\xc0\x0e\xdb\xc0")  # FESC right before FEND
    assert isinstance(events[0], slip.FramingError)


def test_oversize_is_reported_once_and_decoder_recovers():
    dec = slip.Decoder(max_frame=100)
    events = dec.feed(b"\xc0" + b"\x01" * 101 + b"\xc0")
    assert len(events) == 1 and isinstance(events[0], slip.Oversize)
    # a huge frame arriving in pieces: one event, bounded memory, then recovery
    events = []
    for _ in range(50):
        events += dec.feed(b"\x02" * 64)
        assert dec.pending <= 200
    events += dec.feed(b"\xc0" + slip.encode(b"x" * 100))
    assert [type(e) for e in events] == [slip.Oversize, slip.Frame]
    assert events[1].data == b"x" * 100


@settings(max_examples=200)
@given(st.binary(max_size=2000), st.lists(st.integers(0, 3000), max_size=10))
def test_random_bytes_never_crash_and_frames_are_bounded(stream, cuts):
    for event in _decode_all(stream, cuts, max_frame=64):
        if isinstance(event, slip.Frame):
            assert 0 < len(event.data) <= 64
        else:
            assert isinstance(event, (slip.FramingError, slip.Oversize))


@given(st.binary(min_size=1, max_size=200))
def test_escape_roundtrip_and_no_fend_inside(data):
    esc = slip.escape(data)
    assert slip.FEND not in esc
    assert slip.unescape(esc) == data
