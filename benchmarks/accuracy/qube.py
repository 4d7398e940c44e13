"""Train a ``bank`` observer of the Qube (examples/qube) and score it on the logged free swings beside the EKF.

The observer is trained on simulated runs only (``kklcasadi.train.train_observer`` with a
``BankConfig``: the plant's own time scale, dt = 4 ms, the settings below). It is then run over
logged runs of the rig read with ``kklcasadi.plant.logs.read_log`` (angles unwrapped, 4 ms grid,
``u = 0``), and scored after 2 s against a zero-phase Savitzky-Golay derivative of the measured
angles (window 15, cubic): the velocity RMSE of each velocity and of both together, and the
(wrapped) RMSE of each measured angle. The EKF is ``examples/qube/check_logs.py``'s (R = 1e-6 I,
velocity process variance 1e-3 per step), nothing fitted.

Choose settings on ``--runs fit`` (logs 1, 3, 5) and report them on ``--runs report`` (7, 9, 11);
never choose on the reported runs. With ``y = alpha`` the arm angle ``theta`` is unobservable (the
dynamics do not depend on it): its error is printed but not scored.

Usage::

    PYTHONPATH=. python benchmarks/accuracy/qube.py --outputs both --process-std 8 --runs fit --tag q8
    PYTHONPATH=. python benchmarks/accuracy/qube.py --outputs alpha --model DIR/q8_alpha --runs report

Writes ``results/real_rig/qube/<tag>_<outputs>_<runs>.json`` (refused before any work where it, or the model
``--out`` would hold, exists).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

import kklcasadi as kc
from kklcasadi import provenance
from kklcasadi.metrics import rmse
from kklcasadi.plant import logs
from kklcasadi.writes import refuse_existing, write_file

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "examples" / "qube"))
from qube_plant import make_plant, make_plant_alpha  # noqa: E402

DT = 0.004
RUNS = {"fit": (1, 3, 5), "report": (7, 9, 11)}
STATES = ("theta", "alpha", "theta_dot", "alpha_dot")
OUT = ROOT / "results" / "real_rig" / "qube"


def plant_of(outputs: str) -> kc.System:
    return make_plant() if outputs == "both" else make_plant_alpha()


def read(n: int, plant: kc.System) -> tuple[logs.Log, np.ndarray]:
    """Run ``n`` on the 4 ms grid (both angles) and its Savitzky-Golay velocity reference (N, 2)."""
    box = {"theta": tuple(plant.x0_box[0]), "alpha": tuple(plant.x0_box[1])}
    log = logs.read_log(ROOT / "examples" / "qube" / "data" / f"free_swing_{n}.csv", time_col="time",
                        y_cols=("theta", "alpha"), angle_cols=("theta", "alpha"), dt=DT, box=box)
    return log, logs.savgol_derivative(log.t, log.y)


def scores(log: logs.Log, velocity: np.ndarray, xhat: np.ndarray, settle: float = 2.0) -> dict[str, float]:
    """RMSE after ``settle`` seconds: each state against the log (angles wrapped) and both velocities."""
    k = log.t - log.t[0] >= settle
    out = {name: float(rmse(log.y[k, i:i + 1], xhat[k, i:i + 1], angles=(0,))) for i, name in enumerate(STATES[:2])}
    out.update({name: float(rmse(velocity[k, i:i + 1], xhat[k, 2 + i:3 + i])) for i, name in enumerate(STATES[2:])})
    out["velocities"] = float(rmse(velocity[k], xhat[k, 2:]))
    return out


def train(args: argparse.Namespace, plant: kc.System, out: Path) -> tuple[Path, float]:
    from kklcasadi.train import default_config, train_observer

    torch.set_num_threads(1)
    config = default_config(plant.name, "bank", epochs=args.epochs)
    ps = args.process_std
    config = replace(config, measurement_std=args.measurement_std,
                     process_std=ps if args.process_all else (0.0, 0.0, ps, ps),
                     angles=not args.no_angles,
                     rollouts=replace(config.rollouts, n_traj=args.n_traj, T=args.T, box_scale=args.box_scale,
                                      noise_range=(args.noise_lo, args.noise_hi), sample_period=args.sample_period,
                                      dense_period=args.dense_period))
    if args.hidden:
        config = replace(config, decoder=replace(config.decoder, hidden=tuple(int(h) for h in args.hidden.split(","))))
    if args.skip is not None:
        config = replace(config, decoder=replace(config.decoder, skip=args.skip == "on"))
    t0 = time.perf_counter()
    path = train_observer(plant, "bank", out, config=config, dt=DT, seed=args.seed, progress=False)
    return path, time.perf_counter() - t0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--outputs", choices=("both", "alpha"), default="both")
    p.add_argument("--runs", choices=tuple(RUNS), default="fit")
    p.add_argument("--model", type=Path, help="score this model instead of training one")
    p.add_argument("--tag", default="bank")
    p.add_argument("--process-std", type=float, default=8.0, help="on the two velocities (rad/s^2)")
    p.add_argument("--process-all", action="store_true", help="the process noise on every state (as the CLI's "
                   "--process-std), not only the velocities")
    p.add_argument("--measurement-std", type=float, default=1e-3)
    p.add_argument("--noise-lo", type=float, default=0.5)
    p.add_argument("--noise-hi", type=float, default=2.0)
    p.add_argument("--box-scale", type=float, default=1.0)
    p.add_argument("--n-traj", type=int, default=1000)
    p.add_argument("--T", type=float, default=60.0, help="horizon in units of 1 / time scale (13.3 rad/s)")
    p.add_argument("--epochs", type=int, default=15)
    p.add_argument("--sample-period", type=float, default=0.1, help="in units of 1 / time scale")
    p.add_argument("--dense-period", type=float, default=0.05, help="in units of 1 / time scale")
    p.add_argument("--hidden", default="")
    p.add_argument("--no-angles", action="store_true")
    p.add_argument("--skip", choices=("on", "off"), help="the decoder's linear skip path (default: the recipe's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, help="where the trained model goes (default: a new temporary folder)")
    args = p.parse_args()
    record_path = OUT / f"{args.tag}_{args.outputs}_{args.runs}.json"
    trained = {} if args.out is None or args.model is not None else {args.out / f"{args.tag}_{args.outputs}": "--out"}
    refuse_existing({record_path: "--tag", **trained})
    plant = plant_of(args.outputs)
    wall = None
    model = args.model
    if model is None:
        out = args.out if args.out is not None else Path(tempfile.mkdtemp(prefix="kklcasadi-qube-"))
        model, wall = train(args, plant, out / f"{args.tag}_{args.outputs}")
    obs = kc.load_observer(model, system=plant)
    outputs = [0, 1] if args.outputs == "both" else [1]
    ekf = kc.EKF(plant, DT, Q=np.diag([0.0, 0.0, 1e-3, 1e-3]), R=1e-6 * np.eye(plant.ny))
    card = json.loads((Path(model) / "card.json").read_text())["training"]
    record = {"model": str(model), "outputs": args.outputs, "runs": args.runs, "wall_time_s": wall,
              "args": {k: str(v) for k, v in vars(args).items()} if args.model is None else None,
              "model_training": {k: card[k] for k in ("process_std", "measurement_std", "rollouts", "decoder_fit",
                                                      "time_scale", "wall_time_s") if k in card},
              "bank": {}, "ekf": {}}
    for n in RUNS[args.runs]:
        log, velocity = read(n, plant)
        y, u = log.y[:, outputs], np.zeros((log.t.size, 1))
        for name, est in (("bank", obs.simulate(log.t, y, u).xhat), ("ekf", ekf.simulate(log.t, y, u).xhat)):
            record[name][n] = scores(log, velocity, est)
    for name in ("bank", "ekf"):
        record[name]["mean"] = {k: float(np.mean([record[name][n][k] for n in RUNS[args.runs]]))
                                for k in record[name][RUNS[args.runs][0]]}
    cols = list(record["bank"]["mean"])
    print(f"{args.tag} y={args.outputs} runs {RUNS[args.runs]} (train {wall if wall is None else round(wall)} s), "
          "RMSE after 2 s:")
    print(f"{'':10s}" + "".join(f"{c:>12s}" for c in cols))
    for n in (*RUNS[args.runs], "mean"):
        for name in ("bank", "ekf"):
            print(f"{name} {str(n):5s}" + "".join(f"{record[name][n][c]:12.4f}" for c in cols))
    stamp = provenance.stamp(seeds={"training": args.seed} if args.model is None else {})
    write_file(record_path, json.dumps(provenance.json_record(record, stamp), indent=1) + "\n", argument="--tag")


if __name__ == "__main__":
    main()
