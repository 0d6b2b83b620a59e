"""Ground-system definitions generated from ``protocol/``: an OpenC3 COSMOS target
(:mod:`ground.export.openc3`) and an XTCE space system (:mod:`ground.export.xtce`), both rendered
from one description (:mod:`ground.export.model`)."""
