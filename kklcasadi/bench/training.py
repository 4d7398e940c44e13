"""Training throughput (samples/s) per stage with the default architectures (imports torch)."""

from __future__ import annotations

from . import Timing

__all__ = ["bench_training"]


def bench_training(system: str = "duffing", *, device: str = "cpu") -> list[Timing]:
    """Training throughput (samples/s) of each stage with the default architectures, on a short run."""
    import tempfile
    from dataclasses import replace

    from ..modelfile import load_model
    from ..train import LoopConfig, Phase2DataConfig, default_config, train_observer

    loop = LoopConfig(epochs=1, batch_size=512, samples_per_epoch=4096, schedule="cosine")
    stages = []
    with tempfile.TemporaryDirectory() as tmp:
        base = f"{tmp}/autonomous"
        p1 = default_config(system, "autonomous", n_traj=40, n_pde=2000, encoder=replace(loop, batch_size=1024),
                            decoder=replace(loop, batch_size=1024))
        train_observer(system, "autonomous", base, config=p1, device=device, progress=False)
        training = load_model(base).card["training"]
        stages += [(f"phase 1 {k} (width {p1.width})", training[k]) for k in ("encoder", "decoder")]
        data = Phase2DataConfig(n_traj=4, n_signals=4, T=20.0)
        for method in ("obs", "dyn"):
            cfg = default_config(system, method, data=data, loop=loop)
            train_observer(system, method, f"{tmp}/{method}", config=cfg, base=base, device=device, progress=False)
            stages.append((f"phase 2 {method} (window {data.window})",
                           load_model(f"{tmp}/{method}").card["training"][method]))
    out = [Timing(label, summary["wall_time_s"], int(summary["samples_per_s"] * summary["wall_time_s"]))
           for label, summary in stages]
    for timing in out:
        print(f"{timing.label:<44s} {timing.rate:12.0f} samples/s ({device})")
    return out
