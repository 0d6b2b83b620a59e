"""Files a user names on a command line (parameter sets, fault scripts, camera models, pattern
databases, frames), opened safely, and JSON read from users with its depth bounded (issue 40).

* A special file is refused before anything reads it: a FIFO would block the open or the read
  until killed, a device (``/dev/zero``) never ends. Checked on the path (``os.stat``, so a serial
  port is not even opened) and again on the open descriptor.
* The size is checked before reading (``fstat``), and the read itself is bounded: a file that
  grows meanwhile is refused too.
* A missing file, a directory, a symlink loop and a file that cannot be read are each named for
  what they are (``F: a symlink loop``), one line: :class:`UserFileError`, a ValueError.
* JSON nested deeper than :data:`MAX_JSON_DEPTH` is refused before the parser recurses (100 000
  nested brackets raised RecursionError through every reader).
"""

from __future__ import annotations

import errno
import json
import os
import re
import stat
from itertools import accumulate
from pathlib import Path
from typing import Any

#: Deepest JSON nesting accepted from a user (a parameter set is 3 deep, a camera model 1).
MAX_JSON_DEPTH = 64
#: Largest JSON file read from a user (parameter sets, camera models, frame sidecars: a few kB).
MAX_JSON_BYTES = 1 << 20
#: Longest echo of a user's value in a message (a 5000-digit count was echoed whole).
MAX_ECHO_CHARS = 40


class UserFileError(ValueError):
    """A user's file that cannot be read safely; the message is one line naming the file."""


def _special(mode: int) -> str | None:
    """What a file of this mode is when it is not a regular file (None when it is)."""
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "a directory, not a file"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe), not a regular file"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device, not a regular file"
    if stat.S_ISSOCK(mode):
        return "a socket, not a regular file"
    return "not a regular file"


def os_reason(exc: OSError) -> str:
    """A short reason for an OSError met opening a user's file (no path: the caller names it)."""
    if exc.errno == errno.ENOENT:
        return "no such file"
    if exc.errno == errno.ELOOP:
        return "a symlink loop"
    if exc.errno == errno.EISDIR:
        return "a directory, not a file"
    if exc.errno in (errno.EACCES, errno.EPERM):
        return "permission denied"
    if exc.errno == errno.ENOTDIR:
        return "a path through a file, not a directory"
    return exc.strerror or type(exc).__name__


def problem(path: str | os.PathLike, max_bytes: int | None = None) -> str | None:
    """Why ``path`` is not a regular file of at most ``max_bytes`` that can be read (None: it is)."""
    try:
        st = os.stat(path)
    except OSError as exc:
        return os_reason(exc)
    except (ValueError, RuntimeError) as exc:  # an embedded NUL byte; pathlib's own symlink-loop error
        return str(exc)
    special = _special(st.st_mode)
    if special is not None:
        return special
    if max_bytes is not None and st.st_size > max_bytes:
        return f"{st.st_size} bytes, over the {max_bytes}-byte limit"
    return None


def check_file(path: str | os.PathLike, max_bytes: int | None = None) -> Path:
    """``path`` as a Path when it is a regular file (of at most ``max_bytes``); else UserFileError
    ``PATH: reason``. For files a library opens by name (numpy, tifffile, rawpy)."""
    why = problem(path, max_bytes)
    if why is not None:
        raise UserFileError(f"{path}: {why}")
    return Path(path)


def read_bytes(path: str | os.PathLike, max_bytes: int) -> bytes:
    """The bytes of the regular file ``path``, at most ``max_bytes`` (UserFileError otherwise,
    before anything is read)."""
    check_file(path, max_bytes)
    try:
        # O_NONBLOCK: a FIFO swapped in after the check still cannot block the open
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise UserFileError(f"{path}: {os_reason(exc)}") from None
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(fd)
        special = _special(st.st_mode)
        if special is not None:
            raise UserFileError(f"{path}: {special}")
        if st.st_size > max_bytes:
            raise UserFileError(f"{path}: {st.st_size} bytes, over the {max_bytes}-byte limit")
        try:
            data = f.read(max_bytes + 1)
        except OSError as exc:
            raise UserFileError(f"{path}: {os_reason(exc)}") from None
    if len(data) > max_bytes:
        raise UserFileError(f"{path}: over the {max_bytes}-byte limit (it grew while read)")
    return data


def read_text(path: str | os.PathLike, max_bytes: int) -> str:
    """The UTF-8 text of ``path`` (:func:`read_bytes`); UserFileError naming the file when it is
    not UTF-8."""
    data = read_bytes(path, max_bytes)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserFileError(f"{path}: not UTF-8 text (byte 0x{data[exc.start]:02X} at offset {exc.start})") from None


_STRING = re.compile(r'"(?:[^"\\]++|\\.)*+"')
_NOT_BRACKET = re.compile(r"[^\[\]{}]++")


def json_depth(text: str) -> int:
    """How deep the arrays and objects of the JSON ``text`` nest (brackets inside strings not
    counted; text that is not JSON gives some number, the parser says what is wrong with it)."""
    brackets = _NOT_BRACKET.sub("", _STRING.sub("", text))
    return max(accumulate(1 if c in "[{" else -1 for c in brackets), default=0)


def loads(text: str | bytes, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """``json.loads`` with the nesting bounded: ValueError (``nested N deep, ...``) for JSON
    deeper than ``max_depth``, checked before parsing; bytes are decoded as UTF-8 (a
    UnicodeDecodeError, a ValueError, when they are not)."""
    if isinstance(text, (bytes, bytearray)):
        text = bytes(text).decode("utf-8")
    if text.count("[") + text.count("{") > max_depth:  # only then can it be too deep
        depth = json_depth(text)
        if depth > max_depth:
            raise ValueError(f"JSON nested {depth} deep, over the limit of {max_depth}")
    try:
        return json.loads(text)
    except RecursionError:  # belt and braces: the check above should have refused it
        raise ValueError(f"JSON nested too deep (over {max_depth})") from None


def load_json_file(path: str | os.PathLike, max_bytes: int = MAX_JSON_BYTES, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """The JSON document in the user's file ``path``: :func:`read_text` then :func:`loads`;
    UserFileError naming the file for any problem."""
    text = read_text(path, max_bytes)
    try:
        return loads(text, max_depth)
    except ValueError as exc:
        raise UserFileError(f"{path}: not valid JSON ({exc})") from None


MAX_WORD_CHARS = 200  #: longest run of non-blank characters a message keeps whole (a file's path fits)
_LONG_WORD = re.compile(r"\S{" + str(MAX_WORD_CHARS + 1) + ",}")


def shorten_words(message: str, limit: int = MAX_WORD_CHARS) -> str:
    """``message`` with every run of more than ``limit`` non-blank characters cut (:func:`echo`):
    a message that quotes a user's value whole stays one readable line, and one naming a file
    keeps its path."""
    return _LONG_WORD.sub(lambda m: echo(m.group(0), limit), message)


def echo(value: object, limit: int = MAX_ECHO_CHARS) -> str:
    """``repr``-free text of a user's value for a message, cut to ``limit`` characters (a
    5000-digit number was echoed whole)."""
    text = str(value)
    return text if len(text) <= limit else f"{text[: limit - 3]}... ({len(text)} characters)"
