"""Versioned reference indexes: on-disk format, read-only reader, hierarchy scoring.

Written by ``hmpf-index`` (package ``indexer``); read by the service and ``hmpf-eval --index``.
See :mod:`hmpf.index.layout` for the folder layout and :mod:`hmpf.index.storage` for HDF5.
"""

from hmpf.index.layout import (
    FORMAT_VERSION,
    HmpfIndexError,
    IndexBuildError,
    IndexCorruptError,
    IndexLockedError,
    IndexNotFoundError,
    IndexVersionError,
)
from hmpf.index.reader import IndexReader

__all__ = [
    "FORMAT_VERSION",
    "HmpfIndexError",
    "IndexBuildError",
    "IndexCorruptError",
    "IndexLockedError",
    "IndexNotFoundError",
    "IndexReader",
    "IndexVersionError",
]
