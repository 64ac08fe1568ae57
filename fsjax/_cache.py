"""JAX's persistent compilation cache, switched on by the CLI, the tour and one helper.

XLA compilation is most of what a user waits for on a first call (a fit or a tour section
compiles for seconds, then runs in milliseconds). JAX can keep compiled programs on disk and
load them in a later process instead of compiling again; :func:`enable_compile_cache` turns
that on for the running process. ``import fsjax`` never changes global JAX state: the cache is
enabled only by ``fsjax tour``, ``fsjax run``/``evolve`` (the CLI) and by calling the helper.

Where the cache lives:

* ``FSJAX_CACHE_DIR`` (environment) overrides the location; ``FSJAX_CACHE_DIR=off`` (or ``0``,
  ``none``, ``false``) disables the cache everywhere, the CLI included;
* otherwise the user's cache directory: ``$XDG_CACHE_HOME/fsjax/xla`` (default
  ``~/.cache/fsjax/xla``) on Linux, ``~/Library/Caches/fsjax/xla`` on macOS,
  ``%LOCALAPPDATA%\\fsjax\\xla`` on Windows.

Thresholds (measured, see ``docs/compile_cache.md``): by default every compiled program is
written (``min_compile_time_s=0``): on tour sections a warm run took 0.39 of the cold CPU
time this way, against 0.51 with a 0.1 s threshold and 0.48 with JAX's default of 1 s, for
7 % more disk (the small programs of eager op-by-op dispatch are many). Entries of any size
are kept.
The cache is keyed by JAX on the program, the jax/jaxlib version, the backend and the XLA
flags, so a stale entry is never loaded for a different program; deleting the directory is
always safe.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = ["enable_compile_cache", "compile_cache_dir"]

_OFF = {"off", "0", "none", "false", "no", ""}


def compile_cache_dir(path: str | os.PathLike | None = None) -> Path | None:
    """The directory the compile cache would use, or ``None`` when it is switched off.

    Args:
        path: an explicit directory; ``None`` means ``FSJAX_CACHE_DIR`` if set, else the
            platform's user cache directory (see the module docstring).

    Returns:
        The resolved directory (not created), or ``None`` if ``FSJAX_CACHE_DIR`` (or ``path``)
        says ``off``.

    Example:
        >>> import os
        >>> from fsjax import compile_cache_dir
        >>> os.environ["FSJAX_CACHE_DIR"] = "off"
        >>> compile_cache_dir() is None
        True
        >>> del os.environ["FSJAX_CACHE_DIR"]
        >>> str(compile_cache_dir("/tmp/x"))
        '/tmp/x'
    """
    if path is None:
        env = os.environ.get("FSJAX_CACHE_DIR")
        if env is not None:
            if env.strip().lower() in _OFF:
                return None
            return Path(env).expanduser()
    else:
        if str(path).strip().lower() in _OFF:
            return None
        return Path(path).expanduser()
    if sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    elif os.name == "nt":
        base = Path(os.environ.get("LOCALAPPDATA", Path.home() / "AppData" / "Local"))
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "fsjax" / "xla"


def enable_compile_cache(path: str | os.PathLike | None = None, *, min_compile_time_s: float = 0.0,
                         min_entry_size_bytes: int = 0) -> Path | None:
    """Switch on JAX's persistent compilation cache for this process.

    Later processes that compile the same program (same shapes, dtypes, flags and versions)
    load it from disk instead of compiling. Call it once, early (before the first compile);
    calling it again with the same directory is harmless.

    Args:
        path: cache directory; ``None`` resolves it as :func:`compile_cache_dir` does
            (``FSJAX_CACHE_DIR``, else the user's cache directory). ``"off"`` disables.
        min_compile_time_s: programs that compiled faster than this are not stored
            (default 0: all; measured in ``docs/compile_cache.md``).
        min_entry_size_bytes: smaller compiled programs are not stored (default 0: all).

    Returns:
        The directory in use, or ``None`` when the cache is off (nothing is changed then).

    Raises:
        ValueError: ``enable_compile_cache: argument 'min_compile_time_s' must be >= 0``
            (likewise for ``min_entry_size_bytes``).

    Example:
        >>> import tempfile, jax, jax.numpy as jnp
        >>> from fsjax import enable_compile_cache
        >>> d = enable_compile_cache(tempfile.mkdtemp(), min_compile_time_s=0.0)
        >>> _ = jax.jit(lambda x: jnp.sin(x) * 2)(jnp.ones(3)).block_until_ready()
        >>> any(d.iterdir())  # the compiled program was written
        True
        >>> enable_compile_cache("off") is None
        True
    """
    if not min_compile_time_s >= 0:
        raise ValueError(f"enable_compile_cache: argument 'min_compile_time_s' must be >= 0, got {min_compile_time_s!r}")
    if not min_entry_size_bytes >= 0:
        raise ValueError(
            f"enable_compile_cache: argument 'min_entry_size_bytes' must be >= 0, got {min_entry_size_bytes!r}")
    d = compile_cache_dir(path)
    if d is None:
        return None
    import jax

    d.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(d))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", int(min_entry_size_bytes))
    try:  # jax caches the "is the cache initialised" decision; a later dir change needs a reset
        from jax._src import compilation_cache as _cc

        _cc.reset_cache()
    except Exception:  # pragma: no cover - private API moved; the config above still applies
        pass
    return d


def near_map_limit() -> bool:
    """True when this process holds more than half of the kernel's ``vm.max_map_count`` memory
    mappings (Linux; False where it cannot tell). Every executable XLA:CPU compiles keeps a few
    (about 3) until released; at the limit mmap fails inside the JIT linker ("Failed to
    materialize symbols") and the process dies. A long-running caller (the test suite's workers,
    the chain fuzzer) drops its compiled programs (``jax.clear_caches()``) when this says so."""
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            limit = int(f.read())
    except (OSError, ValueError):
        limit = 65530
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f) > limit // 2
    except OSError:
        return False
