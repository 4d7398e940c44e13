"""Phase-1 labels that cannot collapse silently: escapes detected, frozen labels on a damped plant, the
coverage of the box measured, recorded in the card and enforced; label spacing independent of the observer's dt."""

import casadi as ca
import numpy as np
import pytest

import kklcasadi as kc
from kklcasadi.model.card import make_card, parse_card
from kklcasadi.model.files import load_model, save_model
from kklcasadi.nets.hold import foh_matrices
from kklcasadi.plant import data


def damped_plant():
    """A damped oscillator with cubic damping: every backward run escapes in finite time."""
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u")
    return kc.System("damped", x, u, [x[1], -4 * x[0] - 0.3 * x[1] - x[1] ** 3 + u], x[0], [[-1, 1], [-2, 2]])


@pytest.fixture(scope="module")
def damped():
    plant = damped_plant()
    design = kc.Design.default(plant)
    runs = {kind: data.phase1_labels(plant, design, 30, 0, t_keep=4.0, labels=kind) for kind in ("auto", "exact")}
    return plant, design, runs


def test_coverage_of_known_points():
    box = np.array([[0.0, 1.0], [-1.0, 1.0]])
    # a 4 x 4 lattice of cell centres fills every cell of a 4 x 4 grid and 8 of 10 bins of each state
    g = (np.arange(4) + 0.5) / 4
    lattice = np.stack(np.meshgrid(g, 2 * g - 1), axis=-1).reshape(-1, 2)
    per_state, grid, k = data.label_coverage(lattice, box, cells=16)
    assert k == 4 and grid == 1.0 and per_state == (0.4, 0.4)
    # points at one corner, and points outside the box, count for one cell and one bin each
    corner = np.array([[0.01, -0.99], [0.02, -0.98], [5.0, 0.0], [0.5, 7.0]])
    per_state, grid, k = data.label_coverage(corner, box, cells=16)
    assert per_state == (0.2, 0.2) and grid == pytest.approx(1 / 16)          # (0.5, 7) counts for x1 only
    assert data.label_coverage(lattice, box, cells=1000)[2] == 31               # floor(sqrt(1000))


def test_backward_escapes_are_detected_and_frozen_labels_cover_the_damped_plants_box(damped):
    plant, design, runs = damped
    (labels, report), (_, exact) = runs["auto"], runs["exact"]
    assert exact.escaped == report.escaped == 30 and exact.runs == 30
    # exact labels are released at the escape and kept where the forward flow ends: near rest
    assert exact.kind == "exact" and exact.poor and max(exact.per_state) <= 0.4
    assert report.kind == "frozen" and not report.poor
    assert report.per_state == (1.0, 1.0) and report.grid > 0.8 and report.cells_per_axis == 5
    first = labels.x.reshape(30, -1, 2)[:, 0]
    # the runs start at the sampled states (to the RK4 error of the backward pass, retraced by CVODES)
    np.testing.assert_allclose(first, plant.sample_box(30, 0), atol=1e-4)
    # the latents follow zdot = A z + B y along each kept run: one exact step of the latent with y held first-order
    hold = foh_matrices(design.A, design.B, 0.05)
    z, y = labels.z.reshape(30, -1, design.nz), labels.y.reshape(30, -1, 1)
    step = z[:, :-1] @ hold.Ad.T + y[:, :-1] @ hold.Gy.T + y[:, 1:] @ hold.Gy_next.T
    np.testing.assert_allclose(z[:, 1:], step, rtol=0, atol=1e-3 * np.abs(z).max())
    assert "frozen labels (30 runs, 30 of 30 backward runs escaped)" in report.summary()


def test_a_plant_without_escapes_keeps_the_exact_labels_bitwise():
    plant = kc.systems.get("linear")
    design = kc.Design.default(plant)
    exact = data.phase1(plant, design, 6, 2, t_keep=1.0, labels="exact")
    auto, report = data.phase1_labels(plant, design, 6, 2, t_keep=1.0, labels="auto")
    assert report.kind == "exact" and report.escaped == 0
    for a, b in zip(exact, auto):
        np.testing.assert_array_equal(a, b)


def test_forward_labels_burn_in_from_the_box():
    plant = kc.systems.get("duffing")
    design = kc.Design.paper(plant)
    labels, report = data.phase1_labels(plant, design, 5, 1, t_keep=1.0, labels="forward", burn_in_tol=1e-2)
    expected = np.ceil(design.forgetting_time(2.0, 1e-2) / 0.05) * 0.05
    assert report.kind == "forward" and report.escaped == 0 and report.burn_in == pytest.approx(expected)
    # the same runs simulated by hand: from the box with the latent at its equilibrium, kept after the burn-in
    x0 = plant.sample_box(5, 1)
    n_burn, n_keep = round(expected / 0.05), 20
    batch = kc.simulate_batch(data._latent_system(plant, design), np.hstack([x0, design.latent_equilibrium(
        plant.h_batch(x0))]), [np.ones(n_burn + n_keep)] * 5, (n_burn + n_keep) * 0.05, 0.05)
    np.testing.assert_allclose(labels.z, batch.x[:, n_burn:, 2:].reshape(-1, design.nz), rtol=0, atol=1e-12)


@pytest.mark.parametrize("name, kind", [("duffing", "exact"), ("vdp", "exact"), ("rossler", "exact"), ("fhn", "cold"),
                                        ("pendulum", "auto")])
def test_label_defaults_per_plant(name, kind):
    """The paper's plants keep the labels of the shipped models; a new plant gets auto ones, spaced 0.05 s."""
    torch = pytest.importorskip("torch")  # noqa: F841
    from kklcasadi.train import default_config

    config = default_config(name, "autonomous")
    assert config.labels == kind and config.label_dt == 0.05


def test_coverage_is_recorded_in_the_card_validated_and_optional(model_dir_factory, tmp_path):
    plant = kc.systems.get("duffing")
    report = data.LabelReport("frozen", 30, 12, 0.0, (1.0, 0.9), 0.85, 5)
    model = load_model(model_dir_factory("autonomous", card_extra={"coverage": report.to_card()}))
    assert model.spec.coverage == report
    assert load_model(model_dir_factory("autonomous")).spec.coverage is None            # old cards load
    card = make_card(plant, kc.Design.paper(plant), "autonomous", model.spec.architecture, dt=0.05, coverage=report,
                     process_std=0.2, measurement_std=0.1)
    assert card["coverage"]["per_state"] == [1.0, 0.9] and card["noise"] == {"measurement_std": 0.1,
                                                                             "process_std": 0.2}
    saved = save_model(tmp_path / "m", model.arrays, card)
    assert load_model(saved).spec.process_std == 0.2
    full = {"format": "kklcasadi.model", "format_version": 2, "kklcasadi_version": "0", **card}
    for change, message in [({"grid": 1.5}, r"'coverage.grid': expected a number in \[0, 1\]"),
                            ({"per_state": [1.0]}, r"'coverage.per_state': expected a list of 2 numbers"),
                            ({"labels": "auto"}, r"'coverage.labels': expected one of \['exact', 'frozen'"),
                            ({"escaped": 31}, r"'coverage.escaped': expected at most runs = 30"),
                            ({"runs": 0}, r"'coverage.runs': expected an integer >= 1")]:
        bad = {**full, "coverage": {**card["coverage"], **change}}
        with pytest.raises(ValueError, match=message):
            parse_card(bad, require_sha=False)
    with pytest.raises(ValueError, match=r"'noise.process_std': expected a number >= 0"):
        parse_card({**full, "noise": {"measurement_std": 0.1, "process_std": -1}}, require_sha=False)


def test_training_refuses_labels_that_do_not_cover_the_box(damped):
    torch = pytest.importorskip("torch")  # noqa: F841
    from kklcasadi.train.phase1 import check_coverage

    plant, _, runs = damped
    check_coverage(runs["auto"][1], plant)
    with pytest.raises(ValueError) as exc:
        check_coverage(runs["exact"][1], plant)
    message = str(exc.value)
    assert "\n" not in message and message.startswith("labels: expected Phase-1 labels covering the X0 box of "
                                                      "'damped'")
    assert "received exact labels (30 runs, 30 of 30 backward runs escaped)" in message
    assert "labels='auto'" in message and "kklcasadi train --method bank" in message


def test_phase1_costs_the_same_at_any_observer_dt(tmp_path):
    """The labels are spaced by Phase1Config.label_dt: a 4 ms observer gets the labels of a 50 ms one."""
    pytest.importorskip("torch")
    from kklcasadi.train import LoopConfig, default_config, train_observer

    tiny = LoopConfig(epochs=1, batch_size=64, lr=3e-3)
    config = default_config("duffing", "autonomous", width=8, depth=1, n_traj=6, t_keep=2.0, n_pde=50,
                            dtype="float64", encoder=tiny, decoder=tiny)
    cards = {}
    for dt in (0.004, 0.05):
        out = train_observer("duffing", "autonomous", tmp_path / str(dt), config=config, dt=dt, progress=False)
        cards[dt] = load_model(out)
    assert cards[0.004].dt == 0.004 and cards[0.05].dt == 0.05
    labelled = [c.card["training"]["data"]["labelled"] for c in cards.values()]
    assert labelled == [6 * 40, 6 * 40]
    assert cards[0.004].spec.coverage == cards[0.05].spec.coverage
