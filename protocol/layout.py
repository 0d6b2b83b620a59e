"""Declared payload layouts: one description per wire layout, from which ``pack`` and ``unpack``
both come (``protocol.commands`` declares every command and reply payload with it).

A payload is a frozen dataclass that also derives from :class:`Layout` and declares, as class
attributes:

``HEAD``
    a little-endian :mod:`struct` format of the fixed part. Each item packs one field, in
    declaration order (or in the order of ``FIELDS``); a repeated code such as ``8H`` packs one
    tuple field of that many values; ``4s`` packs one ``bytes`` field.
``FORMS`` and ``SELECT``
    instead of ``HEAD``, for a payload with several wire forms: ``FORMS`` maps each value of the
    selector field ``SELECT`` (a field not on the wire) to a :class:`Form`. ``unpack`` tells
    the forms apart by the data length, or takes the selector value as its argument
    (``FORM_ARG``).
``FIELDS``
    the wire order of the head's items when it is not the declaration order; a name that is not
    a field is a class constant, packed as is and not checked on unpack.
``TAIL``
    the name of a final field carried after the head: raw ``bytes`` (at least ``TAIL_MIN``
    bytes, exactly ``TAIL_SIZE`` when set), or, with ``ITEM`` (a struct format), a tuple of
    records of that format, at most ``MAX_ITEMS`` of them packed; ``TAIL_CODEC`` converts a
    raw tail (to bytes, from bytes).
``WRAP``
    pack integers modulo their field width (counters that may have overflowed).
``NAME``
    labels length errors (:class:`PayloadError` with ``BAD_LENGTH``); ``LENGTH_TEXT``, when set,
    is the whole text of such an error.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Callable, Mapping
from dataclasses import fields
from typing import Any, ClassVar, NamedTuple, TypeVar

from protocol.nack import NackReason, PayloadError

#: (to wire, from wire) conversion of one field's value
Codec = tuple[Callable[[Any], Any], Callable[[Any], Any]]


def need(data: bytes, sizes: tuple[int, ...], what: str) -> None:
    """Raise ``BAD_LENGTH`` unless ``len(data)`` is one of ``sizes``."""
    if len(data) not in sizes:
        allowed = " or ".join(str(s) for s in sizes)
        raise PayloadError(NackReason.BAD_LENGTH, f"{what}: {len(data)} data bytes, expected {allowed}")


def at_least(data: bytes, size: int, what: str) -> None:
    """Raise ``BAD_LENGTH`` if ``data`` is shorter than ``size``."""
    if len(data) < size:
        raise PayloadError(NackReason.BAD_LENGTH, f"{what}: {len(data)} data bytes, expected at least {size}")


def le_int(size: int) -> Codec:
    """Codec of an unsigned little-endian integer of ``size`` bytes carried in an ``{size}s`` item."""
    return (lambda v: int(v).to_bytes(size, "little"), lambda b: int.from_bytes(b, "little"))


class Form(NamedTuple):
    """One wire form: the head's struct format and per-field conversions (``wire``)."""

    head: str
    wire: Mapping[str, Codec] = {}


_ITEM = re.compile(r"(\d*)([a-zA-Z?])")


def _items(head: str) -> list[int]:
    """Values per item of ``head``: 1 for a single value or ``Ns``, N for a repeated code."""
    return [1 if code in "sp" or not count else int(count) for count, code in _ITEM.findall(head) if code != "x"]


def _codes(head: str) -> list[str]:
    """The struct code of each value of ``head``, repeats spelt out."""
    return [
        code
        for count, code in _ITEM.findall(head)
        if code != "x"
        for _ in range(1 if code in "sp" else int(count or 1))
    ]


_L = TypeVar("_L", bound="Layout")


class Layout:
    """Base of a declared payload (see the module docstring)."""

    HEAD: ClassVar[str]
    FORMS: ClassVar[Mapping[Any, Form] | None] = None
    SELECT: ClassVar[str | None] = None
    FORM_ARG: ClassVar[bool] = False
    FIELDS: ClassVar[tuple[str, ...] | None] = None
    TAIL: ClassVar[str | None] = None
    TAIL_MIN: ClassVar[int] = 1
    TAIL_SIZE: ClassVar[int | None] = None
    TAIL_CODEC: ClassVar[Codec | None] = None
    ITEM: ClassVar[str | None] = None
    ITEMS_NAME: ClassVar[str | None] = None
    MAX_ITEMS: ClassVar[int | None] = None
    WRAP: ClassVar[bool] = False
    NAME: ClassVar[str]
    LENGTH_TEXT: ClassVar[str | None] = None

    # ------------------------------------------------------------------ the declaration

    @classmethod
    def forms(cls) -> Mapping[Any, Form]:
        """The wire forms by selector value (one form, key None, for a ``HEAD`` layout)."""
        return cls.FORMS if cls.FORMS is not None else {None: Form(cls.HEAD)}

    @classmethod
    def _names(cls, head: str) -> list[str]:
        n = len(_items(head))
        if cls.FIELDS is not None:
            return list(cls.FIELDS[:n])
        skip = {cls.TAIL, cls.SELECT}
        return [f.name for f in fields(cls) if f.name not in skip][:n]  # type: ignore[arg-type]

    @classmethod
    def _sizes(cls) -> list[tuple[int, Any]]:
        """(data length, selector) of each fixed-length form, ascending."""
        tail = cls.TAIL_SIZE if cls.TAIL else 0
        return sorted((struct.calcsize(form.head) + (tail or 0), key) for key, form in cls.forms().items())

    # ------------------------------------------------------------------ encode

    def pack(self) -> bytes:
        cls = type(self)
        form = cls.forms()[getattr(self, cls.SELECT) if cls.SELECT else None]
        values: list[Any] = []
        for name, n in zip(cls._names(form.head), _items(form.head)):
            value = getattr(self, name)
            if name in form.wire:
                value = form.wire[name][0](value)
            values.extend(value if n > 1 else [value])
        if cls.WRAP:
            values = [v & ((1 << (8 * struct.calcsize("<" + c))) - 1) for v, c in zip(values, _codes(form.head))]
        head = struct.pack(form.head, *values)
        if not cls.TAIL:
            return head
        tail = getattr(self, cls.TAIL)
        if cls.ITEM:
            shown = tail if cls.MAX_ITEMS is None else tail[: cls.MAX_ITEMS]
            return head + b"".join(struct.pack(cls.ITEM, *record) for record in shown)
        return head + bytes(cls.TAIL_CODEC[0](tail) if cls.TAIL_CODEC else tail)

    # ------------------------------------------------------------------ decode

    @classmethod
    def unpack(cls: type[_L], data: bytes) -> _L:
        return cls._decode(data)

    @classmethod
    def _decode(cls: type[_L], data: bytes, *form_arg: Any) -> _L:
        try:
            key = cls._form_of(data, *form_arg)
        except PayloadError as exc:
            if cls.LENGTH_TEXT is None:
                raise
            raise PayloadError(exc.reason, cls.LENGTH_TEXT) from None
        return cls._decode_form(data, key)

    @classmethod
    def _form_of(cls, data: bytes, *form_arg: Any) -> Any:
        """The selector value of the form ``data`` is in (``BAD_LENGTH`` if none fits)."""
        forms = cls.forms()
        if cls.FORM_ARG:
            key = form_arg[0]
            size = struct.calcsize(forms[key].head)
            if cls.TAIL and cls.TAIL_SIZE is None:
                at_least(data, size + cls.TAIL_MIN, cls.NAME)
            else:
                need(data, (size + (cls.TAIL_SIZE or 0),), cls.NAME)
        elif cls.TAIL and cls.TAIL_SIZE is None:  # one form, variable tail
            (key,) = forms
            at_least(data, struct.calcsize(forms[key].head) + cls.TAIL_MIN, cls.NAME)
        else:
            sizes = cls._sizes()
            need(data, tuple(s for s, _ in sizes), cls.NAME)
            key = dict(sizes)[len(data)]
        return key

    @classmethod
    def _decode_form(cls: type[_L], data: bytes, key: Any) -> _L:
        form = cls.forms()[key]
        flat = struct.unpack_from(form.head, data)
        values: dict[str, Any] = {}
        at = 0
        for name, n in zip(cls._names(form.head), _items(form.head)):
            value = flat[at] if n == 1 else tuple(flat[at : at + n])
            at += n
            if name in form.wire:
                value = form.wire[name][1](value)
            values[name] = value
        known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
        values = {k: v for k, v in values.items() if k in known}
        if cls.SELECT:
            values[cls.SELECT] = key
        if cls.TAIL:
            rest = bytes(data[struct.calcsize(form.head) :])
            if cls.ITEM:
                step = struct.calcsize(cls.ITEM)
                if len(rest) % step:
                    what = cls.ITEMS_NAME or cls.TAIL
                    raise PayloadError(NackReason.BAD_LENGTH, f"{cls.NAME}: {what} not a multiple of {step} bytes")
                values[cls.TAIL] = tuple(struct.unpack_from(cls.ITEM, rest, i) for i in range(0, len(rest), step))
            else:
                values[cls.TAIL] = cls.TAIL_CODEC[1](rest) if cls.TAIL_CODEC else rest
        return cls(**values)
