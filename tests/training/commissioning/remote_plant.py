"""The independent out-of-process plant, kept at this path for the tests, ``study_remote.py`` and
``twomass commission --drive tests/training/commissioning/remote_plant.py:make_drive``; it lives in
:mod:`training.bench._remote_plant` (the ``twomass bench commission`` plant)."""

from training.bench._remote_plant import (CONFIG, SECOND_ORDER_DELAYED, Plant, PlantOptions, RemoteDrive, make_drive,
                                          make_variant_drive, serve)

__all__ = ["CONFIG", "SECOND_ORDER_DELAYED", "Plant", "PlantOptions", "RemoteDrive", "make_drive", "make_variant_drive",
           "serve"]
