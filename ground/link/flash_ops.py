"""The ground side of the FLASH command (code 0x06 in maintenance mode; docs/ICD.md section 15).

:func:`flash` sends one subcommand through a :class:`~ground.link.client.Client` and returns its
reply after byte 0; a failure reply (syntax, ECC or operation failed) raises :class:`FlashFailed`
with its kind and page. The client reads every NACK of code 0x06 as our NACK layout (the CRC's);
a FLASH failure reply is recognised here from the raw reply, by its trailing kind byte (1-3,
never a text byte).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from protocol import flash, nsp, slip
from protocol.commands import Code, PayloadError
from protocol.flash import Failure, Sub

if TYPE_CHECKING:
    from ground.link.client import Client

MAINTENANCE_ADDRESS = 0x00004000  #: INIT with it enters maintenance mode (ours; firmware_model.device.nand)
#: subcommands a client may repeat on a timeout (they change nothing but read counts)
IDEMPOTENT = frozenset({Sub.READ_BUFFER, Sub.FIND_BAD_BLOCKS, Sub.CRC_BUFFER, Sub.CRC_RAM, Sub.WRITE_BUFFER})


class FlashFailed(Exception):
    """A FLASH subcommand's failure reply."""

    def __init__(self, sub: int, echo: bytes, kind: Failure, page: int):
        name = Sub(sub).name if sub in tuple(Sub) else str(sub)
        super().__init__(f"FLASH {name} failed: {kind.name.lower()} (page {page})")
        self.sub, self.echo, self.kind, self.page = sub, echo, kind, page


def flash_command(client: Client, sub: Sub, *fields: int, data: bytes = b"", long: bool = False) -> bytes:
    """Send FLASH ``sub`` with ``fields`` (and ``data`` for Write Page Buffer); its reply after
    byte 0. :class:`FlashFailed` for a failure reply; the client's own errors otherwise (a NACK
    WRONG_MODE outside maintenance mode, BUSY while a read disturbance test runs)."""
    payload = flash.command(sub, *fields, data=data, long=long)
    try:
        parts = client.transact(Code.CRC, payload, idempotent=sub in IDEMPOTENT, timeout=max(client.timeout, 5.0))
    except Exception:
        failure = _failure(client)
        if failure is not None:
            raise failure from None
        raise
    return parts[-1].data[1:]


def _failure(client: Client) -> FlashFailed | None:
    """The FLASH failure reply among the bytes of the last exchange, if it was one."""
    for event in slip.Decoder(nsp.MAX_MESSAGE).feed(client.last_exchange[1]):
        if not isinstance(event, slip.Frame):
            continue
        try:
            msg = nsp.decode(event.data)
        except nsp.MessageError:
            continue
        if msg.ack or msg.code != Code.CRC or msg.src != client.device_address:
            continue
        try:
            sub, echo, kind, page = flash.unpack_failure(msg.data)
        except (ValueError, PayloadError):
            return None
        return FlashFailed(sub, echo, kind, page)
    return None
