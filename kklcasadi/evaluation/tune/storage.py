"""Where a design search lives: Optuna (imported here, on first use), the storage URL and the RDB storage with
its heartbeat."""

from __future__ import annotations

import time
import warnings
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Any, Iterator, Optional

from ...validation import ArgumentError, Text, error
from ...writes import locked

__all__ = ["MAX_RETRY", "SQLITE_TIMEOUT", "optuna_module", "storage_url", "public_url", "driver_url", "open_storage",
           "storage_errors", "check_sqlite", "complete_trials"]

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


#: Seconds a SQLite connection waits for another worker's lock before it gives up.
SQLITE_TIMEOUT = 60.0
#: Attempts at opening a PostgreSQL storage whose tables another worker is creating at the same moment.
SCHEMA_ATTEMPTS = 5
_SQLITE_HEADER = b"SQLite format 3\x00"


def _sqlite_file(url: str) -> Optional[Path]:
    """The database file of a ``sqlite:///`` URL (None for another storage or an in-memory database)."""
    prefix = "sqlite:///"
    return Path(url[len(prefix):]) if url.startswith(prefix) and len(url) > len(prefix) else None


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


@contextmanager
def storage_errors(url: str, argument: str = "storage") -> Iterator[None]:
    """Any error of the storage (its URL, its driver, its server, its file) as one :class:`ArgumentError` naming
    ``argument`` (the CLI: ``--storage``)."""
    from sqlalchemy.exc import SQLAlchemyError

    optuna = optuna_module()
    try:
        yield
    except (SQLAlchemyError, optuna.exceptions.StorageInternalError, ImportError) as exc:
        raise error(argument, "a storage Optuna can open and use", Text(f"{_safe_url(url)}: {_first_line(exc)}"),
                    "Check the URL, that the server runs and is reachable, and the file's permissions "
                    "(postgresql://user@host:5432/db, sqlite:///path/study.db).") from exc
    except ValueError as exc:                # a malformed URL (a port that is not a number, ...)
        if isinstance(exc, ArgumentError):
            raise
        raise error(argument, "an SQLAlchemy URL such as postgresql://user@host:5432/db",
                    Text(f"{_safe_url(url)} ({_first_line(exc)})")) from exc


def _safe_url(url: str) -> str:
    """The URL with its password hidden; a URL SQLAlchemy cannot parse is shown by its scheme alone."""
    from sqlalchemy.exc import ArgumentError as URLError

    try:
        return public_url(url)
    except (URLError, ValueError):
        return url.split("://", 1)[0] + "://..." if "://" in url else repr(url)


def check_sqlite(url: str) -> None:
    """Refuse a SQLite storage file that exists but is empty or not a SQLite database: Optuna would start a new
    study over it (and over the study's trials)."""
    path = _sqlite_file(url)
    if path is None or not path.exists():
        return
    if not path.is_file():
        raise error("storage", "a SQLite database file", Text(f"{path}, which is not a file"))
    with open(path, "rb") as stream:
        head = stream.read(len(_SQLITE_HEADER))
    if head != _SQLITE_HEADER:
        received = "an empty file" if not head else "a file that is not a SQLite database"
        raise error("storage", "the study's SQLite database", Text(f"{path}, {received}"),
                    "It may have been truncated or overwritten; restore it, or move it away to start a new study "
                    "in another --out (this one's trials/ belong to the old study).")


def open_storage(url: str, heartbeat: int) -> Any:
    """Optuna's RDB storage at ``url``, with the heartbeat and the retry of stale trials.

    Workers started at the same moment on a new storage do not race on its tables: on SQLite they take turns
    (a lock of the database's directory), on PostgreSQL a worker that finds the tables half made tries again.
    Every error of the storage is one :class:`ArgumentError` naming ``storage``.
    """
    optuna = optuna_module()
    driver = driver_url(url)
    sqlite = _sqlite_file(driver)
    engine = {"connect_args": {"timeout": SQLITE_TIMEOUT}} if driver.startswith("sqlite") else {"pool_pre_ping": True}

    def make() -> Any:
        with warnings.catch_warnings(), storage_errors(url):
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            return optuna.storages.RDBStorage(
                driver, engine_kwargs=engine, heartbeat_interval=heartbeat, grace_period=3 * heartbeat,
                heartbeat_stale_trial_callback=optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRY))

    if sqlite is not None:
        with locked(sqlite.parent) if sqlite.parent.is_dir() else nullcontext():
            check_sqlite(url)             # under the lock: a worker creating it now has finished
            return make()
    attempt = 0
    while True:
        try:
            return make()
        except ArgumentError as exc:
            attempt += 1
            if attempt == SCHEMA_ATTEMPTS or not _schema_race(exc.__cause__):
                raise
            time.sleep(0.2 * attempt)


def _schema_race(exc: Optional[BaseException]) -> bool:
    """Whether a storage error is another worker creating the same tables (a table or row that exists already)."""
    from sqlalchemy.exc import IntegrityError

    return isinstance(exc, IntegrityError) or "already exists" in str(exc)


def complete_trials(study: Any) -> list:
    optuna = optuna_module()
    return study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
