"""Train one filter-bank observer (operational decoder) and score it.

Scores: validation SMAPE per input kind on held-out operational rollouts (the selection
criterion: train ranges, seeds disjoint from training and from the protocol), and the protocol's
100 trials per cell with noise (beside the EKF) and without (beside the paper's best).

Example::

    PYTHONPATH=. python benchmarks/accuracy/probe.py duffing --tag base --y-poles 0.2,0.5,1,2,4,7 \
        --u-poles 0.5,2 --clock 0.2 --n-traj 1000 --epochs 20

``--recipe`` starts from the final recipe of the system (``recipes.py``); other flags override it.
``--save DIR`` writes the weights (``<system>_<tag>.npz``) and the record there. Nothing is written over a file:
the record (named by ``--tag``) and the saved files are refused before any fit where they exist.
"""

from __future__ import annotations

import argparse
import io
import json
import time
from pathlib import Path

import numpy as np
import torch
from common import cached_rollouts, kind_of_rollouts, score, table_row
from recipes import PAPER_BEST, RECIPES

import kklcasadi as kc
from kklcasadi import provenance
from kklcasadi.model.operational import OperationalData
from kklcasadi.model.variants import bankdecoder as bd
from kklcasadi.model.variants import filterbank as fb
from kklcasadi.plant.runs import RolloutConfig
from kklcasadi.plant.signals import BENCHMARK_KINDS
from kklcasadi.train.config import LoopConfig
from kklcasadi.train.decoder import DecoderConfig, config_record, fit_bank_decoder
from kklcasadi.writes import refuse_existing, write_files

OUT = Path("results/levers")

DEFAULTS = {"y_poles": "0.2,0.5,1,2,4,7", "u_poles": "0.5,2", "resonators": "", "clock": None, "n_traj": 1000,
            "n_val": 200, "seed": 11, "epochs": 20, "batch": 1024, "lr": 1e-3, "hidden": "256,256,256",
            "activation": "tanh", "loss": "mse", "smape_weight": 0.01, "smape_eps": 1e-3, "asinh": "",
            "sample_period": 0.1, "no_whiten": False}


def floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v.strip()] if text else []


def parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("system")
    p.add_argument("--tag", required=True)
    p.add_argument("--recipe", action="store_true", help="start from recipes.RECIPES[system]")
    p.add_argument("--save", type=Path, help="also write the weights and the record to this folder (default: the "
                   "record alone, under results/levers/SYSTEM/)")
    p.add_argument("--y-poles")
    p.add_argument("--u-poles")
    p.add_argument("--resonators", help="zeta:omega,... second-order y filters")
    p.add_argument("--clock", type=float)
    p.add_argument("--n-traj", type=int)
    p.add_argument("--n-val", type=int)
    p.add_argument("--seed", type=int)
    p.add_argument("--epochs", type=int)
    p.add_argument("--batch", type=int)
    p.add_argument("--lr", type=float)
    p.add_argument("--hidden")
    p.add_argument("--activation")
    p.add_argument("--loss")
    p.add_argument("--smape-weight", type=float)
    p.add_argument("--smape-eps", type=float)
    p.add_argument("--asinh", help="per-state asinh scales, 0 for none")
    p.add_argument("--sample-period", type=float, help="seconds between the decoder's samples after the first 5 s")
    p.add_argument("--no-whiten", action="store_true", default=None)
    args = p.parse_args()
    base = {**DEFAULTS, **(RECIPES[args.system] if args.recipe else {})}
    for key, value in base.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    return args


def main() -> None:
    torch.set_num_threads(1)
    args = parse()
    stem = f"{args.system}_{args.tag}"
    paths = {"record": OUT / args.system / f"{stem}.json"}
    if args.save is not None:
        paths.update(npz=args.save / f"{stem}.npz", json=args.save / f"{stem}.json")
    refuse_existing({path: "--tag" if key == "record" else "--save" for key, path in paths.items()})
    system = kc.systems.get(args.system)
    res = [tuple(float(a) for a in r.split(":")) for r in args.resonators.split(",") if r]
    bank = fb.FilterBank.design(system.ny, system.nu, floats(args.y_poles), floats(args.u_poles),
                                y_resonators=res, clock=args.clock)
    dec = DecoderConfig(hidden=tuple(int(h) for h in args.hidden.split(",")), activation=args.activation,
                        loss=args.loss, smape_weight=args.smape_weight, smape_eps=args.smape_eps,
                        asinh_scale=tuple(floats(args.asinh)) or None, whiten=not args.no_whiten,
                        loop=LoopConfig(epochs=args.epochs, batch_size=args.batch, lr=args.lr, schedule="cosine",
                                        val_fraction=0.05))
    t0 = time.time()
    train = cached_rollouts(args.system, args.n_traj, args.seed)
    val = cached_rollouts(args.system, args.n_val, 777)
    t_sim = time.time() - t0
    sampling = RolloutConfig(n_traj=args.n_traj, sample_period=args.sample_period)
    result = fit_bank_decoder(bank, OperationalData.from_runs(bank, train, sampling), dec, seed=args.seed)
    arrays, decoder = result.arrays, result.spec

    def est(y: np.ndarray, u: np.ndarray) -> np.ndarray:
        return bd.estimate(decoder, arrays, y, u, 0.05)

    xv = est(val.y, val.u)
    sv = kc.metrics.smape(val.x, xv)
    kinds = kind_of_rollouts(len(sv)) if len(sv) == args.n_val else None
    val_scores = ({k: float(np.mean(sv[kinds == k])) for k in BENCHMARK_KINDS} if kinds is not None
                  else {"all": float(np.mean(sv))})
    t1 = time.time()
    noisy, clean = score(args.system, "noisy", est), score(args.system, "clean", est)
    t_eval = time.time() - t1
    print(f"[{args.system} {args.tag}] nz={bank.nz} samples={result.n_samples} fit {result.seconds:.0f}s "
          f"(sim {t_sim:.0f}s, protocol eval {t_eval:.0f}s) best epoch {result.fit.best_epoch} "
          f"val loss {result.fit.best_val:.4g}")
    print("  validation rollouts:", " | ".join(f"{k} {v:.2f}" for k, v in val_scores.items()),
          f"(mean {np.mean(list(val_scores.values())):.2f})")
    print("  noisy ours:", table_row(noisy))
    print("  noisy EKF :", table_row(noisy, "ekf"))
    print("  clean ours:", " | ".join(f"{clean[k]['ours']:.2f}" for k in BENCHMARK_KINDS),
          " paper best", PAPER_BEST[args.system])
    for k in BENCHMARK_KINDS:
        print(f"  per-state {k}: ours {np.round(noisy[k]['ours_per_state'], 2).tolist()} "
              f"ekf {np.round(noisy[k]['ekf_per_state'], 2).tolist()}")
    record = {"system": args.system, "tag": args.tag, "args": {k: str(v) for k, v in vars(args).items()},
              "nz": bank.nz, "config": config_record(sampling, dec),
              "fit_seconds": result.seconds, "n_samples": result.n_samples, "best_epoch": result.fit.best_epoch,
              "history": result.fit.history, "domain": result.domain, "validation": val_scores,
              "noisy": noisy, "clean": clean, "arch": decoder.mlp.to_card()}
    text = json.dumps(provenance.json_record(record, provenance.stamp(seeds={"decoder": args.seed})), indent=1) + "\n"
    weights = io.BytesIO()
    np.savez(weights, **arrays)
    contents = {"record": text, "npz": weights.getvalue(), "json": text}
    write_files({path: contents[key] for key, path in paths.items()}, argument="--tag")


if __name__ == "__main__":
    main()
