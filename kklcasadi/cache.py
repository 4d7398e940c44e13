"""Where kklcasadi keeps its on-disk caches (simulated trials, compiled code): :func:`cache_root`."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["cache_root", "CACHE_ENV"]

#: Environment variable naming the root of kklcasadi's caches (trials and compiled code).
CACHE_ENV = "KKLCASADI_CACHE"


def cache_root() -> Path:
    """The root of kklcasadi's on-disk caches.

    Returns
    -------
    Path
        ``$KKLCASADI_CACHE`` if set, else ``$XDG_CACHE_HOME/kklcasadi``, else
        ``~/.cache/kklcasadi``. Not created here.
    """
    explicit = os.environ.get(CACHE_ENV)
    if explicit:
        return Path(explicit).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg).expanduser() if xdg else Path.home() / ".cache") / "kklcasadi"
