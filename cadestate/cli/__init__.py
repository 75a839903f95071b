"""``cadestate``: the one command line of the pipeline (see ``cadestate --help``).

Modules: :mod:`cadestate.cli.common` (apps, state, output), :mod:`cadestate.cli.pipeline` (clips,
warehouse, configuration), :mod:`cadestate.cli.cad` (the CAD library), :mod:`cadestate.cli.bench`
(the synthetic benchmark). Importing them registers their commands.
"""

from __future__ import annotations

import sys

from rich.markup import escape

from cadestate.cli import bench, cad, export, labels, pipeline  # noqa: F401  (register the commands)
from cadestate.cli.bench import bench_generate
from cadestate.cli.common import CliError, app, err
from cadestate.config import ConfigError

__all__ = ["app", "bench_generate", "main"]


def main() -> None:
    """Entry point: known input errors become one clear line on stderr and exit status 2."""
    from bench.benchmark import BenchmarkError
    from tasks.cad_export import ExportError
    from tasks.cad_sources import CadSourceError
    from tasks.cameras import CameraFileError
    from tasks.labels import LabelError
    from tasks.video import VideoError
    from warehouse import WarehouseError

    try:
        app()
    except (CliError, ConfigError, CameraFileError, VideoError, WarehouseError, CadSourceError, ExportError,
            BenchmarkError, LabelError, FileNotFoundError) as e:
        err.print(f"[red]error:[/] {escape(str(e))}", highlight=False)
        sys.exit(2)
