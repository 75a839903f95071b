"""A new warehouse's Prefect database copied from a migrated template (flows/prefect_db.py)."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from flows.prefect_db import DB_FILE, seed_home, template_path


def migration_head() -> str:
    """The head of Prefect's SQLite migrations, read from its Alembic scripts."""
    import prefect.server.database as database
    from alembic.script import ScriptDirectory

    root = Path(database.__file__).parent / "_migrations"
    [head] = ScriptDirectory(str(root), version_locations=[str(root / "versions" / "sqlite")]).get_heads()
    return head


def test_a_new_home_gets_an_empty_database_at_prefects_head_with_its_block_types(tmp_path):
    home = tmp_path / "home"
    assert seed_home(home) and template_path().is_file()
    con = sqlite3.connect(home / DB_FILE)
    try:
        assert con.execute("SELECT version_num FROM alembic_version").fetchall() == [(migration_head(),)]
        assert con.execute("SELECT count(*) FROM block_type").fetchone()[0] > 0
        assert con.execute("SELECT count(*) FROM flow_run").fetchone()[0] == 0
    finally:
        con.close()
    assert [p.name for p in home.iterdir()] == [DB_FILE]  # no staged copy left behind


def test_a_database_is_never_replaced_and_one_configured_elsewhere_is_left_alone(tmp_path, monkeypatch):
    home = tmp_path / "home"
    home.mkdir()
    (home / DB_FILE).write_bytes(b"runs of a user")
    assert not seed_home(home) and (home / DB_FILE).read_bytes() == b"runs of a user"
    monkeypatch.setenv("PREFECT_SERVER_DATABASE_CONNECTION_URL", "postgresql+asyncpg://u:p@db/prefect")
    assert not seed_home(tmp_path / "other") and not (tmp_path / "other").exists()


def test_a_template_that_cannot_be_built_leaves_the_home_to_prefect(tmp_path, monkeypatch):
    (tmp_path / "not-a-folder").write_text("")
    monkeypatch.setenv("CADESTATE_PREFECT_DB_CACHE", str(tmp_path / "not-a-folder"))
    assert not seed_home(tmp_path / "home")
    assert not (tmp_path / "home" / DB_FILE).exists()


def test_a_seeded_home_runs_flows_on_its_ephemeral_api(tmp_path):
    """Prefect's own start path (our start_ephemeral_api) on a new home: the copy is what it uses."""
    script = textwrap.dedent("""
        import os, sqlite3, sys
        from pathlib import Path
        from flows.runtime import start_ephemeral_api
        from prefect import flow
        start_ephemeral_api(120)
        @flow(name="seeded")
        def seeded(x: int) -> int:
            return x + 1
        assert seeded(1) == 2
        con = sqlite3.connect(Path(os.environ["PREFECT_HOME"]) / "prefect.db")
        print(con.execute("SELECT count(*) FROM flow_run WHERE name IS NOT NULL").fetchone()[0])
    """)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(PREFECT_HOME=str(tmp_path / "home"), PREFECT_SERVER_ANALYTICS_ENABLED="false")
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split()[-1] == "1"
    con = sqlite3.connect(tmp_path / "home" / DB_FILE)
    try:
        assert con.execute("SELECT version_num FROM alembic_version").fetchall() == [(migration_head(),)]
    finally:
        con.close()


@pytest.fixture(autouse=True)
def _default_cache(monkeypatch):
    """Each test sees the template cache the product uses unless it sets its own."""
    monkeypatch.delenv("CADESTATE_PREFECT_DB_CACHE", raising=False)
    for name in ("PREFECT_SERVER_DATABASE_CONNECTION_URL", "PREFECT_API_DATABASE_CONNECTION_URL"):
        monkeypatch.delenv(name, raising=False)
