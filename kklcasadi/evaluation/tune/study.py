"""One worker of a design search (:func:`tune`): the study, its trials' models and the best one as a model
directory (:func:`export_best`)."""

from __future__ import annotations

import json
import os
import socket
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Union

from ... import provenance
from ...model import variants
from ...model.card import Search
from ...model.digest import DIGEST, read_json_object
from ...model.files import EXTRA_FILES, load_model, save_model
from ...observer.kkl import load_observer
from ...plant.systems import System
from ...validation import Text, error, positive_int
from ...writes import write_file
from ..trialcache import TrialCache
from .report import search_plot, summary_table
from .space import Space, search_space
from .storage import (
    MAX_RETRY,
    complete_trials,
    driver_url,
    open_storage,
    optuna_module,
    public_url,
    storage_errors,
    storage_url,
)
from .validation import VALIDATION_SEED, Validation, score, validation_cells

__all__ = ["TuneResult", "tune", "export_best", "TRIALS_DIR", "BEST_DIR", "BASELINE_DIR", "BINDING"]

PathLike = Union[str, os.PathLike]

#: Directory names under the study's ``--out``.
TRIALS_DIR, BEST_DIR, BASELINE_DIR = "trials", "best", "baseline"


@dataclass(frozen=True, eq=False)
class TuneResult:
    """What :func:`tune` did: the study, where the best model, the summary and the plot were written,
    and how many trials this worker ran."""

    study: Any
    best_dir: Optional[Path]
    summary: Path
    plot: Path
    ran: int


def _train(system: System, method: str, config: Any, out: Path, *, base: Optional[Path], seed: int,
           threads: int, overwrite: bool = False) -> float:
    from ...train import train_observer

    t0 = time.perf_counter()
    train_observer(system, method, out, config=config, base=base, seed=seed, progress=False, threads=threads,
                   overwrite=overwrite)
    return time.perf_counter() - t0


def _study_record(system: System, method: str, space: Space, validation: Validation, seed: int) -> dict:
    return {"system": system.name, "fingerprint": system.fingerprint, "method": method, "seed": seed,
            "space": space.describe(), "objective": validation.describe()}


def tune(system: System, method: str, out_dir: PathLike, *, n_trials: int, study: Optional[str] = None,
         storage: Optional[str] = None, config: Any = None, caps: Optional[dict] = None,
         base: Optional[PathLike] = None, seed: int = 0, threads: int = 1, val_trials: int = 20,
         heartbeat: int = 30, baseline: bool = False, copy_from: Optional[str] = None,
         sampler_seed: Optional[int] = None, progress: bool = True,
         stamp: Optional[provenance.Stamp] = None) -> TuneResult:
    """Run one worker of an Optuna study of ``method``'s design on ``system``.

    Parameters
    ----------
    system : System
    method : str
        A method with a search space (:data:`SPACES`).
    out_dir : path
        Where this worker writes: ``trials/NNNN/`` (each trial's model), ``best/`` (the best trial's
        model, its card's ``search`` records the study), ``summary.md``, ``search.png``, and
        ``study.db`` (the default storage).
    n_trials : int
        Complete trials the study stops at (over all workers); run again to resume, or with a larger
        number to extend it.
    study : str, optional
        The study's name; default ``"<system>-<method>"``.
    storage : str, optional
        An SQLAlchemy URL (``postgresql://user@host:port/db``, ``sqlite:///path``); default the
        SQLite file ``out_dir/study.db``.
    config : dataclass, optional
        The base configuration (default ``default_config(system.name, method)``).
    caps : dict, optional
        Budget caps (``{"runs": N, "epochs": M}``), default the configuration's own.
    base : path, optional
        The Phase-1 model, for methods that build on one.
    seed : int
        Training seed of every trial (the trials differ by configuration only).
    threads : int
        Torch threads of each training (1 per worker on a shared machine).
    val_trials : int
        Validation trials per cell.
    heartbeat : int
        Seconds between a running trial's heartbeats; a trial silent for three of them is failed
        and queued again by the next worker that starts a trial.
    baseline : bool
        Also train the base configuration at the budget caps (the recipe) and record its validation
        score in the study (once per study).
    copy_from : str, optional
        A storage URL to copy the study from before joining it (e.g. a local SQLite study that is
        to continue on PostgreSQL); nothing is copied when the study already exists in ``storage``
        (several workers may be started with it: one copies, the others join).
    sampler_seed : int, optional
        Seed of this worker's TPE sampler (default: none; workers must not share one).
    progress : bool
        Optuna's log lines per trial.
    stamp : kklcasadi.provenance.Stamp, optional
        The provenance of ``summary.md`` and ``search.png`` (default: this process's, with the seeds).

    Returns
    -------
    TuneResult
    """
    optuna = optuna_module()
    if not isinstance(system, System):
        raise error("system", "a kklcasadi.System", Text(type(system).__name__), kind=TypeError)
    n_trials = positive_int(n_trials, "n_trials")
    heartbeat = positive_int(heartbeat, "heartbeat")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    name = study or f"{system.name}-{method}"
    url = storage_url(storage, out)
    space = search_space(method, config, system=system.name, caps=caps)
    if base is None and variants.get(method).needs_base:
        raise error("base", f"the Phase-1 model {method!r} builds on (every worker's trials share it)", None,
                    "Train it once first: kklcasadi train --method autonomous --out DIR, then pass --base DIR.")
    base_path = None if base is None else Path(base).resolve()
    optuna.logging.set_verbosity(optuna.logging.INFO if progress else optuna.logging.WARNING)
    with storage_errors(url):
        binding = {"study": name, "storage": public_url(url)}
    moved_from = None                     # with --copy-from, the binding of the study before it moves on
    if copy_from is not None:
        with storage_errors(copy_from, "copy_from"):
            moved_from = {"study": name, "storage": public_url(copy_from)}
    _check_binding(out, binding, moved_from)
    storage_obj = open_storage(url, heartbeat)
    with storage_errors(url):
        exists = name in optuna.get_all_study_names(storage_obj)
    if copy_from and not exists:
        with storage_errors(copy_from, "copy_from"):
            try:
                optuna.copy_study(from_study_name=name, from_storage=driver_url(copy_from), to_storage=storage_obj)
            except optuna.exceptions.DuplicatedStudyError:
                pass                      # another worker started with --copy-from copied it first: join it
        exists = True
    if not exists:
        _check_new(out, binding)
    validation = Validation.build(system, validation_cells(space.base, n_trials=val_trials),
                                  trials=TrialCache(out / "cache"))
    record = _study_record(system, method, space, validation, seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        sampler = optuna.samplers.TPESampler(seed=sampler_seed, multivariate=True, group=True, constant_liar=True,
                                             n_startup_trials=min(10, max(2, n_trials // 3)))
    with storage_errors(url):
        the_study = optuna.create_study(study_name=name, storage=storage_obj, direction="minimize", sampler=sampler,
                                        load_if_exists=True)
        _check_record(the_study, record, name)
    _bind(out, binding, moved_from)
    if baseline and "baseline" not in the_study.user_attrs:
        path = out / BASELINE_DIR
        try:
            seconds = (load_model(path).card["training"].get("wall_time_s") if (path / "card.json").exists()
                       else _train(system, method, space.baseline(), path, base=base_path, seed=seed, threads=threads))
        except FileExistsError:          # another worker here trains it now (or just wrote it): that one records it
            seconds = None
        if (path / "card.json").exists() and seconds is not None:
            value, cells = score(load_observer(path, system=system), validation)
            with storage_errors(url):
                the_study.set_user_attr("baseline", {"value": value, "cells": cells, "train_s": round(seconds, 1)})

    started: list[int] = []                       # the trials this worker starts

    def objective(trial: Any) -> float:
        started.append(trial.number)
        trial.set_user_attr("worker", f"{socket.gethostname()}:{os.getpid()}")
        path = out / TRIALS_DIR / f"{trial.number:04d}"
        seconds = _train(system, method, space.suggest(trial), path, base=base_path, seed=seed, threads=threads)
        trial.set_user_attr("model", load_model(path).card[DIGEST]["sha256"])
        value, cells = score(load_observer(path, system=system), validation)
        trial.set_user_attr("cells", cells)
        trial.set_user_attr("train_s", round(seconds, 1))
        return value

    complete = len(the_study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,)))
    todo = n_trials - complete
    if todo > 0:
        stop = optuna.study.MaxTrialsCallback(n_trials, states=(optuna.trial.TrialState.COMPLETE,))
        # at most the missing number of trials in this worker: trials that fail count too
        with storage_errors(url):
            the_study.optimize(objective, n_trials=todo + MAX_RETRY, callbacks=[stop],
                               catch=(ValueError, RuntimeError))
    best_dir = export_best(the_study, out, system, method, space, validation, url=url, base=base_path, seed=seed,
                           threads=threads)
    stamp = stamp or provenance.stamp(seeds={"training": seed, "sampler": sampler_seed,
                                             "validation": VALIDATION_SEED})
    summary = out / "summary.md"
    write_file(summary, provenance.markdown(summary_table(the_study, url) + "\n", stamp), overwrite=True,
               argument="out_dir")
    plot = search_plot(the_study, out / "search.png", stamp=stamp)
    return TuneResult(the_study, best_dir, summary, plot, len(started))


#: The file that binds a study's ``--out`` to it: ``{"study": name, "storage": URL, password hidden}``.
BINDING = "study.json"
_UNREADABLE_BINDING = f"Restore it, or give the study another --out ({BINDING} binds one study's trials to it)."


def _check_binding(out: Path, binding: dict, moved_from: Optional[dict] = None) -> None:
    """Refuse a second study in a ``--out``: its trials/ and best/ belong to the study it was started with (which
    may move on to the storage it is copied to, ``moved_from`` its binding before)."""
    path = out / BINDING
    if not path.is_file():
        return
    stored = read_json_object(path, _UNREADABLE_BINDING)
    if stored != binding and stored != moved_from:
        raise error("out_dir", f"the directory of the study {stored.get('study')!r} on {stored.get('storage')} "
                    f"({path})", Text(f"the study {binding['study']!r} on {binding['storage']}"),
                    "Give another study another --out; one --out holds one study's trials.")


def _check_new(out: Path, binding: dict) -> None:
    """Before a study is created: its ``--out`` holds no other study's trials (a storage that lost its study, an
    empty or replaced database, must not start over the trials it had)."""
    trials = out / TRIALS_DIR
    if (out / BINDING).is_file() or (trials.is_dir() and any(trials.iterdir())):
        raise error("storage", f"the study {binding['study']!r} that {out} holds the trials of",
                    Text(f"{binding['storage']}, which has no such study"),
                    "The storage was emptied or replaced: restore it, or start the new study in another --out. "
                    f"Nothing in {out} was changed.")


def _bind(out: Path, binding: dict, moved_from: Optional[dict] = None) -> None:
    path = out / BINDING
    if moved_from is not None and path.is_file() and read_json_object(path, _UNREADABLE_BINDING) == moved_from:
        write_file(path, json.dumps(binding, indent=1) + "\n", overwrite=True, argument="out_dir")  # it moved on
        return
    try:
        write_file(path, json.dumps(binding, indent=1) + "\n", argument="out_dir")
    except FileExistsError:              # another worker bound it at the same moment: the same study, or refuse
        _check_binding(out, binding, moved_from)


def _check_record(study: Any, record: dict, name: str) -> None:
    """Record what the study searches, or check that a resumed study searches the same (plant, method,
    seed, space and validation cells; the EKF's scores are measured again by every worker)."""
    ours = json.loads(json.dumps(record))
    stored = study.user_attrs.get("record")
    if stored is None:
        study.set_user_attr("record", ours)
        return

    def key(r: dict) -> dict:
        return {"plant": r["fingerprint"], "method": r["method"], "seed": r["seed"], "space": r["space"],
                "cells": r["objective"]["cells"]}

    differ = [k for k, v in key(ours).items() if key(stored)[k] != v]
    if differ:
        raise error("study", f"the settings study {name!r} was started with", Text(f"another {', '.join(differ)}"),
                    "Use another --study name, or the study's own settings.")



def export_best(study: Any, out: Path, system: System, method: str, space: Space, validation: Validation, *,
                url: str, base: Optional[Path] = None, seed: int = 0, threads: int = 1) -> Optional[Path]:
    """Write the best trial's model to ``out/best`` with the study in its card (``search``).

    The trial's model is taken from ``out/trials/NNNN`` where this worker (or another on this
    machine) trained it, else trained again from the trial's parameters with the study's seed.
    Returns None while the study has no complete trial.
    """
    optuna = optuna_module()
    if not complete_trials(study):
        return None
    best = study.best_trial
    source = out / TRIALS_DIR / f"{best.number:04d}"
    here = (source / "card.json").exists()          # else trained on another machine: trained again here
    if not here:
        _train(system, method, space.suggest(optuna.trial.FixedTrial(best.params)), source, base=base, seed=seed,
               threads=threads)
    model = load_model(source)
    recorded = best.user_attrs.get("model")
    if here and recorded is not None and recorded != model.card[DIGEST]["sha256"]:
        raise error("out_dir", f"the model of trial {best.number} in {source} (digest {recorded})",
                    Text(f"another model (digest {model.card[DIGEST]['sha256']})"),
                    "Its trials/ holds another study's models; give each study its own --out.")
    baseline = study.user_attrs.get("baseline")
    search = Search(study.study_name, public_url(url), best.number, float(best.value), dict(best.params),
                    space.describe(), validation.describe(), None if baseline is None else baseline["value"])
    target = out / BEST_DIR
    card = {**model.card, "search": search.to_card()}
    if card.get("base") is not None:                    # the base's path is relative to the model's directory
        card["base"] = {**card["base"], "path": os.path.relpath(model.base.path, target.resolve())}
    save_model(target, model.arrays, card, overwrite=True,
               extra={name: (source / name).read_bytes() for name in EXTRA_FILES if (source / name).is_file()})
    return target
