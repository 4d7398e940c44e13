"""Train a damped3 bank variant: the one command's configuration with one field changed."""
import sys
from dataclasses import replace
from pathlib import Path

from kklcasadi.plant.systems import load_plant
from kklcasadi.train import default_config, train_observer

name = sys.argv[1]
plant = load_plant("examples/damped3_plant.py:make_plant")
config = default_config(plant.name, "bank")
config = {"all": replace(config, process_on="all"),
          "u30": replace(config, u_poles=(0.1, 0.3, 1.0, 3.0, 10.0, 30.0))}[name]
train_observer(plant, "bank", Path(f"/tmp/rig17b/d3_{name}"), config=config, dt=0.05, seed=0, overwrite=True,
               progress=False, threads=1)
print("done", name)
