"""The device's slots and resumable transfers into them (docs/ICD.md §9): the slot handlers that
check and install a committed image, and the XFER BEGIN / DATA / STATUS / COMMIT / ABORT and
SLOT INFO commands over a :class:`~firmware_model.device.slots.SlotStore`."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from firmware_model.device.dispatch import Refused
from firmware_model.device.slots import Conflict, SlotStore
from protocol import nsp
from protocol.catalog_patch import PatchError, PatchReason, apply_patch, parse_patch
from protocol.commands import (
    MAX_SLOT_BYTES,
    MAX_STATUS_RANGES,
    NackReason,
    Slot,
    SlotImage,
    SlotRejected,
    SlotRequest,
    XferBegin,
    XferData,
    XferDataAck,
    XferState,
    XferStatus,
)
from protocol.crc import crc32

log = logging.getLogger("firmware_model.device.device")  # one logger for the device shell


@dataclass
class SlotHandler:
    """How a slot checks and installs a committed image.

    ``validate(data)`` raises :class:`~protocol.commands.SlotRejected` (code >= 0x0100, message)
    for an unacceptable image; ``activate(data)`` returns the installed object the solver sees;
    ``info(data, obj)`` returns the SLOT INFO blob (bytes).
    """

    validate: Callable[[bytes], None]
    activate: Callable[[bytes], Any] = bytes
    info: Callable[[bytes, Any], bytes] = lambda data, obj: b""
    #: a patch slot: the slot whose active image this slot's images patch (None: an ordinary slot)
    patches: int | None = None
    #: ``apply(active image of the patched slot or None, patch)`` -> its new image; raises SlotRejected
    apply: Callable[[bytes | None, bytes], bytes] | None = None
    #: ``applied(active image of the patched slot, patch)``: is that image already what the patch
    #: makes (a COMMIT cut after it installed the result, before it dropped the transfer)?
    applied: Callable[[bytes, bytes], bool] | None = None


def _reject_empty(data: bytes) -> None:
    if not data:
        raise SlotRejected(0x0100, "empty image")


def _params_validate(data: bytes) -> None:
    try:
        obj = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise SlotRejected(0x0101, f"parameter set is not UTF-8 JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise SlotRejected(0x0102, "parameter set must be a JSON object")


def _patch_validate(data: bytes) -> None:
    try:
        parse_patch(data)
    except PatchError as exc:
        raise SlotRejected(int(exc.code), exc.message) from None


def _patch_apply(base: bytes | None, patch: bytes) -> bytes:
    if base is None:
        raise SlotRejected(int(PatchReason.NO_BASE), "no active catalog to patch (upload one to slot 0)")
    try:
        return apply_patch(base, patch)
    except PatchError as exc:
        raise SlotRejected(int(exc.code), exc.message) from None


def _patch_applied(active: bytes, patch: bytes) -> bool:
    try:
        base_len, _, result_crc, _ = parse_patch(patch)
    except PatchError:
        return False
    return len(active) == base_len and crc32(active) == result_crc


def patch_slot_handler(target: int) -> SlotHandler:
    """A slot whose committed image is a ``protocol.catalog_patch`` of slot ``target``'s active image:
    applied to a copy, its CRC-32s checked and the result validated by ``target``'s handler before
    it replaces ``target``'s image (docs/ICD.md section 9)."""
    return SlotHandler(_patch_validate, patches=target, apply=_patch_apply, applied=_patch_applied)


def default_slots() -> dict[int, SlotHandler]:
    """Handlers used until the real catalog/frame validators are plugged in: slots 0 and 1 accept
    any non-empty image (kept as bytes); slot 2 accepts a JSON object (activated as a dict); slot
    3 patches slot 0."""

    def blob(data: bytes, obj: Any) -> bytes:
        return json.dumps({"length": len(data)}).encode()

    return {
        Slot.CATALOG: SlotHandler(_reject_empty, bytes, blob),
        Slot.FRAME: SlotHandler(_reject_empty, bytes, blob),
        Slot.PARAMS: SlotHandler(
            _params_validate,
            lambda d: json.loads(d.decode("utf-8")),
            lambda d, obj: json.dumps({"keys": sorted(obj)}).encode(),
        ),
        Slot.CATALOG_PATCH: patch_slot_handler(Slot.CATALOG),
    }


class Transfers:
    """The slots of one device: ``store`` persists images and pending transfers, ``slots`` maps
    slot numbers to handlers (over :func:`default_slots`), ``objects`` holds each slot's
    activated object; ``frame_pending`` is set when a frame is committed to slot 1 and cleared
    by the GO that takes it."""

    def __init__(self, store: SlotStore | None, slots: Mapping[int, SlotHandler] | None):
        self.store = store if store is not None else SlotStore(None)
        self.slots = {**default_slots(), **(slots or {})}
        self.objects: dict[int, Any] = {}
        self.frame_pending = False

    def activate_stored(self) -> None:
        """Validate and activate every image the store holds (at start)."""
        for slot in self.store.active_slots():
            data = self.store.active(slot)
            assert data is not None  # active_slots() lists the slots that hold an image
            if slot not in self.slots:
                log.warning("device: slot %d in the state directory is not a slot of this device; ignored", slot)
                continue
            try:
                self._install(slot, data)
            except Exception as exc:  # a persisted image the current validator refuses
                log.warning("device: slot %d image not activated at start: %s", slot, " ".join(str(exc).split()))

    def _install(self, slot: int, data: bytes) -> None:
        handler = self.slots[slot]
        handler.validate(data)
        self.objects[slot] = handler.activate(data)
        log.info("device: slot %d: image of %d bytes activated", slot, len(data))

    def _handler(self, slot: int) -> SlotHandler:
        if slot not in self.slots:
            raise Refused(NackReason.BAD_SLOT, f"no slot {slot} (slots: {sorted(self.slots)})")
        return self.slots[slot]

    def _status(self, slot: int) -> XferStatus:
        tr = self.store.transfer(slot)
        if tr is None:
            return XferStatus(slot, XferState.NONE)
        missing = tr.missing()
        state = XferState.COMPLETE if tr.complete else XferState.RECEIVING
        return XferStatus(
            slot,
            state,
            tr.length,
            tr.crc32,
            tr.contiguous,
            tr.received,
            len(missing),
            tuple(missing[:MAX_STATUS_RANGES]),
        )

    # ------------------------------------------------------------------ commands

    def xfer_begin(self, req: XferBegin) -> bytes:
        self._handler(req.slot)
        if not 1 <= req.length <= MAX_SLOT_BYTES:
            raise Refused(NackReason.TOO_LARGE, f"length {req.length} outside 1..{MAX_SLOT_BYTES}")
        try:
            self.store.begin(req.slot, req.length, req.crc32)
        except OSError as exc:
            raise Refused(NackReason.STORAGE_ERROR, str(exc)) from None
        return self._status(req.slot).pack()

    def xfer_data(self, req: XferData) -> bytes:
        self._handler(req.slot)
        tr = self.store.transfer(req.slot)
        if tr is None:
            raise Refused(NackReason.NO_TRANSFER, f"no transfer in progress for slot {req.slot} (send BEGIN)")
        if req.offset + len(req.data) > tr.length:
            raise Refused(NackReason.OUT_OF_RANGE, f"bytes {req.offset}+{len(req.data)} beyond length {tr.length}")
        try:
            tr = self.store.write(req.slot, req.offset, req.data)
        except Conflict as exc:
            raise Refused(
                NackReason.CONFLICT,
                f"byte {exc.offset} differs from the one already received there: received bytes are write-once, "
                f"the transfer keeps them (ABORT to start again)",
            ) from None
        except OSError as exc:
            raise Refused(NackReason.STORAGE_ERROR, str(exc)) from None
        return XferDataAck(req.slot, tr.contiguous).pack()

    def xfer_status(self, req: SlotRequest) -> bytes:
        self._handler(req.slot)
        return self._status(req.slot).pack()

    def xfer_abort(self, req: SlotRequest) -> bytes:
        self._handler(req.slot)
        self.store.drop_transfer(req.slot)
        return self._status(req.slot).pack()

    def xfer_commit(self, req: SlotRequest) -> bytes:
        handler = self._handler(req.slot)
        tr = self.store.transfer(req.slot)
        if tr is None:
            raise Refused(NackReason.NO_TRANSFER, f"no transfer in progress for slot {req.slot}")
        if not tr.complete:
            raise Refused(NackReason.INCOMPLETE, f"{tr.length - tr.received} of {tr.length} bytes missing")
        try:
            image = self.store.transfer_bytes(req.slot)
        except OSError as exc:
            raise Refused(NackReason.STORAGE_ERROR, str(exc)) from None
        if len(image) != tr.length or crc32(image) != tr.crc32:
            self.store.drop_transfer(req.slot)
            raise Refused(
                NackReason.CRC_MISMATCH,
                f"image CRC-32 0x{crc32(image):08X} != announced 0x{tr.crc32:08X}; transfer discarded",
            )
        target = req.slot if handler.patches is None else handler.patches
        current = self.store.active(target) if target in self.objects else None
        try:
            handler.validate(image)
            if handler.patches is not None:  # the whole new image is built and checked before anything changes
                assert handler.apply is not None
                image = handler.apply(current, image)
                self.slots[target].validate(image)
            obj = self.slots[target].activate(image)
        except SlotRejected as exc:
            if exc.code == PatchReason.BASE_MISMATCH and current is not None and handler.applied is not None:
                if handler.applied(current, image):  # this patch's result is active already: the commit that
                    log.warning(  # installed it was cut before it dropped the transfer (a kill, a power loss)
                        "device: slot %d: the patch's result (CRC-32 0x%08X) is slot %d's active image already; "
                        "the transfer is dropped",
                        req.slot,
                        crc32(current),
                        target,
                    )
                    self.store.drop_transfer(req.slot)
                    return SlotImage(req.slot, True, len(current), crc32(current)).pack()
            self.store.drop_transfer(req.slot)
            raise Refused(exc.code, exc.message) from None
        except Exception as exc:
            self.store.drop_transfer(req.slot)
            raise Refused(NackReason.BAD_PARAMETER, f"slot {req.slot} image refused: {exc}") from None
        try:
            self.store.set_active(target, image)
        except OSError as exc:
            raise Refused(NackReason.STORAGE_ERROR, str(exc)) from None
        self.objects[target] = obj
        if target == Slot.FRAME:  # consumed by the next GO before the capture source
            self.frame_pending = True
        self.store.drop_transfer(req.slot)
        return SlotImage(req.slot, True, len(image), crc32(image)).pack()

    def slot_info(self, req: SlotRequest) -> bytes:
        handler = self._handler(req.slot)
        image = self.store.active(req.slot)
        if image is None or req.slot not in self.objects:
            return SlotImage(req.slot, False, 0, 0).pack()
        blob = bytes(handler.info(image, self.objects[req.slot]))[: nsp.MAX_DATA - 10]
        return SlotImage(req.slot, True, len(image), crc32(image), blob).pack()
