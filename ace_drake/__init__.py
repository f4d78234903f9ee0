"""ace_drake: the table tennis robot of Sony AI's Ace (Nature, 2026) as a Drake model.

Importing the package points numba's on-disk cache of compiled kernels at a directory named by a
hash of every source file that compiles kernels. numba keys a cached kernel on its own file only,
so a kernel that calls a kernel in another file (``propagate._simulate_ball`` calls
``physics.contact``'s) would otherwise keep the stale callee after that file changes. An edit to
any kernel file now recompiles them all, once. ``NUMBA_CACHE_DIR``, if set, is kept.
"""

import hashlib
import os
import pathlib
import re
import sys
import time


def _kernel_cache_dir(package: pathlib.Path) -> pathlib.Path:
    """``package/__pycache__/numba-<hash>``, the hash of the package's kernel sources (the files
    that import numba); other such directories older than a day are removed."""
    digest = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        text = path.read_bytes()
        if re.search(rb"^import numba", text, re.MULTILINE):
            digest.update(str(path.relative_to(package)).encode() + b"\0" + text)
    cache = package / "__pycache__" / f"numba-{digest.hexdigest()[:16]}"
    try:
        for stale in cache.parent.glob("numba-*"):
            if stale != cache and time.time() - stale.stat().st_mtime > 86400:
                import shutil

                shutil.rmtree(stale, ignore_errors=True)
        cache.mkdir(parents=True, exist_ok=True)
    except OSError:  # a read-only installation: numba falls back to its own locations
        pass
    return cache


if "NUMBA_CACHE_DIR" not in os.environ:
    os.environ["NUMBA_CACHE_DIR"] = str(_kernel_cache_dir(pathlib.Path(__file__).resolve().parent))
    if "numba" in sys.modules:  # imported first: its configuration has read the environment already
        sys.modules["numba"].config.CACHE_DIR = os.environ["NUMBA_CACHE_DIR"]
