"""Read-only SQL over a warehouse (``cadestate sql``): its tables and nothing else.

A query runs in a session of its own: an in-memory DuckDB database holding the catalog's views
(the catalog file attached read-only when it is current for this warehouse, after a rebuild when
it is not; else views made from the warehouse it is given: a moved or copied warehouse answers
from itself, and a broken catalog file does not matter), then locked down before the statement runs:

- one statement, of a read-only kind: SELECT and its forms (WITH, FROM, VALUES, TABLE, DESCRIBE,
  SHOW, SUMMARIZE, UNPIVOT), or EXPLAIN [ANALYZE] of one. Every other kind (COPY, EXPORT, ATTACH,
  INSTALL, LOAD, SET, PRAGMA, CREATE, INSERT, CHECKPOINT, ...) is refused, before the warehouse is
  even read. A change written inside a SELECT (``WITH x AS (DELETE ... RETURNING ...) SELECT ...``)
  is of the SELECT kind; it fails on the views, which nothing can change (the catalog is attached
  read-only, or the views are made in memory over the files);
- files: only the warehouse's ``tables/`` folder can be read, and the catalog file the session
  attached (``enable_external_access = false`` with ``allowed_directories``): no other file, no
  network, no extension installed or loaded (none is auto-installed or auto-loaded), no Python object;
- the configuration is locked, and intermediate results that spill go to a private temporary
  folder, removed with the session. Nothing is written to the warehouse but derived files, as any
  command that opens the catalog writes them: the catalog file and a table's schema file
  (``tables/<table>/_schema/_schema.parquet``) when missing or outdated.

Results come in batches of rows (:func:`run_query`), so output starts at once and memory stays
bounded. A table file that vanishes before the first rows come (its partition rewritten or
compacted meanwhile) makes the statement run again, as :meth:`Warehouse.read` lists the files again;
so does a partition swapped in while the statement was planned (when DuckDB lists the files), which
could have left that partition's rows out without an error.
"""

from __future__ import annotations

import base64
import contextlib
import csv
import datetime as dt
import json
import math
import os
import re
import tempfile
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import duckdb

from warehouse.catalog import attach_views, one_line
from warehouse.snapshot import literal
from warehouse.store import READ_RETRIES, Warehouse, WarehouseError

BATCH_ROWS = 10_000
PLAN_TRIES = 20
"""Times :func:`run_query` plans a statement at most while partitions are swapped in as it is
planned. A try costs about its planning (1-5 ms): with a partition rewritten every 4-8 ms, 12 of
2,000 statements were still planned over a swap after 5 tries."""
READ_ONLY_KINDS = "SELECT (or WITH, FROM, VALUES, TABLE, DESCRIBE, SHOW, SUMMARIZE) or EXPLAIN of one"
_EXPLAIN = re.compile(r"^\s*EXPLAIN\s+(ANALYZE\s+)?", re.IGNORECASE)
_WORD = re.compile(r"[\s(]*([A-Za-z_]+)")
_LINE_CONTEXT = re.compile(r"\n\s*LINE \d+:.*", re.DOTALL)


class QueryError(WarehouseError):
    """A statement refused or failed (one line)."""


def _error(e: duckdb.Error) -> QueryError:
    """A DuckDB error as one line, without the echo of the statement (``LINE 1: ...``)."""
    return QueryError(f"SQL error: {one_line(_LINE_CONTEXT.sub('', str(e)))}")


_QUOTED = re.compile(r"""['"]([^'"]+)['"]""")


def _table_files(e: duckdb.Error, wh: Warehouse) -> list[Path]:
    """The paths under ``wh``'s ``tables/`` that DuckDB's error ``e`` names (in quotes), there or not
    (normalised: ``tables/../catalog.duckdb``, a file a statement named, is not a table's)."""
    tables = wh.root / "tables"
    return [path for path in (Path(os.path.normpath(q)) for q in _QUOTED.findall(str(e))) if path.is_relative_to(tables)]


def _failure(e: duckdb.Error, wh: Warehouse) -> WarehouseError:
    """A DuckDB error of a running statement as one line: a file of ``wh``'s tables that cannot be
    read (damaged: "No magic bytes found", "too small to be a Parquet file") is the warehouse's
    failure, said as :func:`read_rows` says it (a :class:`WarehouseError`, not a
    :class:`QueryError`: the statement is not what is wrong); any other error is the statement's."""
    if isinstance(e, (duckdb.IOException, duckdb.InvalidInputException)):
        for path in _table_files(e, wh):
            if path.is_file():
                table = path.relative_to(wh.root / "tables").parts[0]
                return WarehouseError(f"table {table}: cannot read its files: {one_line(_LINE_CONTEXT.sub('', str(e)))}")
    return _error(e)


def _parse(parser: duckdb.DuckDBPyConnection, sql: str) -> list[duckdb.Statement]:
    """The statements of ``sql``; a :class:`QueryError` when it does not parse."""
    try:
        sql.encode("utf-8")
    except UnicodeEncodeError as e:  # bytes of an argument that were not UTF-8 (surrogate-escaped)
        raise QueryError(f"SQL error: the statement is not UTF-8 text (character {e.start + 1})") from None
    try:
        return parser.extract_statements(sql)
    except duckdb.Error as e:
        raise _error(e) from None


def _kind(statement: duckdb.Statement) -> str:
    """The statement's kind (SELECT, COPY, ...); OTHER for one the Python client has no name for."""
    try:
        return statement.type.name
    except ValueError:  # UPDATE EXTENSIONS, say
        return "OTHER"


def read_only_statement(parser: duckdb.DuckDBPyConnection, sql: str) -> duckdb.Statement:
    """The one statement of ``sql`` if it only reads (see the module); a :class:`QueryError`
    otherwise. Only parsed (by ``parser``): nothing runs."""
    statements = _parse(parser, sql)
    if len(statements) != 1:
        raise QueryError(f"SQL error: {'no statement' if not statements else f'{len(statements)} statements'}: "
                         "give one statement")
    statement = checked = statements[0]
    if _kind(statement) == "EXPLAIN" and _EXPLAIN.match(statement.query):
        inner = _parse(parser, _EXPLAIN.sub("", statement.query, count=1))
        checked = inner[0] if len(inner) == 1 else statement
    kind = _kind(checked)
    if kind != "SELECT":
        word = _WORD.match(checked.query)
        said = word.group(1).upper() if word else kind
        hint = " (DESCRIBE <table> shows its columns)" if kind == "PRAGMA" else ""
        raise QueryError(f"SQL error: {said} is not allowed{f' (a {kind} statement)' if kind not in (said, 'OTHER') else ''}: "
                         f"`cadestate sql` is read-only ({READ_ONLY_KINDS}){hint}")
    return statement


def sql_condition(text: str) -> str:
    """``text``, to put between ``WHERE (`` and a newline and ``)``, if it is one SQL expression (a
    condition such as ``split = 'val'``): a :class:`QueryError` for anything else, a second statement
    (``;``), a parenthesis closing the ``WHERE`` or a clause after it (``true) UNION SELECT ...``,
    ``ORDER BY``, ``LIMIT``) included, and what one expression of a SELECT list may have after it
    but a condition may not (an alias, ``true AS x``; a ``;``, ``true;``): the text is parsed where
    it goes, too. Only parsed: nothing runs."""
    if not text.strip():
        raise QueryError("empty: give a SQL condition, e.g. \"split = 'val'\" (or true)")
    try:
        duckdb.SQLExpression(text)
    except duckdb.Error as e:
        raise QueryError(f"not one SQL condition: {one_line(str(e))}") from None
    parser = _reader()
    try:
        parser.extract_statements(f"SELECT 1 WHERE (\n{text}\n)")
    except duckdb.Error as e:  # SQLExpression takes "true AS x" (an alias) and "true;" (its ';' dropped)
        raise QueryError(f"not one SQL condition: {one_line(_LINE_CONTEXT.sub('', str(e)))} "
                         "(nothing may follow the condition: no alias, no ';')") from None
    finally:
        parser.close()
    return text


@dataclass
class Result:
    """Column names and the rows, in batches (a batch is a list of tuples)."""

    names: list[str]
    batches: Iterator[list[tuple]]


def _lock_down(con: duckdb.DuckDBPyConnection, wh: Warehouse) -> None:
    """Give ``con`` the views of ``wh`` (:func:`warehouse.catalog.attach_views`), then allow reading
    its ``tables/`` only and lock the configuration."""
    try:
        attach_views(con, wh)
    except (OSError, duckdb.Error) as e:
        raise WarehouseError(f"cannot read the warehouse {wh.root}: {one_line(str(e))}") from None
    tables = wh.root / "tables"  # as the views name it too: a pattern whose '[', '*' and '?' match themselves
    readable = sorted({f"{tables.as_posix()}/", f"{literal(tables)}/"})
    con.execute("SET allowed_directories = ?", [readable])
    con.execute("SET enable_external_access = false")
    con.execute("SET lock_configuration = true")


def _fetch(cursor: duckdb.DuckDBPyConnection, batch_rows: int) -> list[tuple]:
    """The next ``batch_rows`` rows of the open result of ``cursor`` (DuckDB's errors raised as
    they are; its interrupt as :class:`KeyboardInterrupt`)."""
    try:
        return cursor.fetchmany(batch_rows)
    except duckdb.InterruptException:
        raise KeyboardInterrupt from None


def _batches(cursor: duckdb.DuckDBPyConnection, first: list[tuple], batch_rows: int,
             wh: Warehouse) -> Iterator[list[tuple]]:
    """``first`` (the rows already fetched), then the rest of the open result of ``cursor`` (over
    ``wh``), ``batch_rows`` at a time; errors as one line (:func:`_failure`)."""
    rows = first
    while rows:
        yield rows
        try:
            rows = _fetch(cursor, batch_rows)
        except duckdb.Error as e:
            raise _failure(e, wh) from None


def _vanished(e: duckdb.Error, wh: Warehouse) -> bool:
    """Whether ``e`` says a file under ``wh``'s ``tables/`` that is no longer there could not be
    opened: a partition rewritten (its files swapped) while the statement read it."""
    if not isinstance(e, duckdb.IOException) or "Cannot open file" not in str(e):
        return False
    return any(not path.exists() for path in _table_files(e, wh))


def _execute(con: duckdb.DuckDBPyConnection, statement: duckdb.Statement) -> duckdb.DuckDBPyConnection:
    """``con.execute(statement)`` in a thread of its own, so that Ctrl-C (KeyboardInterrupt, in
    this thread) interrupts the query at once: DuckDB itself noticed it only after many seconds."""
    done: dict[str, Any] = {}
    finished = threading.Event()  # not Thread.join: a join that Ctrl-C broke may return at once after

    def work() -> None:
        try:
            done["cursor"] = con.execute(statement)
        except BaseException as e:  # handed to the caller's thread
            done["error"] = e
        finally:
            finished.set()

    threading.Thread(target=work, name="cadestate-sql", daemon=True).start()
    try:
        while not finished.wait(0.1):
            pass
    except BaseException:  # Ctrl-C, or SIGTERM's exit: the query stops before its connection closes
        con.interrupt()
        while True:
            try:
                finished.wait()
                break
            except KeyboardInterrupt:  # a second Ctrl-C: still waiting for the query to stop
                continue
        raise
    if "error" in done:
        raise done["error"]
    return done["cursor"]


@contextlib.contextmanager
def run_query(wh: Warehouse, sql: str, limit: int | None = None, batch_rows: int = BATCH_ROWS) -> Iterator[Result]:
    """Run ``sql`` over ``wh`` in a locked-down session (see the module) and stream its rows (at
    most ``limit``). The statement is checked before the warehouse is read, then started as
    :func:`_start` starts it (again where partitions were rewritten under it)."""
    with tempfile.TemporaryDirectory(prefix="cadestate-sql-") as spill:
        config = {"temp_directory": spill, "autoinstall_known_extensions": False,
                  "autoload_known_extensions": False, "allow_community_extensions": False,
                  "allow_unsigned_extensions": False}
        con = duckdb.connect(":memory:", config=config)
        try:
            statement = read_only_statement(con, sql)
            _lock_down(con, wh)
            cursor, first = _start(con, statement, wh, batch_rows)
            yield Result([d[0] for d in cursor.description], head(_batches(cursor, first, batch_rows, wh), limit))
        finally:
            con.close()


def _start(con: duckdb.DuckDBPyConnection, statement: duckdb.Statement, wh: Warehouse,
           batch_rows: int) -> tuple[duckdb.DuckDBPyConnection, list[tuple]]:
    """Run ``statement`` and fetch its first ``batch_rows`` rows; the cursor and those rows. Run again
    when a table's folder changed while it was planned (:meth:`Warehouse.table_times`: a partition
    swapped in then may have been listed short, its rows left out without an error; see
    :mod:`warehouse.store`), up to :data:`PLAN_TRIES` times, and when a file of a table vanished
    before the first rows came (its partition rewritten or compacted after it was planned), up to
    :data:`READ_RETRIES` times: it only reads. Still planned over swaps after that: a
    :class:`QueryError`, not rows that may miss a partition."""
    vanished = 0
    for _ in range(PLAN_TRIES):
        planned = wh.table_times()
        try:
            cursor = _execute(con, statement)
            if wh.table_times() == planned:  # DuckDB lists the files of its globs as it plans
                return cursor, _fetch(cursor, batch_rows)
        except duckdb.Error as e:
            vanished += 1
            if not _vanished(e, wh) or vanished == READ_RETRIES:
                raise _failure(e, wh) from None
    raise QueryError(f"SQL error: partitions of the tables were rewritten under each of {PLAN_TRIES} tries of the "
                     "statement: run it again")


EPOCH = dt.datetime(1970, 1, 1, tzinfo=dt.timezone.utc)
_READER: tuple[int, duckdb.DuckDBPyConnection] | None = None
"""The process's in-memory DuckDB database for :func:`read_rows` (with the pid that opened it)."""


def _reader() -> duckdb.DuckDBPyConnection:
    """A new cursor on the process's reading database: opening a DuckDB database costs ~25 ms, a
    cursor (a connection of its own, safe to use from its thread) almost nothing. A forked child
    opens its own database."""
    global _READER
    if _READER is None or _READER[0] != os.getpid():
        _READER = (os.getpid(), duckdb.connect())
    return _READER[1].cursor()


def read_rows(wh: Warehouse, table: str, columns: Sequence[str], partitions: Sequence[str] | None = None,
              timestamps: Sequence[str] = ()) -> list[dict[str, Any]]:
    """The ``columns`` of ``wh.read(table, partitions).to_pylist()``, read by DuckDB: neither pyarrow
    nor its dataset module (which imports pandas) is imported, so that ``cadestate status`` costs
    little more than importing DuckDB. For columns of scalar types (strings, integers, floats,
    booleans) and ``timestamps``, UTC timestamp columns, which come back as UTC datetimes (as
    pyarrow gives them, whatever DuckDB's time zone). Rows sorted by the table's whole key, as
    :meth:`Warehouse.read` sorts them; a column that no file has (an older schema) reads as None. A
    file that vanishes while it is read (its partition compacted) makes it list the files again."""
    for attempt in range(READ_RETRIES):
        files = wh.file_paths(table, partitions)
        if not files:
            return []
        con = _reader()
        patterns = [literal(Path(f)) for f in files]  # each matches its file alone
        try:
            try:  # every column in some file (the common case): one pass
                rows = _select(con, patterns, columns, timestamps, wh.info[table].key, set(columns) | set(wh.info[table].key))
            except duckdb.BinderException:  # a column that no file has (an older schema) reads as None
                source = "read_parquet(?, union_by_name = true)"
                present = {r[0] for r in con.execute(f"DESCRIBE SELECT * FROM {source}", [patterns]).fetchall()}
                rows = _select(con, patterns, columns, timestamps, wh.info[table].key, present)
            break
        except duckdb.IOException as e:
            if all(Path(f).exists() for f in files) or attempt == READ_RETRIES - 1:
                raise WarehouseError(f"table {table}: cannot read its files: {one_line(str(e))}") from None
        except duckdb.Error as e:  # a damaged file ("No magic bytes found"): one line naming it, not a traceback
            raise WarehouseError(f"table {table}: cannot read its files: {one_line(str(e))}") from None
        finally:
            con.close()
    out = [dict(zip(columns, r)) for r in rows]
    for c in timestamps:
        for r in out:
            if r[c] is not None:
                r[c] = EPOCH + dt.timedelta(microseconds=r[c])
    return out


def _select(con: duckdb.DuckDBPyConnection, patterns: list[str], columns: Sequence[str], timestamps: Sequence[str],
            key: Sequence[str], present: set[str]) -> list[tuple]:
    """:func:`read_rows`'s query over the files of ``patterns`` (:func:`warehouse.snapshot.literal`),
    reading as NULL the columns not ``present``."""
    select = [("epoch_us" + f"({_ident(c)})" if c in timestamps else _ident(c)) if c in present else "NULL"
              for c in columns]
    order = "".join(f"{', ' if i else ' ORDER BY '}{_ident(k)}" for i, k in enumerate(k for k in key if k in present))
    return con.execute(f"SELECT {', '.join(select)} FROM read_parquet(?, union_by_name = true){order}", [patterns]).fetchall()


def _ident(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def head(batches: Iterator[list[tuple]], limit: int | None) -> Iterator[list[tuple]]:
    """The batches cut after ``limit`` rows in all (all of them when None)."""
    if limit is None:
        yield from batches
        return
    for rows in batches:
        if limit <= 0:
            return
        yield rows[:limit]
        limit -= len(rows)


def split(batches: Iterator[list[tuple]], limit: int) -> tuple[list[tuple], int]:
    """The first ``limit`` rows, and how many rows follow them (counted, not kept)."""
    first: list[tuple] = []
    rest = 0
    for rows in batches:
        take = rows[: max(0, limit - len(first))]
        first += take
        rest += len(rows) - len(take)
    return first, rest


def json_value(value: Any) -> Any:
    """``value`` as JSON can hold it: non-finite floats become null, map keys strings, bytes (a
    BLOB) base64, and what JSON has no type for (dates, decimals, UUIDs) its text."""
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, (bytes, bytearray)):  # str() gave Python's repr, b'...'
        return base64.b64encode(value).decode("ascii")
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_value(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_value(v) for v in value]
    return str(value)


def unique_names(names: Sequence[str]) -> list[str]:
    """``names`` with a repeated one suffixed ``_1``, ``_2``, ... (a join's two ``translation``
    columns; never a name another column has): a JSON object keeps one value per key."""
    reserved, out = set(names), []
    for name in names:
        new, k = name, 0
        while new in out:
            k += 1
            new = f"{name}_{k}"
            while new in reserved:
                k += 1
                new = f"{name}_{k}"
        out.append(new)
    return out


def write_json(result: Result, out: TextIO) -> None:
    """A JSON array of one object per row, one row a line, written as the rows come (repeated
    column names made unique: :func:`unique_names`)."""
    names = unique_names(result.names)
    out.write("[")
    sep = "\n"
    for rows in result.batches:
        for row in rows:
            out.write(sep + json.dumps({n: json_value(v) for n, v in zip(names, row)}, allow_nan=False))
            sep = ",\n"
    out.write("\n]\n" if sep != "\n" else "]\n")


def csv_value(value: Any) -> Any:
    """``value`` as a CSV field: lists and maps as JSON and bytes base64 (not Python's repr),
    non-finite floats empty."""
    if isinstance(value, (bytes, bytearray)):
        return json_value(value)
    if isinstance(value, (list, tuple, dict)):
        return json.dumps(json_value(value))
    if isinstance(value, float) and not math.isfinite(value):
        return ""
    return value


def write_csv(result: Result, out: TextIO) -> None:
    """CSV with a header line, Unix line ends, written as the rows come."""
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(result.names)
    for rows in result.batches:
        writer.writerows([csv_value(v) for v in row] for row in rows)
