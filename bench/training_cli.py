"""What the two models `make models` trains share: their command line and their training warehouse.

    python -m bench.detector_train   --warehouse W --out MODELS_DIR [--seed S] [--rooms R] [--frames F] [--steps N]
    python -m bench.descriptor_train --warehouse W --out MODELS_DIR [...]
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from cadestate.lineage import file_sha256
from warehouse import Warehouse


def ensure_library(wh: Warehouse, show_progress: bool = True) -> None:
    """Ingest the embedded CAD library into ``wh`` unless it holds view descriptors already."""
    if wh.partitions("cad_embeddings"):
        return
    print(f"models: ingesting the embedded CAD library into the training warehouse {wh.root} (about 4 minutes)",
          file=sys.stderr, flush=True)
    from cadestate.config import CadEmbedConfig, Config, WarehouseConfig
    from flows.runtime import prepare_prefect_environment

    prepare_prefect_environment(wh.root)  # before Prefect is imported: the warehouse's Prefect home, quiet logs
    from flows.cad_library import run_cad_library
    from tasks.cad.sources import default_source, source_items

    config = Config(warehouse=WarehouseConfig(root=str(wh.root)), cad_embed=CadEmbedConfig(whitening="whiten"))
    reports = run_cad_library(source_items("sweethome3d", default_source()), config, show_progress)
    failed = [f"{r.stage} {r.clip}: {r.message}" for r in reports if r.state == "failed"]
    if failed:
        raise SystemExit(f"the training library did not build: {'; '.join(failed)}")


def training_main(doc: str, spec_type: type, build: Callable, what: str, argv: list[str] | None = None) -> int:
    """Parse a trainer's command line (``--warehouse``, ``--out`` and the ``seed``, ``rooms``, ``frames``
    and ``steps`` of its ``spec_type``), give the warehouse the library, ``build`` into ``--out`` and
    print the file's path and SHA-256."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--warehouse", type=Path, required=True, help="the training warehouse (gets the embedded CAD library if it has none)")
    parser.add_argument("--out", type=Path, required=True, help=f"models folder ({what} is written there)")
    defaults = spec_type()
    for name in ("seed", "rooms", "frames", "steps"):
        parser.add_argument(f"--{name}", type=int, default=getattr(defaults, name))
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    spec = spec_type(seed=args.seed, rooms=args.rooms, frames=args.frames, steps=args.steps)
    wh = Warehouse(args.warehouse)
    ensure_library(wh, not args.no_progress)
    path = build(wh, args.out, spec, not args.no_progress)
    print(f"{path} sha256 {file_sha256(path)}")
    return 0
