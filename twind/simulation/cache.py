"""numba's on-disk cache of the engine's compiled loops, kept by every source they compile from.

numba keys a cached function on its own file alone. The engine's loops (`kernel.py`) take in
the vector intrinsics of `simd.py` and the generators of `rng.py` when compiled, so a change
to either, with `kernel.py` unchanged, would leave the cached loops compiled from the old
code, silently. Functions defined in this package are cached by the hash of all three files.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from numba.core import config
from numba.core.caching import CacheImpl, InTreeCacheLocator

PACKAGE = Path(__file__).resolve().parent
SOURCES = ("kernel.py", "rng.py", "simd.py")


def sources_hash() -> bytes:
    """SHA-256 of the files the engine's loops are compiled from."""
    digest = hashlib.sha256()
    for name in SOURCES:
        digest.update((PACKAGE / name).read_bytes())
    return digest.digest()


class EngineCacheLocator(InTreeCacheLocator):
    """numba's in-tree cache (``__pycache__`` beside the sources) for this package's
    functions, stamped with :func:`sources_hash`; ``NUMBA_CACHE_DIR``, when set, is left
    to numba's own locator."""

    @classmethod
    def from_function(cls, py_func, py_file: str) -> EngineCacheLocator | None:  # noqa: ANN001
        if config.CACHE_DIR or Path(py_file).resolve().parent != PACKAGE:
            return None
        return super().from_function(py_func, py_file)

    def get_source_stamp(self) -> bytes:
        return sources_hash()


def register() -> None:
    """Have numba's cache locate this package's functions with :class:`EngineCacheLocator`
    (idempotent). numba chooses a function's locator when it is decorated, so each module
    of cached functions calls this before its first."""
    if EngineCacheLocator not in CacheImpl._locator_classes:
        CacheImpl._locator_classes.insert(0, EngineCacheLocator)
