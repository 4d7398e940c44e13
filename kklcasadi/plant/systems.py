"""Plants written symbolically in CasADi, and the registry of benchmark systems.

A :class:`System` holds the exact right-hand side ``f(x, u)``, the output map ``h(x)`` and their
Jacobians as :class:`casadi.Function` objects, built once from SX symbols. The registry
(:func:`get`, :func:`names`) provides the four systems of the HyperKKL paper exactly as in
``docs/protocol.md``, plus Lorenz and a linear test plant with a known KKL map.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import json
from pathlib import Path
from typing import Any, Callable, Sequence

import casadi as ca
import numpy as np

from ..validation import ArgumentError, Text, error, finite_array, finite_number, index_tuple, one_of, positive_int

__all__ = ["System", "get", "names", "families", "register", "load_plant", "read_states"]


def _column_symbol(value: object, arg: str) -> ca.SX:
    """Check that ``value`` is a column vector of purely symbolic SX entries."""
    if not isinstance(value, ca.SX):
        raise error(arg, f"a casadi.SX symbol (e.g. ca.SX.sym('{arg}', n))", Text(type(value).__name__),
                    kind=TypeError)
    if value.size2() != 1 or value.numel() == 0:
        raise error(arg, "a non-empty column vector", Text(f"shape {value.shape}"))
    if not value.is_valid_input():
        raise error(arg, "distinct purely symbolic entries (ca.SX.sym), not expressions", Text(str(value)))
    return value


def _column_expr(value: object, arg: str, n: int | None = None) -> ca.SX:
    if isinstance(value, (list, tuple)):
        value = ca.vertcat(*value)
    if not isinstance(value, ca.SX):
        raise error(arg, "a casadi.SX expression or a list of them", Text(type(value).__name__), kind=TypeError)
    if value.size2() != 1:
        raise error(arg, "a column expression", Text(f"shape {value.shape}"))
    if n is not None and value.size1() != n:
        raise error(arg, f"{n} entries (one per state)", Text(f"{value.size1()} entries"))
    return value


def _box(value: object, n: int, arg: str = "x0_box", size: str = "nx") -> np.ndarray:
    box = np.asarray(value, dtype=float)
    if box.shape != (n, 2):
        raise error(arg, f"shape ({size}, 2) = ({n}, 2) as [[lo, hi], ...]", Text(f"shape {box.shape}"))
    if not np.all(np.isfinite(box)):
        raise error(arg, "finite bounds", box.tolist())
    if np.any(box[:, 1] <= box[:, 0]):
        bad = np.nonzero(box[:, 1] <= box[:, 0])[0].tolist()
        raise error(arg, f"rows [lo, hi] with lo < hi (rows {bad} are empty or inverted)", box.tolist())
    box.setflags(write=False)
    return box


def _nominal(value: object, box: np.ndarray) -> np.ndarray:
    """The nominal parameter values: the box centre by default, else inside the box."""
    nominal = box.mean(axis=1) if value is None else np.asarray(value, dtype=float).reshape(-1)
    if nominal.shape != (len(box),) or not np.all(np.isfinite(nominal)):
        raise error("param_nominal", f"{len(box)} finite values (one per parameter)", np.asarray(value).tolist())
    if np.any((nominal < box[:, 0]) | (nominal > box[:, 1])):
        raise error("param_nominal", "values inside param_box", nominal.tolist(),
                    f"param_box is {box.tolist()}.")
    nominal.setflags(write=False)
    return nominal


class System:
    """A controlled plant ``xdot = f(x, u)``, ``y = h(x)`` written with CasADi SX symbols.

    Parameters
    ----------
    name : str
        Identifier used in model cards and file names.
    x : casadi.SX, shape (nx, 1)
        State symbols.
    u : casadi.SX, shape (nu, 1)
        Input symbols.
    xdot : casadi.SX or list, shape (nx, 1)
        Right-hand side ``f(x, u)``.
    y : casadi.SX or list, shape (ny, 1)
        Output map ``h(x)``; must not depend on ``u``.
    x0_box : array_like, shape (nx, 2)
        Box ``[[lo, hi], ...]`` of initial states (the operating domain of the observer).
    description : str, optional
        One line shown by ``kklcasadi`` listings.
    paper_design : bool, optional
        Train with the HyperKKL paper's latent pair (:meth:`kklcasadi.Design.paper`) instead of
        :meth:`kklcasadi.Design.default`; set for the paper's four plants, whose protocol and
        shipped models use it.
    angle_states, angle_outputs : sequence of int, optional
        Indices of the states and of the outputs that are angles in radians, defined modulo
        ``2 pi`` (e.g. a pendulum angle): errors on them are wrapped (:func:`kklcasadi.metrics.wrap_angle`)
        and logs unwrap them (:func:`kklcasadi.plant.logs.read_log`). Default none.
    u_box : array_like, shape (nu, 2), optional
        The range ``[[lo, hi], ...]`` of each input on the rig (e.g. a drive's voltage limits, or
        what its logs reach); in the fingerprint when given. Default None (not declared).
    params : casadi.SX, shape (n_params, 1), optional
        Uncertain parameters that ``xdot`` and ``y`` may use (distinct ``ca.SX.sym`` entries). A plant
        with parameters is a family: :attr:`f` and :attr:`h` (and everything built on them: the EKF,
        MHE, particle filter, model copies) use :attr:`param_nominal`; :attr:`f_param`, :attr:`h_param`
        and :func:`kklcasadi.simulate` ``(..., params=)`` take other values, :meth:`at` fixes them.
    param_box : array_like, shape (n_params, 2)
        ``[[lo, hi], ...]``, the values the parameters may take; required with ``params``.
    param_nominal : array_like, shape (n_params,), optional
        Nominal values, inside the box; default its centre.

    Attributes
    ----------
    f : casadi.Function
        ``f(x, u) -> xdot`` (at the nominal parameters).
    h : casadi.Function
        ``h(x) -> y`` (at the nominal parameters).
    f_param, h_param : casadi.Function or None
        ``f_param(x, u, p) -> xdot`` and ``h_param(x, p) -> y`` of a plant with parameters (None without).
    n_params : int
        Number of parameters (0 without).
    param_names : tuple of str
        The names of the parameters' symbols.
    param_box : numpy.ndarray, shape (n_params, 2), or None
    param_nominal : numpy.ndarray, shape (n_params,), or None
    f_jac : casadi.Function
        ``f_jac(x, u) -> (df_dx (nx, nx), df_du (nx, nu))``, exact.
    h_jac : casadi.Function
        ``h_jac(x) -> dh_dx (ny, nx)``, exact.
    angle_states, angle_outputs : tuple of int
        The sorted indices given (empty tuples by default).
    u_box : numpy.ndarray, shape (nu, 2), or None
        The input range given (read-only).
    family : System or None
        The plant with parameters this one was fixed from (:meth:`at`); None otherwise. Not in the fingerprint;
        model copies at parameter values of their own take their plants from it
        (:class:`kklcasadi.model.variants.copies.ModelCopies`).

    Examples
    --------
    >>> import casadi as ca, kklcasadi as kc
    >>> x = ca.SX.sym("x", 2); u = ca.SX.sym("u")
    >>> pend = kc.System("pend", x, u, [x[1], -ca.sin(x[0]) + u], x[0], x0_box=[[-1, 1], [-2, 2]])
    >>> pend.nx, pend.nu, pend.ny
    (2, 1, 1)
    """

    def __init__(self, name: str, x: ca.SX, u: ca.SX, xdot: ca.SX | Sequence[ca.SX], y: ca.SX | Sequence[ca.SX],
                 x0_box: object, *, description: str = "", paper_design: bool = False,
                 angle_states: Sequence[int] = (), angle_outputs: Sequence[int] = (),
                 u_box: object = None, params: ca.SX | None = None, param_box: object = None,
                 param_nominal: object = None) -> None:
        if not isinstance(name, str) or not name.isidentifier():
            raise error("name", "a Python identifier such as 'duffing'", name)
        x = _column_symbol(x, "x")
        u = _column_symbol(u, "u")
        xdot = _column_expr(xdot, "xdot", x.size1())
        y = _column_expr(y, "y")
        if y.size1() == 0:
            raise error("y", "at least one output", Text("0 outputs"))
        if ca.depends_on(y, u):
            raise error("y", "an output map h(x) that does not depend on the input u", Text(str(y)),
                        "Direct feedthrough is not supported.")
        p = None if params is None else _column_symbol(params, "params")
        free = ca.symvar(ca.vertcat(xdot, y))
        known = set(ca.symvar(ca.vertcat(x, u) if p is None else ca.vertcat(x, u, p)))
        extra = [str(s) for s in free if s not in known]
        if extra:
            what = "x and u" if p is None else "x, u and params"
            raise error("xdot, y", f"expressions in the symbols of {what} only", Text(f"free symbols {extra}"))
        if p is None and (param_box is not None or param_nominal is not None):
            raise error("params", "a casadi.SX symbol of the parameters that param_box and param_nominal describe",
                        None)
        self.p_sym = p
        self.family: System | None = None
        self.n_params = 0 if p is None else p.size1()
        self.param_box = None if p is None else _box(param_box, self.n_params, "param_box", "n_params")
        self.param_nominal = None if p is None else _nominal(param_nominal, self.param_box)
        self.param_names = () if p is None else tuple(str(e) for e in ca.vertsplit(p))
        self.f_param = self.h_param = None
        self.xdot_param_expr, self.y_param_expr = xdot, y
        if p is not None:
            self.f_param = ca.Function("f_param", [x, u, p], [xdot], ["x", "u", "p"], ["xdot"])
            self.h_param = ca.Function("h_param", [x, p], [y], ["x", "p"], ["y"])
            xdot, y = ca.substitute([xdot, y], [p], [ca.DM(self.param_nominal)])
        self.name = name
        self.description = description
        self.paper_design = bool(paper_design)
        self.nx, self.nu, self.ny = x.size1(), u.size1(), y.size1()
        self.x0_box = _box(x0_box, self.nx)
        self.angle_states = index_tuple(angle_states, "angle_states", self.nx)
        self.angle_outputs = index_tuple(angle_outputs, "angle_outputs", self.ny)
        self.u_box = None if u_box is None else _box(u_box, self.nu, "u_box", "nu")
        self.x_sym, self.u_sym = x, u
        self.xdot_expr, self.y_expr = xdot, y
        self.f = ca.Function("f", [x, u], [xdot], ["x", "u"], ["xdot"])
        self.h = ca.Function("h", [x], [y], ["x"], ["y"])
        self.f_jac = ca.Function("f_jac", [x, u], [ca.jacobian(xdot, x), ca.jacobian(xdot, u)],
                                 ["x", "u"], ["df_dx", "df_du"])
        self.h_jac = ca.Function("h_jac", [x], [ca.jacobian(y, x)], ["x"], ["dh_dx"])

    def __repr__(self) -> str:
        return f"System({self.name!r}, nx={self.nx}, nu={self.nu}, ny={self.ny})"

    @property
    def fingerprint(self) -> str:
        """SHA-256 of what the plant computes: ``f`` and ``h`` on fixed points, the sizes and the box.

        The points are 64 seeded draws over the X0 box (inputs in [-1, 1]); values are rounded to
        10 significant digits, so the fingerprint does not depend on symbol names, on how the
        expressions are written or on the CasADi version, but changes with the dynamics. Model
        cards record it, and a model refuses to load against a plant with another fingerprint.
        The angle indices and the input range enter only when given, so a plant without them keeps
        the fingerprint it had before they existed; likewise the parameters (``f`` and ``h`` on the same
        points with parameters drawn over their box, the box and the nominal values).
        """
        rng = np.random.default_rng(20261127)
        lo, hi = self.x0_box[:, 0], self.x0_box[:, 1]
        x = lo + (hi - lo) * rng.random((64, self.nx))
        u = rng.uniform(-1.0, 1.0, (64, self.nu))
        values = np.concatenate([self.f_batch(x, u).ravel(), self.h_batch(x).ravel(), self.x0_box.ravel()])
        text = f"{self.nx},{self.nu},{self.ny};" + ",".join(np.format_float_scientific(v, precision=9)
                                                             for v in values)
        if self.angle_states or self.angle_outputs:
            text += f";angles x{list(self.angle_states)} y{list(self.angle_outputs)}"
        if self.u_box is not None:
            text += ";u_box " + ",".join(np.format_float_scientific(v, precision=9) for v in self.u_box.ravel())
        if self.n_params:
            box = self.param_box
            p = box[:, 0] + (box[:, 1] - box[:, 0]) * rng.random((64, self.n_params))
            family = np.concatenate([self.f_batch(x, u, params=p).ravel(), self.h_batch(x, params=p).ravel(),
                                     box.ravel(), self.param_nominal])
            text += ";params " + ",".join(np.format_float_scientific(v, precision=9) for v in family)
        return hashlib.sha256(text.encode()).hexdigest()

    @property
    def definition_digest(self) -> str:
        """SHA-256 of the plant's exact definition: name, sizes, X0 box (and input range, where given) and the
        serialised ``f`` and ``h``.

        Unlike :attr:`fingerprint` (what the plant computes, rounded), any change of the expressions
        changes it, down to the last bit of a constant; caches of simulated trials are keyed by it.
        """
        digest = hashlib.sha256()
        header = {"name": self.name, "nx": self.nx, "nu": self.nu, "ny": self.ny,
                  "x0_box": np.asarray(self.x0_box, dtype=float).tolist()}
        if self.u_box is not None:
            header["u_box"] = self.u_box.tolist()
        if self.n_params:
            header["params"] = {"box": self.param_box.tolist(), "nominal": self.param_nominal.tolist()}
        digest.update(json.dumps(header, sort_keys=True).encode())
        for function in (self.f, self.h) + ((self.f_param, self.h_param) if self.n_params else ()):
            digest.update(function.serialize().encode())
        return digest.hexdigest()

    def f_batch(self, x: object, u: object = None, *, params: object = None) -> np.ndarray:
        """``f`` on many points in one mapped call.

        Parameters
        ----------
        x : array_like, shape (M, nx)
        u : array_like, shape (M, nu), optional
            Default 0 (the autonomous field).
        params : array_like, shape (M, n_params) or (n_params,), optional
            Parameter values per point (or one for all); default the nominal ones.

        Returns
        -------
        numpy.ndarray, shape (M, nx)
        """
        x = self._rows(x, self.nx, "x")
        u = np.zeros((len(x), self.nu)) if u is None else self._rows(u, self.nu, "u")
        if len(u) != len(x):
            raise ValueError(f"u: expected {len(x)} rows (one per row of x), received {len(u)}.")
        if len(x) == 0:
            return np.zeros((0, self.nx))
        if params is None:
            return np.asarray(self.f.map(len(x))(x.T, u.T)).T.reshape(len(x), self.nx)
        p = self.param_rows(params, len(x))
        return np.asarray(self.f_param.map(len(x))(x.T, u.T, p.T)).T.reshape(len(x), self.nx)

    def h_batch(self, x: object, *, params: object = None) -> np.ndarray:
        """``h`` on many points in one mapped call: ``x`` (M, nx) -> ``y`` (M, ny); ``params`` as in :meth:`f_batch`."""
        x = self._rows(x, self.nx, "x")
        if len(x) == 0:
            return np.zeros((0, self.ny))
        if params is None:
            return np.asarray(self.h.map(len(x))(x.T)).T.reshape(len(x), self.ny)
        p = self.param_rows(params, len(x))
        return np.asarray(self.h_param.map(len(x))(x.T, p.T)).T.reshape(len(x), self.ny)

    def param_rows(self, params: object, m: int, arg: str = "params") -> np.ndarray:
        """Parameter values as ``(m, n_params)`` rows: one row per point, or one row repeated.

        Raises a ValueError naming ``arg`` for a plant without parameters, a wrong shape or a
        non-finite value (values outside :attr:`param_box` are allowed: effects beyond the family).
        """
        self._require_params(arg)
        p = np.asarray(params, dtype=float)
        if p.ndim == 1:
            p = np.broadcast_to(p, (m, p.size))
        if p.shape != (m, self.n_params):
            raise error(arg, f"shape ({self.n_params},) or ({m}, {self.n_params})", Text(f"shape {np.shape(params)}"))
        return finite_array(p, arg)

    def at(self, params: object) -> System:
        """The plant with its parameters fixed at ``params`` (n_params,): a :class:`System` without parameters.

        ``system.at(system.param_nominal)`` computes bitwise what :attr:`f` and :attr:`h` compute. The result's
        :attr:`family` is this plant.
        """
        p = self.param_rows(params, 1)[0]
        xdot, y = ca.substitute([self.xdot_param_expr, self.y_param_expr], [self.p_sym], [ca.DM(p)])
        plant = System(self.name, self.x_sym, self.u_sym, xdot, y, self.x0_box, description=self.description,
                       paper_design=self.paper_design, angle_states=self.angle_states,
                       angle_outputs=self.angle_outputs, u_box=self.u_box)
        plant.family = self
        return plant

    def sample_params(self, n: int, seed: int | np.random.Generator | None = 0, *,
                      scale: float = 1.0) -> np.ndarray:
        """Latin-hypercube sample of ``n`` parameter vectors over :attr:`param_box` (scaled about its centre).

        Returns
        -------
        numpy.ndarray, shape (n, n_params)
        """
        self._require_params("sample_params")
        return _latin(self.param_box, n, seed, scale)

    def _require_params(self, arg: str) -> None:
        if not self.n_params:
            raise error(arg, f"None for plant {self.name!r}, which declares no parameters", Text("parameter values"),
                        "Give kc.System(..., params=P, param_box=...) to make a family of plants.")

    @staticmethod
    def _rows(value: object, width: int, arg: str) -> np.ndarray:
        arr = np.asarray(value, dtype=float)
        if arr.ndim != 2 or arr.shape[1] != width:
            raise ValueError(f"{arg}: expected shape (M, {width}), received {arr.shape}.")
        return arr

    def check_state(self, x: object, arg: str = "x0") -> np.ndarray:
        """Return ``x`` as a float array of shape (nx,), or raise a ValueError naming ``arg``."""
        arr = np.asarray(x, dtype=float)
        if arr.shape not in ((self.nx,), (self.nx, 1)):
            raise error(arg, f"shape ({self.nx},) for system {self.name!r}", Text(f"shape {arr.shape}"))
        if not np.all(np.isfinite(arr)):
            raise error(arg, "finite values", arr.ravel().tolist())
        return arr.reshape(self.nx)

    def sample_box(self, n: int, seed: int | np.random.Generator | None = 0, *, scale: float = 1.0) -> np.ndarray:
        """Latin-hypercube sample of ``n`` states over the X0 box (optionally scaled about its centre).

        Returns
        -------
        numpy.ndarray, shape (n, nx)
        """
        return _latin(self.x0_box, n, seed, scale)


def _latin(box: np.ndarray, n: int, seed: int | np.random.Generator | None, scale: float) -> np.ndarray:
    from scipy.stats import qmc

    n = positive_int(n, "n")
    centre = box.mean(axis=1)
    half = 0.5 * (box[:, 1] - box[:, 0]) * scale
    unit = qmc.LatinHypercube(d=len(box), seed=seed).random(n)
    return centre + (2.0 * unit - 1.0) * half


_REGISTRY: dict[str, Callable[..., System]] = {}
_FAMILIES: set[str] = set()


def read_states(system: System) -> tuple[int, ...]:
    """The states the plant's equations read: ``i`` such that ``xdot`` or ``y`` depends on ``x_i`` (the structural
    nonzeros of the Jacobian of ``(f, h)`` with respect to ``x``), ascending. A state outside it (an integrator
    read by nothing, such as a rotary pendulum's arm angle measured by the pendulum encoder alone) changes nothing
    the plant does: model copies leave it out, and training runs neither start nor stop by it."""
    jac = ca.jacobian(ca.vertcat(system.xdot_expr, system.y_expr), system.x_sym)
    return tuple(sorted(set(jac.sparsity().get_col())))


def register(name: str, factory: Callable[..., System], *, family: bool = False) -> None:
    """Add a plant factory to the registry used by :func:`get` and the CLI.

    With ``family=True`` the factory also takes ``param_spread=s`` and then returns the plant with
    its coefficients as parameters, each in ``nominal (1 -+ s)`` (:func:`get`).
    """
    if not callable(factory):
        raise error("factory", "a callable returning a System", Text(type(factory).__name__), kind=TypeError)
    _REGISTRY[name] = factory
    (_FAMILIES.add if family else _FAMILIES.discard)(name)


def names() -> list[str]:
    """Names of the registered systems, sorted."""
    return sorted(_REGISTRY)


def families() -> list[str]:
    """Names of the registered systems that have a parameterised form (``get(name, param_spread=s)``), sorted."""
    return sorted(_FAMILIES)


def get(name: str, *, param_spread: float | None = None) -> System:
    """Build the registered system ``name`` (e.g. ``"duffing"``).

    Parameters
    ----------
    name : str
    param_spread : float, optional
        A relative uncertainty ``0 < s < 1``: the plant's parameterised form, every coefficient a
        parameter in ``nominal (1 -+ s)`` with the nominal values (today's plant) at its centre
        (systems of :func:`families`). Default: the plant without parameters.
    """
    factory = _REGISTRY[one_of(name, "name", names())]
    if param_spread is None:
        return factory()
    if name not in _FAMILIES:
        raise error("param_spread", f"None for {name!r}, which has no parameterised form (those that have: "
                    f"{families()})", param_spread)
    return factory(param_spread=param_spread)


def _run_user_code(what: str, call: Callable[[], Any], fix: str) -> Any:
    """Run a plant file's code (its import, its factory): what it raises, or a ``sys.exit`` in it, is an error
    naming ``--plant``'s argument, not a traceback or a silent exit."""
    try:
        return call()
    except SystemExit as exc:
        raise error("plant", f"{what} to define the plant", Text(f"a call of sys.exit({exc.code!r})"),
                    "A plant file defines make_plant(); put what runs a program under "
                    "if __name__ == '__main__':.") from None
    except Exception as exc:  # any error of the user's code is reported as such, one line
        raise error("plant", f"{what} to run without error", Text(f"{type(exc).__name__}: {exc}"), fix) from exc


def load_plant(spec: str) -> System:
    """A user's plant from a file or module: ``"path/to/plant.py:make_plant"`` or ``"pkg.mod:make_plant"``.

    This runs Python code: the file (or module) is imported and the function is called, as
    ``python plant.py`` would. Pass only files and modules you trust. The name after ``:``
    (default ``make_plant``) must be a :class:`System`, or a Python function that takes no
    arguments and returns one; anything else (``os:getcwd``, a class, a function that needs
    arguments) is refused before it is called, and what the function returns is checked before it
    is used.

    Parameters
    ----------
    spec : str
        ``FILE.py[:NAME]`` or ``MODULE[:NAME]``.

    Returns
    -------
    System

    Raises
    ------
    ArgumentError
        The file or module cannot be found or imported (or raises, or calls ``sys.exit``, while
        imported), the name is missing or is not a System or a function without arguments, or the
        function raises, exits or does not return a System (the message says which and what to write).
    """
    if not isinstance(spec, str) or not spec:
        raise error("plant", "'path/to/plant.py:make_plant' or 'module:make_plant'", spec, kind=TypeError)
    source, _, attribute = spec.rpartition(":") if ":" in spec else (spec, ":", "make_plant")
    attribute = attribute or "make_plant"
    fix = "Write a function make_plant() that returns a kklcasadi.System and pass 'plant.py:make_plant'."
    if source.endswith(".py") or Path(source).is_file():
        path = Path(source)
        if not path.is_file():
            raise error("plant", "an existing Python file", str(path), fix)
        module_spec = importlib.util.spec_from_file_location(f"kklcasadi_user_plant_{path.stem}", path)
        module = importlib.util.module_from_spec(module_spec)
        _run_user_code(f"importing {path}", lambda: module_spec.loader.exec_module(module), "Fix the file.")
    else:
        try:
            module = _run_user_code(f"importing {source}", lambda: importlib.import_module(source), fix)
        except ArgumentError as exc:
            if isinstance(exc.__cause__, ImportError):
                raise error("plant", "an importable module or a .py file", source, fix) from exc
            raise
    if not hasattr(module, attribute):
        raise error("plant", f"a name {attribute!r} in {source}", Text("no such name"), fix)
    value = getattr(module, attribute)
    if isinstance(value, System):
        return value
    if not inspect.isfunction(value) or not _takes_no_arguments(value):
        raise error("plant", f"{source}:{attribute} to be a kklcasadi.System or a Python function without arguments "
                    "that returns one", Text(f"{type(value).__name__} {getattr(value, '__qualname__', '')}".strip()),
                    fix, kind=TypeError)
    plant = _run_user_code(f"{source}:{attribute}()", value, "Fix the function.")
    if not isinstance(plant, System):
        raise error("plant", f"{source}:{attribute}() to return a kklcasadi.System", Text(type(plant).__name__), fix,
                    kind=TypeError)
    return plant


def _takes_no_arguments(function: Callable) -> bool:
    try:
        inspect.signature(function).bind()
    except TypeError:
        return False
    return True


def _symbols(nx: int) -> tuple[ca.SX, ca.SX]:
    return ca.SX.sym("x", nx), ca.SX.sym("u", 1)


def _family(name: str, x: ca.SX, u: ca.SX, p: ca.SX, xdot: list, y: ca.SX, box: list, nominal: list,
            param_spread: float | None, **options: object) -> System:
    """A plant written with its coefficients ``p``: without ``param_spread`` they are substituted by
    their nominal values (a plant without parameters), with it they are parameters in
    ``nominal (1 -+ param_spread)``."""
    nominal = np.asarray(nominal, dtype=float)
    if param_spread is None:
        xdot, y = ca.substitute([ca.vertcat(*xdot), y], [p], [ca.DM(nominal)])
        return System(name, x, u, xdot, y, box, **options)
    spread = finite_number(param_spread, "param_spread")
    if not 0.0 < spread < 1.0:
        raise error("param_spread", "a relative uncertainty 0 < s < 1 (0.3: every coefficient +-30 %)", param_spread)
    half = spread * np.abs(nominal)
    return System(name, x, u, xdot, y, box, params=p, param_box=np.column_stack([nominal - half, nominal + half]),
                  param_nominal=nominal, **options)


def _coefficients(*names: str) -> ca.SX:
    return ca.vertcat(*(ca.SX.sym(n) for n in names))


def duffing(*, param_spread: float | None = None) -> System:
    """Duffing, ``x2' = -alpha x1 - beta x1^3 + u`` with ``alpha = beta = 1`` (parameters with ``param_spread``)."""
    x, u = _symbols(2)
    p = _coefficients("alpha", "beta")
    return _family("duffing", x, u, p, [x[1], -p[0] * x[0] - p[1] * x[0] ** 3 + u], x[0], [[-1, 1], [-1, 1]],
                   [1.0, 1.0], param_spread, description="Duffing oscillator, y = x1", paper_design=True)


def vdp(*, param_spread: float | None = None) -> System:
    """Van der Pol, ``x2' = (a - b x1^2) x2 - k x1 + u`` with ``a = b = k = 1`` (parameters with ``param_spread``)."""
    x, u = _symbols(2)
    p = _coefficients("a", "b", "k")
    return _family("vdp", x, u, p, [x[1], (p[0] - p[1] * x[0] ** 2) * x[1] - p[2] * x[0] + u], x[0],
                   [[-3, 3], [-3, 3]], [1.0, 1.0, 1.0], param_spread,
                   description="Van der Pol oscillator (mu = 1), y = x1", paper_design=True)


def rossler() -> System:
    x, u = _symbols(3)
    xdot = [-(x[1] + x[2]), x[0] + 0.1 * x[1] + u, 0.1 + x[2] * (x[0] - 14)]
    return System("rossler", x, u, xdot, x[1], [[-10, 10]] * 3, description="Roessler (a=0.1, b=0.1, c=14), y = x2",
                  paper_design=True)


def fhn() -> System:
    x, u = _symbols(2)
    xdot = [10 * (x[0] - x[0] ** 3 - x[1]) + u, 1.5 * x[0] - x[1] + 0.8]
    return System("fhn", x, u, xdot, x[0], [[-2.5, 2.5], [-1.5, 1.5]],
                  description="FitzHugh-Nagumo as in the HyperKKL paper, y = x1", paper_design=True)


def lorenz() -> System:
    x, u = _symbols(3)
    sigma, rho, beta = 10.0, 28.0, 8.0 / 3.0
    xdot = [sigma * (x[1] - x[0]), x[0] * (rho - x[2]) - x[1] + u, x[0] * x[1] - beta * x[2]]
    return System("lorenz", x, u, xdot, x[1], [[-15, 15], [-20, 20], [5, 40]],
                  description="Lorenz (sigma 10, rho 28, beta 8/3), u on x2, y = x2")


LINEAR_F = np.array([[0.0, 1.0], [-2.0, -0.5]])
LINEAR_G = np.array([[0.0], [1.0]])
LINEAR_H = np.array([[1.0, 0.0]])


def linear() -> System:
    """Damped linear oscillator ``xdot = F x + G u``, ``y = H x``: its KKL map solves a Sylvester equation."""
    x, u = _symbols(2)
    xdot = ca.mtimes(ca.DM(LINEAR_F), x) + ca.mtimes(ca.DM(LINEAR_G), u)
    return System("linear", x, u, xdot, ca.mtimes(ca.DM(LINEAR_H), x), [[-1, 1], [-1, 1]],
                  description="damped linear oscillator (test plant with an exact KKL map)")


for _factory in (duffing, vdp, rossler, fhn, lorenz, linear):
    register(_factory.__name__, _factory, family=_factory in (duffing, vdp))
