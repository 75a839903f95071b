"""What the config's own checks cannot see, checked before a run (``cadestate config check``,
``ingest`` and ``run``): ``[detect]`` against its label map and model file
(:func:`tasks.detection.detectors.check_detect_config`), and the ``[pose]`` class lists against
the classes a CAD model can have (:data:`tasks.cad.classes.BY_NAME`): a name of none ("Chair",
"chairs") was taken and never matched, which quietly left that class out of the up-axis term or
the support prior."""

from __future__ import annotations

from cadestate.config import Config, ConfigError
from tasks.cad.classes import BY_NAME
from tasks.detection.detectors import check_detect_config

CLASS_LISTS = ("upright_classes", "floor_classes", "wall_classes")
"""The ``[pose]`` keys that name CAD classes."""


def check_config(config: Config) -> None:
    """Raise :class:`ConfigError` (``"{source}: [section] key: what is wrong"``) on a ``[detect]``
    its model cannot run, or a ``[pose]`` class list naming a class no CAD model has."""
    check_detect_config(config.detect, config.source)
    for key in CLASS_LISTS:
        if unknown := [c for c in getattr(config.pose, key) if c not in BY_NAME]:
            raise ConfigError(f"{config.source or 'built-in defaults'}: [pose] {key}: {unknown[0]!r} is no class a CAD "
                              f"model has (the classes: {', '.join(sorted(BY_NAME))})")
