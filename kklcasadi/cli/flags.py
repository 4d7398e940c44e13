"""What every command of the ``kklcasadi`` command line shares: flag types, the flags that mean the
same in every command, and the one error path.

One meaning per flag name across commands:

``--system NAME``      a plant kklcasadi ships (``--systems`` for several)
``--plant FILE.py:NAME`` your plant (a ``kklcasadi.System`` or a function returning one)
``--model DIR``        a model directory (positional ``MODEL``/``MODELS`` where it is the subject)
``--method NAME``      an observer variant (``kklcasadi.model.variants``); with ``--system`` it names the
                       shipped model ``models/SYSTEM/NAME``
``--noise on|off|both`` which noise columns of the benchmark to run
``--measurement-std``, ``--process-std`` noise standard deviations: of a run, of the training data
                       where the method uses them, and of the EKF/MHE beside the observer
``--dt SECONDS``       the sample time (train: the observer's; evaluate, compare: the protocol's)
``--box-scale FACTOR`` the X0 box, scaled about its centre, the training data's initial states come from
``--trials N``         how many trials the command runs (the benchmark: per cell; tune: design trials)
``--kinds``            input regimes of the benchmark
``--families``         input families of the generalisation benchmark (``kklcasadi.plant.signals.FAMILIES``)
``--noise-levels``     process and measurement noise std of the generalisation cases
``--pf N``             add the particle filter with N particles
``--seed``             the seed of what the command draws
``--out``              where the command writes
``--threads``          CPU threads the command may use

Every error is one line ``error: ...`` on stderr with exit status 2, naming the command's own
flags (set ``KKLCASADI_DEBUG=1`` to see the traceback instead).
"""

from __future__ import annotations

import argparse
import os
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator, NoReturn, Optional

import numpy as np

from .. import provenance
from ..model.shipped import inside_shipped, is_shipped, resolve, shipped_model
from ..model.shipped import shipped as shipped_listing
from ..plant import signals as sig
from ..plant import systems
from ..plant.systems import System
from ..validation import ArgumentError, ArgumentTypeError

__all__ = ["CommandError", "Parser", "positive_int", "nonnegative_int", "positive_float", "nonnegative_float", "c_name",
           "columns", "flagged", "flagged_by", "plant_of", "load", "shipped", "out_path", "needs_torch", "add_plant",
           "add_noise", "add_kinds", "add_cache", "levels_text", "add_dt", "add_noise_levels", "check_dt",
           "model_label", "quiet_casadi", "stamp_of", "add_system", "run_noise", "PROTOCOL_STD", "NOISE",
           "USER_ERRORS", "labelled_models", "benchmark_caches"]

#: Noise std of a run (and its EKF) where a model's card records no levels (docs/protocol.md).
PROTOCOL_STD = 0.1
#: ``--noise`` choices -> the benchmark's noise columns (False: noise-free).
NOISE = {"on": (True,), "off": (False,), "both": (False, True)}


class CommandError(Exception):
    """A user error of the command line, printed as one line ``error: ...``."""


#: The exceptions that are user errors: printed as one line, exit status 2. OSError: a path that cannot be read or
#: written (permissions, a full disk, a directory where a file was meant); ArithmeticError: a training that diverged.
USER_ERRORS = (CommandError, ValueError, TypeError, OSError, ArithmeticError)


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``error: ...`` and exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"error: {message}\n")


def _number(kind: type, lowest: float, strict: bool, what: str) -> Callable[[str], Any]:
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, received {text!r}") from None
        if not np.isfinite(value) or value < lowest or (strict and value == lowest):
            raise argparse.ArgumentTypeError(f"expected {what}, received {text!r}")
        return value

    parse.__name__ = what
    return parse


positive_int = _number(int, 0, True, "a positive integer")
nonnegative_int = _number(int, 0, False, "an integer >= 0")
positive_float = _number(float, 0.0, True, "a positive number")
nonnegative_float = _number(float, 0.0, False, "a number >= 0")


def columns(text: str) -> tuple[str, ...]:
    """Column names of a CSV file (``--y-cols``, ...): ``a,b,c`` -> ("a", "b", "c"); an empty string -> ()."""
    names = tuple(name.strip() for name in text.split(",")) if text.strip() else ()
    if any(not name for name in names):
        raise argparse.ArgumentTypeError(f"expected comma-separated column names, received {text!r}")
    return names


def c_name(text: str) -> str:
    """A C identifier (for ``--name``)."""
    from ..observer.codegen import check_c_name

    try:
        return check_c_name(text)
    except ArgumentError as exc:
        raise argparse.ArgumentTypeError(exc.detail) from None


def flagged(flag: str, fn: Callable[..., Any], /, *fn_args: Any, **kwargs: Any) -> Any:
    """Call ``fn``; an error about one of its arguments becomes one about ``flag``.

    An :class:`~kklcasadi.validation.ArgumentError` (or ``ArgumentTypeError``) whose ``argument`` is a
    Python name is said of ``flag`` instead (``flag: expected ..., received ...``); one about a file's
    field, and any other ValueError or TypeError, keeps its message after ``flag``.
    """
    return flagged_by({}, flag, fn, *fn_args, **kwargs)


def flagged_by(flags: dict[str, str], default: str, fn: Callable[..., Any], /, *fn_args: Any,
               **kwargs: Any) -> Any:
    """:func:`flagged`, with the errors about the Python arguments ``flags`` names said of their own flags
    (``{"resume": "--resume"}``) and the others of ``default``."""
    try:
        return fn(*fn_args, **kwargs)
    except (ArgumentError, ArgumentTypeError) as exc:
        if not exc.argument.isidentifier():
            raise CommandError(f"{default}: {exc}") from exc
        raise CommandError(f"{flags.get(exc.argument, default)}: {exc.detail}") from exc
    except (ValueError, TypeError) as exc:
        raise CommandError(f"{default}: {exc}") from exc


def plant_of(args: argparse.Namespace) -> Optional[System]:
    """The plant of ``--plant FILE.py:NAME`` (None without it)."""
    return None if getattr(args, "plant", None) is None else flagged("--plant", systems.load_plant, args.plant)


def load(model: str | Path, plant: Optional[System], flag: str = "--model") -> Any:
    """The observer of a model directory, errors naming ``flag`` (and ``--plant`` for a model of a plant
    kklcasadi does not ship, given without it)."""
    from ..model.files import CARD_FILE, load_model
    from ..model.shipped import resolve
    from ..model.variants.copies import copies_plant
    from ..observer.kkl import KKLObserver

    loaded = flagged(flag, load_model, flagged(flag, resolve, model))
    if plant is None:
        name = loaded.card["system"]["name"]
        if name not in systems.names():
            raise CommandError(f"--plant: expected the plant of the model {flag} {model} (its card names the system "
                               f"{name!r}, which kklcasadi does not ship), received none; pass --plant FILE.py:NAME")
        plant = flagged(flag, copies_plant, loaded.card, loaded.path / CARD_FILE) or systems.get(name)
    elif plant.n_params:            # a family: the observer runs with its nominal plant (as load_observer)
        plant = plant.at(plant.param_nominal)
    return flagged(flag, KKLObserver, loaded, plant)


def labelled_models(args: argparse.Namespace, plant: Optional[System]) -> list[tuple[str, Any]]:
    """The observers of ``MODELS`` (of one plant) with their ``--labels`` (default: the directories' names)."""
    if args.labels is not None and len(args.labels) != len(args.models):
        raise CommandError(f"--labels: expected one label per model ({len(args.models)}), "
                           f"received {len(args.labels)}")
    observers: list[tuple[str, Any]] = []
    for i, model in enumerate(args.models):
        obs = load(model, plant, "MODELS")
        if observers and obs.system.fingerprint != observers[0][1].system.fingerprint:
            raise CommandError(f"MODELS: expected models of one plant, received {model} for {obs.system.name!r} "
                               f"after models for {observers[0][1].system.name!r}")
        observers.append((args.labels[i] if args.labels else Path(model).resolve().name, obs))
    return observers


def benchmark_caches(args: argparse.Namespace) -> tuple[Any, Any]:
    """The trial cache and the compiler of ``--cache-dir``, ``--no-cache`` and ``--vm`` (None: the CasADi VM)."""
    from ..evaluation.compiled import Compiler
    from ..evaluation.trialcache import TrialCache, cache_root
    from ..observer.codegen import fast_kernels

    root = Path(args.cache_dir) if args.cache_dir else cache_root()
    trials = TrialCache(None if args.no_cache else root / "trials")
    return trials, None if args.vm else Compiler(cache_dir=root / "compiled", postprocess=fast_kernels)


def shipped(system: str, method: str) -> Path:
    """The shipped model ``models/SYSTEM/METHOD``, errors naming ``--system`` and ``--method``."""
    return flagged(f"--system {system} --method {method}", shipped_model, system, method)


def out_path(path: Optional[str], flag: str, *, directory: bool) -> Optional[Path]:
    """Where a command writes (None stays None), checked before any work: not a shipped model (they are read-only to
    the command line), and a directory path (``directory``) or a file path, not the other kind."""
    if path is None:
        return None
    target = Path(path)
    if inside_shipped(target):
        raise CommandError(f"{flag} {path}: a model that ships with kklcasadi, read-only to the command line; write to "
                           "a directory of your own")
    if directory and target.exists() and not target.is_dir():
        raise CommandError(f"{flag} {path}: expected a directory, received a file")
    if not directory and target.is_dir():
        raise CommandError(f"{flag} {path}: expected a file path, received a directory; name a file inside it")
    return target


def needs_torch(command: str) -> None:
    """Refuse ``command`` with the install line where torch is missing."""
    try:
        import torch  # noqa: F401
    except ImportError:
        raise CommandError(f"{command} needs torch, which is not installed; install the training extra: "
                           "pip install 'kklcasadi[train]'") from None


def add_plant(parser: argparse.ArgumentParser, what: str = "") -> None:
    parser.add_argument("--plant", help="your plant: FILE.py:NAME or MODULE:NAME, NAME a kklcasadi.System or a "
                                        "function returning one" + (f" ({what})" if what else ""))


def add_system(parser: argparse.ArgumentParser, *, with_models: bool, what: str = "", flag: str = "--system",
               **kwargs: Any) -> None:
    """``--system NAME`` (``flag``): with ``with_models`` one of the systems with shipped models, else any
    registered system; the help says which systems have shipped models and which have none."""
    having = sorted(shipped_listing())
    none = [name for name in systems.names() if name not in having]
    listing = f"shipped models for {', '.join(having)}" + (f"; none for {', '.join(none)} (train one: kklcasadi "
                                                             "train --system NAME)" if none else "")
    parser.add_argument(flag, choices=having if with_models else systems.names(),
                        help=(what + "; " if what else "") + listing, **kwargs)


def add_noise(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--noise", default="both", choices=tuple(NOISE),
                        help="noise columns of the benchmark: noisy (on), noise-free (off) or both (default)")


def add_kinds(parser: argparse.ArgumentParser, help: str = "input regimes of the benchmark") -> None:
    parser.add_argument("--kinds", nargs="+", default=list(sig.BENCHMARK_KINDS), choices=sig.BENCHMARK_KINDS,
                        help=help)


def levels_text(value: Any) -> str:
    """A noise level for printing: ``0.1`` for one std, ``(0, 0, 16, 16)`` for one per state."""
    if isinstance(value, (int, float)) or getattr(value, "ndim", 1) == 0:
        return f"{float(value):g}"
    return "(" + ", ".join(f"{float(v):g}" for v in value) + ")"


def add_cache(parser: argparse.ArgumentParser) -> None:
    """``--cache-dir`` and ``--no-cache``: where the trial and compiled-code caches live, or none for the trials."""
    parser.add_argument("--cache-dir", help="root of the trial and compiled-code caches (default: $KKLCASADI_CACHE, "
                        "else ~/.cache/kklcasadi)")
    parser.add_argument("--no-cache", action="store_true", help="simulate the trials instead of reading/writing the "
                        "trial cache")


def add_dt(parser: argparse.ArgumentParser, help: str) -> None:
    parser.add_argument("--dt", type=positive_float, metavar="SECONDS", help=help)


def add_noise_levels(parser: argparse.ArgumentParser, what: str, default: Optional[float] = None) -> None:
    """``--measurement-std`` and ``--process-std`` (``what``: what they set; ``default``: None = unset)."""
    shown = "" if default is None else f"; default {default:g}"
    parser.add_argument("--measurement-std", type=nonnegative_float, default=default,
                        help=f"measurement noise std on y: {what}{shown}")
    parser.add_argument("--process-std", type=nonnegative_float, default=default,
                        help=f"process noise std on xdot: {what}{shown}")


def add_roughening(parser: argparse.ArgumentParser) -> None:
    """``--pf-roughening K``: the particle filter's roughening (default the benchmarks')."""
    from ..estimators.pf import ROUGHENING

    parser.add_argument("--pf-roughening", type=nonnegative_float, default=ROUGHENING, metavar="K",
                        help=f"with --pf: jitter the resampled particles by K times their range times N^(-1/nx) "
                        f"(default {ROUGHENING:g}; 0: the plain bootstrap filter)")


def check_dt(dt: float, T: float, models: dict[str, float]) -> None:
    """The protocol's ``dt`` (``--dt``) fits its horizon ``T`` and every model's sample time."""
    n = round(T / dt)
    if abs(n * dt - T) > 1e-9 * T:
        raise CommandError(f"--dt {dt:g}: expected a sample time that divides the horizon T = {T:g} s")
    for model, model_dt in models.items():
        if abs(model_dt - dt) > 1e-12 * dt:
            raise CommandError(f"--dt: the protocol runs at dt = {dt:g} s, the model {model} at {model_dt:g} s; "
                               f"pass --dt {model_dt:g} (or a model trained at {dt:g} s)")


def model_label(path: str | Path) -> str:
    """``shipped model models/S/M`` or ``your model PATH`` (the CLI tells them apart; a shipped model's name
    ``S/M`` is resolved as :func:`kklcasadi.load_observer` resolves it)."""
    if is_shipped(resolve(path)):
        resolved = resolve(path).resolve()
        return f"shipped model models/{resolved.parent.name}/{resolved.name}"
    return f"your model {path}"


@contextmanager
def quiet_casadi() -> Iterator[None]:
    """Hide what CasADi prints to the process's stderr while the block runs (the inputs of a Function
    whose evaluation failed: pages for a plant that escapes), so an error is one line;
    ``KKLCASADI_DEBUG=1`` shows them."""
    if os.environ.get("KKLCASADI_DEBUG"):
        yield
        return
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def stamp_of(args: argparse.Namespace, **seeds: Any) -> provenance.Stamp:
    """The provenance stamp of what a command writes: its command line as parsed by :func:`kklcasadi.cli.main`
    (this process's otherwise) and the seeds, by role, of what it drew."""
    return provenance.stamp(command=getattr(args, "command_line", None), seeds=seeds)


def run_noise(obs: Any, process_std: Optional[float] = None, measurement_std: Optional[float] = None) -> tuple:
    """``(process_std, measurement_std)`` of a run of ``obs`` and its EKF: the given levels, else the card's where
    it records both, else :data:`PROTOCOL_STD` (a per-state process std stays a tuple)."""
    spec = obs.model.spec
    recorded = spec.process_std is not None
    return (process_std if process_std is not None else spec.process_std if recorded else PROTOCOL_STD,
            measurement_std if measurement_std is not None else spec.measurement_std if recorded else PROTOCOL_STD)
