"""Every writer killed at each of its file operations leaves the old artefact or the new one whole.

A forked child runs the writer with its file operations under the artefact's directory counted (``open`` for
writing, ``os.open`` with ``O_CREAT``, ``mkdir``, ``link``, ``rename``, ``replace``, ``unlink``, ``rmdir``,
``fsync``, the directory exchange) and dies (``os._exit``, no cleanup, as ``kill -9``) at the k-th; the test then
checks what is on disk, for k = 1, 2, ... until the writer finishes unkilled. The writers: ``export --c`` and
``--casadi`` (over an earlier export), ``train`` (over an earlier model), ``estimate`` (over an earlier estimate),
``tune``'s outputs (``best/``, ``summary.md``, ``search.png``) and ``save_model``."""

import builtins
import io
import os
import shutil
import sys
import traceback
from pathlib import Path

import numpy as np
import pytest

import kklcasadi.writes as writes
from kklcasadi.model.files import load_model, save_model

ROOT = Path(__file__).resolve().parents[1]
KILLED = 137


def _under(root: str, value) -> bool:
    if isinstance(value, (str, bytes, os.PathLike)):
        text = os.fsdecode(value)
        return os.path.abspath(text).startswith(root)
    return False


def _install(root: Path, k: int) -> None:
    """In the child: count the file operations under ``root`` and die at the ``k``-th."""
    root_text = str(root.resolve())
    count = [0]

    def tick():
        count[0] += 1
        if count[0] == k:
            os._exit(KILLED)

    def counted(fn, test):
        def wrapper(*args, **kwargs):
            if test(*args, **kwargs):
                tick()
            return fn(*args, **kwargs)
        return wrapper

    any_path = lambda *a, **k: any(_under(root_text, v) for v in a[:2])  # noqa: E731
    writing = lambda file, mode="r", *a, **k: _under(root_text, file) and any(c in mode for c in "wax+")  # noqa: E731
    creating = lambda path, flags, *a, **k: _under(root_text, path) and bool(flags & (os.O_CREAT | os.O_WRONLY))  # noqa: E731
    for name in ("rename", "replace", "link", "unlink", "remove", "rmdir", "mkdir", "symlink"):
        setattr(os, name, counted(getattr(os, name), any_path))
    os.open = counted(os.open, creating)
    os.fsync = counted(os.fsync, lambda *a, **k: True)
    builtins.open = io.open = counted(io.open, writing)
    writes._exchange = counted(writes._exchange, any_path)


def _run_killed(root: Path, k: int, writer) -> int:
    """Fork, kill the writer at its k-th file operation under ``root``; the child's exit status."""
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:                                                   # the child
        try:
            _install(root, k)
            writer()
        except BaseException:  # an error in the writer is a failure of this test: shown, and reported by the status
            traceback.print_exc()
            os._exit(3)
        os._exit(0)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)


def _sweep(root: Path, prepare, writer, check, *, at_most: int = 80) -> int:
    """Kill ``writer`` at its 1st, 2nd, ... file operation (after ``prepare`` restores the old state each time) and
    ``check`` what is left; returns the number of operations the unkilled writer does."""
    for k in range(1, at_most + 1):
        prepare()
        code = _run_killed(root, k, writer)
        assert code in (0, KILLED), f"the writer failed (status {code}) at k = {k}"
        check(killed=code == KILLED)
        if code == 0:
            return k - 1
    raise AssertionError(f"the writer did more than {at_most} file operations")


def _files(directory: Path) -> dict:
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir()) if p.is_file()}


def _content(path: Path) -> bytes:
    """What a file says, without its provenance stamp (its time differs from run to run): a CSV or markdown file
    without the stamp line, a PNG as its decoded pixels (which a truncated file does not decode to)."""
    from kklcasadi import provenance

    if path.suffix == ".png":
        import matplotlib.image

        return matplotlib.image.imread(path).tobytes()
    text = path.read_text()
    if provenance.read(path) is not None:
        text = text.partition("\n")[2]
    return text.encode()


def _reset(target: Path, snapshot: Path) -> None:
    """``target`` as ``snapshot``, alone in its directory (a killed writer's temporary files removed)."""
    for entry in target.parent.iterdir():
        shutil.rmtree(entry) if entry.is_dir() and not entry.is_symlink() else entry.unlink()
    shutil.copytree(snapshot, target) if snapshot.is_dir() else shutil.copyfile(snapshot, target)


def test_export_c_killed_at_each_file_operation_leaves_one_whole_export(tmp_path):
    from kklcasadi.cli import main

    old_model, new_model = ROOT / "models" / "duffing" / "autonomous", ROOT / "models" / "duffing" / "inject"
    work, snaps = tmp_path / "work", tmp_path / "snaps"
    work.mkdir()
    snaps.mkdir()
    assert main(["export", str(old_model), "--c", str(snaps / "old")]) == 0
    (snaps / "old" / "kkl_obs").write_bytes(b"the user's binary")           # not the writer's: it stays
    assert main(["export", str(new_model), "--c", str(snaps / "new")]) == 0
    old, new = _files(snaps / "old"), {**_files(snaps / "new"), "kkl_obs": b"the user's binary"}
    assert old != new
    target = work / "c"

    def check(killed):
        assert _files(target) in (old, new)
        if not killed:
            assert _files(target) == new and sorted(os.listdir(work)) == ["c"]

    ops = _sweep(work, lambda: _reset(target, snaps / "old"),
                 lambda: main(["export", str(new_model), "--c", str(target), "--overwrite"]), check)
    assert ops >= 5, ops


def test_export_casadi_killed_at_each_file_operation(tmp_path):
    from kklcasadi.cli import main

    work, snaps = tmp_path / "work", tmp_path / "snaps"
    work.mkdir()
    snaps.mkdir()
    assert main(["export", str(ROOT / "models" / "duffing" / "autonomous"), "--casadi", str(snaps / "old")]) == 0
    assert main(["export", str(ROOT / "models" / "duffing" / "inject"), "--casadi", str(snaps / "new")]) == 0
    target = work / "step.casadi"

    def check(killed):
        assert target.read_bytes() in ((snaps / "old").read_bytes(), (snaps / "new").read_bytes())

    _sweep(work, lambda: _reset(target, snaps / "old"),
           lambda: main(["export", str(ROOT / "models" / "duffing" / "inject"), "--casadi", str(target),
                         "--overwrite"]), check)


def test_save_model_killed_at_each_file_operation(tmp_path):
    source = load_model(ROOT / "models" / "duffing" / "autonomous")
    old_arrays = dict(source.arrays)
    new_arrays = {name: value + 1.0 if name.endswith("W0") else value for name, value in old_arrays.items()}
    work, snaps = tmp_path / "work", tmp_path / "snaps"
    work.mkdir()
    save_model(snaps / "old", old_arrays, source.card)
    target = work / "m"

    def check(killed):
        arrays = load_model(target).arrays
        assert all(np.array_equal(arrays[n], old_arrays[n]) for n in arrays) or \
            all(np.array_equal(arrays[n], new_arrays[n]) for n in arrays)

    _sweep(work, lambda: _reset(target, snaps / "old"),
           lambda: save_model(target, new_arrays, source.card, overwrite=True), check)


@pytest.fixture
def one_thread():
    """Torch on one thread while the test forks (an OpenMP pool does not survive a fork), and the same sums in the
    child as in the parent."""
    torch = pytest.importorskip("torch")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_train_killed_at_each_file_operation_leaves_the_old_or_the_new_model(tmp_path, one_thread):
    from kklcasadi.train import default_config, train_observer
    from kklcasadi.train.config import LoopConfig

    loop = LoopConfig(epochs=1, batch_size=64, lr=3e-3)
    config = default_config("duffing", "autonomous", width=8, depth=2, n_traj=8, t_keep=1.0, n_pde=100,
                            dtype="float64", encoder=loop, decoder=loop)
    work, snaps = tmp_path / "work", tmp_path / "snaps"
    work.mkdir()
    snaps.mkdir()
    shutil.copytree(ROOT / "models" / "duffing" / "autonomous", snaps / "old")
    new = load_model(train_observer("duffing", "autonomous", snaps / "new", config=config, progress=False))
    old = load_model(snaps / "old")
    target = work / "m"

    def check(killed):
        model = load_model(target)                        # whole: it loads, its card's digest and hash match
        assert model.card["weights_sha256"] in (old.card["weights_sha256"], new.card["weights_sha256"])

    ops = _sweep(work, lambda: _reset(target, snaps / "old"),
                 lambda: train_observer("duffing", "autonomous", target, config=config, progress=False,
                                        overwrite=True), check, at_most=120)
    assert ops >= 10, ops                                 # checkpoints, their record, the model


def test_estimate_killed_at_each_file_operation(tmp_path):
    import kklcasadi as kc
    from kklcasadi.cli import main

    plant = kc.systems.get("duffing")
    tr = kc.simulate(plant, [0.5, 0.0], kc.signals.make("sinusoid", amplitude=0.5, omega=1.0), T=3.0, dt=0.05,
                     measurement_std=0.02, seed=1)
    work, snaps = tmp_path / "work", tmp_path / "snaps"
    work.mkdir()
    snaps.mkdir()
    log = tmp_path / "log.csv"
    rows = zip(tr.t, tr.y[:, 0], tr.u[:, 0])
    log.write_text("time,y,u\n" + "".join(f"{float(t)!r},{float(y)!r},{float(u)!r}\n" for t, y, u in rows))
    args = ["estimate", str(ROOT / "models" / "duffing" / "bank"), "--data", str(log), "--y-cols", "y", "--u-cols",
            "u"]
    old_args = [args[0], str(ROOT / "models" / "duffing" / "autonomous"), *args[2:]]
    assert main([*old_args, "--out", str(snaps / "old.csv")]) == 0
    assert main([*args, "--out", str(snaps / "new.csv")]) == 0
    target = work / "est.csv"
    old, new = _content(snaps / "old.csv"), _content(snaps / "new.csv")
    assert old != new

    def check(killed):
        assert _content(target) in (old, new)

    _sweep(work, lambda: _reset(target, snaps / "old.csv"), lambda: main([*args, "--out", str(target)]), check)


def test_tune_outputs_killed_at_each_file_operation(tmp_path, one_thread):
    optuna = pytest.importorskip("optuna")
    from kklcasadi.evaluation import tune as tn
    from kklcasadi.evaluation.trialcache import TrialCache
    from kklcasadi.plant.systems import get

    out = tmp_path / "out"
    settings = dict(caps={"runs": 24, "epochs": 2}, val_trials=2, heartbeat=30, sampler_seed=1, progress=False)
    tn.tune(get("duffing"), "bank", out, n_trials=1, **settings)
    space = tn.search_space("bank", system="duffing", caps=settings["caps"])
    validation = tn.Validation.build(get("duffing"), tn.validation_cells(space.base, n_trials=2),
                                     trials=TrialCache(out / "cache"))
    snaps = tmp_path / "snaps"
    shutil.copytree(out, snaps)
    best = load_model(out / "best")
    summary, plot = _content(out / "summary.md"), _content(out / "search.png")
    url = tn.storage_url(None, out)

    def prepare():
        for name in ("best", "summary.md", "search.png"):
            target = out / name
            shutil.rmtree(target) if target.is_dir() else target.unlink(missing_ok=True)
            (shutil.copytree if (snaps / name).is_dir() else shutil.copyfile)(snaps / name, target)
        for entry in out.iterdir():
            if entry.name.startswith("."):
                shutil.rmtree(entry) if entry.is_dir() else entry.unlink()

    def writer():
        study = optuna.load_study(study_name="duffing-bank", storage=tn.storage.open_storage(url, 30))
        tn.export_best(study, out, get("duffing"), "bank", space, validation, url=url)
        writes.write_file(out / "summary.md", tn.summary_table(study, url) + "\n", overwrite=True)
        tn.search_plot(study, out / "search.png")

    def check(killed):
        model = load_model(out / "best")
        assert model.card["digest"] == best.card["digest"]
        assert _content(out / "summary.md") == summary and _content(out / "search.png") == plot

    _sweep(out, prepare, writer, check)
