"""Glue between :class:`OnboardCatalog` and the binary catalog image of ``protocol.catalog_image``.

The device side (:func:`catalog_from_image`, used by ``firmware_model.device.catalog_slot``) builds the catalog on
numpy views into the uploaded bytes: nothing but the validation temporaries is copied.
"""

from __future__ import annotations

import os
import time

import numpy as np

from firmware_model.catalog.onboard import OnboardCatalog
from protocol.catalog_image import (
    FLAG_COLOUR,
    PAIR_DTYPE,
    STAR_DTYPE,
    STAR_FLAG_VARIABLE,
    CatalogImage,
    ImageParams,
    pack_image,
    parse_image,
)

SOURCE_IDS = {"hipparcos": 1, "bsc5": 2}
SOURCE_NAMES = {v: k for k, v in SOURCE_IDS.items()}


def catalog_to_image(cat: OnboardCatalog, created_unix: int | None = None) -> bytes:
    """Serialise ``cat``; build parameters are taken from ``cat.meta`` where present.

    ``created_unix`` defaults to ``$SOURCE_DATE_EPOCH`` if set (reproducible images), else now.
    """
    design = cat.meta.get("design", {})
    stars = np.zeros(cat.n_stars, STAR_DTYPE)
    stars["star_id"] = cat.star_id
    flags = np.asarray(cat.meta.get("colour_source", np.zeros(cat.n_stars)), dtype=np.uint32)
    if "variable" in cat.meta:
        flags |= np.where(cat.meta["variable"], STAR_FLAG_VARIABLE, 0).astype(np.uint32)
    stars["flags"] = flags
    stars["vec"] = cat.vec
    stars["mag"], stars["rg"], stars["bg"] = cat.mag, cat.rg, cat.bg
    pairs = np.zeros(cat.n_pairs, PAIR_DTYPE)
    pairs["i"], pairs["j"], pairs["phi"] = cat.pair_i, cat.pair_j, cat.pair_phi
    nan = float("nan")
    params = ImageParams(
        epoch=float(cat.meta.get("epoch", nan)),
        phi_min=cat.phi_min,
        phi_max=cat.phi_max,
        dphi_star=cat.dphi_star,
        kv_m=cat.kv_m,
        kv_q=cat.kv_q,
        n_h=cat.n_h,
        theta_fov=float(np.radians(design["theta_fov_deg"])) if "theta_fov_deg" in design else nan,
        m_thresh=float(design.get("m_thresh", nan)),
        sigma_phi=float(cat.meta.get("sigma_phi", nan)),
        sigma_rg=float(design.get("sigma_rg", nan)),
        sigma_bg=float(design.get("sigma_bg", nan)),
        source_id=SOURCE_IDS.get(source, 0) if isinstance(source := cat.meta.get("source"), str) else 0,
        flags=FLAG_COLOUR if cat.has_colour else 0,
        n_pattern_stars=cat.n_pattern_stars if cat.has_deep_stars else 0,
        created_unix=int(os.environ.get("SOURCE_DATE_EPOCH", time.time()))
        if created_unix is None
        else int(created_unix),
    )
    kvector = cat.kvector if cat.kvector is not None else np.empty(0, np.uint32)
    assert cat.hash_index is not None  # OnboardCatalog.__post_init__ always builds it
    return pack_image(params, stars, pairs, cat.hash_index, kvector)


def catalog_from_parsed(img: CatalogImage) -> OnboardCatalog:
    """An :class:`OnboardCatalog` whose arrays are views into the validated image."""
    p = img.params
    return OnboardCatalog(
        star_id=img.stars["star_id"],
        vec=img.stars["vec"],
        mag=img.stars["mag"],
        rg=img.stars["rg"],
        bg=img.stars["bg"],
        pair_i=img.pairs["i"],
        pair_j=img.pairs["j"],
        pair_phi=img.pairs["phi"],
        phi_min=p.phi_min,
        phi_max=p.phi_max,
        n_h=p.n_h,
        dphi_star=p.dphi_star,
        hash_index=img.hash_index,
        kvector=img.kvector if img.n_pairs >= 2 else None,
        kv_m=p.kv_m,
        kv_q=p.kv_q,
        n_pattern_stars=p.n_pattern_stars,
        meta={
            "epoch": p.epoch,
            "source": SOURCE_NAMES.get(p.source_id, "unknown"),
            "colour_source": img.stars["flags"] & 0xFF,
            "theta_fov": p.theta_fov,
            "m_thresh": p.m_thresh,
            "sigma_phi": p.sigma_phi,
            "sigma_rg": p.sigma_rg,
            "sigma_bg": p.sigma_bg,
            "created_unix": p.created_unix,
            "image_version": img.version,
        },
    )


def catalog_from_image(data) -> OnboardCatalog:
    """Validate and load an image (raises :class:`CatalogImageError`)."""
    return catalog_from_parsed(parse_image(data))


def image_info(img: CatalogImage) -> dict:
    """What ``catalog info`` reports about an image."""
    p = img.params
    return {
        "version": img.version,
        "n_stars": img.n_stars,
        "n_pairs": img.n_pairs,
        "n_pattern_stars": p.n_pattern_stars or img.n_stars,
        "n_h": p.n_h,
        "epoch": p.epoch,
        "source": SOURCE_NAMES.get(p.source_id, "unknown"),
        "phi_min_deg": round(float(np.degrees(p.phi_min)), 9),
        "phi_max_deg": round(float(np.degrees(p.phi_max)), 9),
        "theta_fov_deg": round(float(np.degrees(p.theta_fov)), 9),
        "m_thresh": p.m_thresh,
        "colour": bool(p.flags & FLAG_COLOUR),
        "created_unix": p.created_unix,
        "data_crc32": f"0x{img.data_crc32:08X}",
    }
