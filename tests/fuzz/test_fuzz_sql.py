"""Fuzz `cadestate sql` with hostile statements: writes to every table file, the catalog and places
outside the warehouse; DDL, DML, ATTACH, INSTALL, LOAD, SET, PRAGMA, EXPORT, CHECKPOINT; reads of
files outside the warehouse's tables; several statements at once; garbage; huge literals.

Every case runs in every output format and must end in one `error:` line on stderr, a non-zero
exit code, no traceback, a warehouse unchanged to the byte (no file added, removed or changed
anywhere under its root), no file created at any target, and nothing of the files it must not read
in what it printed. Hypothesis is derandomized (the same cases every run), without a database or
deadline.
"""

from __future__ import annotations

import hashlib
import os
import uuid
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import table_rows
from fuzz.harness import assert_clean_error, count_case, run_cli, warehouse_digest
from warehouse import Warehouse

SUITE = "sql"
FORMATS = ("table", "csv", "json")
SECRET = "s3cr3t-c0ntent-91"
"""Content of the files outside the tables; never in what the command prints."""

# Placeholders in generated statements, replaced by the paths of the module's warehouse (all lower
# case, so a statement written in lower case names the same paths).
ROOT, OUT, SECRET_FILE, TMP = "@root@", "@out@", "@secret@", "@tmp@"

WRITE_TARGETS = [
    f"{ROOT}/tables/clips/clip=a/part.parquet", f"{ROOT}/catalog.duckdb", f"{ROOT}/_schemas/runs.parquet",
    f"{ROOT}/tables/clips/clip=zzz/part.parquet", f"{ROOT}/new.csv", f"{ROOT}/tables/../catalog.duckdb",
    f"{ROOT}/tables/new_dir", f"{OUT}/out.csv", f"{TMP}/x.parquet", SECRET_FILE,
]
READ_PATHS = [
    "/etc/passwd", SECRET_FILE, f"{ROOT}/inputs/a/cameras.txt", f"{ROOT}/tables/../inputs/a/cameras.txt",
    f"{ROOT}/tables/clips/../../inputs/a/cameras.txt", f"{ROOT}/catalog.duckdb", f"{ROOT}/*", f"{ROOT}/inputs/*/*",
    "/proc/self/environ", "/etc/*", "file:///etc/passwd", "https://example.com/x.csv", "s3://bucket/x.parquet",
    "~/.bashrc", f"{OUT}/../secret/*",
]
READERS = ["read_csv", "read_csv_auto", "read_text", "read_blob", "read_json", "read_json_auto", "read_ndjson",
           "read_parquet", "parquet_metadata", "parquet_schema", "glob", "sniff_csv"]
READ_FORMS = [
    "SELECT * FROM {fn}('{p}')", "SELECT count(*) FROM {fn}('{p}')", "FROM {fn}(['{p}'])",
    "WITH t AS (FROM {fn}('{p}')) SELECT * FROM t", "SELECT * FROM clips, {fn}('{p}')",
    "SELECT * FROM query('SELECT * FROM {fn}(''{p}'')')", "SELECT * FROM '{p}'", "DESCRIBE SELECT * FROM {fn}('{p}')",
    "SUMMARIZE SELECT * FROM {fn}('{p}')", "EXPLAIN ANALYZE SELECT * FROM {fn}('{p}')",
]
PATH_STATEMENTS = [
    "COPY (SELECT 'x' AS clip) TO '{p}' (FORMAT parquet)", "COPY clips TO '{p}'", "COPY (FROM runs) TO '{p}' (FORMAT json)",
    "COPY clips TO '{p}' (FORMAT csv, HEADER)", "COPY clips FROM '{p}'", "EXPLAIN ANALYZE COPY clips TO '{p}'",
    "COPY clips TO '{p}' (FORMAT parquet, PARTITION_BY (clip), OVERWRITE_OR_IGNORE)", "EXPORT DATABASE '{p}'",
    "EXPORT DATABASE '{p}' (FORMAT parquet)", "IMPORT DATABASE '{p}'", "ATTACH '{p}' AS x", "ATTACH '{p}'",
    "ATTACH '{p}' (READ_ONLY)", "ATTACH 'sqlite:{p}' AS s", "LOAD '{p}'", "INSTALL '{p}'",
    "SET profiling_output = '{p}'", "SET log_query_path = '{p}'", "SET temp_directory = '{p}'",
    "PRAGMA import_database('{p}')", "CALL enable_logging(storage = 'file', storage_path = '{p}')",
]
STATEMENTS = [
    "CREATE TABLE t AS FROM clips", "CREATE VIEW v AS SELECT 1", "CREATE OR REPLACE VIEW clips AS SELECT 1",
    "CREATE MACRO m() AS 1", "CREATE TEMP TABLE t (i INT)", "CREATE SCHEMA s", "CREATE SEQUENCE q",
    "CREATE TYPE e AS ENUM ('a')", "CREATE SECRET (TYPE s3, KEY_ID 'k', SECRET 's')", "CREATE PERSISTENT SECRET (TYPE s3)",
    "INSERT INTO clips SELECT * FROM clips", "UPDATE clips SET num_cameras = 0", "DELETE FROM clips",
    "DROP VIEW clips", "DROP TABLE clips", "ALTER VIEW clips RENAME TO c2", "ALTER TABLE clips ADD COLUMN z INT",
    "TRUNCATE clips", "COMMENT ON VIEW clips IS 'x'", "MERGE INTO clips USING runs ON true WHEN MATCHED THEN DELETE",
    "CHECKPOINT", "FORCE CHECKPOINT", "VACUUM", "ANALYZE", "BEGIN TRANSACTION", "COMMIT", "ROLLBACK",
    "PREPARE p AS SELECT 1", "EXECUTE p", "DEALLOCATE p", "USE memory", "DETACH memory", "CALL checkpoint()",
    "CALL enable_logging()", "CALL pragma_table_info('clips')", "PIVOT clips ON split", "SET VARIABLE x = 1",
    "RESET ALL", "INSTALL httpfs", "LOAD httpfs", "FORCE INSTALL httpfs", "INSTALL spatial FROM community",
    "INSTALL httpfs FROM 'http://example.com'", "UPDATE EXTENSIONS", "LOAD json", "SET enable_external_access = true",
    "SET lock_configuration = false", "RESET lock_configuration", "SET allowed_directories = ['/']",
    "SET allowed_paths = ['/etc/passwd']", "SET GLOBAL enable_external_access = true", "SET threads = 1",
    "SET memory_limit = '1GB'", "SET autoinstall_known_extensions = true", "SET search_path = 'x'",
    "PRAGMA enable_profiling", "PRAGMA threads = 1", "PRAGMA table_info('clips')", "PRAGMA show_tables",
    "PRAGMA database_size", "SET max_expression_depth TO 100000",
]
TOKENS = ["SELECT", "FROM", "WHERE", "clips", "runs", "*", ",", "(", ")", "'", '"', "1", "COPY", "TO", "AS", "JOIN",
          "ON", "GROUP", "BY", ";", "=", "NULL", "read_csv", "$$", "[", "]", "{", "}", "::", "INSTALL", "ATTACH"]


def statement(template: str, path: str) -> str:
    return template.replace("{p}", path)


read_statements = st.builds(lambda form, fn, p: form.replace("{fn}", fn).replace("{p}", p),
                            st.sampled_from(READ_FORMS), st.sampled_from(READERS), st.sampled_from(READ_PATHS))
path_statements = st.builds(statement, st.sampled_from(PATH_STATEMENTS), st.sampled_from(WRITE_TARGETS))
plain_statements = st.sampled_from(STATEMENTS)
single = st.one_of(path_statements, read_statements, plain_statements)
disguised = st.builds(lambda wrap, s: wrap.format(s=s), st.sampled_from([
    "{s}", "EXPLAIN {s}", "EXPLAIN ANALYZE {s}", "/* c */ {s}", "-- c\n{s}", "  \n\t{s} ;", "({s})",
    "WITH x AS (SELECT 1) {s}", "SELECT 1; {s}", "{s}; SELECT 1", "SELECT 1;\n{s};", "{s}; {s}", "SELECT 1; SELECT 2",
]), single)
hostile = st.builds(lambda s, lower: s.lower() if lower else s, disguised, st.booleans())
garbage = st.one_of(
    st.text(max_size=200).map(lambda t: "FROBNICATE " + t),
    st.text(alphabet=st.characters(categories=["Cs", "Cc", "Zs", "Ll", "Lo"]), max_size=50)
    .map(lambda t: "SELECT '" + t + "' + nope"),
    st.lists(st.sampled_from(TOKENS), max_size=30).map(lambda ts: " ".join(ts) + " )"),
    st.text(alphabet=" \t\n;", max_size=20),
    st.text(max_size=30).map(lambda t: "-- " + t.replace("\n", " ").replace("\r", " ")),
)
huge = st.builds(lambda n, form: form.replace("{n}", "x" * n), st.sampled_from([1_000, 100_000, 2_000_000]), st.sampled_from([
    "SELECT '{n}' + nope", f"COPY clips TO '{OUT}/{{n}}.csv'", "SELECT * FROM read_csv('/{n}')",
    f"SELECT * FROM read_text('{ROOT}/tables/../{{n}}')", "SELECT 1; SELECT '{n}'", "INSTALL {n}",
    "SELECT * FROM clips WHERE clip IN ('{n}', " + ", ".join(["'a'"] * 5000) + ") AND nope",
]))
FUZZ = settings(derandomize=True, database=None, deadline=None, suppress_health_check=list(HealthCheck))


@pytest.fixture(scope="module")
def place(tmp_path_factory) -> dict[str, Path]:
    """A small warehouse (clips, runs, frames with rows; an input file), a secret file outside it,
    and targets that must never come to exist."""
    base = Path(str(tmp_path_factory.mktemp("fuzzsql")).lower())
    base.mkdir(parents=True, exist_ok=True)
    wh = Warehouse(base / "w")
    for clip in ("a", "b"):
        wh.write("clips", clip, table_rows("clips", [{"clip": clip, "num_cameras": 2}]))
        wh.write("frames", clip, table_rows("frames", [{"clip": clip, "frame_index": i, "timestamp_us": i} for i in range(3)]))
    wh.write("runs", "a", table_rows("runs", [{"clip": "a", "run_id": "r1"}]))
    (wh.root / "inputs" / "a").mkdir(parents=True)
    (wh.root / "inputs" / "a" / "cameras.txt").write_text(f"{SECRET}\n")
    secret = base / "secret" / "secret.csv"
    secret.parent.mkdir()
    secret.write_text(f"password\n{SECRET}\n")
    tmp = Path("/tmp") / f"cadestate-fuzz-sql-{uuid.uuid4().hex[:8]}"
    return {"root": wh.root, "out": base / "out", "secret": secret, "tmp": tmp}


def tree(root: Path) -> dict[str, str]:
    """Every path under ``root`` with the SHA-256 of the files: any change shows."""
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
            for p in sorted(root.rglob("*"))}


@pytest.fixture(scope="module")
def baseline(place) -> tuple[dict[str, str], dict[str, str], dict[str, str]]:
    return warehouse_digest(place["root"]), tree(place["root"]), tree(place["secret"].parent)


def resolve(sql: str, place: dict[str, Path]) -> str:
    return (sql.replace(ROOT, str(place["root"])).replace(OUT, str(place["out"]))
            .replace(SECRET_FILE, str(place["secret"])).replace(TMP, str(place["tmp"])))


def check_refused(sql: str, place: dict[str, Path], baseline) -> None:
    """``sql`` in every format: a clean one-line refusal, and nothing changed or created anywhere."""
    count_case(SUITE)
    for fmt in FORMATS:
        result = run_cli("-w", str(place["root"]), "sql", "-f", fmt, "--", sql)
        assert_clean_error(result)
        assert len(result.stderr.strip().splitlines()) == 1, result.stderr
        assert SECRET not in result.stdout + result.stderr and "root:x:0:0" not in result.stdout
        assert (warehouse_digest(place["root"]), tree(place["root"]), tree(place["secret"].parent)) == baseline, sql[:300]
        assert not place["out"].exists() and not place["tmp"].exists(), sql[:300]


def test_copy_to_every_file_of_the_warehouse_is_refused(place, baseline):
    root = place["root"]
    targets = [p.as_posix() for p in sorted(root.rglob("*")) if p.is_file() and "_schemas" not in p.parts]
    targets += [resolve(t, place) for t in WRITE_TARGETS]  # one schema file among them
    assert any("/tables/" in t for t in targets) and any(t.endswith("catalog.duckdb") for t in targets)
    for target in targets:
        for form in ("COPY (SELECT 'x' AS clip) TO '{p}' (FORMAT parquet)", "COPY clips TO '{p}' (FORMAT csv)"):
            check_refused(statement(form, target), place, baseline)


@settings(FUZZ, max_examples=80)
@given(sql=hostile)
def test_hostile_statements_are_refused(place, baseline, sql):
    check_refused(resolve(sql, place), place, baseline)


@settings(FUZZ, max_examples=25)
@given(sql=garbage)
def test_garbage_is_refused(place, baseline, sql):
    check_refused(sql, place, baseline)


@settings(FUZZ, max_examples=8)
@given(sql=huge)
def test_huge_statements_are_refused(place, baseline, sql):
    check_refused(resolve(sql, place), place, baseline)


def test_the_fuzzed_warehouse_still_answers(place):
    """The same session answers ordinary queries (the refusals are not a broken command)."""
    result = run_cli("-w", str(place["root"]), "sql", "-f", "csv", "SELECT clip, count(*) AS n FROM frames GROUP BY clip ORDER BY clip")
    assert result.code == 0 and result.stdout.splitlines() == ["clip,n", "a,3", "b,3"]
    assert os.listdir(place["secret"].parent) == ["secret.csv"]
