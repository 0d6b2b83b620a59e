"""The device's slot 0: the catalog image, validated on COMMIT with the image's reason code."""

from __future__ import annotations

import json

from firmware_model.catalog.image_io import catalog_from_image, image_info
from firmware_model.catalog.onboard import OnboardCatalog
from firmware_model.device.device import SlotHandler
from protocol.catalog_image import CatalogImageError, parse_image
from protocol.commands import SlotRejected


def catalog_slot_handler(prepare=None):
    """The device's slot-0 handler: validate (NACK with the image reason code), activate (then
    ``prepare(catalog)`` if given: work the solver does once per catalog), info."""

    def validate(data: bytes) -> None:
        try:
            parse_image(data)
        except CatalogImageError as exc:
            raise SlotRejected(int(exc.code), exc.message) from None

    def info(data: bytes, cat: OnboardCatalog) -> bytes:
        return json.dumps(image_info(parse_image(data))).encode()

    def activate(data: bytes) -> OnboardCatalog:
        cat = catalog_from_image(data)
        if prepare is not None:
            prepare(cat)
        return cat

    return SlotHandler(validate, activate, info)
