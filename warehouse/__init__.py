"""Parquet storage with atomic partition writes, and the DuckDB catalog over it.

The names below are imported on first use (a module ``__getattr__``), so ``from warehouse import
Warehouse`` does not import DuckDB, and nothing here imports pyarrow before a table is read or written.
Importing the package registers the catalog's check (:func:`warehouse.catalog.after_write`: once
per process, the catalog is made current) as the store's after-write hook
(:data:`warehouse.store.AFTER_WRITE`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from warehouse import store as _store

if TYPE_CHECKING:
    from warehouse.catalog import connect, refresh_catalog
    from warehouse.store import Warehouse, WarehouseError, atomic_write_bytes, check_name

__all__ = ["Warehouse", "WarehouseError", "atomic_write_bytes", "check_name", "connect", "refresh_catalog"]

_FROM = {"Warehouse": "warehouse.store", "WarehouseError": "warehouse.store", "atomic_write_bytes": "warehouse.store",
         "check_name": "warehouse.store", "connect": "warehouse.catalog", "refresh_catalog": "warehouse.catalog"}


def _after_write(wh: Warehouse) -> None:
    """After a write, the catalog exists and is current (:func:`warehouse.catalog.after_write`,
    checked once per process; DuckDB is imported on the first write). Wired here, above both
    modules, so that the store does not import the catalog that imports it."""
    from warehouse.catalog import after_write

    after_write(wh)


_store.AFTER_WRITE.append(_after_write)


def __getattr__(name: str) -> Any:
    """The names of :data:`__all__`, from :mod:`warehouse.store` and :mod:`warehouse.catalog`."""
    import importlib

    if name not in _FROM:
        raise AttributeError(f"module 'warehouse' has no attribute {name!r}")
    value = getattr(importlib.import_module(_FROM[name]), name)
    globals()[name] = value
    return value
