"""kklcasadi tune on PostgreSQL, against a real server this test starts: a throwaway cluster in a
temporary directory (``initdb``, ``pg_ctl``), listening on 127.0.0.1 on a free port, stopped at the end.
A study started on SQLite is copied to it and continued there by two worker processes."""

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

import pytest
from test_tune import _finish, _worker

from kklcasadi.evaluation import tune as tn
from kklcasadi.model.files import load_model
from kklcasadi.plant.systems import get

optuna = pytest.importorskip("optuna", reason="the tune extra is not installed: pip install 'kklcasadi[tune]'")
pytest.importorskip("psycopg", reason="no PostgreSQL driver: pip install 'kklcasadi[tune]' (psycopg 3)")
pytest.importorskip("kklcasadi.train", reason="tune trains observers (torch)")


def _bin_dir() -> Path | None:
    """The directory of PostgreSQL's server programs: ``initdb`` on PATH, else Debian's layout."""
    found = shutil.which("initdb") or next(iter(sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))[::-1]), None)
    return None if found is None else Path(found).resolve().parent


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def postgres():
    """``postgresql://kkl@127.0.0.1:PORT/tune`` of a server started for these tests."""
    bin_dir = _bin_dir()
    if bin_dir is None:
        pytest.skip("PostgreSQL's initdb was not found (on PATH or in /usr/lib/postgresql/*/bin): no server to test "
                    "against; apt-get install postgresql")
    run_as: list[str] = []
    if os.geteuid() == 0:                        # initdb and postgres refuse to run as root
        try:
            user = pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root, and there is no 'postgres' user to run the PostgreSQL server as")
        if shutil.which("runuser") is None:
            pytest.skip("running as root without runuser, so the PostgreSQL server cannot be started as 'postgres'")
        run_as = ["runuser", "-u", "postgres", "--"]
    root = Path(tempfile.mkdtemp(prefix="kklcasadi-pg-"))          # in /tmp: the server's user can reach it
    if run_as:
        os.chown(root, user.pw_uid, user.pw_gid)
    data, port = root / "data", _free_port()

    def pg(program: str, *args: str, **kwargs) -> subprocess.CompletedProcess:
        return subprocess.run([*run_as, str(bin_dir / program), *args], capture_output=True, text=True, **kwargs)

    started = False
    try:
        init = pg("initdb", "-D", str(data), "-U", "kkl", "--auth=trust", "-E", "UTF8", "--no-sync")
        if init.returncode != 0:
            pytest.skip(f"no PostgreSQL server could be started here: initdb failed: {init.stderr.strip()[-300:]}")
        start = pg("pg_ctl", "-D", str(data), "-l", str(root / "server.log"), "-w", "-t", "60", "-o",
                   f"-p {port} -k {root} -c listen_addresses=127.0.0.1 -c fsync=off", "start")
        started = start.returncode == 0
        if not started:
            log = (root / "server.log").read_text() if (root / "server.log").exists() else ""
            pytest.skip(f"no PostgreSQL server could be started here: pg_ctl start failed: "
                        f"{(start.stderr + log).strip()[-300:]}")
        created = pg("createdb", "-h", "127.0.0.1", "-p", str(port), "-U", "kkl", "tune")
        assert created.returncode == 0, created.stderr
        yield f"postgresql://kkl@127.0.0.1:{port}/tune"
    finally:
        if started:
            pg("pg_ctl", "-D", str(data), "-m", "immediate", "-w", "stop")
        shutil.rmtree(root, ignore_errors=True)


def test_a_sqlite_study_continues_on_postgresql_with_two_workers(tmp_path, postgres):
    local, sqlite_url = tmp_path / "here", f"sqlite:///{tmp_path / 'here' / 'study.db'}"
    settings = dict(caps={"runs": 32, "epochs": 3}, val_trials=4, heartbeat=1, sampler_seed=1, progress=False)
    assert tn.tune(get("duffing"), "bank", local, n_trials=1, **settings).ran == 1     # on this machine's SQLite
    # the first worker on a new server alone (it creates Optuna's tables): it copies the study, which is complete
    copied = tn.tune(get("duffing"), "bank", local, n_trials=1, storage=postgres, copy_from=sqlite_url, **settings)
    assert copied.ran == 0 and len(copied.study.trials) == 1
    workers = [_worker(tmp_path / f"w{i}", 3, 10 + i, "--storage", postgres) for i in range(2)]   # then two join
    for proc in workers:
        _finish(proc)
    sqlite = optuna.load_study(study_name="duffing-bank", storage=sqlite_url)
    study = optuna.load_study(study_name="duffing-bank", storage=postgres.replace("postgresql", "postgresql+psycopg"))
    complete = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    assert len(complete) >= 3 and len(sqlite.trials) == 1
    assert (study.trials[0].params, study.trials[0].value) == (sqlite.trials[0].params, sqlite.trials[0].value)
    new = {t.user_attrs["worker"] for t in complete[1:]}
    assert {f"{socket.gethostname()}:{proc.pid}" for proc in workers} == new         # both did trials
    assert study.user_attrs["record"] == sqlite.user_attrs["record"]
    cards = [load_model(tmp_path / f"w{i}" / "best").card["search"] for i in range(2)]   # the best when each ended
    assert all(card["storage"] == postgres and card["value"] == study.trials[card["trial"]].value for card in cards)
    assert min(card["value"] for card in cards) == study.best_value


def test_workers_started_at_the_same_moment_on_a_new_postgresql_storage(postgres):
    """A new database's tables are made by whichever worker comes first; the others try again and join."""
    import sqlalchemy
    from conftest import race
    from test_tune_safety import _open

    admin = sqlalchemy.create_engine(tn.storage.driver_url(postgres), isolation_level="AUTOCOMMIT")
    for attempt in range(4):
        with admin.connect() as connection:
            connection.execute(sqlalchemy.text(f"CREATE DATABASE fresh{attempt}"))
        url = postgres.rsplit("/", 1)[0] + f"/fresh{attempt}"
        assert race(_open, [(url,)] * 3, timeout=120) == ["ok"] * 3
    admin.dispose()
