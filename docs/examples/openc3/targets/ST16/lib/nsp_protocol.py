"""NSP multi-part replies for an OpenC3 interface (template of the generated target's
``lib/nsp_protocol.py``; ``ground.export.openc3`` fills in the generated block from protocol/).

Stacked after ``SlipProtocol`` and ``CrcProtocol`` (CRC stripped), it sees one NSP message per
call: ``dst, src, MCF, data``. READ RESULT answers in parts of ``u16 address + bytes``, only the
last with the Final bit; COMBINATION sends one part per requested result section and splits a
long section likewise. This protocol joins contiguous parts into one message (the first part's
address, all the bytes, the last part's MCF): a READ RESULT reply becomes one message, a
COMBINATION reply one message per section, so the telemetry definitions identify each by its
address. A part that does not continue the held one replaces it. Everything else passes as is.
"""

from openc3.interfaces.protocols.protocol import Protocol

# BEGIN GENERATED
READ_RESULT = 0x0D
COMBINATION = 0x12
SECTION_ENDS = frozenset({0x0004, 0x0008, 0x0028, 0x0040, 0x0048, 0x0080, 0x012C, 0x0440, 0x04A8, 0x07E8, 0x0948, 0x1018})
# END GENERATED
FINAL = 0x80
CODE_MASK = 0x1F


class NspProtocol(Protocol):
    """Join the parts of READ RESULT and COMBINATION replies (see the module docstring)."""

    def __init__(self, allow_empty_data=None):
        super().__init__(allow_empty_data)
        self.held = None  # (header bytes, first address, joined bytes) of an unfinished reply

    def reset(self):
        super().reset()
        self.held = None

    def read_data(self, data, extra=None):
        while True:
            if len(data) < 5 or data[2] & CODE_MASK not in (READ_RESULT, COMBINATION):
                return super().read_data(data, extra)
            joined = self._join(bytes(data))
            if joined is not None:
                return joined, extra
            # The interface would wait for new bytes after a STOP, though the protocols below
            # may already hold the next part: take it from them.
            data, extra = self._next_below(extra)
            if isinstance(data, str):  # STOP or DISCONNECT
                return data, extra

    def _join(self, data):
        """The message to pass on, or None while a reply is unfinished (the part is held)."""
        code, address, body = data[2] & CODE_MASK, int.from_bytes(data[3:5], "little"), data[5:]
        held, self.held = self.held, None
        if held is not None and held[0][2] & CODE_MASK == code and held[1] + len(held[2]) == address:
            address, body = held[1], held[2] + body
        if data[2] & FINAL or (code == COMBINATION and address + len(body) in SECTION_ENDS):
            return data[:3] + address.to_bytes(2, "little") + body
        self.held = (data[:3], address, body)
        return None

    def _next_below(self, extra):
        """The next message the protocols below this one have buffered ("STOP" if none)."""
        protocols = self.interface.read_protocols if self.interface is not None else [self]
        data = b""
        for protocol in protocols[: protocols.index(self)]:
            data, extra = protocol.read_data(data, extra)
            if isinstance(data, str):
                return data, extra
        return (data, extra) if data else ("STOP", extra)
