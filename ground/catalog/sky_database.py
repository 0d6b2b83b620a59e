"""The whole-sky pattern database: built once from the bundled Hipparcos, kept on disk, shared by
every offline solve (``solve-file``, ``ground.api.solve_image``, ``replay --offline``, the
whole-sky simulation) whatever the camera.

The file is an uncompressed NumPy ``.npz`` (zip): the pattern table's arrays
(``firmware_model.pipeline.pattern_index``), the stars' magnitudes and Hipparcos numbers, and a
``meta`` member (JSON: format, :data:`VERSION`, the recipe it was built with, counts, build
seconds). Each zip member carries a CRC-32 that reading checks, so a damaged or truncated file
fails to load, as does one of another version or recipe; all three are one line naming the file
(:class:`DatabaseError`). The default file, in the user's cache directory, is built again when it
fails; a file the user names is not overwritten unasked (``st16-ground database build``).
Writing goes to a temporary file beside the target (``.NAME.PID.part.npz``) that replaces it
only once complete, so a full disk leaves the old file as it was; a part left by a build that was
killed (its process gone) is removed by the next save (whole or nothing).

Reading refuses a FIFO, a device or a symlink loop in one line before opening it, and checks
every member's header against the bytes the member holds before loading it (a crafted member
claiming 10**12 float64 raised numpy's _ArrayMemoryError).

Figures (this machine class: docs/identification.md, "Blind and wide"): ~2.3e6 patterns of
~41 000 stars, ~85 MB, built in ~15 s, loaded in ~0.05 s.
"""

from __future__ import annotations

import json
import logging
import os
import time
import zipfile
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

_log = logging.getLogger(__name__)

#: The database format's version: a file of another one is rebuilt.
VERSION = 2
#: The field the stars are selected for: the narrowest the database serves (its deepest stars).
STAR_FIELD = (1280, 960, 5.0)


class DatabaseError(ValueError):
    """A database file that cannot be used; the message is one line naming the file."""


def recipe() -> dict:
    """What the patterns depend on besides the stars: a file built with another recipe is stale."""
    from firmware_model.pipeline import pattern_index, scale_free, sky_patterns

    return {
        "half_fields_deg": [round(h, 6) for h in sky_patterns.HALF_FIELDS_DEG],
        "stars_in_view": sky_patterns.STARS_IN_VIEW,
        "faintest_mag": sky_patterns.FAINTEST_MAG,
        "neighbours": sky_patterns.NEIGHBOURS,
        "region_stars": scale_free.REGION_STARS,
        "region_spacing": scale_free.REGION_SPACING,
        "stars_per_cap": scale_free.PATTERN_STARS_PER_CAP,
        "radius_factors": list(scale_free.PATTERN_RADIUS_FACTORS),
        "cell": pattern_index.CELL,
        "star_field": list(STAR_FIELD),
    }


@dataclass
class SkyDatabase:
    """A loaded database: the pattern table, its stars' magnitudes (V) and Hipparcos numbers,
    its ``meta`` and the file it came from."""

    index: object  # firmware_model.pipeline.pattern_index.PatternIndex
    mag: np.ndarray
    star_id: np.ndarray
    meta: dict
    path: Path | None = None
    load_s: float = 0.0  #: seconds its loading took (0 once loaded in this process, or built)

    @cached_property
    def search(self):
        """The ``sky_search.SkySearch`` over this table (its star tree built on first use)."""
        from firmware_model.pipeline.sky_search import SkySearch

        return SkySearch(self.index, self.mag)  # type: ignore[arg-type]

    def summary(self) -> str:
        m = self.meta
        size = self.path.stat().st_size / 1e6 if self.path is not None and self.path.exists() else float("nan")
        return (
            f"sky database {self.path}: version {m['version']}, {m['patterns']} patterns of {m['stars']} stars "
            f"(V <= {m['faintest_mag']:.1f}), fields {m['fov_deg'][0]:g}-{m['fov_deg'][1]:g} deg, "
            f"{size:.0f} MB, built in {m['build_s']:.1f} s"
        )


def default_path() -> Path:
    """The database in the user's cache directory."""
    from firmware_model import user_cache_dir

    return user_cache_dir() / "sky-database" / f"sky-v{VERSION}.npz"


def build(progress: bool = False) -> SkyDatabase:
    """Build the database from the bundled Hipparcos (~15 s; a bar on stderr with ``progress``)."""
    from tqdm import tqdm

    from firmware_model.pipeline.sky_patterns import HALF_FIELDS_DEG, sky_pattern_index
    from firmware_model.pipeline.sky_search import BLIND_FOV_DEG
    from ground.catalog.build import build_catalog
    from ground.catalog.design import CatalogDesign

    t0 = time.perf_counter()
    steps = 1 + len(HALF_FIELDS_DEG)  # the stars, then each rung of the ladder
    with tqdm(total=steps, desc="sky database", unit=" step", disable=not progress, leave=False) as bar:
        cat = build_catalog(CatalogDesign.for_field(*STAR_FIELD))
        bar.update(1)
        order = np.argsort(cat.mag, kind="stable")
        vec, mag = cat.vec[order], cat.mag[order].astype(float)
        index = sky_pattern_index(vec, mag, lambda done, total: bar.update(1))
    meta = {
        "format": "colour-st16 sky database",
        "version": VERSION,
        "recipe": recipe(),
        "source": f"{cat.meta.get('source')} (bundled), epoch {cat.meta.get('epoch')}",
        "stars": len(vec),
        "patterns": len(index),
        "faintest_mag": float(mag.max()),
        "fov_deg": list(BLIND_FOV_DEG),
        "build_s": round(time.perf_counter() - t0, 2),
    }
    return SkyDatabase(index, mag, cat.star_id[order], meta)


def save(db: SkyDatabase, path: str | Path) -> None:
    """Write ``db`` to ``path`` whole or not at all (OSError, the old file intact, when not); in
    the user cache, other versions' files go once it is written (nothing reads them again)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_parts(path)
    meta = np.frombuffer(json.dumps(db.meta).encode(), np.uint8)
    tmp = path.parent / f".{path.stem}.{os.getpid()}.part{path.suffix}"
    try:
        with open(tmp, "wb") as f:
            np.savez(f, meta=meta, mag=db.mag, star_id=db.star_id, **db.index.arrays())  # type: ignore[attr-defined]
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    db.path = path
    if path.resolve() == default_path().resolve():
        for old in path.parent.glob("sky-v*.npz"):
            if old != path:
                old.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process: alive
        return True
    return True


def remove_stale_parts(path: str | Path) -> list[Path]:
    """Remove the temporary files beside ``path`` that a save killed midway left
    (``.NAME.PID.part.npz`` of a process that has gone, or ``.NAME.*.part.npz`` of the earlier
    naming); returns those removed. A part being written by a running process is kept."""
    path = Path(path)
    removed = []
    prefix, suffix = f".{path.stem}.", f".part{path.suffix}"
    for part in path.parent.glob(f"{prefix}*{suffix}"):
        tag = part.name[len(prefix) : -len(suffix)]
        if tag.isdigit() and (int(tag) == os.getpid() or _alive(int(tag))):
            continue
        try:
            part.unlink()
        except OSError:
            continue
        removed.append(part)
    if removed:
        _log.info("sky database: removed %d part(s) of a save that did not finish", len(removed))
    return removed


def _check_members(path: Path) -> None:
    """Every member of the ``.npz`` at ``path`` stored (the database is never compressed) within
    the file, its ``.npy`` header claiming no more bytes than the member holds: checked before any
    array is allocated (DatabaseError otherwise)."""
    size = path.stat().st_size
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            name = info.filename
            if info.compress_type != zipfile.ZIP_STORED or info.file_size != info.compress_size:
                raise DatabaseError(f"sky database {path}: member {name} is compressed: not a sky database")
            if info.file_size > size:
                raise DatabaseError(f"sky database {path}: member {name} claims more bytes than the file holds")
            if not name.endswith(".npy"):
                continue
            with zf.open(info) as f:
                version = np.lib.format.read_magic(f)
                read_header = {
                    (1, 0): np.lib.format.read_array_header_1_0,
                    (2, 0): np.lib.format.read_array_header_2_0,
                }.get(version)
                if read_header is None:
                    raise DatabaseError(f"sky database {path}: member {name} of .npy version {version}")
                shape, _, dtype = read_header(f)
                claimed = int(np.prod(np.asarray(shape, dtype=np.float64))) * dtype.itemsize
                if dtype.hasobject or claimed > info.file_size:
                    raise DatabaseError(
                        f"sky database {path}: member {name} claims {' x '.join(map(str, shape))} "
                        f"{dtype} ({claimed} bytes) in {info.file_size}: damaged"
                    )


def load(path: str | Path) -> SkyDatabase:
    """The database in ``path``; :class:`DatabaseError` (one line naming the file) when it is
    missing, damaged, truncated, not a database or of another version or recipe."""
    from firmware_model import user_files
    from firmware_model.pipeline.pattern_index import PatternIndex

    path = Path(path)
    t0 = time.perf_counter()
    why = user_files.problem(path)  # a FIFO hung np.load until killed; a symlink loop: RuntimeError
    if why is not None:
        raise DatabaseError(f"sky database {path}: {why}")
    try:
        _check_members(path)
        with np.load(path, allow_pickle=False) as z:
            if "meta" not in z.files:
                raise DatabaseError(f"sky database {path}: not a sky database (no meta member)")
            meta = user_files.loads(bytes(z["meta"]).decode())
            if meta.get("format") != "colour-st16 sky database":
                raise DatabaseError(f"sky database {path}: not a sky database")
            if meta.get("version") != VERSION or meta.get("recipe") != recipe():
                raise DatabaseError(
                    f"sky database {path}: version {meta.get('version')} of another recipe than this "
                    f"program's (version {VERSION})"
                )
            index = PatternIndex.from_arrays(z)
            mag, star_id = z["mag"], z["star_id"]
    except DatabaseError:
        raise
    except FileNotFoundError:
        raise DatabaseError(f"sky database {path}: no such file") from None
    except (
        OSError,
        ValueError,
        KeyError,
        EOFError,
        zipfile.BadZipFile,
        json.JSONDecodeError,
        UnicodeDecodeError,
    ) as exc:
        raise DatabaseError(f"sky database {path}: damaged or truncated ({_one_line(exc)})") from None
    if len(mag) != len(index.vec) or len(star_id) != len(index.vec):
        raise DatabaseError(f"sky database {path}: damaged (star arrays of different lengths)")
    return SkyDatabase(index, mag, star_id, meta, path, time.perf_counter() - t0)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


_LOADED: dict[Path, SkyDatabase] = {}


def sky_database(path: str | Path | None = None, progress: bool = False) -> SkyDatabase:
    """The database for this process: ``path`` (a :class:`DatabaseError` when it cannot be used;
    ``st16-ground database build --database PATH`` makes one), or the user cache's, built (with a
    line on stderr and, with ``progress``, a bar) when missing, damaged or of another version, and
    kept when the folder can be written. Loaded once per process."""
    if path is not None:
        from firmware_model import user_files

        why = user_files.problem(Path(path).expanduser())  # before resolve(), which raised RuntimeError on a loop
        if why is not None and why != "no such file":  # a missing file: load() says it, with the build command
            raise DatabaseError(f"sky database {path}: {why}")
    target = Path(path).expanduser().resolve() if path is not None else default_path()
    if target in _LOADED:
        _LOADED[target].load_s = 0.0  # loaded before: this call cost nothing
        return _LOADED[target]
    if path is not None:
        try:
            db = load(target)
        except DatabaseError as exc:
            raise DatabaseError(f"{exc}; rebuild it with: st16-ground database build --database {path}") from None
    else:
        try:
            db = load(target)
        except DatabaseError as exc:
            if target.exists():
                _log.warning("%s: building it again", exc)
            _log.warning("building the sky pattern database once (about 15 s), kept in %s", target)
            db = build(progress)
            try:
                save(db, target)
            except OSError as err:
                _log.warning("sky database not kept in %s: %s", target, _one_line(err))
    _LOADED[target] = db
    return db
