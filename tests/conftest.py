import numpy as np
import pytest


@pytest.fixture(autouse=True, scope="session")
def _private_cache(tmp_path_factory):
    """The trial and compiled-code caches of the test run live in a temporary directory, not the user's."""
    patch = pytest.MonkeyPatch()
    patch.setenv("KKLCASADI_CACHE", str(tmp_path_factory.mktemp("kklcasadi-cache")))
    yield
    patch.undo()


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def no_torch_env(tmp_path):
    """The environment of an interpreter in which torch cannot be imported (a ``sitecustomize`` on ``PYTHONPATH``
    that refuses it, as on a deploy-only install)."""
    block = tmp_path / "no_torch" / "sitecustomize.py"
    block.parent.mkdir()
    block.write_text("import sys\n\n\nclass NoTorch:\n    def find_spec(self, name, path=None, target=None):\n"
                     "        if name.split('.')[0] == 'torch':\n"
                     "            raise ModuleNotFoundError(\"No module named 'torch'\", name='torch')\n\n\n"
                     "sys.meta_path.insert(0, NoTorch())\n")
    return {**__import__("os").environ, "PYTHONPATH": str(block.parent)}


def _random_model_arrays(card, seed):
    """Random float64 arrays for every array the card names (kklcasadi.model.files shapes).

    Each array is drawn from its own stream keyed by ``(seed, name)``, so two cards with the same
    encoder/decoder architecture get bitwise-identical encoder/decoder arrays for the same seed.
    Weights are scaled by 1/sqrt(fan_in); normalisation scales lie in [0.5, 2].
    """
    import zlib

    from kklcasadi.model.card import model_array_shapes

    arrays = {}
    for name, shape in model_array_shapes(card).items():
        rng = np.random.default_rng([seed, zlib.crc32(name.encode())])
        if name.endswith("asinh_scale"):
            arrays[name] = np.zeros(shape)                     # no output transform
        elif name.endswith("_std"):
            arrays[name] = rng.uniform(0.5, 2.0, shape)
        elif name.endswith("/scale"):
            arrays[name] = np.array(1.0)                 # make the LoRA modulation visible
        elif len(shape) == 2:
            arrays[name] = rng.normal(size=shape) / np.sqrt(shape[1])
        else:
            arrays[name] = 0.3 * rng.normal(size=shape)
    return arrays


@pytest.fixture
def model_dir_factory(tmp_path_factory):
    """Write a random-weight model directory for any method; returns its path.

    ``make(method, system="duffing", *, hidden=(8, 8), window=3, seed=0, base=False,
    card_extra=None, dt=0.05)`` (``window`` for the windowed methods; the others have 1); ``system`` is a
    registered name or a ``kklcasadi.System`` (then
    pass it to ``load_observer(path, system=...)``). Encoder/decoder MLPs ``[nx, *hidden, nz]`` / ``[nz, *hidden,
    nx]`` (tanh), ``A = -diag(1..nz)``, ``B = ones``; obs, obs_stream: GRU 4, projection 3, gain
    ``[nz + 3, 6, nz*nu]``; dyn, dyn_stream: hypernetwork GRU 4, embeddings 3, backbone ``[5, 5]``,
    rank 2, scale 1.
    With ``base=True`` an autonomous model with the same encoder/decoder is written first and
    named as ``card["base"]``. ``card_extra`` adds top-level card fields; ``skip`` gives the decoder a
    linear skip path.
    """
    import kklcasadi
    from kklcasadi.model.card import make_card
    from kklcasadi.model.files import save_model
    from kklcasadi.model.variants import BankSpec, DynModelSpec, MapsSpec, ObsModelSpec
    from kklcasadi.nets.specs import HyperSpec, MLPSpec, ObsSpec

    counter = iter(range(10**6))

    def make(method, system="duffing", *, hidden=(8, 8), window=3, seed=0, base=False,
             card_extra=None, dt=0.05, skip=False):
        plant = kklcasadi.plant.systems.get(system) if isinstance(system, str) else system
        nx, nu = plant.nx, plant.nu
        design = kklcasadi.Design.paper(plant)
        nz = design.nz
        maps = MapsSpec(MLPSpec((nx, *hidden, nz)), MLPSpec((nz, *hidden, nx), skip=skip))
        obs = lambda: ObsModelSpec(maps.encoder, maps.decoder,  # noqa: E731
                                   ObsSpec(4, 3, MLPSpec((nz + 3, 6, nz * nu))))
        dyn = lambda: DynModelSpec(maps.encoder, maps.decoder, HyperSpec(4, 3, (5, 5), 2), nu)  # noqa: E731
        bank = lambda: BankSpec(MLPSpec((nz + plant.ny + nu, *hidden, nx)), design.A, design.B, dt, nu,  # noqa: E731
                                {"y_poles": [1.0], "u_poles": [], "y_resonators": [], "clock": None})
        spec = {"obs": obs, "obs_stream": obs, "dyn": dyn, "dyn_stream": dyn, "bank": bank}.get(method, lambda: maps)()
        windowed = kklcasadi.model.variants.get(method).windowed
        card = {**make_card(plant, design, method, spec, dt=dt, window=window if windowed else 1,
                            training={"seed": seed}), **(card_extra or {})}
        root = tmp_path_factory.mktemp(f"model{next(counter)}")
        if base:
            base_card = make_card(plant, design, "autonomous", maps, dt=dt, window=1, training={"seed": seed})
            base_dir = save_model(root / "autonomous", _random_model_arrays(base_card, seed),
                                  base_card)
            sha = kklcasadi.model.files.load_model(base_dir).card["weights_sha256"]
            card["base"] = {"path": "../autonomous", "weights_sha256": sha}
        return save_model(root / method, _random_model_arrays(card, seed), card)

    return make


@pytest.fixture
def mimo_plant():
    """A plant with two inputs and two outputs (nx = 2, nz = 10), not in the registry."""
    import casadi as ca

    import kklcasadi

    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 2)
    return kklcasadi.System("mimo", x, u, [x[1] + 0.5 * u[0], -x[0] - x[0] ** 3 + u[1]],
                            [x[0], x[0] + x[1] ** 2], [[-1, 1], [-1, 1]])


def bank_runs(system="duffing", n=12, T=10.0, seed=3):
    """Noisy RK runs under the four benchmark regimes' train ranges (the monitored bank's fitting runs)."""
    import kklcasadi

    plant = kklcasadi.systems.get(system)
    rng = np.random.default_rng(seed)
    kinds = ("zero", "constant", "sinusoid", "square") * (n // 4)
    inputs = [kklcasadi.signals.sample(k, rng, "train") for k in kinds]
    return kklcasadi.simulate_batch(plant, plant.sample_box(n, seed), inputs, T, 0.05, process_std=0.1,
                                    measurement_std=0.1, seed=seed, method="rk")


@pytest.fixture
def monitored_bank(model_dir_factory):
    """A random-weight bank model with a monitor calibrated on its own features over noisy runs
    (:func:`bank_runs`), ``fit_families`` zero and constant and noise level 0.1; returns ``(path, monitor)``."""
    from kklcasadi.model.files import load_model, save_model
    from kklcasadi.model.monitor import calibrate_runs
    from kklcasadi.observer.kkl import load_observer

    path = model_dir_factory("bank")
    obs = load_observer(path)
    runs = bank_runs()
    est = obs.simulate(runs.t, runs.y, runs.u)
    features = np.concatenate([est.z, runs.y, runs.u], axis=-1)
    monitor = calibrate_runs(features, runs.t, n_prototypes=300, quantile=0.9, seed=0)
    model = load_model(path)
    card = {**model.card, "monitor": monitor.spec.to_card(), "noise": {"measurement_std": 0.1},
            "fit_families": {"zero": {}, "constant": {"value": [-1.0, 1.0]}}}
    save_model(path, {**model.arrays, **monitor.arrays()}, card, overwrite=True)
    return path, monitor


def assert_exp_tanh_ulps(x, got_exp, got_tanh):
    """kklcasadi's vector exp and tanh of ``x`` within 1 and 3 ulp of numpy's, NaN and infinities as the C library."""
    with np.errstate(over="ignore"):
        for got, want, ulps in ((got_exp, np.exp(x), 1), (got_tanh, np.tanh(x), 3)):
            finite = np.isfinite(want)
            assert np.array_equal(np.isnan(got), np.isnan(want))
            assert np.array_equal(got[~finite & ~np.isnan(want)], want[~finite & ~np.isnan(want)])
            scale = np.spacing(np.maximum(np.abs(want[finite]), np.finfo(float).tiny))
            assert np.max(np.abs(got[finite] - want[finite]) / scale) <= ulps


def c_program_estimates(obs, folder, name, t, y, u):
    """The estimates of ``obs``'s C program (``generate_c`` with the C library's math, built by gcc) fed the log
    ``time, y1.., u1..`` on stdin: (N, nx); every sample fed (no guard flag)."""
    import subprocess

    from kklcasadi.observer.codegen import generate_c

    files = generate_c(obs, folder, name, math="libm")
    subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", str(files[0]), str(files[2]), "-lm",
                    "-o", str(folder / name)], check=True)
    header = ",".join(["time", *(f"y{j + 1}" for j in range(obs.ny)), *(f"u{j + 1}" for j in range(obs.nu))])
    rows = "\n".join(",".join(repr(float(v)) for v in row) for row in np.column_stack([t, y, u]))
    out = subprocess.run([str(folder / name)], input=f"{header}\n{rows}\n", capture_output=True, text=True, check=True)
    table = np.loadtxt(out.stdout.splitlines()[1:], delimiter=",", ndmin=2)
    assert np.all(table[:, -1] == 0)                      # the status column: every sample fed
    return table[:, 1:1 + obs.nx]


def write_signed_card(directory, card):
    """Write ``card`` as ``directory``'s card.json with a digest that matches it: a card edited as a tool that signs
    would, so that what the loader checks after the digest (the fields, the weights) is what a test sees."""
    import json

    from kklcasadi.model.digest import DIGEST, card_digest

    body = {key: value for key, value in card.items() if key != DIGEST}
    (directory / "card.json").write_text(json.dumps({**body, DIGEST: card_digest(body)}))


def race(target, arguments, *, timeout=300):
    """Run ``target(*args, barrier, results)`` in one forked process per entry of ``arguments``, released at the
    same moment by ``barrier``; returns what each put on ``results``, in the order they finished."""
    import multiprocessing

    context = multiprocessing.get_context("fork")
    barrier, results = context.Barrier(len(arguments)), context.Queue()
    procs = [context.Process(target=target, args=(*args, barrier, results)) for args in arguments]
    for proc in procs:
        proc.start()
    for proc in procs:
        proc.join(timeout)
    return [results.get(timeout=5) for _ in procs]


def one_winner(outcome, *losing):
    """Of the ``(key, "wrote" | message)`` pairs of a :func:`race` exactly one wrote; the others' messages are one
    line holding one of ``losing``. Returns the winner's key."""
    winners = [key for key, what in outcome if what == "wrote"]
    assert len(winners) == 1, outcome
    for _, what in outcome:
        assert what == "wrote" or ("\n" not in what and any(text in what for text in losing)), what
    return winners[0]
