"""kklcasadi bench scaling: the chain plant against an independent numpy right-hand side, the C timing
loops against the CasADi VM (they run the step they time), the growth fits on known power laws, and
one tiny run end to end."""

import json
import shutil
import subprocess

import casadi as ca
import numpy as np
import pytest

from kklcasadi import provenance
from kklcasadi.estimators.ekf import EKF
from kklcasadi.evaluation.bench import scaling as sc
from kklcasadi.observer.codegen import generate_c
from kklcasadi.observer.kkl import load_observer
from kklcasadi.plant.systems import get

needs_gcc = pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc is not installed")


def _chain_rhs(x, u, n, k=1.0, c=0.1, beta=1.0):
    q, p = x[:n], x[n:]
    padded = np.concatenate([[0.0], q, [0.0]])
    acc = -q - beta * q ** 3 - c * p + k * (padded[:-2] - 2 * q + padded[2:])
    acc[0] += u[0]
    return np.concatenate([p, acc])


@pytest.mark.parametrize("n,ny", [(1, 1), (8, 1), (9, 2), (17, 3), (32, 4)])
def test_the_chain_is_coupled_duffing_oscillators(n, ny, rng):
    plant = sc.oscillator_chain(n)
    assert (plant.nx, plant.nu, plant.ny) == (2 * n, 1, ny)
    for _ in range(3):
        x, u = rng.uniform(-1, 1, 2 * n), rng.uniform(-1, 1, 1)
        np.testing.assert_allclose(np.array(plant.f(x, u)).ravel(), _chain_rhs(x, u, n), rtol=1e-14, atol=1e-14)
        np.testing.assert_array_equal(np.array(plant.h(x)).ravel(), x[0:n:8])


def _row(nx, observer_us, ekf_us):
    return sc.ScalingRow(nx // 2, nx, 1, 12, 1.0 * nx, 10.0, observer_us, None, 1000 * nx, 0.1,
                         {"sx": ekf_us, "dense": 2 * ekf_us}, {}, {"sx": 0.1, "dense": 0.1}, 0.5 * nx ** 2, 0, 1.0, 1.0)


def test_growth_exponents_and_the_crossover_on_power_laws():
    rows = [_row(nx, 10.0 * nx, 0.05 * nx ** 3) for nx in (2, 4, 8, 16, 32, 64)]
    result = sc.ScalingResult(rows)
    slopes = result.exponents()
    assert slopes["observer C step"] == pytest.approx(1.0) and slopes["EKF C step (sx)"] == pytest.approx(3.0)
    assert slopes["MHE solve"] == pytest.approx(2.0) and slopes["training per simulated second"] == pytest.approx(1.0)
    assert "observer C instructions" not in slopes                 # not measured: no fit
    assert result.crossover() == 16                                # 10 nx < 0.05 nx^3 from nx = 16 on (14.1)
    assert sc.ScalingResult(rows[:2]).crossover() is None
    assert "from nx = 16 on" in result.table()


def _run(binary, steps):
    out = subprocess.run([str(binary), str(steps), "1"], capture_output=True, text=True, check=True).stdout.split()
    return float(out[1])


def _pattern(n):
    return 0.1 * ((np.arange(n) % 5) - 2) / 2.0


@needs_gcc
def test_the_ekf_loop_runs_the_step_it_times(tmp_path):
    plant = get("vdp")
    ekf = EKF(plant, 0.05)
    for form in ("sx", "dense"):
        files = ekf.generate_c(tmp_path / form, "ekf_bench", form=form, math="libm")
        ns = plant.nx * (plant.nx + 1)
        loop = tmp_path / form / "loop.c"
        loop.write_text(sc._loop_source("ekf_bench", [ns, plant.nu + plant.ny], [ns], [(0, 0)], plant.ny))
        sc._compile("gcc", [files[0], loop], tmp_path / form / "loop", ("-std=c99", "-O1"))
        state, uy, checksum = np.array(ekf.start(np.zeros(plant.ny))).ravel(), _pattern(plant.nu + plant.ny), 0.0
        step = ekf.step_of(form)
        for _ in range(7):
            state = np.array(step(state, uy)).ravel()
            checksum += state[0]
        assert _run(tmp_path / form / "loop", 7) == pytest.approx(checksum, rel=1e-13, abs=1e-15)


@needs_gcc
def test_the_observer_loop_runs_the_step_it_times(tmp_path, model_dir_factory):
    obs = load_observer(model_dir_factory("bank"))
    files = generate_c(obs, tmp_path, "obs_bench", math="libm")
    rows, cols = obs.memory_shape
    sizes = [obs.nz, rows * cols, obs.ny, obs.ny, obs.nu]
    loop = tmp_path / "loop.c"
    loop.write_text(sc._loop_source("obs_bench", sizes, [obs.nz, rows * cols, obs.nx], [(0, 0), (1, 1)], None))
    sc._compile("gcc", [files[0], loop], tmp_path / "loop", ("-std=c99", "-O2"))
    z, w, y, y_next, u_next = (_pattern(n) for n in sizes)
    checksum = 0.0
    for _ in range(5):
        outputs = obs.step(z, ca.reshape(ca.DM(w), rows, cols), y, y_next, u_next)
        z, w, _ = (np.array(v).ravel(order="F") for v in outputs)
        checksum += z[0]
    assert _run(tmp_path / "loop", 5) == pytest.approx(checksum, rel=1e-13, abs=1e-15)


@needs_gcc
def test_a_tiny_scaling_run(tmp_path):
    pytest.importorskip("kklcasadi.train", reason="the benchmark trains observers (torch)")
    result = sc.bench_scaling((1,), runs=8, epochs=1, T=20.0, trials=2, mhe_steps=8, mhe_horizon=4, repeat=5,
                              callgrind=False, out=tmp_path, progress=False)
    (row,) = result.rows
    # the recipe's bank: 8 output and 5 input filters and a clock, decoder 3 x 256
    assert (row.nx, row.ny, row.nz) == (2, 1, 14) and row.observer_us > 0 and row.ekf_best_us > 0
    assert row.observer_work == 14 * (14 + 2 + 1 + 1) + 16 * 256 + 2 * 256 * 256 + 256 * 2
    assert 0 < row.smape_observer and 0 < row.smape_ekf and row.simulated_s == 8 * 20.0
    assert (tmp_path / "scaling.png").stat().st_size > 0 and "| 2 | 1 | 14 |" in (tmp_path / "scaling.md").read_text()
    saved = json.loads((tmp_path / "scaling.json").read_text())
    for name in ("scaling.md", "scaling.json", "scaling.png"):
        assert provenance.read(tmp_path / name).seeds == {"training_and_trials": 0}
    assert sc.ScalingRow(**saved["rows"][0]) == row and saved["settings"]["runs"] == 8
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    with pytest.raises(FileExistsError, match="^out: .*scaling.md exists and this command does not overwrite"):
        sc.bench_scaling((1,), out=tmp_path)                        # refused before any training
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
