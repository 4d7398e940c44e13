"""Training side: gradients, exactness, determinism, resumability and the model files it writes."""

import dataclasses
from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import kklcasadi as kc  # noqa: E402
from kklcasadi.model.files import load_model  # noqa: E402
from kklcasadi.nets.specs import lora_target_shapes  # noqa: E402
from kklcasadi.train import LoopConfig, Phase2DataConfig, default_config, train_observer, with_epochs  # noqa: E402
from kklcasadi.train.loop import ArrayDataset, fit  # noqa: E402
from kklcasadi.train.nets import MLP, LoRAHyperNet, ObsInjection  # noqa: E402
from kklcasadi.train.phase1 import latent_noise_covariance, pde_residual  # noqa: E402

TINY_LOOP = LoopConfig(epochs=3, batch_size=64, lr=3e-3)


def tiny_phase1(**overrides):
    return default_config("duffing", "autonomous", width=16, depth=2, n_traj=12, t_keep=2.0, n_pde=200,
                          dtype="float64", encoder=TINY_LOOP, decoder=TINY_LOOP, **overrides)


@pytest.fixture(scope="module")
def phase1_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("models") / "duffing" / "autonomous"
    train_observer("duffing", "autonomous", out, config=tiny_phase1(), progress=False)
    return out


def test_pde_residual_gradient_flows_and_matches_finite_differences():
    torch.manual_seed(0)
    enc = MLP([2, 8, 8, 5]).double()
    d = kc.Design.paper(kc.systems.get("duffing"))
    A, B = torch.tensor(d.A), torch.tensor(d.B)
    x = torch.randn(32, 2, dtype=torch.float64)
    f = torch.randn(32, 2, dtype=torch.float64)
    y = x[:, :1]

    def loss():
        return (pde_residual(enc, x, f, y, A, B)[1] ** 2).mean()

    w = enc.layers[0].weight
    loss().backward()
    grad = w.grad[1, 0].item()
    assert grad != 0.0
    eps = 1e-6
    with torch.no_grad():
        w[1, 0] += eps
        up = loss().item()
        w[1, 0] -= 2 * eps
        down = loss().item()
        w[1, 0] += eps
    assert grad == pytest.approx((up - down) / (2 * eps), rel=1e-6)
    # and the directional derivative is the Jacobian times f
    J = torch.autograd.functional.jacobian(lambda v: enc(v[None])[0], x[3])
    z, res = pde_residual(enc, x[3:4], f[3:4], y[3:4], A, B)
    np.testing.assert_allclose((res + z @ A.T + y[3:4] @ B.T).detach().numpy()[0], (J @ f[3]).detach().numpy(),
                               rtol=1e-12)


def test_latent_noise_covariance_solves_the_lyapunov_equation():
    d = kc.Design.paper(kc.systems.get("vdp"))
    S = latent_noise_covariance(d, 0.1, 0.05)
    np.testing.assert_allclose(d.A @ S + S @ d.A.T + d.B @ d.B.T * 0.01 * 0.05, 0, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(S) > 0)


def test_fit_stops_on_a_non_finite_loss():
    p = torch.zeros(3, requires_grad=True)
    data = ArrayDataset({"x": np.ones((200, 1))})
    with pytest.raises(FloatingPointError, match="stage-x: the loss became nan at epoch 0, batch 0"):
        fit([p], lambda b, e: ((p.sum() * np.nan), {}), data, TINY_LOOP, name="stage-x", progress=False)


def _regression_problem():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(400, 3))
    data = ArrayDataset({"x": x, "y": x @ np.array([1.0, -2.0, 0.5])[:, None]})
    return data


@pytest.mark.parametrize("kernel", [True, False])
def test_fit_uses_the_fused_adam_on_the_cpu_only_where_torch_has_it(monkeypatch, kernel):
    """torch 2.4 on has a fused Adam for the CPU (one kernel for all parameters); setup.cfg allows torch 2.2, where
    ``fused=True`` on CPU tensors raises: there the per-tensor Adam runs, to the same fit."""
    from kklcasadi.train import loop

    made = []

    class Spy(torch.optim.Adam):
        def __init__(self, params, **kwargs):
            made.append(kwargs.get("fused"))
            super().__init__(params, **kwargs)

    monkeypatch.setattr(loop, "FUSED_CPU_ADAM", kernel)
    monkeypatch.setattr(torch.optim, "Adam", Spy)
    data = _regression_problem()
    w = torch.zeros(3, 1, dtype=torch.float64, requires_grad=True)
    res = fit([w], lambda b, e: (((b["x"] @ w - b["y"]) ** 2).mean(), {}), data,
              LoopConfig(epochs=6, batch_size=32, lr=0.1), name="reg", progress=False)
    assert made == [True if kernel else None]
    assert res.history["train"][-1] < res.history["train"][0] / 10


def test_resume_continues_exactly(tmp_path):
    data = _regression_problem()
    cfg = LoopConfig(epochs=6, batch_size=32, lr=0.1)

    def run(epochs, ckpt, resume):
        torch.manual_seed(0)
        w = torch.zeros(3, 1, dtype=torch.float64, requires_grad=True)
        res = fit([w], lambda b, e: (((b["x"] @ w - b["y"]) ** 2).mean(), {}), data, replace(cfg, epochs=epochs),
                  name="reg", checkpoint=ckpt, resume=resume, progress=False)
        return w.detach().clone(), res

    straight, res = run(6, None, False)
    assert res.history["train"][-1] < res.history["train"][0] / 10
    run(3, tmp_path / "reg.ckpt.npz", False)
    resumed, res2 = run(6, tmp_path / "reg.ckpt.npz", True)
    assert torch.equal(straight, resumed)
    assert len(res2.history["val"]) == 6


@pytest.mark.parametrize("epochs", [1, 4])
def test_validation_subset_scores_fewer_samples_and_the_kept_model_on_all(epochs):
    data = _regression_problem()                    # 40 held-out samples at val_fraction 0.1
    cfg = LoopConfig(epochs=epochs, batch_size=32, lr=0.05)

    def run(val_samples):
        torch.manual_seed(0)
        w = torch.zeros(3, 1, dtype=torch.float64, requires_grad=True)
        res = fit([w], lambda b, e: (((b["x"] @ w - b["y"]) ** 2).mean(), {}), data,
                  replace(cfg, val_samples=val_samples), name="reg", progress=False)
        return w.detach().clone(), res

    w_all, res_all = run(None)
    w_sub, res_sub = run(8)
    assert res_all.val_all == res_all.best_val and res_all.summary()["val_all"] == res_all.best_val
    assert res_all.held_out == res_sub.held_out == 40 and res_sub.summary()["trained_samples"] == epochs * 352
    # the epochs train on the same batches; only the scores differ (8 of the 40 held-out samples)
    np.testing.assert_array_equal(res_sub.history["train"], res_all.history["train"])
    assert res_sub.history["val"] != res_all.history["val"]
    if res_sub.best_epoch == res_all.best_epoch:    # same kept model: its loss on all held-out samples
        assert torch.equal(w_sub, w_all) and res_sub.val_all == res_all.best_val
    assert res_sub.val_all != res_sub.best_val


@pytest.mark.parametrize("value, kind", [(0, ValueError), (-5, ValueError), (2.5, TypeError)])
def test_loop_config_rejects_a_bad_val_samples(value, kind):
    with pytest.raises(kind, match="val_samples"):
        LoopConfig(val_samples=value)


def test_bench_phase2_epoch_times_both_validation_settings(phase1_dir, capsys):
    from kklcasadi.evaluation.bench.training import bench_phase2_epoch

    timings = bench_phase2_epoch("duffing", phase1_dir, methods=("obs",), threads=1,
                                 data=Phase2DataConfig(n_traj=2, n_signals=2, T=20.0))
    assert [t.label for t in timings] == ["obs epoch, validation on all held-out", "obs epoch, validation on 8192"]
    assert all(t.seconds > 0 and t.items == 5 * 256 for t in timings)     # 1436 training samples: 5 batches
    out = capsys.readouterr().out
    assert "obs: 160 samples held out, 1280 trained per epoch, 40 epochs by default" in out
    assert f"ratio {timings[0].seconds / timings[1].seconds:.2f}x per epoch" in out      # of the returned times


@pytest.mark.parametrize("methods", [("autonomous",), (), "obs"])
def test_bench_phase2_epoch_rejects_other_methods(phase1_dir, methods):
    from kklcasadi.evaluation.bench.training import bench_phase2_epoch

    with pytest.raises(ValueError, match=r"methods: expected a non-empty tuple of \('obs', 'dyn'\)"):
        bench_phase2_epoch("duffing", phase1_dir, methods=methods)


@pytest.mark.parametrize("stream", [False, True])
def test_dyn_loss_differentiates_the_encoder_along_state_and_context(stream):
    """The PDE part equals the residual of dT/dt by central differences along (xdot, context_dot)."""
    from kklcasadi.train.nets import mlp_forward_lora
    from kklcasadi.train.phase2 import make_dyn_loss

    torch.manual_seed(3)
    design = kc.Design.paper(kc.systems.get("duffing"))
    enc, dec = MLP([2, 7, 7, design.nz]).double(), MLP([design.nz, 7, 2]).double()
    hyper = LoRAHyperNet(lora_target_shapes(enc.spec, dec.spec), 1, hidden=5, embed=3, backbone=(6,), rank=2,
                         scale_init=0.7).double()
    factors_of = hyper.factors_of_hidden if stream else hyper
    context = torch.randn(6, 5) if stream else torch.randn(6, 4, 1)
    context, context_dot = context.double(), torch.randn_like(context).double()
    x, xdot, y = (torch.randn(6, n, dtype=torch.float64) for n in (2, 2, 1))
    x_scale, z_scale = torch.tensor([1.3, 0.7], dtype=torch.float64), torch.rand(design.nz, dtype=torch.float64) + 0.5
    loss = make_dyn_loss(design, 0.1, enc, dec, hyper, factors_of, x_scale, z_scale)

    def encode(eps):
        f = factors_of(context + eps * context_dot)
        return mlp_forward_lora(enc, x + eps * xdot, f[:len(enc.layers)], hyper.scale)

    def pde_of(dz):
        res = dz - z @ torch.tensor(design.A).T - y @ torch.tensor(design.B).T
        return float(((res / z_scale) ** 2).mean())

    with torch.no_grad():
        z = encode(0.0)
        xhat = mlp_forward_lora(dec, z, factors_of(context)[len(enc.layers):], hyper.scale)
        total, parts = loss(x, xdot, y, context, context_dot)
        _, frozen = loss(x, xdot, y, context, torch.zeros_like(context_dot))
        eps = 1e-6
        dz = (encode(eps) - encode(-eps)) / (2 * eps)
    assert parts["pde"] == pytest.approx(pde_of(dz), rel=1e-7)
    assert parts["recon"] == pytest.approx(float((((xhat - x) / x_scale) ** 2).mean()), rel=1e-12)
    assert float(total) == pytest.approx(parts["recon"] + 0.1 * parts["pde"], rel=1e-12)
    assert abs(frozen["pde"] - parts["pde"]) > 1e-5 * parts["pde"]      # the context's motion counts


def test_phase1_end_to_end_writes_a_torch_free_model(phase1_dir):
    model = load_model(phase1_dir)
    card = model.card
    assert card["method"] == "autonomous" and card["window"] == 1
    # a paper plant trains with the paper's design (Design.paper), as its shipped models do
    np.testing.assert_array_equal(model.A, -np.diag(np.arange(1.0, 6.0)))
    np.testing.assert_array_equal(model.B, np.ones((5, 1)))
    assert card["training"]["data"]["labelled"] == 12 * 40
    assert (phase1_dir / "history.png").stat().st_size > 1000
    import json

    hist = json.loads((phase1_dir / "history.json").read_text())
    from kklcasadi import provenance  # the model's files name what trained them

    stamp = provenance.read(phase1_dir / "history.json")
    assert stamp.command and stamp == provenance.read(phase1_dir / "history.png") == provenance.read(
        phase1_dir / "card.json") and stamp.seeds == {"training": card["training"]["seed"]}
    for stage in ("encoder", "decoder"):          # the card's record is the history's
        record, history = card["training"][stage], hist[stage]
        assert record["epochs"] == len(history["val"]) == 3 and record["final_train"] == history["train"][-1]
        assert record["best_val"] == min(history["val"]) == history["val"][record["best_epoch"]]
        assert record["val_all"] == record["best_val"]             # no validation subset: all held-out
    # losses fall: measured on this seeded run (3 epochs) encoder validation 1.336 -> 0.602 (2.2x),
    # its PDE term 12.0 -> 4.9 (2.5x), decoder validation 0.655 -> 0.432 (1.5x)
    assert hist["encoder"]["val"][-1] < hist["encoder"]["val"][0] / 1.8
    assert hist["encoder"]["pde"][-1] < hist["encoder"]["pde"][0] / 2.0
    assert hist["decoder"]["val"][-1] < hist["decoder"]["val"][0] / 1.3
    # the card records the plant's fingerprint and where the maps were trained
    import kklcasadi as kc

    assert model.spec.system.fingerprint == kc.systems.get("duffing").fingerprint
    domain = model.spec.domain
    assert np.all(domain.x_lo <= -0.9) and np.all(domain.x_hi >= 0.9) and np.all(domain.z_lo < domain.z_hi)
    # the saved arrays rebuild the same network bitwise
    net = MLP.from_arrays(model.arrays, "encoder", model.spec.architecture.encoder)
    again = {k: v for k, v in net.to_arrays("encoder").items()}
    for k, v in again.items():
        np.testing.assert_array_equal(v, model.arrays[k])


def test_a_plant_without_the_paper_flag_trains_with_the_default_design(tmp_path):
    plant = kc.systems.get("linear")
    assert not plant.paper_design
    loop = LoopConfig(epochs=1, batch_size=32)
    config = default_config("linear", "autonomous", width=8, depth=1, n_traj=4, t_keep=1.0, n_pde=50,
                            dtype="float64", encoder=loop, decoder=loop)
    model = load_model(train_observer(plant, "autonomous", tmp_path / "linear", config=config, progress=False))
    design = kc.Design.default(plant)
    np.testing.assert_array_equal(model.A, design.A)
    np.testing.assert_array_equal(model.B, design.B)


def test_training_is_deterministic(tmp_path, phase1_dir):
    out = tmp_path / "again"
    train_observer("duffing", "autonomous", out, config=tiny_phase1(), progress=False)
    a, b = load_model(out), load_model(phase1_dir)
    assert a.card["weights_sha256"] == b.card["weights_sha256"]


def test_noise_aware_decoder_records_its_noise_level(tmp_path):
    out = tmp_path / "noisy"
    train_observer("duffing", "autonomous", out, config=tiny_phase1(measurement_std=0.1), progress=False)
    assert load_model(out).card["noise"]["measurement_std"] == 0.1


SMALL = Phase2DataConfig(n_traj=3, n_signals=3, T=3.0, window=10)
P2_LOOP = LoopConfig(epochs=2, batch_size=32, lr=1e-3, schedule="cosine", samples_per_epoch=128)


@pytest.mark.parametrize("method, config", [
    ("obs", default_config("duffing", "obs", data=SMALL, loop=P2_LOOP, hidden=8, proj=4, gain_hidden=(8,))),
    ("obs", default_config("duffing", "obs", data=SMALL, loop=P2_LOOP, hidden=8, proj=4, gain_hidden=(8,),
                           model_based_injection=True)),
    ("dyn", default_config("duffing", "dyn", data=SMALL, loop=P2_LOOP, hidden=8, embed=4, backbone=(8,), rank=2)),
    ("curriculum", default_config("duffing", "curriculum", n_traj=2, n_signals_per_stage=1, t_keep=2.0,
                                  loop=LoopConfig(epochs=1, batch_size=32))),
    ("inject", None),
    ("obs_stream", default_config("duffing", "obs_stream", data=SMALL, hidden=8, proj=4, gain_hidden=(8,),
                                  loop=LoopConfig(epochs=2, batch_size=2, schedule="cosine"))),
    ("dyn_stream", default_config("duffing", "dyn_stream", data=SMALL, hidden=8, embed=4, backbone=(8,), rank=2,
                                  loop=LoopConfig(epochs=2, batch_size=2, schedule="cosine"))),
])
def test_phase2_methods_write_models_that_refer_to_their_base(tmp_path, phase1_dir, method, config):
    out = tmp_path / method
    train_observer("duffing", method, out, config=config, base=phase1_dir, progress=False)
    model = load_model(out)
    assert model.method == method
    base_sha = load_model(phase1_dir).card["weights_sha256"]
    if method == "inject":                     # self-contained: the base is recorded, not needed
        assert model.base is None and model.card["training"]["derived_from"]["weights_sha256"] == base_sha
    else:
        assert model.base is not None and model.base.card["weights_sha256"] == base_sha
    if method in ("obs", "dyn", "obs_stream", "dyn_stream"):
        assert model.window == (1 if method.endswith("_stream") else 10)
        # the frozen maps are the base's, bitwise
        for k in ("encoder/W0", "decoder/W1"):
            np.testing.assert_array_equal(model.arrays[k], model.base.arrays[k])
    if method == "obs":
        assert model.card["model_based_injection"] is config.model_based_injection
        net = ObsInjection.from_arrays(model.arrays, "", model.spec.architecture.obs)
        z = torch.randn(5, 5, dtype=torch.float64)
        w = torch.randn(5, 10, 1, dtype=torch.float64)
        assert torch.equal(net(z, w, torch.zeros(5, 1, dtype=torch.float64)), torch.zeros(5, 5, dtype=torch.float64))
    if method == "dyn":
        hyper = LoRAHyperNet.from_arrays(model.arrays, "hyper", model.spec.architecture.hyper,
                                         lora_target_shapes(model.spec.architecture.encoder,
                                                            model.spec.architecture.decoder), nu=1)
        for a, b in hyper(torch.zeros(2, 10, 1, dtype=torch.float64)):
            assert torch.count_nonzero(a) == 0 and torch.count_nonzero(b) == 0
    if method == "obs_stream":       # the torch streaming context is the observer's, sample by sample
        import kklcasadi as kc

        obs = kc.load_observer(out)
        net = ObsInjection.from_arrays(model.arrays, "", model.spec.architecture.obs)
        u = np.sin(np.arange(30.0) / 3)[:, None]
        h = net.context.sequence(torch.as_tensor(u)[None])[0].detach().numpy()
        w = obs.memory_init(0.0, u[0])
        for k in range(1, len(u)):
            w = obs.memory.next(w, 0.0, u[k])
        np.testing.assert_allclose(np.array(w)[:-1].ravel(), h[-1], rtol=0, atol=1e-13)
        z = np.linspace(-1, 1, 5)
        gain = net.gain_of_hidden(torch.as_tensor(z)[None], torch.as_tensor(h[-1])[None])[0].detach().numpy()
        np.testing.assert_allclose(np.array(obs.rhs(z, [0.0], u[-1], w)).ravel(),
                                   obs.A @ z + gain @ u[-1], rtol=0, atol=1e-12)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("method, config", [
    ("autonomous", tiny_phase1()),
    ("obs", default_config("duffing", "obs", data=SMALL, loop=P2_LOOP, hidden=8, proj=4, gain_hidden=(8,))),
    ("dyn", default_config("duffing", "dyn", data=SMALL, loop=P2_LOOP, hidden=8, embed=4, backbone=(8,), rank=2)),
    ("curriculum", default_config("duffing", "curriculum", n_traj=2, n_signals_per_stage=1, t_keep=2.0,
                                  loop=LoopConfig(epochs=1, batch_size=32))),
])
def test_cuda_training_gives_the_cpu_model(tmp_path, phase1_dir, method, config):
    """Same seed, float64: the model trained on the GPU equals the CPU one up to reduction order.

    Adam divides each gradient element by its own running scale, so a reduction-order difference
    in a near-zero gradient can move a weight by up to ~1e-4 of a step (lr 1e-3): atol 1e-6. A
    device bug (wrong data, a detached term) moves weights by whole steps.
    """
    base = None if method == "autonomous" else phase1_dir
    models = {}
    for device in ("cpu", "cuda"):
        train_observer("duffing", method, tmp_path / device, config=config, base=base, device=device, progress=False)
        models[device] = load_model(tmp_path / device)
    cpu, gpu = models["cpu"], models["cuda"]
    assert gpu.card["training"]["device"] == "cuda"
    assert sorted(cpu.arrays) == sorted(gpu.arrays)
    for name in cpu.arrays:
        np.testing.assert_allclose(gpu.arrays[name], cpu.arrays[name], rtol=1e-5, atol=1e-6, err_msg=name)


def test_train_observer_rejects_bad_arguments(tmp_path, phase1_dir):
    with pytest.raises(ValueError, match=r"method: expected one of \['autonomous', 'curriculum', 'obs'"):
        train_observer("duffing", "lstm", tmp_path / "x")
    with pytest.raises(ValueError, match=r"name: expected one of \['duffing'"):
        train_observer("dufing", "autonomous", tmp_path / "x")
    with pytest.raises(FileExistsError, match="overwrite"):
        train_observer("duffing", "autonomous", phase1_dir, config=tiny_phase1(), progress=False)
    with pytest.raises(ValueError, match="base: expected a model for system 'vdp'.*system 'duffing'"):
        train_observer("vdp", "inject", tmp_path / "y", base=phase1_dir)
    with pytest.raises(TypeError, match="config: expected a ObsConfig"):
        train_observer("duffing", "obs", tmp_path / "z", base=phase1_dir, config=tiny_phase1())
    with pytest.raises(TypeError, match=r"overrides: expected fields of ObsConfig.*unknown field\(s\) \['width'\]"):
        default_config("duffing", "obs", width=3)


def test_decoder_only_retraining_keeps_the_encoder(tmp_path, phase1_dir):
    out = tmp_path / "dec"
    train_observer("duffing", "autonomous", out, config=tiny_phase1(measurement_std=0.05), base=phase1_dir,
                   progress=False)
    new, old = load_model(out), load_model(phase1_dir)
    for k in old.arrays:
        if k.startswith("encoder/"):
            np.testing.assert_array_equal(new.arrays[k], old.arrays[k])
    assert not np.array_equal(new.arrays["decoder/W0"], old.arrays["decoder/W0"])
    assert new.card["training"]["encoder"] == "kept from the base model"
    assert new.base is not None and new.card["noise"]["measurement_std"] == 0.05


def test_epochs_change_only_the_epochs():
    base = default_config("duffing", "autonomous")
    short = default_config("duffing", "autonomous", epochs=8)
    for stage in ("encoder", "decoder"):
        assert getattr(short, stage) == dataclasses.replace(getattr(base, stage), epochs=8)
    assert dataclasses.replace(short, encoder=base.encoder, decoder=base.decoder) == base
    obs = with_epochs(default_config("duffing", "obs"), 5)
    assert obs.loop.epochs == 5 and obs.loop.batch_size == default_config("duffing", "obs").loop.batch_size
    with pytest.raises(TypeError, match="epochs: expected a positive int"):
        default_config("duffing", "obs", epochs=2.5)


def test_a_training_runs_on_its_own_threads_and_gives_torch_its_count_back(monkeypatch, tmp_path):
    import kklcasadi.train as kt

    seen = []

    def spy(*args, **kwargs):
        seen.append(torch.get_num_threads())
        if len(seen) == 3:
            raise RuntimeError("a training that fails")
        return tmp_path

    monkeypatch.setattr(kt, "_train", spy)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        kt.train_observer("rossler", "bank", tmp_path / "m", progress=False)
        kt.train_observer("rossler", "bank", tmp_path / "m", progress=False, threads=3)
        assert torch.get_num_threads() == 2
        with pytest.raises(RuntimeError, match="a training that fails"):
            kt.train_observer("rossler", "bank", tmp_path / "m", progress=False, threads=4)
        assert seen == [kt.TRAIN_THREADS, 3, 4] and kt.TRAIN_THREADS == 1
        assert torch.get_num_threads() == 2
        with pytest.raises(ValueError, match="threads"):
            kt.train_observer("rossler", "bank", tmp_path / "m", progress=False, threads=0)
    finally:
        torch.set_num_threads(before)
