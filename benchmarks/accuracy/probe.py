"""Train one filter-bank observer (operational decoder) and score it.

Scores: validation SMAPE per input kind on held-out operational rollouts (the selection
criterion: train ranges, seeds disjoint from training and from the protocol), and the protocol's
100 trials per cell with noise (beside the EKF) and without (beside the paper's best).

Example::

    python benchmarks/accuracy/probe.py duffing --tag base --y-poles 0.2,0.5,1,2,4,7 --u-poles 0.5,2 \
        --clock 0.2 --n-traj 1000 --epochs 20
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

import kklcasadi as kc
from kklcasadi import filterbank as fb
from kklcasadi.signals import BENCHMARK_KINDS
from kklcasadi.train.config import LoopConfig
from kklcasadi.train.operational import DecoderConfig, RolloutConfig, config_record, fit_bank_decoder

from common import cached_rollouts, kind_of_rollouts, score, table_row

#: The paper's best noise-free SMAPE per cell (PROTOCOL.md Table I).
PAPER_BEST = {"duffing": [5.6, 21.1, 22.7, 21.3], "vdp": [5.0, 26.0, 15.5, 17.9],
              "rossler": [52.7, 55.4, 53.5, 54.0], "fhn": [9.8, 42.1, 30.9, 32.5]}
OUT = Path("results/accuracy")
#: Probe weights stay out of the repository (the final models go to results/accuracy/weights).
WEIGHTS = Path("/tmp/acc_weights")


def floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v.strip()] if text else []


def main() -> None:
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("system")
    p.add_argument("--tag", required=True)
    p.add_argument("--y-poles", default="0.2,0.5,1,2,4,7")
    p.add_argument("--u-poles", default="0.5,2")
    p.add_argument("--resonators", default="", help="zeta:omega,... second-order y filters")
    p.add_argument("--clock", type=float, default=None)
    p.add_argument("--n-traj", type=int, default=1000)
    p.add_argument("--n-val", type=int, default=200)
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--hidden", default="256,256,256")
    p.add_argument("--activation", default="tanh")
    p.add_argument("--loss", default="mse")
    p.add_argument("--smape-weight", type=float, default=0.01)
    p.add_argument("--smape-eps", type=float, default=1e-3)
    p.add_argument("--asinh", default="", help="per-state asinh scales, 0 for none")
    p.add_argument("--stride", type=int, default=2)
    p.add_argument("--no-whiten", action="store_true")
    p.add_argument("--box-scale", type=float, default=1.0)
    args = p.parse_args()

    system = kc.systems.get(args.system)
    res = [tuple(float(a) for a in r.split(":")) for r in args.resonators.split(",") if r]
    bank = fb.FilterBank.design(system.ny, system.nu, floats(args.y_poles), floats(args.u_poles),
                                y_resonators=res, clock=args.clock)
    dec = DecoderConfig(hidden=tuple(int(h) for h in args.hidden.split(",")), activation=args.activation,
                        loss=args.loss, smape_weight=args.smape_weight, smape_eps=args.smape_eps,
                        asinh_scale=tuple(floats(args.asinh)) or None, stride=args.stride,
                        whiten=not args.no_whiten,
                        loop=LoopConfig(epochs=args.epochs, batch_size=args.batch, lr=args.lr, schedule="cosine",
                                        val_fraction=0.05))
    overrides = {} if args.box_scale == 1.0 else {"box_scale": args.box_scale}
    t0 = time.time()
    train = cached_rollouts(args.system, args.n_traj, args.seed, **overrides)
    val = cached_rollouts(args.system, args.n_val, 777)
    t_sim = time.time() - t0
    result = fit_bank_decoder(bank, train, dec, seed=args.seed)
    arrays, arch = result.arrays, result.arch

    def est(y: np.ndarray, u: np.ndarray) -> np.ndarray:
        return fb.estimate(arrays, arch, y, u, 0.05)

    xv = est(val.y, val.u)
    sv = kc.metrics.smape(val.x, xv)
    kinds = kind_of_rollouts(len(sv)) if len(sv) == args.n_val else None
    val_scores = ({k: float(np.mean(sv[kinds == k])) for k in BENCHMARK_KINDS} if kinds is not None
                  else {"all": float(np.mean(sv))})
    noisy, clean = score(args.system, "noisy", est), score(args.system, "clean", est)
    print(f"[{args.system} {args.tag}] nz={bank.nz} samples={result.n_samples} fit {result.seconds:.0f}s "
          f"(sim {t_sim:.0f}s) best epoch {result.fit.best_epoch} val loss {result.fit.best_val:.4g}")
    print("  validation rollouts:", " | ".join(f"{k} {v:.2f}" for k, v in val_scores.items()))
    print("  noisy ours:", table_row(noisy))
    print("  noisy EKF :", table_row(noisy, "ekf"))
    print("  clean ours:", " | ".join(f"{clean[k]['ours']:.2f}" for k in BENCHMARK_KINDS),
          " paper best", PAPER_BEST[args.system])
    for k in BENCHMARK_KINDS:
        print(f"  per-state {k}: ours {np.round(noisy[k]['ours_per_state'], 2).tolist()} "
              f"ekf {np.round(noisy[k]['ekf_per_state'], 2).tolist()}")
    (OUT / "probes").mkdir(parents=True, exist_ok=True)
    WEIGHTS.mkdir(parents=True, exist_ok=True)
    record = {"system": args.system, "tag": args.tag, "args": vars(args), "nz": bank.nz,
              "config": config_record(RolloutConfig(n_traj=args.n_traj), dec), "fit_seconds": result.seconds,
              "best_epoch": result.fit.best_epoch, "history": result.fit.history, "domain": result.domain,
              "validation": val_scores, "noisy": noisy, "clean": clean, "arch": arch}
    (OUT / "probes" / f"{args.system}_{args.tag}.json").write_text(json.dumps(record, indent=1))
    np.savez(WEIGHTS / f"{args.system}_{args.tag}.npz", **arrays)


if __name__ == "__main__":
    main()
