"""The functional processor's NAND flash and maintenance mode (docs/ICD.md section 15).

:class:`Nand` models an SLC NAND of :data:`~protocol.flash.BLOCKS` blocks of 64 pages
(:data:`~protocol.flash.PAGE_BYTES` each): erased pages read 0xFF, a page is programmed once
between erases, a block is erased whole. Faults as the ICD's "Flash Memory Issues" (page 1-35923)
describe them:

* **factory bad blocks**: a few blocks, drawn from the seed, carry the factory bad-block flag on
  their first page (Find NAND Bad Blocks counts them); the boot blocks and the application image
  are good;
* **ECC** per page (ours: the pages do not give the code's span): one flipped bit is corrected
  on read, two or more are detected and uncorrectable;
* **read disturbance**: every :attr:`Nand.disturb_reads` page reads of a block flip one bit in one
  of its programmed pages (the page drawn from the seed); an erase clears the block's count, and
  Rewrite NAND (erase and reprogram from the corrected data) removes the flips;
* **bad-block relocation**: an erase or program of a bad block (factory, grown, or one a fault
  script made fail) maps the block to a spare from the top :data:`SPARE_BLOCKS` blocks and marks
  it bad; with no spare left the operation fails.

The flash error counts (hardware telemetry +0x00) are the pages whose last read found a corrected
error, the pages whose last read found an uncorrectable one (both until the page is rewritten or
erased), and the bad blocks.

With a state directory the NAND persists crash-safe: one file per block holding the block's pages
and metadata, and ``meta.json`` with the relocation table, each written to a temporary file,
fsynced and renamed (as the slots are). An erase or program is committed when its files are
renamed, before the reply: a kill -9 during one leaves the block as it was or as it became,
never torn. Read counts are written at the end of each FLASH command (a crash loses the reads
since).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from firmware_model.device.dispatch import Refused
from firmware_model.device.slots import atomic_write
from protocol import flash
from protocol.commands import CrcReply, CrcRequest, MemorySpace, NackReason
from protocol.crc import crc16_mcrf4xx, crc32
from protocol.flash import PAGE_BYTES, PAGES_PER_BLOCK, Failure, FlashFailure, Sub

log = logging.getLogger(__name__)

SPARE_BLOCKS = 256  #: ours: the top blocks, kept for relocation (not addressable by commands)
LOGICAL_BLOCKS = flash.BLOCKS - SPARE_BLOCKS
LOGICAL_PAGES = LOGICAL_BLOCKS * PAGES_PER_BLOCK
FACTORY_BAD = 20  #: ours: factory bad blocks of a new part (datasheets allow up to 2 %)
DISTURB_READS = 100_000  #: ours: page reads of a block per flipped bit (literature: ~1e6 reads per bit)
ENDURANCE = 100_000  #: program/erase cycles of a block (page 1-35923); beyond it the block fails
APP_BLOCK = 0x8000  #: the application image's first block (page 1-35916)
APP_PAGES = 4 * PAGES_PER_BLOCK  #: ours: a 512 KiB application image
CATALOG_BLOCK = 0x9000  #: ours: where the catalog image is programmed (the pages do not place it)
CATALOG_MAGIC = b"ST16CAT1"  #: ours: the catalog region's first page: magic, u32 length, u32 CRC-32
BOOT_HEADER = b"ST16BOOT"  #: ours: the Configuration Header's magic (its content is not visible)
MAINTENANCE_ADDRESS = 0x00004000  #: ours: INIT with this address enters maintenance mode
ERASED = b"\xff" * PAGE_BYTES
DISTURB_MESSAGE_CYCLES = 1000  #: a progress message in EDAC every 1000 read cycles (page 1-35915)
ICD_PAGE_READ_S = 1.0 / 9000.0  #: the read disturbance test's pace on the real unit (page 1-35915)


def _image(name: bytes, n: int) -> bytes:
    """``n`` deterministic bytes standing for a factory image (the boot code, the application)."""
    return np.random.default_rng(list(hashlib.sha256(name).digest()[:8])).bytes(n)


class EccError(Exception):
    def __init__(self, page: int):
        super().__init__(f"uncorrectable ECC error in page {page}")
        self.page = page


class Nand:
    """The NAND of one head; ``root`` its folder (None: in memory); ``seed`` draws the factory bad
    blocks and where disturbance flips bits."""

    def __init__(self, root: str | os.PathLike | None = None, seed: int = 0, disturb_reads: int = DISTURB_READS):
        self.root = Path(root) if root is not None else None
        self.seed = seed
        self.disturb_reads = disturb_reads
        self.pages: dict[int, bytes] = {}  #: physical page -> data (programmed pages only)
        self.errors: dict[int, int] = {}  #: physical page -> flipped bits held
        self.seen: dict[int, int] = {}  #: physical page -> 1 corrected / 2 uncorrectable at its last read
        self.reads: dict[int, int] = {}  #: physical block -> page reads since its erase
        self.erases: dict[int, int] = {}  #: physical block -> erase cycles
        self.relocation: dict[int, int] = {}  #: logical block -> physical spare block
        self.grown_bad: set[int] = set()  #: physical blocks found bad in use
        self.failing: set[int] = set()  #: physical blocks whose next erase or program fails (fault scripts)
        rng = np.random.default_rng([seed, 45])
        reserved = set(range(4)) | set(range(APP_BLOCK, APP_BLOCK + APP_PAGES // PAGES_PER_BLOCK))
        drawn = [int(b) for b in rng.choice(flash.BLOCKS, FACTORY_BAD + 8, replace=False) if int(b) not in reserved]
        self.factory_bad = frozenset(drawn[:FACTORY_BAD])
        self._dirty: set[int] = set()
        if self.root is not None and (self.root / "meta.json").exists():
            self._load()
        else:
            self._factory()

    # ------------------------------------------------------------------ addressing

    def physical_block(self, block: int) -> int:
        return self.relocation.get(block, block)

    def physical_page(self, page: int) -> int:
        block, offset = divmod(page, PAGES_PER_BLOCK)
        return self.physical_block(block) * PAGES_PER_BLOCK + offset

    def is_bad(self, physical: int) -> bool:
        return physical in self.factory_bad or physical in self.grown_bad

    # ------------------------------------------------------------------ operations

    def read_page(self, page: int) -> bytes:
        """The data of logical ``page`` after ECC (a single flipped bit corrected); EccError when
        uncorrectable. Each read disturbs its block."""
        pp = self.physical_page(page)
        self.disturb(pp // PAGES_PER_BLOCK, 1)
        return self._check(pp, page)

    def _check(self, pp: int, page: int) -> bytes:
        held = self.errors.get(pp, 0)
        if held >= 2 or self.is_bad(pp // PAGES_PER_BLOCK):
            self.seen[pp] = 2
            raise EccError(page)
        if held == 1:
            self.seen[pp] = 1
        else:
            self.seen.pop(pp, None)
        return self.pages.get(pp, ERASED)

    def erased(self, page: int) -> bool:
        return self.physical_page(page) not in self.pages

    def disturb(self, physical_block: int, reads: int) -> None:
        """Count ``reads`` page reads of a block; flip the bits they cost."""
        before = self.reads.get(physical_block, 0)
        after = before + reads
        self.reads[physical_block] = after
        self._dirty.add(physical_block)
        first, last = before // self.disturb_reads, after // self.disturb_reads
        if last == first:
            return
        base = physical_block * PAGES_PER_BLOCK
        programmed = [p for p in range(base, base + PAGES_PER_BLOCK) if p in self.pages]
        if not programmed:
            return
        for k in range(first + 1, last + 1):
            pick = int(np.random.default_rng([self.seed, physical_block, k]).integers(len(programmed)))
            pp = programmed[pick]
            self.errors[pp] = self.errors.get(pp, 0) + 1

    def erase_block(self, block: int) -> int:
        """Erase logical ``block`` (relocating a bad one); the physical block erased. FlashFailure
        (operation) with no spare left."""
        phys = self._usable(block, copy=False)
        self._clear(phys)
        self.erases[phys] = self.erases.get(phys, 0) + 1
        if self.erases[phys] >= ENDURANCE:
            self.failing.add(phys)  # worn out: its next erase or program fails
        self._commit(phys)
        return phys

    def write_page(self, page: int, data: bytes) -> None:
        """Program logical ``page`` with ``data`` (PAGE_BYTES); FlashFailure when it is not erased."""
        self.write_pages(page, [data])

    def write_pages(self, first: int, datas: list[bytes]) -> None:
        """Program the logical pages from ``first`` with ``datas`` (PAGE_BYTES each), in order; each
        block is committed once, after its last page (a crash leaves every block as it was or
        as it became). FlashFailure at the first page not erased (the blocks before it stay
        programmed)."""
        pending = None  # the physical block programmed and not yet committed
        try:
            for page, data in enumerate(datas, first):
                block = page // PAGES_PER_BLOCK
                if not self.erased(page):
                    raise FlashFailure(Sub.WRITE_PAGE, b"", Failure.OPERATION, page, f"page {page} is not erased")
                phys = self._usable(block, copy=True)
                if pending is not None and phys != pending:
                    self._commit(pending)
                pending = phys
                pp = phys * PAGES_PER_BLOCK + page % PAGES_PER_BLOCK
                self.pages[pp] = bytes(data)
                self.errors.pop(pp, None)
                self.seen.pop(pp, None)
        finally:
            if pending is not None:
                self._commit(pending)

    def _usable(self, block: int, copy: bool) -> int:
        """The physical block to erase or program for logical ``block``: relocated to a spare when
        it is bad or failing (its programmed pages copied when ``copy``)."""
        phys = self.physical_block(block)
        if not (self.is_bad(phys) or phys in self.failing):
            return phys
        spare = next(
            (
                b
                for b in range(flash.BLOCKS - 1, LOGICAL_BLOCKS - 1, -1)
                if not self.is_bad(b) and b not in self.failing and b not in self.relocation.values()
            ),
            None,
        )
        if spare is None:
            raise FlashFailure(Sub.ERASE_BLOCK, b"", Failure.OPERATION, block * PAGES_PER_BLOCK, "no spare block left")
        self._clear(spare)
        if copy:
            for off in range(PAGES_PER_BLOCK):
                old = phys * PAGES_PER_BLOCK + off
                if old in self.pages and self.errors.get(old, 0) < 2:
                    self.pages[spare * PAGES_PER_BLOCK + off] = self.pages[old]
        if phys in self.failing:
            self.failing.discard(phys)
        if phys not in self.factory_bad:
            self.grown_bad.add(phys)
        self.relocation[block] = spare
        self._commit(spare)
        self._save_meta()  # the commit point of the relocation
        log.info("nand: block %d relocated to spare %d", block, spare)
        return spare

    def _clear(self, phys: int) -> None:
        base = phys * PAGES_PER_BLOCK
        for pp in range(base, base + PAGES_PER_BLOCK):
            self.pages.pop(pp, None)
            self.errors.pop(pp, None)
            self.seen.pop(pp, None)
        self.reads[phys] = 0

    def rewrite(self, first_block: int, last_block: int) -> tuple[int, int, int]:
        """Rewrite NAND: read each programmed block of the range, erase it and program it again
        from the corrected data, the block with the most errors first. (blocks rewritten, bits
        corrected, first uncorrectable page + 1 or 0). An uncorrectable page is rewritten as read
        (its two flipped bits become its data)."""
        blocks = []
        for b in range(first_block, last_block + 1):
            phys = self.physical_block(b)
            base = phys * PAGES_PER_BLOCK
            held = [(pp, self.errors.get(pp, 0)) for pp in range(base, base + PAGES_PER_BLOCK) if pp in self.pages]
            if held:
                blocks.append((-sum(e for _, e in held), b, phys, held))
        blocks.sort()
        corrected, bad_page = 0, 0
        for _, b, phys, held in blocks:
            image = {}
            for pp, e in held:
                data = self.pages[pp]
                if e >= 2:
                    data = _flip(data, self.seed, pp)
                    bad_page = bad_page or (b * PAGES_PER_BLOCK + pp % PAGES_PER_BLOCK + 1)
                else:
                    corrected += e
                image[pp % PAGES_PER_BLOCK] = data
            phys = self.erase_block(b)
            for off, data in image.items():
                self.pages[phys * PAGES_PER_BLOCK + off] = data
            self._commit(phys)
        return len(blocks), corrected, bad_page

    # ------------------------------------------------------------------ telemetry

    def error_counts(self) -> tuple[int, int, int]:
        """(pages with a corrected error, pages with an uncorrectable error, bad blocks): the
        hardware telemetry's flash error counts."""
        corrected = sum(1 for v in self.seen.values() if v == 1)
        return corrected, len(self.seen) - corrected, len(self.factory_bad) + len(self.grown_bad)

    # ------------------------------------------------------------------ persistence

    def _factory(self) -> None:
        """A new part: the boot block (and its backups) and the application image programmed."""
        boot = boot_image(b"\x00" * flash.BOOT_BYTES)
        for start in flash.BOOT_PAGES:
            for i in range(0, len(boot), PAGE_BYTES):
                self.pages[start + i // PAGE_BYTES] = boot[i : i + PAGE_BYTES].ljust(PAGE_BYTES, b"\xff")
        app = _image(b"ST16-EMU application image", APP_PAGES * PAGE_BYTES)
        for i in range(APP_PAGES):
            self.pages[APP_BLOCK * PAGES_PER_BLOCK + i] = app[i * PAGE_BYTES : (i + 1) * PAGE_BYTES]
        if self.root is not None:
            self.root.mkdir(parents=True, exist_ok=True)
            for b in {pp // PAGES_PER_BLOCK for pp in self.pages}:
                self._commit(b)
            self._save_meta()

    def _block_path(self, phys: int) -> Path:
        assert self.root is not None
        return self.root / f"block-{phys:05x}.bin"

    def _commit(self, phys: int) -> None:
        """Write block ``phys`` (pages and metadata) crash-safe."""
        self._dirty.discard(phys)
        if self.root is None:
            return
        base = phys * PAGES_PER_BLOCK
        offsets = [pp - base for pp in range(base, base + PAGES_PER_BLOCK) if pp in self.pages]
        head = {
            "programmed": offsets,
            "errors": {str(pp - base): e for pp in range(base, base + PAGES_PER_BLOCK) if (e := self.errors.get(pp))},
            "seen": {str(pp - base): s for pp in range(base, base + PAGES_PER_BLOCK) if (s := self.seen.get(pp))},
            "reads": self.reads.get(phys, 0),
            "erases": self.erases.get(phys, 0),
        }
        raw = json.dumps(head).encode()
        body = b"".join(self.pages[base + off] for off in offsets)
        atomic_write(self._block_path(phys), struct.pack("<I", len(raw)) + raw + body + struct.pack("<I", crc32(body)))

    def _save_meta(self) -> None:
        if self.root is None:
            return
        meta = {
            "seed": self.seed,
            "relocation": {str(k): v for k, v in self.relocation.items()},
            "grown_bad": sorted(self.grown_bad),
            "failing": sorted(self.failing),
        }
        atomic_write(self.root / "meta.json", json.dumps(meta).encode())

    def flush_reads(self) -> None:
        """After a solve's reads: write only the blocks where an error was found (their error
        state must survive a restart); the read counts of the others wait for the next flush."""
        for phys in sorted(self._dirty):
            base = phys * PAGES_PER_BLOCK
            if any(base <= pp < base + PAGES_PER_BLOCK for pp in self.seen):
                self._commit(phys)

    def flush(self) -> None:
        """Write the blocks whose read counts changed (the end of a FLASH command)."""
        for phys in sorted(self._dirty):
            self._commit(phys)
        self._save_meta()

    def _load(self) -> None:
        assert self.root is not None
        meta = json.loads((self.root / "meta.json").read_text())
        self.relocation = {int(k): int(v) for k, v in meta.get("relocation", {}).items()}
        self.grown_bad = {int(b) for b in meta.get("grown_bad", [])}
        self.failing = {int(b) for b in meta.get("failing", [])}
        for path in sorted(self.root.glob("block-*.bin")):
            phys = int(path.stem.split("-")[1], 16)
            raw = path.read_bytes()
            (n,) = struct.unpack_from("<I", raw)
            head = json.loads(raw[4 : 4 + n])
            body = raw[4 + n : -4]
            if struct.unpack_from("<I", raw, len(raw) - 4)[0] != crc32(body):
                log.warning("nand: %s damaged: its block reads as bad", path.name)
                self.grown_bad.add(phys)
                continue
            base = phys * PAGES_PER_BLOCK
            for i, off in enumerate(head["programmed"]):
                self.pages[base + off] = body[i * PAGE_BYTES : (i + 1) * PAGE_BYTES]
            self.errors.update({base + int(k): int(v) for k, v in head.get("errors", {}).items()})
            self.seen.update({base + int(k): int(v) for k, v in head.get("seen", {}).items()})
            self.reads[phys] = int(head.get("reads", 0))
            self.erases[phys] = int(head.get("erases", 0))


def boot_image(sram: bytes) -> bytes:
    """Make Boot Block's bytes: the Configuration Header (ours: magic, u32 length, u32 CRC-32)
    prepended to 32 kB of SRAM."""
    body = sram[: flash.BOOT_BYTES].ljust(flash.BOOT_BYTES, b"\x00")
    return BOOT_HEADER + struct.pack("<II", len(body), crc32(body)) + body


def _flip(data: bytes, seed: int, pp: int) -> bytes:
    """``data`` with the two bits an uncorrectable page holds flipped (where: drawn from the seed)."""
    out = bytearray(data)
    for bit in np.random.default_rng([seed, pp, 2]).choice(len(out) * 8, 2, replace=False):
        out[int(bit) // 8] ^= 1 << (int(bit) % 8)
    return bytes(out)


class Maintenance:
    """Maintenance mode and the FLASH command of one device. ``active()`` says whether the
    tracker is in maintenance mode; ``crc(request)`` is the supervisor's CRC (what 0x06 means
    outside it); ``ram(address, length)`` reads the memory map for CRC RAM and Make Boot Block;
    ``message(text)`` leaves a functional processor message in EDAC; ``lock`` is the device's."""

    def __init__(
        self,
        nand: Nand,
        lock: threading.RLock,
        crc: Callable[[CrcRequest], bytes],
        ram: Callable[[int, int], bytes],
        message: Callable[[str], None],
    ):
        self.nand = nand
        self.entered = False  #: INIT MAINTENANCE_ADDRESS in bootloader mode; cleared by INIT 0x2000, a boot, a reset
        self.buffer = bytearray(ERASED)  #: the page buffer
        self._lock = lock
        self._cond = threading.Condition(lock)
        self._crc = crc
        self._ram = ram
        self._message = message
        self.busy = False  #: a read disturbance test runs: the functional processor does not answer
        self.aborted = False
        self.pace_s = 0.0  #: seconds per page read in the disturbance test (0: compute speed; ICD_PAGE_READ_S)

    def reset(self) -> None:
        """A reset of the functional processor: maintenance mode left, a disturbance test aborted."""
        self.entered = False
        if self.busy:
            self.aborted = True
        self.buffer = bytearray(ERASED)

    # ------------------------------------------------------------------ boot from NAND

    def boot_check(self) -> None:
        """What a GO with LOAD_NAND in bootloader mode reads from the NAND (page 1-35916): the
        boot block (the first of pages 0, 64, 128, 192 whose pages all pass ECC: "searched, in
        order, if the primary boot block suffers an irrecoverable ECC error", page 1-35914), then
        the application image at block 0x8000. Refused (EDAC_UNCORRECTABLE) when no boot block or
        the image cannot be read: the functional processor does not start. Every page read
        disturbs its block and counts in the flash error telemetry."""
        nand = self.nand
        boot_pages = -(-(flash.BOOT_BYTES + len(BOOT_HEADER) + 8) // PAGE_BYTES)
        try:
            with self._lock:
                for start in flash.BOOT_PAGES:
                    try:
                        for page in range(start, start + boot_pages):
                            nand.read_page(page)
                        break
                    except EccError:
                        continue
                else:
                    raise Refused(
                        NackReason.EDAC_UNCORRECTABLE,
                        "boot from NAND failed: every boot block (pages 0, 64, 128, 192) has an uncorrectable ECC error",
                    )
                first = APP_BLOCK * PAGES_PER_BLOCK
                for page in range(first, first + APP_PAGES):
                    try:
                        nand.read_page(page)
                    except EccError as exc:
                        raise Refused(
                            NackReason.EDAC_UNCORRECTABLE,
                            f"boot from NAND failed: the application image has an uncorrectable ECC error in page {exc.page}",
                        ) from None
        finally:
            nand.flush()

    # ------------------------------------------------------------------ the catalog in the NAND

    def store_catalog(self, image: bytes | None) -> None:
        """Program the active catalog image into the NAND from :data:`CATALOG_BLOCK` (a header
        page, then the image), unless it is there already: a commit to slot 0 or 3 writes it, as
        the real unit keeps its star, hash and triangle tables in the NAND."""
        if not image:
            return
        nand = self.nand
        first = CATALOG_BLOCK * PAGES_PER_BLOCK
        header = CATALOG_MAGIC + struct.pack("<II", len(image), crc32(image))
        with self._lock:
            pp = nand.physical_page(first)
            if nand.pages.get(pp, b"")[: len(header)] == header:
                return
            n_pages = 1 + -(-len(image) // PAGE_BYTES)
            for block in range(CATALOG_BLOCK, CATALOG_BLOCK + -(-n_pages // PAGES_PER_BLOCK)):
                nand.erase_block(block)
            pages = [image[i : i + PAGE_BYTES].ljust(PAGE_BYTES, b"\xff") for i in range(0, len(image), PAGE_BYTES)]
            nand.write_pages(first + 1, pages)
            nand.write_page(first, header.ljust(PAGE_BYTES, b"\xff"))  # last: a copy cut short has no header
            nand.flush()

    def read_catalog(self) -> None:
        """The reads of one cycle: every page of the catalog in the NAND (the ICD reads the entire
        star and hash tables each cycle, page 1-35923; ours: the whole image). Refused
        (EDAC_UNCORRECTABLE) at an uncorrectable page; nothing when no catalog is programmed."""
        nand = self.nand
        first = CATALOG_BLOCK * PAGES_PER_BLOCK
        with self._lock:
            head = nand.pages.get(nand.physical_page(first), b"")
            if head[: len(CATALOG_MAGIC)] != CATALOG_MAGIC:
                return
            (length,) = struct.unpack_from("<I", head, len(CATALOG_MAGIC))
            try:
                for page in range(first, first + 1 + -(-length // PAGE_BYTES)):
                    nand.read_page(page)
            except EccError as exc:
                raise Refused(
                    NackReason.EDAC_UNCORRECTABLE,
                    f"the catalog in the NAND has an uncorrectable ECC error in page {exc.page}: rewrite it in "
                    "maintenance mode (Rewrite NAND) or commit the catalog again",
                ) from None
            finally:
                nand.flush_reads()

    # ------------------------------------------------------------------ scripted faults

    def apply_fault(self, fault: Any) -> int:
        """A flash fault of a fault script (docs/ICD.md section 13), applied at load; the pages or
        blocks it struck. ``flash_ecc bits=B count=N``: N programmed pages (drawn from the seed)
        hold B flipped bits; ``flash_bad_block count=N``: N programmed blocks fail at their next
        erase or program (relocated then, counted bad); ``flash_disturb reads=R``: one bit flips
        every R page reads of a block from now on."""
        nand = self.nand
        rng = np.random.default_rng([fault.seed, 45, 1])
        count = int(fault.keys.get("count", 1))
        with self._lock:
            programmed = sorted(nand.pages)
            if fault.name == "flash_ecc":
                picks = [
                    programmed[int(i)] for i in rng.choice(len(programmed), min(count, len(programmed)), replace=False)
                ]
                for pp in picks:
                    nand.errors[pp] = max(nand.errors.get(pp, 0), int(fault.keys["bits"]))
                    nand._dirty.add(pp // PAGES_PER_BLOCK)
                nand.flush()
                return len(picks)
            if fault.name == "flash_bad_block":
                blocks = sorted({pp // PAGES_PER_BLOCK for pp in programmed})
                picks = [blocks[int(i)] for i in rng.choice(len(blocks), min(count, len(blocks)), replace=False)]
                nand.failing.update(picks)
                nand.flush()
                return len(picks)
            if fault.name == "flash_disturb":
                nand.disturb_reads = int(fault.keys["reads"])
                return 1
        raise ValueError(f"not a flash fault: {fault.name}")

    # ------------------------------------------------------------------ 0x06

    def crc_or_flash(self, active: bool, data: bytes) -> Any:
        """Code 0x06: FLASH in maintenance mode (``active``), the supervisor's CRC otherwise (a field
        of a CRC request's 9 bytes is one; another whose byte 0 is a FLASH subcommand is NACKed
        WRONG_MODE naming maintenance mode)."""
        if active:
            return self.flash(data)
        size = CrcRequest.size() if hasattr(CrcRequest, "size") else 9
        if len(data) != size and data and data[0] in tuple(Sub):  # a 9-byte field is a CRC request
            raise Refused(
                NackReason.WRONG_MODE,
                f"FLASH {Sub(data[0]).name} needs maintenance mode (INIT 0x{MAINTENANCE_ADDRESS:08X} in "
                "bootloader mode); outside it 0x06 is the supervisor's CRC",
            )
        return self._crc(CrcRequest.unpack(data))

    def flash(self, data: bytes) -> Any:
        if self.busy:
            raise Refused(NackReason.BUSY, "the functional processor runs a NAND read disturbance test")
        if not data:
            raise Refused(NackReason.BAD_LENGTH, "FLASH needs a subcommand byte")
        try:
            sub = Sub(data[0])
        except ValueError:
            text = f"FLASH subcommand {data[0]} is not documented"
            raise _refusal(data[0], data[1:], FlashFailure(data[0], b"", Failure.SYNTAX, 0, text)) from None
        try:
            return self._run(sub, data[1:])
        except FlashFailure as exc:
            raise _refusal(sub, data[1:], exc) from None
        except EccError as exc:
            raise _refusal(sub, data[1:], FlashFailure(sub, b"", Failure.ECC, exc.page, str(exc))) from None
        finally:
            if sub != Sub.READ_DISTURB_TEST:
                self.nand.flush()

    def _fields(self, sub: Sub, rest: bytes, fmt: str | None = None) -> tuple[int, ...]:
        fmt = fmt or flash.FIELDS[sub]
        if len(rest) != struct.calcsize(fmt):
            raise FlashFailure(
                sub,
                rest,
                Failure.SYNTAX,
                0,
                f"FLASH {sub.name} takes {struct.calcsize(fmt)} bytes after the subcommand",
            )
        return struct.unpack(fmt, rest)

    def _run(self, sub: Sub, rest: bytes) -> Any:
        nand = self.nand
        if sub == Sub.READ_BUFFER:
            fmt = "<HB" if len(rest) == 3 else "<HH"
            offset, count = self._fields(sub, rest, fmt)
            count = count or (256 if fmt == "<HB" else 0)
            if count == 0 or offset + count > PAGE_BYTES:
                raise _syntax(sub, rest, f"buffer bytes {offset}+{count} beyond the {PAGE_BYTES}-byte page buffer")
            return bytes([sub]) + struct.pack("<H", offset) + bytes(self.buffer[offset : offset + count])
        if sub == Sub.WRITE_BUFFER:
            if len(rest) < 3:
                raise _syntax(sub, rest, "Write Page Buffer needs an offset and at least one byte")
            (offset,) = struct.unpack_from("<H", rest)
            payload = rest[2:]
            if offset + len(payload) > PAGE_BYTES:
                raise _syntax(sub, rest[:2], f"bytes {offset}+{len(payload)} beyond the {PAGE_BYTES}-byte page buffer")
            self.buffer[offset : offset + len(payload)] = payload
            return bytes([sub]) + rest
        if sub in (Sub.ERASE_BLOCK, Sub.WRITE_PAGE, Sub.READ_PAGE, Sub.MAKE_BOOT_BLOCK):
            (page,) = self._fields(sub, rest)
            _in_range(sub, rest, page, page)
            if sub == Sub.ERASE_BLOCK:
                nand.erase_block(page // PAGES_PER_BLOCK)
            elif sub == Sub.WRITE_PAGE:
                nand.write_page(page, bytes(self.buffer))
            elif sub == Sub.READ_PAGE:
                self.buffer[:] = nand.read_page(page)
            else:
                if page not in flash.BOOT_PAGES:
                    raise _syntax(sub, rest, f"a boot block starts at page {', '.join(map(str, flash.BOOT_PAGES))}")
                image = boot_image(self._ram(0, flash.BOOT_BYTES))
                nand.erase_block(page // PAGES_PER_BLOCK)
                nand.write_pages(
                    page,
                    [image[i : i + PAGE_BYTES].ljust(PAGE_BYTES, b"\xff") for i in range(0, len(image), PAGE_BYTES)],
                )
            return bytes([sub]) + rest
        if sub == Sub.FIND_BAD_BLOCKS:
            first, last = self._fields(sub, rest)
            _in_range(sub, rest, first, last)
            flagged = [
                b * PAGES_PER_BLOCK
                for b in range(first // PAGES_PER_BLOCK, last // PAGES_PER_BLOCK + 1)
                if b in nand.factory_bad and first <= b * PAGES_PER_BLOCK <= last
            ]
            return bytes([sub]) + rest + struct.pack("<II", len(flagged), flagged[0] if flagged else 0)
        if sub == Sub.CRC_BUFFER:
            self._fields(sub, rest)
            return bytes([sub]) + struct.pack("<H", crc16_mcrf4xx(bytes(self.buffer)))
        if sub == Sub.CRC_NAND:
            first, last = self._fields(sub, rest)
            _in_range(sub, rest, first, last)
            crc = 0xFFFF
            for page in range(first, last + 1):
                if nand.erased(page):
                    raise FlashFailure(sub, rest, Failure.OPERATION, page, f"page {page} is erased")
                crc = crc16_mcrf4xx(nand.read_page(page), crc)
            return bytes([sub]) + rest + struct.pack("<H", crc)
        if sub == Sub.CRC_RAM:
            address, length = self._fields(sub, rest)
            try:
                reply = CrcReply.unpack(self._crc(CrcRequest(MemorySpace.MEMORY, address, length)))
            except Refused as exc:
                raise _syntax(sub, rest, exc.text) from None
            return bytes([sub]) + rest + struct.pack("<H", reply.crc)
        if sub == Sub.READ_DISTURB_TEST:
            return self._disturb_test(rest)
        if sub == Sub.REWRITE_NAND:
            first, last = self._fields(sub, rest)
            _in_range(sub, rest, first, last)
            blocks, corrected, bad = nand.rewrite(first // PAGES_PER_BLOCK, last // PAGES_PER_BLOCK)
            if bad:
                raise FlashFailure(
                    sub, rest, Failure.ECC, bad - 1, f"page {bad - 1} was uncorrectable; rewritten as read"
                )
            return bytes([sub]) + rest + struct.pack("<II", blocks, corrected)
        raise _syntax(sub, rest, f"FLASH subcommand {int(sub)} is not modelled")

    # ------------------------------------------------------------------ read disturbance test

    def _disturb_test(self, rest: bytes) -> Any:
        from firmware_model.device.dispatch import Pending

        sub = Sub.READ_DISTURB_TEST
        start, final, cycles = self._fields(sub, rest)
        _in_range(sub, rest, start, final)
        if final - start + 1 > flash.MAX_DISTURB_PAGES or cycles == 0:
            raise _syntax(sub, rest, f"at most {flash.MAX_DISTURB_PAGES} pages (16 MB) and at least one cycle")
        self.busy, self.aborted = True, False
        outcome: dict[str, Any] = {}
        worker = threading.Thread(
            target=self._disturb_worker, args=(start, final, cycles, outcome), daemon=True, name="nand-disturb"
        )
        worker.start()

        def wait() -> list[bytes]:
            with self._cond:
                while "done" not in outcome:
                    self._cond.wait(0.5)
            if outcome.get("aborted"):
                raise Refused(NackReason.BUSY, "read disturbance test aborted by a reset")
            failed = outcome.get("failed")
            if failed is not None:
                raise _refusal(sub, rest, failed)
            return [bytes([sub]) + struct.pack("<III", start, final, outcome["cycles"])]

        return Pending(wait)

    def _disturb_worker(self, start: int, final: int, cycles: int, outcome: dict[str, Any]) -> None:
        nand = self.nand
        per_block: dict[int, int] = {}
        for page in range(start, final + 1):
            pb = nand.physical_page(page) // PAGES_PER_BLOCK
            per_block[pb] = per_block.get(pb, 0) + 1
        done = 0
        try:
            while done < cycles:
                step = min(DISTURB_MESSAGE_CYCLES, cycles - done)
                if self.pace_s > 0:
                    time.sleep(self.pace_s * step * (final - start + 1))
                with self._lock:
                    if self.aborted:
                        outcome["aborted"] = True
                        return
                    for pb, n in per_block.items():
                        nand.disturb(pb, n * step)
                    for page in range(start, final + 1):  # every cycle checks the ECC: the last one's view
                        pp = nand.physical_page(page)
                        try:
                            nand._check(pp, page)
                        except EccError as exc:
                            outcome["cycles"] = done + step
                            outcome["failed"] = FlashFailure(
                                Sub.READ_DISTURB_TEST, b"", Failure.ECC, exc.page, str(exc)
                            )
                            return
                    done += step
                    if done % DISTURB_MESSAGE_CYCLES == 0 or done == cycles:
                        self._message(f"NAND DISTURB {done}/{cycles} CYCLES PAGES {start}-{final}")
            outcome["cycles"] = done
        finally:
            with self._cond:
                self.busy = False
                nand.flush()
                outcome["done"] = True
                self._cond.notify_all()


def _in_range(sub: Sub, rest: bytes, first: int, last: int) -> None:
    if not (0 <= first <= last < LOGICAL_PAGES):
        raise _syntax(sub, rest, f"pages {first}-{last}: the NAND has pages 0-{LOGICAL_PAGES - 1}, first <= last")


def _syntax(sub: Sub, rest: bytes, text: str) -> FlashFailure:
    return FlashFailure(sub, rest, Failure.SYNTAX, 0, text)


def _refusal(sub: int, rest: bytes, failure: FlashFailure) -> Refused:
    """The NACK of a failed subcommand: the ICD's failure reply (the command echoed, then ours:
    kind and page)."""
    echo = rest[: struct.calcsize(flash.FIELDS[Sub(sub)])] if sub in tuple(Sub) else rest
    reply = FlashFailure(sub, echo, failure.kind, failure.page, failure.text)
    reason = {Failure.SYNTAX: NackReason.BAD_PARAMETER, Failure.ECC: NackReason.EDAC_UNCORRECTABLE}.get(
        failure.kind, NackReason.STORAGE_ERROR
    )
    return Refused(reason, failure.text, data=reply.pack())
