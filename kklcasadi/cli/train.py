"""``kklcasadi train``: train an observer variant and write its model directory."""

from __future__ import annotations

import argparse
from dataclasses import fields
from pathlib import Path

from ..model import variants
from ..plant import systems
from .flags import CommandError, add_plant, flagged, needs_torch, nonnegative_float, plant_of, positive_int

#: Flags that set a field of the method's training configuration: flag -> (field, value from args).
_CONFIG_FLAGS = {"--measurement-std": ("measurement_std", lambda a: a.measurement_std),
                 "--width": ("width", lambda a: a.width),
                 "--on-inject": ("model_based_injection", lambda a: True if a.on_inject else None)}


def add_parser(sub: argparse._SubParsersAction) -> None:
    t = sub.add_parser("train", help="train an observer variant and write its model directory")
    t.add_argument("--system", choices=systems.names(), help="a shipped system")
    add_plant(t)
    t.add_argument("--method", required=True, choices=variants.trainable(),
                   help="; ".join(f"{v.name}: {v.summary}" for v in variants.VARIANTS.values()))
    t.add_argument("--out", required=True, help="model directory to write")
    t.add_argument("--base", help="Phase-1 model (default OUT/../autonomous for Phase-2 methods)")
    t.add_argument("--measurement-std", type=nonnegative_float,
                   help="the measurement-noise std the observer is fit for (autonomous: its decoder)")
    t.add_argument("--width", type=positive_int, help="autonomous: hidden width of T and T* (default 150; the "
                   "paper uses 350 for rossler and fhn)")
    t.add_argument("--on-inject", action="store_true",
                   help="obs: learn the residual on top of the model-based injection of 'inject'")
    t.add_argument("--epochs", type=positive_int, help="override the number of epochs of every stage")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    t.add_argument("--resume", action="store_true", help="continue from the checkpoints in OUT/.train")
    t.add_argument("--overwrite", action="store_true")
    t.add_argument("--quiet", action="store_true", help="no progress bars")
    t.add_argument("--threads", type=positive_int, help="torch CPU threads (1 per process on a shared machine)")
    t.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if (args.plant is None) == (args.system is None):
        raise CommandError("--system/--plant: give exactly one: a shipped system name or your plant FILE.py:NAME")
    plant = plant_of(args) or systems.get(args.system)
    needs_torch("kklcasadi train")
    from ..train import default_config, train_observer

    out = Path(args.out)
    if (out / "card.json").exists() and not (args.overwrite or args.resume):
        raise CommandError(f"--out {out}: a model already exists there; pass --overwrite to replace it")
    variant = variants.get(args.method)
    config_class = variant.config_class()
    settable = set() if config_class is None else {f.name for f in fields(config_class)}
    overrides = {}
    for flag, (name, value) in _CONFIG_FLAGS.items():
        if value(args) is None:
            continue
        if name not in settable:
            takes = [v.name for v in variants.VARIANTS.values()
                     if v.config_class() is not None and name in {f.name for f in fields(v.config_class())}]
            raise CommandError(f"{flag}: only --method {' or '.join(takes)} takes it, received --method {args.method}")
        overrides[name] = value(args)
    config = None if config_class is None else default_config(plant.name, args.method, **overrides)
    path = flagged("--" + args.method, train_observer, plant, args.method, out, config=config, base=args.base,
                   seed=args.seed, device=args.device, resume=args.resume, overwrite=args.overwrite,
                   progress=not args.quiet, threads=args.threads, epochs=args.epochs)
    print(f"wrote {path}/weights.npz and card.json")
    return 0
