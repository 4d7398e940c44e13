"""The package version (one place: setup.cfg, model cards and cache keys read it)."""

__version__ = "0.1.0"
