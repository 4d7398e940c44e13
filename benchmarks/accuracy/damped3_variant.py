"""Train a damped3 bank variant: the one command's configuration with one field changed.

The two Python-only variants of the damped 3-state plant's validation tables
(``results/own_plant/damped3/validation_seed7/``, scored by ``kklcasadi evaluate OUT --plant
examples/damped3_plant.py:make_plant --ekf --trials 100 --seed 7 --noise on``):

    PYTHONPATH=. python benchmarks/accuracy/damped3_variant.py all OUT      # process noise on every state
    PYTHONPATH=. python benchmarks/accuracy/damped3_variant.py u30 OUT      # a sixth input filter at 30

The model is written to ``OUT`` (a new directory; its card records the training).
"""

import argparse
from dataclasses import replace
from pathlib import Path

from kklcasadi.plant.systems import load_plant
from kklcasadi.train import default_config, train_observer

VARIANTS = ("all", "u30")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("variant", choices=VARIANTS, help="all: process noise on every state; u30: input filters "
                                                          "up to 30 time-scale units")
    parser.add_argument("out", type=Path, help="the model directory to write (must not exist)")
    args = parser.parse_args()
    plant = load_plant("examples/damped3_plant.py:make_plant")
    config = default_config(plant.name, "bank")
    config = {"all": replace(config, process_on="all"),
              "u30": replace(config, u_poles=(0.1, 0.3, 1.0, 3.0, 10.0, 30.0))}[args.variant]
    train_observer(plant, "bank", args.out, config=config, dt=0.05, seed=0, progress=False, threads=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
