"""A new warehouse's Prefect database, copied from one migrated once per Prefect version.

Prefect's API creates its SQLite database (``$PREFECT_HOME/prefect.db``) on its first start in a
new home: every Alembic migration, then its block types. Here (2 cores) that made the first start
of the ephemeral API in a new warehouse take 9.8 s, against 3.3 s in a home that had one already,
and every new warehouse paid it (every test's too). :func:`seed_home` copies a template instead:
an empty database migrated to this Prefect version's head with its block types registered, built
once (:func:`build_template`, a subprocess with a home of its own) under
``$CADESTATE_PREFECT_DB_CACHE`` or ``~/.cache/cadestate/prefect``, one file per Prefect version.
Prefect still checks the migrations and the block types at every start; a copy only spares it
building them. A home with a database, or a database Prefect is told elsewhere
(``PREFECT_SERVER_DATABASE_CONNECTION_URL``, ``PREFECT_API_DATABASE_CONNECTION_URL``, PostgreSQL
for a server), is left alone; anything failing here leaves the home to Prefect, as before.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

DB_FILE = "prefect.db"
DATABASE_URL_VARIABLES = ("PREFECT_SERVER_DATABASE_CONNECTION_URL", "PREFECT_API_DATABASE_CONNECTION_URL")

_BUILD = """
import asyncio, sqlite3, sys
from prefect.server.database import provide_database_interface
from prefect.server.models.block_registration import run_block_auto_registration

async def build():
    db = provide_database_interface()
    await db.create_db()
    async with await db.session() as session:
        await run_block_auto_registration(session=session)
        await session.commit()

asyncio.run(build())
con = sqlite3.connect(sys.argv[1])
con.execute("VACUUM INTO ?", (sys.argv[2],))  # one self-contained file, write-ahead log folded in
con.close()
"""


def template_path() -> Path:
    """The template of this Prefect version (it may not exist yet)."""
    import importlib.metadata

    version = importlib.metadata.version("prefect")
    cache = os.environ.get("CADESTATE_PREFECT_DB_CACHE") or Path.home() / ".cache" / "cadestate" / "prefect"
    return Path(cache).expanduser() / f"prefect-{version}.db"


def build_template(path: Path, timeout_s: float = 300.0) -> None:
    """Migrate an empty database in a home of its own and write it to ``path`` (atomically)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="cadestate-prefect-db-") as home:
        env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
        env.update(PREFECT_HOME=home, PREFECT_SERVER_ANALYTICS_ENABLED="false", PREFECT_LOGGING_LEVEL="CRITICAL")
        part = Path(home) / "template.db"
        done = subprocess.run([sys.executable, "-c", _BUILD, str(Path(home) / DB_FILE), str(part)], env=env,
                              capture_output=True, text=True, timeout=timeout_s)
        if done.returncode != 0 or not part.is_file():
            last = (done.stderr.strip().splitlines() or ["no database written"])[-1]
            raise RuntimeError(f"building Prefect's database template failed: {last}")
        staged = path.with_name(f".{path.name}.{os.getpid()}")
        shutil.copyfile(part, staged)
        os.replace(staged, path)


def seed_home(home: Path) -> bool:
    """Give the Prefect home ``home`` a copy of the template database if it has none and Prefect
    uses its default database there (module docstring); True if it did. The template is built
    first when missing. Never replaces a database: the copy is linked in only where none is."""
    home = Path(home)
    if (home / DB_FILE).exists() or any(os.environ.get(v) for v in DATABASE_URL_VARIABLES):
        return False
    try:
        template = template_path()
        if not template.is_file():
            build_template(template)
        home.mkdir(parents=True, exist_ok=True)
        staged = home / f".{DB_FILE}.{os.getpid()}"
        shutil.copyfile(template, staged)
        try:
            os.link(staged, home / DB_FILE)  # fails if a database appeared meanwhile: that one stays
        finally:
            staged.unlink()
    except (OSError, RuntimeError, subprocess.SubprocessError):
        return False
    return True
