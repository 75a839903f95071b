"""Parquet storage with atomic partition writes, and the DuckDB catalog over it."""

from warehouse.catalog import connect, refresh_catalog
from warehouse.store import Warehouse, WarehouseError, atomic_write_bytes, check_name

__all__ = ["Warehouse", "WarehouseError", "atomic_write_bytes", "check_name", "connect", "refresh_catalog"]
