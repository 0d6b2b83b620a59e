"""The device's slot 0: the catalog image, validated on COMMIT with the image's reason code."""

from __future__ import annotations

import json

from firmware_model.catalog.image_io import catalog_from_parsed, image_info
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.device.device import SlotHandler
from protocol.catalog_image import CatalogImage, CatalogImageError, parse_image
from protocol.commands import SlotRejected

INFO_KEY = "_slot_info"  #: the SLOT INFO blob, kept in the activated catalog's ``__dict__``


def catalog_slot_handler(prepare=None):
    """The device's slot-0 handler: validate (NACK with the image reason code), activate (then
    ``prepare(catalog)`` if given: work the solver does once per catalog), info.

    An image is parsed and checked once per COMMIT (0.3-0.5 s for a 15 MB image, on the link
    thread): activate takes the parse its validate just made of the same bytes, and SLOT INFO's
    blob is made at activation, not by parsing the image again at each request."""
    last: list[tuple[bytes, CatalogImage]] = []  # the image validate last accepted, and its parse

    def parse(data: bytes) -> CatalogImage:
        try:
            return parse_image(data)
        except CatalogImageError as exc:
            raise SlotRejected(int(exc.code), exc.message) from None

    def validate(data: bytes) -> None:
        img = parse(data)
        last[:] = [(data, img)]

    def activate(data: bytes) -> OnboardCatalog:
        known = [img for seen, img in last if seen is data]  # the very bytes object validated
        last.clear()
        img = known[0] if known else parse(data)
        cat = catalog_from_parsed(img)
        cat.__dict__[INFO_KEY] = json.dumps(image_info(img)).encode()
        if prepare is not None:
            prepare(cat)
        return cat

    def info(data: bytes, cat: OnboardCatalog) -> bytes:
        blob = cat.__dict__.get(INFO_KEY)
        return blob if blob is not None else json.dumps(image_info(parse_image(data))).encode()

    return SlotHandler(validate, activate, info)
