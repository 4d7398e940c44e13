"""Train one ``bank`` model with a configuration given by flags (``BankConfig.for_system`` plus overrides).

The model directory is what ``kklcasadi train --method bank`` writes (card, weights, history); the
flags reach the fields the command line does not. Score it with ``kklcasadi generalise`` (held-out
families and seeds) or ``kklcasadi evaluate`` (the protocol).

Example::

    PYTHONPATH=. python benchmarks/accuracy/train_bank.py duffing /tmp/bank_wide --kinds all --regime wide \\
        --noise-range 0.5,2 --n-traj 1000 --epochs 10 --seed 11
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import torch

import kklcasadi as kc
from kklcasadi.plant.runs import FAMILIES
from kklcasadi.train import default_config, train_observer
from kklcasadi.train.decoder import LOSSES


def floats(text: str) -> tuple[float, ...]:
    return tuple(float(v) for v in text.split(",") if v.strip())


def pairs(text: str) -> list[tuple[float, float]]:
    return [tuple(float(v) for v in pair.split(":")) for pair in text.split(",") if pair.strip()]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("system", help="a shipped system name or FILE.py:NAME")
    p.add_argument("out", type=Path)
    p.add_argument("--kinds", help="comma-separated families, or 'all' (kklcasadi.plant.runs.FAMILIES)")
    p.add_argument("--regime")
    p.add_argument("--noise-range", help="lo,hi factors on the noise levels")
    p.add_argument("--y-poles")
    p.add_argument("--u-poles")
    p.add_argument("--y-resonators", help="zeta:omega,... second-order filters of each output")
    p.add_argument("--clock", type=float)
    p.add_argument("--time-scale", type=float)
    p.add_argument("--n-traj", type=int)
    p.add_argument("--T", type=float)
    p.add_argument("--epochs", type=int)
    p.add_argument("--hidden")
    p.add_argument("--asinh-scale", help="per-state scales s of the decoder's s sinh(v) outputs (0: none)")
    p.add_argument("--activation", help="the decoder's activation (kklcasadi.nets.specs.ACTIVATIONS)")
    p.add_argument("--skip", action="store_true", help="give the decoder a linear skip path (DecoderConfig.skip)")
    p.add_argument("--loss", choices=LOSSES, help="the decoder's loss (DecoderConfig.loss)")
    p.add_argument("--smape-weight", type=float, help="with --loss mse+smape: the weight of the SMAPE term")
    p.add_argument("--lr", type=float, help="the decoder fit's learning rate")
    p.add_argument("--batch-size", type=int, help="the decoder fit's batch size")
    p.add_argument("--members", type=int, help="decoder networks averaged (default: the system's)")
    p.add_argument("--copies", help="comma-separated weights of the latent's model copies (BankConfig.copies), or "
                   "'none'")
    p.add_argument("--copy-substeps", type=int, help="RK4 substeps of the copies per sample (BankConfig.copy_substeps)")
    p.add_argument("--teacher", help="a bank model directory whose estimates are the decoders' targets (distillation)")
    p.add_argument("--measurement-std", type=float)
    p.add_argument("--process-std", help="one std or one per state")
    p.add_argument("--box-scale", help="a factor or lo,hi")
    p.add_argument("--box-share", type=float, help="share of the runs started in the --box-scale range")
    p.add_argument("--input-scale", help="a factor or lo,hi on the runs' inputs (RolloutConfig.input_scale: a "
                   "student's runs wider than its --teacher's)")
    p.add_argument("--sample-period", type=float)
    p.add_argument("--dt", type=float, default=0.05)
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1: a shared machine)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    plant = kc.systems.load_plant(args.system) if ":" in args.system else kc.systems.get(args.system)
    config = default_config(plant.name, "bank", epochs=args.epochs)
    top = {}
    for name in ("y_poles", "u_poles"):
        if getattr(args, name) is not None:
            top[name] = floats(getattr(args, name))
    if args.y_resonators is not None:
        top["y_resonators"] = tuple(pairs(args.y_resonators))
    for name in ("clock", "time_scale", "measurement_std"):
        if getattr(args, name) is not None:
            top[name] = getattr(args, name)
    if args.process_std is not None:
        std = floats(args.process_std)
        top["process_std"] = std[0] if len(std) == 1 else std
    runs = {}
    if args.kinds:
        runs["kinds"] = FAMILIES if args.kinds == "all" else tuple(args.kinds.split(","))
    if args.noise_range:
        runs["noise_range"] = floats(args.noise_range)
    for name in ("box_scale", "input_scale"):
        if getattr(args, name):
            scale = floats(getattr(args, name))
            runs[name] = scale[0] if len(scale) == 1 else scale
    for name in ("regime", "n_traj", "T", "sample_period", "box_share"):
        if getattr(args, name) is not None:
            runs[name] = getattr(args, name)
    if args.members is not None:
        top["members"] = args.members
    if args.teacher is not None:
        top["teacher"] = args.teacher
    if args.copies:
        top["copies"] = () if args.copies == "none" else floats(args.copies)
    if args.copy_substeps is not None:
        top["copy_substeps"] = args.copy_substeps
    config = replace(config, **top, rollouts=replace(config.rollouts, **runs))
    if args.hidden:
        config = replace(config, decoder=replace(config.decoder, hidden=tuple(int(h) for h in args.hidden.split(","))))
    if args.asinh_scale:
        config = replace(config, decoder=replace(config.decoder, asinh_scale=floats(args.asinh_scale)))
    if args.activation:
        config = replace(config, decoder=replace(config.decoder, activation=args.activation))
    if args.skip:
        config = replace(config, decoder=replace(config.decoder, skip=True))
    if args.loss:
        config = replace(config, decoder=replace(config.decoder, loss=args.loss))
    if args.smape_weight is not None:
        config = replace(config, decoder=replace(config.decoder, smape_weight=args.smape_weight))
    loop = {name: getattr(args, name) for name in ("lr", "batch_size") if getattr(args, name) is not None}
    if loop:
        config = replace(config, decoder=replace(config.decoder, loop=replace(config.decoder.loop, **loop)))
    t0 = time.perf_counter()
    train_observer(plant, "bank", args.out, config=config, dt=args.dt, seed=args.seed, overwrite=True, progress=False)
    print(f"wrote {args.out} in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
