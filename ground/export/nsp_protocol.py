"""NSP multi-part replies for an OpenC3 interface (template of the generated target's
``lib/nsp_protocol.py``; ``ground.export.openc3`` fills in the generated block from protocol/).

Stacked after ``SlipProtocol`` and ``CrcProtocol`` (CRC stripped), it sees one NSP message per
call: ``dst, src, MCF, data``. READ RESULT answers in parts of ``u16 address + bytes``, only the
last with the Final bit; this protocol joins contiguous parts into one message (the first part's
address, all the bytes, the last part's MCF), so the telemetry definitions identify it by its
address (a part that does not continue the held one replaces it).

COMBINATION's success reply (ICD page 1-35918) is the requested result sections, in increasing
address order, as one stream in messages of ``u16 bytes already transmitted + bytes``. On the
way out this protocol remembers the section mask of the last COMBINATION command it wrote (data
byte 1 on, 3 or 4 bytes little-endian after the go code); on the way in it joins the reply's
messages by their count and, when they hold exactly the mask's sections, passes one message per
section with the section's result address in bytes 0-1 (Final on the last), as the telemetry
definitions expect; a mask of 0 gives one message with no data. A reply without a remembered
mask, or whose length is not the mask's, passes as one joined message (its first count, all the
bytes). A failure reply (ACK 0) passes as is. Everything else passes as is.
"""

from openc3.interfaces.protocols.protocol import Protocol

# BEGIN GENERATED
READ_RESULT = 0x0D
COMBINATION = 0x12
SECTIONS = {0x0001: (0x000, 4)}
# END GENERATED
FINAL = 0x80
ACK = 0x20
CODE_MASK = 0x1F


class NspProtocol(Protocol):
    """Join the parts of READ RESULT and COMBINATION replies (see the module docstring)."""

    def __init__(self, allow_empty_data=None):
        super().__init__(allow_empty_data)
        self.held = None  # (header bytes, first address or count, joined bytes) of an unfinished reply
        self.mask = None  # section mask of the last COMBINATION written, until its reply
        self.ready = []  # messages to pass on, one per read

    def reset(self):
        super().reset()
        self.held = None
        self.mask = None
        self.ready = []

    def write_data(self, data, extra=None):
        if len(data) in (7, 8) and data[2] & (CODE_MASK | ACK) == COMBINATION:
            self.mask = int.from_bytes(bytes(data[4:]), "little")
        return super().write_data(data, extra)

    def read_data(self, data, extra=None):
        while _ours(data):
            self.ready.extend(self._join(bytes(data)))
            if self.ready:
                data = b""
                break
            # The interface would wait for new bytes after a STOP, though the protocols below
            # may already hold the next part: take it from them.
            data, extra = self._next_below(extra)
        if data == "DISCONNECT":
            return data, extra
        if isinstance(data, str):  # STOP: nothing more below
            data = b""
        if self.ready:  # what is ready first (the blank-string read of every packet drains it)
            if data:
                self.ready.append(bytes(data))
            return self.ready.pop(0), extra
        return super().read_data(data, extra)

    def _join(self, data):
        """The messages to pass on (none while a reply is unfinished: the part is held)."""
        code = data[2] & CODE_MASK
        if not data[2] & ACK:  # a refusal (COMBINATION's failure reply, a NACK): one message
            self.held = None
            if code == COMBINATION:
                self.mask = None
            return [data]
        if len(data) < 5:
            return [data]
        start, body = int.from_bytes(data[3:5], "little"), data[5:]
        held, self.held = self.held, None
        if held is not None and held[0][2] & CODE_MASK == code and held[1] + len(held[2]) == start:
            start, body = held[1], held[2] + body
        if not data[2] & FINAL:
            self.held = (data[:3], start, body)
            return []
        if code == COMBINATION:
            mask, self.mask = self.mask, None
            return self._sections(data[:3], mask, start, body)
        return [data[:3] + start.to_bytes(2, "little") + body]

    def _sections(self, header, mask, start, body):
        """A whole COMBINATION reply as one message per section of ``mask`` (see the docstring)."""
        sections = sorted(section for bit, section in SECTIONS.items() if mask is not None and mask & bit)
        if mask is None or start != 0 or len(body) != sum(length for _, length in sections):
            return [header + start.to_bytes(2, "little") + body]
        if not sections:
            return [header]
        out, more = [], header[:2] + bytes((header[2] & ~FINAL,))
        for i, (address, length) in enumerate(sections):
            head = header if i == len(sections) - 1 else more
            out.append(head + address.to_bytes(2, "little") + body[:length])
            body = body[length:]
        return out

    def _next_below(self, extra):
        """The next message the protocols below this one have buffered ("STOP" if none)."""
        protocols = self.interface.read_protocols if self.interface is not None else [self]
        data = b""
        for protocol in protocols[: protocols.index(self)]:
            data, extra = protocol.read_data(data, extra)
            if isinstance(data, str):
                return data, extra
        return (data, extra) if data else ("STOP", extra)


def _ours(data):
    """A reply message this protocol joins (READ RESULT or COMBINATION)."""
    return not isinstance(data, str) and len(data) >= 3 and data[2] & CODE_MASK in (READ_RESULT, COMBINATION)
