"""Where a design search lives: Optuna (imported here, on first use), the storage URL and the RDB storage with
its heartbeat."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, Optional

__all__ = ["MAX_RETRY", "optuna_module", "storage_url", "public_url", "driver_url", "open_storage",
           "complete_trials"]

#: How often a killed trial is queued again (Optuna's ``RetryHeartbeatStaleTrialCallback(max_retry)``).
MAX_RETRY = 2


def _install_hint() -> str:
    return "pip install 'kklcasadi[tune]'"


def optuna_module() -> Any:
    try:
        import optuna
    except ImportError:
        raise ModuleNotFoundError(f"kklcasadi tune needs optuna, which is not installed; install the tune extra: "
                                  f"{_install_hint()}", name="optuna") from None
    return optuna


def storage_url(storage: Optional[str], out: Path) -> str:
    """The storage URL: ``storage`` as given, else the SQLite file ``out/study.db``."""
    return storage if storage else f"sqlite:///{(out / 'study.db').resolve()}"


def public_url(url: str) -> str:
    from sqlalchemy.engine import make_url

    return make_url(url).render_as_string(hide_password=True)


def driver_url(url: str) -> str:
    """A bare ``postgresql://`` URL with the driver the tune extra installs (psycopg 3), which SQLAlchemy
    before 2.1 does not take by default."""
    return "postgresql+psycopg://" + url[len("postgresql://"):] if url.startswith("postgresql://") else url


def open_storage(url: str, heartbeat: int) -> Any:
    optuna = optuna_module()
    url = driver_url(url)
    engine = {"connect_args": {"timeout": 60}} if url.startswith("sqlite") else {"pool_pre_ping": True}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.storages.RDBStorage(
            url, engine_kwargs=engine, heartbeat_interval=heartbeat, grace_period=3 * heartbeat,
            heartbeat_stale_trial_callback=optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRY))


def complete_trials(study: Any) -> list:
    optuna = optuna_module()
    return study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
