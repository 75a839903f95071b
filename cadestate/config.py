"""Pipeline configuration: one TOML file, one section per stage, validated strictly.

Every key has a default, so an empty file (or none) is a valid configuration. Unknown sections,
unknown keys, wrong types and out-of-range values are errors that name the file, the section and
the key. Each stage section hashes to a short digest that the ``runs`` table records, so a rerun
knows which stages a config change made stale (see :mod:`cadestate.lineage`).

Sections ``warehouse`` and ``prefect`` say *where* and *how* to run; they do not change any
result and take no part in lineage. Every other section belongs to the stage of the same name.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

DEFAULT_CONFIG_FILE = "cadestate.toml"
ENV_CONFIG = "CADESTATE_CONFIG"
ENV_WAREHOUSE = "CADESTATE_WAREHOUSE"


class ConfigError(ValueError):
    """An invalid configuration; the message names the file, section and key."""


def _opt(default: Any, doc: str, *, choices: tuple | None = None, lo: float | None = None, hi: float | None = None):
    """A config key with its documentation and constraints (kept in dataclass field metadata)."""
    return field(default=default, metadata={"doc": doc, "choices": choices, "lo": lo, "hi": hi})


@dataclass(frozen=True)
class WarehouseConfig:
    """Where the warehouse lives (not part of lineage)."""

    root: str = _opt("data/warehouse", "Warehouse root directory; env CADESTATE_WAREHOUSE and --warehouse override it.")


@dataclass(frozen=True)
class PrefectConfig:
    """How flows run (not part of lineage)."""

    task_runner: str = _opt("threads", "Task runner: 'threads' (local threads) or 'dask' (a Dask cluster).", choices=("threads", "dask"))
    max_workers: int = _opt(2, "Worker threads for the 'threads' runner.", lo=1, hi=256)
    dask_address: str = _opt("", "Address of a running Dask scheduler; empty starts a local cluster.")


@dataclass(frozen=True)
class IngestConfig:
    """Stage ``ingest``: validate a clip's video and camera file and register it."""

    link_inputs: bool = _opt(True, "Hard-link inputs into the warehouse when possible instead of copying them.")


@dataclass(frozen=True)
class FramesConfig:
    """Stage ``frames``: extract the video frame at every camera timestamp."""

    image_format: str = _opt("jpg", "Frame image format.", choices=("jpg", "png"))
    jpeg_quality: int = _opt(95, "JPEG quality (1-100) when image_format = 'jpg'.", lo=1, hi=100)
    max_timestamp_error_us: int = _opt(
        3000, "Largest accepted |decoded frame time - camera timestamp| in µs (the official tool expects 2,000-3,000).", lo=0
    )
    seek_threshold_us: int = _opt(
        1_000_000, "Seek when the next camera timestamp is further ahead than this; decode forward otherwise.", lo=0
    )


@dataclass(frozen=True)
class CadIngestConfig:
    """Stage ``cad_ingest``: canonicalise a CAD library, detect symmetries, sample surfaces."""

    source: str = _opt("", "CAD source folder (Sweet Home 3D *.sh3f, ShapeNet layout, or meshes + models.csv); empty = the embedded Sweet Home 3D library.")
    samples: int = _opt(4096, "Surface samples per model (symmetry detection, later geometry).", lo=256, hi=1_000_000)
    symmetry_tolerance: float = _opt(0.008, "Largest symmetric-copy distance, relative to the model size, that counts as symmetric.", lo=0.0, hi=1.0)
    workers: int = _opt(2, "Processes that ingest models in parallel (results do not depend on it).", lo=1, hi=256)


@dataclass(frozen=True)
class CadViewsConfig:
    """Stage ``cad_views``: render every model from random viewpoints (for appearance retrieval)."""

    views: int = _opt(10, "Rendered views per model.", lo=1, hi=100)
    size: int = _opt(224, "Side of the square renders.", lo=32, hi=2048)
    seed: int = _opt(0, "Seed of the random viewpoints.", lo=0)


@dataclass(frozen=True)
class Config:
    """The whole configuration. ``source`` is the file it came from (None for built-in defaults)."""

    warehouse: WarehouseConfig = field(default_factory=WarehouseConfig)
    prefect: PrefectConfig = field(default_factory=PrefectConfig)
    ingest: IngestConfig = field(default_factory=IngestConfig)
    frames: FramesConfig = field(default_factory=FramesConfig)
    cad_ingest: CadIngestConfig = field(default_factory=CadIngestConfig)
    cad_views: CadViewsConfig = field(default_factory=CadViewsConfig)
    source: str | None = None

    def section(self, name: str) -> Any:
        """The dataclass of section ``name``."""
        if name not in SECTIONS:
            raise KeyError(f"unknown config section {name!r}")
        return getattr(self, name)

    def section_hash(self, name: str) -> str:
        """Digest of one section (see :func:`section_hash`)."""
        return section_hash(name, self.section(name))


SECTIONS: dict[str, type] = {
    "warehouse": WarehouseConfig,
    "prefect": PrefectConfig,
    "ingest": IngestConfig,
    "frames": FramesConfig,
    "cad_ingest": CadIngestConfig,
    "cad_views": CadViewsConfig,
}
"""Section name -> dataclass; one entry per field of :class:`Config` (a test keeps them in step)."""
RUNTIME_SECTIONS = ("warehouse", "prefect")
"""Sections that do not affect results (no lineage)."""


def section_hash(name: str, section: Any) -> str:
    """Stable 16-hex digest of a section's values (key order and file formatting do not matter)."""
    payload = json.dumps({"section": name, **dataclasses.asdict(section)}, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def _check_value(where: str, f: dataclasses.Field, value: Any) -> Any:
    expected = type(f.default)
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if type(value) is not expected:
        raise ConfigError(f"{where}: expected {expected.__name__}, got {type(value).__name__} {value!r}")
    meta = f.metadata
    if meta.get("choices") and value not in meta["choices"]:
        raise ConfigError(f"{where}: must be one of {', '.join(map(repr, meta['choices']))}, got {value!r}")
    if meta.get("lo") is not None and value < meta["lo"]:
        raise ConfigError(f"{where}: must be >= {meta['lo']}, got {value!r}")
    if meta.get("hi") is not None and value > meta["hi"]:
        raise ConfigError(f"{where}: must be <= {meta['hi']}, got {value!r}")
    return value


def config_from_dict(data: dict[str, Any], source: str = "<config>") -> Config:
    """Validate a parsed TOML document into a :class:`Config`."""
    sections: dict[str, Any] = {}
    for name, values in data.items():
        if name not in SECTIONS:
            raise ConfigError(f"{source}: unknown section [{name}] (known: {', '.join(SECTIONS)})")
        if not isinstance(values, dict):
            raise ConfigError(f"{source}: [{name}] must be a table of keys")
        cls = SECTIONS[name]
        known = {f.name: f for f in dataclasses.fields(cls)}
        kwargs = {}
        for key, value in values.items():
            if key not in known:
                raise ConfigError(f"{source}: [{name}] unknown key {key!r} (known: {', '.join(known)})")
            kwargs[key] = _check_value(f"{source}: [{name}] {key}", known[key], value)
        sections[name] = cls(**kwargs)
    return Config(**sections, source=source)


def load_config(path: str | os.PathLike | None = None) -> Config:
    """Load the configuration.

    Resolution: ``path`` if given, else ``$CADESTATE_CONFIG``, else ``./cadestate.toml`` if it
    exists, else the built-in defaults. ``$CADESTATE_WAREHOUSE`` overrides ``[warehouse] root``.
    """
    explicit = path or os.environ.get(ENV_CONFIG)
    candidate = Path(explicit) if explicit else Path(DEFAULT_CONFIG_FILE)
    if explicit and not candidate.is_file():
        raise ConfigError(f"{candidate}: config file not found")
    if candidate.is_file():
        try:
            data = tomllib.loads(candidate.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise ConfigError(f"{candidate}: not valid TOML: {e}") from None
        config = config_from_dict(data, str(candidate))
    else:
        config = Config()
    if os.environ.get(ENV_WAREHOUSE):
        config = dataclasses.replace(config, warehouse=WarehouseConfig(root=os.environ[ENV_WAREHOUSE]))
    return config


def describe_defaults() -> str:
    """The default configuration as commented TOML (``cadestate config show --defaults``)."""
    lines = []
    for name, cls in SECTIONS.items():
        lines.append(f"[{name}]")
        if cls.__doc__:
            lines.append(f"# {cls.__doc__.strip()}")
        for f in dataclasses.fields(cls):
            lines.append(f"# {f.metadata['doc']}")
            lines.append(f"{f.name} = {json.dumps(f.default)}")
        lines.append("")
    return "\n".join(lines)


def to_toml(config: Config) -> str:
    """The effective configuration as TOML."""
    lines = []
    for name in SECTIONS:
        lines.append(f"[{name}]")
        for key, value in dataclasses.asdict(config.section(name)).items():
            lines.append(f"{key} = {json.dumps(value)}")
        lines.append("")
    return "\n".join(lines)
