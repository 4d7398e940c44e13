"""Model copies over the states the plant's equations read (:func:`kklcasadi.model.variants.copies.read_states`):
a state that neither ``xdot`` nor ``y`` depends on (the Qube's arm angle under ``y = alpha``) is left out of the
copy, whose gain is then designed on the reduced linearisation. The reduced copy against the full plant with the
unread state at any value, its card and refusals, the observer's CasADi step against the reference, the torch
decoder and the generated C; and the plants whose copies carry every state train the arrays they trained before."""

import json
import shutil
import subprocess
from dataclasses import replace
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
import scipy.linalg
from conftest import c_program_estimates, write_signed_card

import kklcasadi as kc
from kklcasadi.model.variants.copies import ModelCopies, read_states

ROOT = Path(__file__).resolve().parents[1]
QUBE = ROOT / "examples" / "qube" / "qube_plant.py"
GCC = shutil.which("gcc")
needs_gcc = pytest.mark.skipif(GCC is None, reason="needs gcc")


def qube_alpha():
    return kc.systems.load_plant(f"{QUBE}:make_plant_alpha")


def _plants():
    return {"qube_alpha": qube_alpha(), "qube": kc.systems.load_plant(f"{QUBE}:make_plant"),
            "emps": kc.systems.load_plant(f"{ROOT / 'examples' / 'emps' / 'emps_plant.py'}:make_plant"),
            "damped3": kc.systems.load_plant(f"{ROOT / 'examples' / 'damped3_plant.py'}:make_plant"),
            "duffing": kc.systems.get("duffing"), "vdp": kc.systems.get("vdp")}


@pytest.mark.parametrize("name, read", [("qube_alpha", (1, 2, 3)), ("qube", (0, 1, 2, 3)), ("emps", (0, 1)),
                                        ("damped3", (0, 1, 2)), ("duffing", (0, 1)), ("vdp", (0, 1))])
def test_read_states_are_the_states_that_move_f_or_h(name, read):
    """Numerically: moving an unread state changes neither ``f`` nor ``h`` anywhere (bit for bit); moving a read
    one changes one of them at some drawn state."""
    system = _plants()[name]
    assert read_states(system) == read
    rng = np.random.default_rng(0)
    box = system.x0_box
    for i in range(system.nx):
        moved = False
        for _ in range(8):
            x, u = rng.uniform(box[:, 0], box[:, 1]), rng.uniform(-1, 1, system.nu)
            x2 = x.copy()
            x2[i] += rng.uniform(0.1, 1.0)
            a = np.concatenate([np.array(system.f(x, u)).ravel(), np.array(system.h(x)).ravel()])
            b = np.concatenate([np.array(system.f(x2, u)).ravel(), np.array(system.h(x2)).ravel()])
            moved |= not np.array_equal(a, b)
        assert moved == (i in read), i


def test_the_full_linearisation_of_the_pendulum_only_qube_is_not_detectable_and_the_reduced_one_is():
    """Under ``y = alpha`` the arm angle's column of ``F`` and ``H`` is zero: an eigenvalue at 0 that no gain moves
    (the full Riccati equation has no stabilising solution). Over the read states the gain is the Kalman-Bucy gain
    of the reduced linearisation, which it stabilises."""
    system = qube_alpha()
    r = system.x0_box.mean(axis=1)
    F = np.array(system.f_jac(r, [0.0])[0])
    H = np.array(system.h_jac(r))
    assert not np.any(F[:, 0]) and not np.any(H[:, 0])
    w = [0.0, 0.0, 2500.0, 2500.0]
    with pytest.raises((np.linalg.LinAlgError, ValueError)):
        P = scipy.linalg.solve_continuous_are(F.T, H.T, np.diag(w), np.eye(1))
        assert np.linalg.eigvals(F - P @ H.T @ H).real.max() < 0    # never reached: the solver refuses it
    copies = ModelCopies.design(system, [w, 4.0])
    K = [1, 2, 3]
    assert copies.states == tuple(K) and copies.nk == 3 and copies.nz == 6 and not copies.carries_all
    Fk, Hk = F[np.ix_(K, K)], H[:, K]
    for wi, L in zip([np.diag(w)[np.ix_(K, K)], 4.0 * np.eye(3)], copies.gains):
        P = scipy.linalg.solve_continuous_are(Fk.T, Hk.T, wi, np.eye(1))
        np.testing.assert_allclose(L, P @ Hk.T, rtol=1e-12)
        assert np.linalg.eigvals(Fk - L @ Hk).real.max() < 0
    np.testing.assert_array_equal(copies.reference, r[K])
    np.testing.assert_allclose(copies.bound, 10 * 0.5 * (system.x0_box[K, 1] - system.x0_box[K, 0]))
    A, B = copies.linear_part()
    np.testing.assert_array_equal(A, scipy.linalg.block_diag(*[Fk - L @ Hk for L in copies.gains]))
    np.testing.assert_array_equal(B, np.vstack(list(copies.gains)))


def _rk4_full(system, x, L, y, y_next, u, dt, n):
    """A copy of the whole plant in numpy: ``x' = f(x, u) + L (y - h(x))``, ``y`` first-order hold, ``u`` held."""
    def field(s, xx):
        ys = y + s * (y_next - y)
        return np.array(system.f(xx, u)).ravel() + L @ (ys - np.array(system.h(xx)).ravel())
    h = dt / n
    for k in range(n):
        s = k / n
        k1 = field(s, x)
        k2 = field(s + 0.5 / n, x + 0.5 * h * k1)
        k3 = field(s + 0.5 / n, x + 0.5 * h * k2)
        k4 = field(s + 1.0 / n, x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


@pytest.mark.parametrize("held", [0.0, 7.3, -2.0])
def test_the_reduced_copy_is_the_whole_plants_copy_whatever_the_unread_state_holds(held):
    """Each reduced copy's step equals an RK4 copy of the whole plant (numpy, gain 0 on the arm angle) on the carried
    states, with the arm angle held at any value: nothing reads it."""
    system = qube_alpha()
    copies = ModelCopies.design(system, [4.0, [0.0, 0.0, 2500.0, 2500.0]], substeps=3)
    step = copies.step_function(0.004)
    rng = np.random.default_rng(int(abs(held) * 10) + 5)
    for _ in range(4):
        z = rng.uniform(-1, 1, copies.nz)
        y, y_next, u = rng.uniform(2, 4, 1), rng.uniform(2, 4, 1), rng.uniform(-1, 1, 1)
        got = np.ravel(step(z, y, y_next, u))
        for i, L in enumerate(copies.gains):
            x = np.concatenate([[held], copies.reference + z[3 * i:3 * i + 3]])
            Lfull = np.vstack([np.zeros((1, 1)), L])
            want = _rk4_full(system, x, Lfull, y, y_next, u, 0.004, 3)[1:] - copies.reference
            np.testing.assert_allclose(got[3 * i:3 * i + 3], want, rtol=0, atol=1e-12)


def test_a_copy_that_leaves_out_a_state_the_equations_read_is_refused():
    system = qube_alpha()
    copies = ModelCopies.design(system, [4.0])
    with pytest.raises(ValueError, match=r"states: expected every state qube_alpha's equations read .*: \[0\]\), "
                                         r"received \[2, 3\], without \[1\]") as raised:
        ModelCopies(system, copies.gains[:, 1:], copies.reference[1:], copies.bound[1:], 1, (2, 3))
    assert "\n" not in str(raised.value)
    for states in [(3, 2, 1), (), (1, 2, 4), (1, 1, 2)]:
        with pytest.raises(ValueError, match="states: expected ascending distinct state indices"):
            ModelCopies(system, copies.gains, copies.reference, copies.bound, 1, states)
    with pytest.raises(ValueError, match=r"gains: expected finite gains of shape \(m >= 1, nk = 3, ny = 1\)"):
        ModelCopies(system, np.zeros((1, 4, 1)), copies.reference, copies.bound, 1, (1, 2, 3))
    with pytest.raises(ValueError, match=r"reference: expected nk = 3 finite numbers"):
        ModelCopies(system, copies.gains, np.zeros(4), copies.bound, 1, (1, 2, 3))


# ---------------------------------------------------------------------- the pendulum-only Qube end to end
@pytest.fixture(scope="module")
def alpha_dir(tmp_path_factory):
    pytest.importorskip("torch")
    from kklcasadi.plant.runs import RolloutConfig
    from kklcasadi.train import LoopConfig, default_config, train_observer
    from kklcasadi.train.decoder import DecoderConfig

    system = qube_alpha()
    config = replace(default_config(system.name, "bank"), y_poles=(0.5, 2.0), u_poles=(1.0,), members=1,
                     noise_copy=True, measurement_std=0.002, rollouts=RolloutConfig(n_traj=6, T=1.0),
                     decoder=DecoderConfig(hidden=(8, 8), loop=LoopConfig(epochs=1, batch_size=64)))
    return train_observer(system, "bank", tmp_path_factory.mktemp("alpha") / "bank", config=config, dt=0.004,
                          seed=3, progress=False, threads=1)


def test_the_card_records_the_states_the_copy_carries(alpha_dir):
    from kklcasadi.model.files import load_model

    system = qube_alpha()
    model = load_model(alpha_dir)
    spec = model.spec.architecture
    entry = model.card["architecture"]["bank"]["copies"]
    assert entry["states"] == [1, 2, 3] and set(entry) == {"weights", "substeps", "states"}
    assert spec.copy_states == (1, 2, 3) and spec.decoder_spec.copy_states == (1, 2, 3)
    assert model.arrays["copies/gains"].shape == (1, 3, 1) and model.arrays["copies/reference"].shape == (3,)
    assert spec.n_copies == 1 and spec.n_filters == spec.nz - 3
    assert "over the states its equations read [1, 2, 3]" in model.card["training"]["noise_copy"]
    copies = spec.model_copies(model.arrays, system)
    A, B = copies.linear_part()
    n = spec.n_filters
    np.testing.assert_array_equal(model.A[n:, n:], A)
    np.testing.assert_array_equal(model.B[n:], B)


def _signed_copy(alpha_dir, tmp_path, edit):
    from kklcasadi.model.files import load_model

    path = tmp_path / "m"
    shutil.copytree(alpha_dir, path)
    card = json.loads(json.dumps(load_model(path).card))
    edit(card["architecture"]["bank"]["copies"])
    write_signed_card(path, card)
    return path


@pytest.mark.parametrize("states", [[3, 2, 1], [0, 1, 2, 3], [1, 2, 9], "all", []])
def test_a_card_with_malformed_copy_states_is_refused_in_one_line(alpha_dir, tmp_path, states):
    from kklcasadi.model.files import load_model

    path = _signed_copy(alpha_dir, tmp_path, lambda c: c.update(states=states))
    with pytest.raises(ValueError, match=r"architecture\.bank\.copies\.states.*ascending distinct state indices in "
                                         r"\[0, nx = 4\), fewer than nx") as raised:
        load_model(path)
    assert "\n" not in str(raised.value)


def test_a_card_without_its_copy_states_is_refused(alpha_dir, tmp_path):
    """Without ``states`` the copy would carry every state: the arrays' shapes say otherwise."""
    path = _signed_copy(alpha_dir, tmp_path, lambda c: c.pop("states"))
    with pytest.raises(ValueError, match="the weights do not match the architecture"):
        kc.load_observer(path, system=qube_alpha())


def _qube_log(obs, seconds=3.0):
    system = obs.system
    tr = kc.simulate(system, [0.3, np.pi - 0.8, 1.0, -2.0], kc.signals.make("sinusoid", amplitude=0.5, omega=2.0),
                     T=seconds, dt=obs.dt, measurement_std=0.002, seed=4)
    return tr.t, tr.y, tr.u


def test_the_observer_equals_the_reference_estimate_and_the_live_step(alpha_dir):
    from kklcasadi.model.files import load_model
    from kklcasadi.model.variants import bankdecoder as bd

    obs = kc.load_observer(alpha_dir, system=qube_alpha())
    t, y, u = _qube_log(obs)
    model = load_model(alpha_dir)
    spec = model.spec.architecture
    copies = spec.model_copies(model.arrays, obs.system)
    expected = bd.estimate(spec.decoder_spec, spec.filter_arrays(model.arrays), y, u, obs.dt, copies=copies)
    est = obs.simulate(t, y, u)
    np.testing.assert_allclose(est.xhat, expected, rtol=1e-10, atol=1e-10)
    live = obs.estimator()
    np.testing.assert_allclose([live.make_step(yk, uk) for yk, uk in zip(y, u)], est.xhat, rtol=0, atol=1e-12)


def test_the_torch_decoder_equals_the_casadi_one_and_follows_the_copys_angle(alpha_dir):
    """The torch decoder (training's path) and the CasADi decoder agree; both take the copy's measured angle from
    the copy's first latent (state 1 of (1, 2, 3)), so moving ``y`` and that latent by a turn moves the estimate's
    angle by a turn and nothing else."""
    import torch

    from kklcasadi.model.files import load_model
    from kklcasadi.model.variants import bankdecoder as bd
    from kklcasadi.train.decoder import torch_decoder

    model = load_model(alpha_dir)
    spec = model.spec.architecture
    arrays = spec.filter_arrays(model.arrays)
    dspec = spec.decoder_spec
    casadi_decoder = bd.decoder_function(dspec, arrays)
    torch_dec = torch_decoder(dspec, arrays)
    rng = np.random.default_rng(2)
    z, y, u = rng.normal(size=(20, spec.nz)), rng.uniform(0, 2 * np.pi, (20, 1)), rng.normal(size=(20, 1))
    ref = np.array([np.ravel(casadi_decoder(zk, yk, uk)) for zk, yk, uk in zip(z, y, u)])
    got = torch_dec(*(torch.as_tensor(a) for a in (z, y, u))).detach().numpy()
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(bd.decode(dspec, arrays, z, y, u), ref, rtol=1e-12, atol=1e-12)
    turn = np.zeros(spec.nz)
    turn[:spec.n_filters] = 2 * np.pi * bd.dc_gains(spec.filter_bank(model.arrays))[:, 0]
    turn[spec.n_filters] = 2 * np.pi                                    # the copy's alpha, its first latent
    moved = np.array([np.ravel(casadi_decoder(zk + turn, yk + 2 * np.pi, uk)) for zk, yk, uk in zip(z, y, u)])
    np.testing.assert_allclose(moved[:, 1], ref[:, 1] + 2 * np.pi, atol=1e-9)
    np.testing.assert_allclose(np.delete(moved, 1, axis=1), np.delete(ref, 1, axis=1), atol=1e-9)


def test_the_domain_check_leaves_out_the_state_nothing_reads(alpha_dir):
    """The box check of ``[xhat; z]`` tests the states the plant reads and the latents: an arm angle estimate
    anywhere leaves the verdict as it is (numpy and the CasADi check alike), a read state out of its box does not."""
    obs = kc.load_observer(alpha_dir, system=qube_alpha())
    t, y, u = _qube_log(obs)
    est = obs.simulate(t, y, u)
    inside = np.flatnonzero(est.in_domain)[:6]                                # samples in the domain
    assert inside.size >= 3
    xhat, z = est.xhat[inside], est.z[inside]
    w = np.concatenate([y[inside], u[inside]], axis=1)[:, :, None]
    base = obs.in_domain(xhat, z, w)
    assert base.all()
    hi = obs._domain_bounds[1]
    for theta in (-50.0, 7.0, 1e6):
        moved = xhat.copy()
        moved[:, 0] = theta
        np.testing.assert_array_equal(obs.in_domain(moved, z, w), base)
        np.testing.assert_array_equal([float(obs.domain_check(zk, wk, xk)) for zk, wk, xk in zip(z, w, moved)],
                                      base.astype(float))
    fast = xhat.copy()
    fast[:, 3] = 10 * hi[3]
    assert not obs.in_domain(fast, z, w).any()


@needs_gcc
@pytest.mark.parametrize("math, tol", [("libm", 0.0), ("vector", 1e-12)])
def test_the_c_step_equals_the_casadi_step(alpha_dir, tmp_path, math, tol):
    """The generated C step against the CasADi VM's, fed back over 12 steps: bitwise with libm, within 1e-12 with
    the vector kernels."""
    from kklcasadi.observer.codegen import generate_c

    obs = kc.load_observer(alpha_dir, system=qube_alpha())
    files = generate_c(obs, tmp_path, "qa", math=math)
    library = tmp_path / "libqa.so"
    subprocess.run([GCC, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-fPIC", "-shared", str(files[0]),
                    "-o", str(library), "-lm"], check=True)
    step = ca.external("qa_step", str(library))
    rng = np.random.default_rng(6)
    z, w, y = 0.1 * rng.normal(size=obs.nz), rng.normal(size=obs.step.size_in(1)), np.array([3.0])
    for k in range(12):
        y_next, u_next = 3.0 + 0.1 * rng.normal(size=obs.ny), rng.normal(size=obs.nu)
        c_out = [np.array(v) for v in step(z, w, y, y_next, u_next)]
        vm_out = [np.array(v) for v in obs.step(z, w, y, y_next, u_next)]
        for a, b in zip(c_out, vm_out):
            if tol == 0:
                assert np.array_equal(a, b), (k, np.max(np.abs(a - b)))
            else:
                np.testing.assert_allclose(a, b, rtol=tol, atol=tol * np.max(np.abs(b)))
        z, w, y = vm_out[0], vm_out[1], y_next


@needs_gcc
def test_the_c_program_reproduces_simulate(alpha_dir, tmp_path):
    obs = kc.load_observer(alpha_dir, system=qube_alpha())
    t, y, u = _qube_log(obs, seconds=1.0)
    np.testing.assert_array_equal(c_program_estimates(obs, tmp_path, "qa", t, y, u), obs.simulate(t, y, u).xhat)


# ---------------------------------------------------------------------- copies of every state: unchanged
#: ``weights_sha256`` of tiny trainings (below) at main 55e7ebb, before copies left unread states out: EMPS (its
#: u_box gives it a noise copy of both states), damped3 (no u_box, no copy), the Qube with both encoders without a
#: copy and with its noise copy (every state read).
BEFORE = {("emps", False): "267a294e20df3967e36fcde0f923fee63879902b131fa6317d86725b42181177",
          ("damped3", False): "06f14366c2fc6ddec0d6c8afe2cb0883cd58970423e8beae641ae5d14d832e0f",
          ("qube", False): "26f2370b753d9eef69bc7349ebc1ce9e113c5a73eb26949e525afc812368ddf9",
          ("qube", True): "6dfa15bf7e5d519b17c64e017881068e42b66351dba3dd172906de9b3dc536e6"}


@pytest.mark.parametrize("name, copy", list(BEFORE))
def test_plants_whose_copies_carry_every_state_train_the_arrays_they_trained_before(name, copy, tmp_path):
    """The same tiny training (6 runs, one epoch, a 2 x 8 decoder, seed 1, one thread) gives the same weights, bit
    for bit, and a card whose copies record no ``states``."""
    pytest.importorskip("torch")
    from kklcasadi.train import LoopConfig, default_config, train_observer

    system = _plants()[name]
    config = default_config(system.name, "bank")
    if copy:
        config = replace(config, noise_copy=True, measurement_std=0.002)
    config = replace(config, rollouts=replace(config.rollouts, n_traj=6, T=2.0),
                     decoder=replace(config.decoder, hidden=(8, 8), loop=LoopConfig(epochs=1, batch_size=64)))
    dt = {"emps": 0.01, "damped3": 0.05, "qube": 0.004}[name]
    out = train_observer(system, "bank", tmp_path / "m", config=config, dt=dt, seed=1, progress=False, threads=1)
    card = json.loads((out / "card.json").read_text())
    copies = card["architecture"]["bank"].get("copies")
    assert (copies is not None) == (name == "emps" or copy)
    assert copies is None or set(copies) == {"weights", "substeps"}
    assert card["weights_sha256"] == BEFORE[(name, copy)]
