"""Paired decoder comparison: fit one ``bank`` decoder per variant and seed on the same runs, score each
on the same validation trials.

    PYTHONPATH=. python benchmarks/accuracy/decoder_pairs.py duffing --variants plain skip --seeds 11 12 13 14 \\
        --n-traj 1000 --epochs 10 --out results/generalisation/duffing/duffing_3030_cheap_skip

The runs are the system's recipe (:meth:`kklcasadi.train.bank.BankConfig.for_system`) with ``--n-traj`` runs,
simulated once (training seed ``--run-seed``); each variant's decoder is fitted on them from every seed of
``--seeds`` (:func:`kklcasadi.train.decoder.fit_bank_decoder`, one decoder, the recipe's configuration
with the variant's change), so that a variant and the plain decoder of one seed start from the same draw of
the layers. The trials are those of ``kklcasadi generalise`` (seed ``--trial-seed``, ``--trials`` per case,
from the trial cache), decoded through the bank's latent in numpy
(:func:`kklcasadi.model.variants.bankdecoder.estimate`); the EKF is scored on the same trials. Writes
``OUT.json`` (every SMAPE) and ``OUT.md`` (mean SMAPE per case and variant over the seeds, its ratio to the
EKF, and per seed the geometric mean over the cases of each variant / plain), together; refused before any fit
where one of them exists.

Variants: ``plain`` (the recipe), ``skip`` (a linear skip path,
:attr:`kklcasadi.train.decoder.DecoderConfig.skip`), ``smape`` (the loss ``mse+smape`` with weight 0.5
on the SMAPE term, :attr:`kklcasadi.train.decoder.DecoderConfig.loss`), ``smape01`` (weight 0.1), and
``copies``, which changes the latent rather than the decoder: model copies of the plant with the weights
``--copies`` (:attr:`kklcasadi.train.bank.BankConfig.copies`) after the filters, the decoder of the recipe
fit on the same runs through that latent; ``copies_skip`` is that latent with the skip path.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

import kklcasadi as kc
from kklcasadi import metrics, provenance
from kklcasadi.evaluation.compiled import ekf_estimator
from kklcasadi.evaluation.generalisation import Case, Settings, case_ekf
from kklcasadi.evaluation.trialcache import TrialCache, cache_root
from kklcasadi.model.operational import operational_data
from kklcasadi.model.variants import bankdecoder as bd
from kklcasadi.train.bank import BankConfig, bank_time_scale, design_bank, design_copies, process_stds
from kklcasadi.train.decoder import DecoderConfig, fit_bank_decoder
from kklcasadi.writes import refuse_existing, write_dir

VARIANTS = {"plain": lambda d: d, "skip": lambda d: replace(d, skip=True),
            "smape": lambda d: replace(d, loss="mse+smape", smape_weight=0.5),
            "smape01": lambda d: replace(d, loss="mse+smape", smape_weight=0.1), "copies": lambda d: d,
            "copies_skip": lambda d: replace(d, skip=True)}
#: The variants that change the latent: the model copies of ``--copies``.
LATENT_VARIANTS = ("copies", "copies_skip")
FAMILIES = (("square", "id"), ("sinusoid", "id"), ("square", "ood"), ("chirp", "held_out"),
            ("feedback", "held_out"), ("random", "held_out"))


def geometric_mean(values: list[float]) -> float:
    return float(np.exp(np.mean(np.log(values))))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("system")
    p.add_argument("--variants", nargs="+", default=["plain", "skip"], choices=sorted(VARIANTS))
    p.add_argument("--seeds", nargs="+", type=int, default=[11, 12, 13])
    p.add_argument("--n-traj", type=int, default=1000)
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--run-seed", type=int, default=11)
    p.add_argument("--trial-seed", type=int, default=3030)
    p.add_argument("--trials", type=int, default=40)
    p.add_argument("--noise-levels", nargs="+", type=float, default=[0.05, 0.1])
    p.add_argument("--copies", type=float, nargs="+", default=[1.0, 100.0, 1e4],
                   help="the weights of the model copies of variant copies")
    p.add_argument("--copy-substeps", type=int, default=None,
                   help="RK4 substeps of the copies per sample (default: from their speed, BankConfig.copy_substeps)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", type=Path, required=True, help="OUT.json and OUT.md are written")
    args = p.parse_args()
    if args.variants[0] != "plain":
        p.error("--variants: the first must be plain (the ratios are to it)")
    written = {ext: args.out.with_suffix(ext) for ext in (".json", ".md")}
    refuse_existing({path: "--out" for path in written.values()})
    torch.set_num_threads(args.threads)
    system = kc.systems.get(args.system)
    config = BankConfig.for_system(args.system)
    config = replace(config, rollouts=replace(config.rollouts, n_traj=args.n_traj),
                     decoder=replace(config.decoder, loop=replace(config.decoder.loop, epochs=args.epochs)))
    rate = bank_time_scale(system, config)
    bank = design_bank(system, config, rate)
    angles = bd.Angles.of(system) if config.angles else bd.NO_ANGLES
    copies = design_copies(system, replace(config, copies=tuple(args.copies), copy_substeps=args.copy_substeps), 0.05)
    runs = {latent: operational_data(system, bank, config.rollouts, args.run_seed, dt=0.05,
                                     measurement_std=config.measurement_std, process_std=process_stds(system, config),
                                     time_scale=rate, copies=latent)
            for latent in ([None] + ([copies] if set(args.variants) & set(LATENT_VARIANTS) else []))}
    settings = Settings(n_trials=args.trials, seed=args.trial_seed)
    cache = TrialCache(cache_root() / "trials")
    cases = [Case(f, r, n) for n in args.noise_levels for f, r in FAMILIES]
    trials = {}
    for case in cases:
        batch = cache.trials(system, case.cell(settings))
        x, y, u = batch.x[batch.ok], batch.y[batch.ok], batch.u[batch.ok]
        ekf = case_ekf(system, case.noise, settings.dt)
        trials[case.label] = (x, y, u, float(np.mean(metrics.smape(x, ekf_estimator(ekf)(batch.t, y, u)))))
    smape: dict[str, dict[str, dict[str, float]]] = {}
    seconds = {}
    for variant in args.variants:
        for seed in args.seeds:
            t0 = time.perf_counter()
            decoder: DecoderConfig = VARIANTS[variant](config.decoder)
            latent = copies if variant in LATENT_VARIANTS else None
            fit = fit_bank_decoder(bank, runs[latent], decoder, angles=angles, seed=seed)
            seconds[f"{variant}@{seed}"] = round(time.perf_counter() - t0, 1)
            arrays = {**fit.arrays, **({} if latent is None else latent.arrays())}
            smape.setdefault(variant, {})[str(seed)] = {
                label: float(np.nanmean(metrics.smape(x, bd.estimate(fit.spec, arrays, y, u, settings.dt,
                                                                     copies=latent))))
                for label, (x, y, u, _) in trials.items()}
            print(variant, seed, seconds[f"{variant}@{seed}"], "s", flush=True)
    ekf = {label: t[3] for label, t in trials.items()}
    record = {"system": args.system, "samples": len(runs[None]), "ekf": ekf, "smape": smape, "fit_seconds": seconds,
              "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}}
    stamp = provenance.stamp(seeds={"trials": args.trial_seed, "runs": args.run_seed,
                                    **{f"decoder_{s}": s for s in args.seeds}})
    labels = list(trials)
    seeds = [str(s) for s in args.seeds]
    lines = [f"**{args.system}, paired decoders** ({args.n_traj} runs, {args.epochs} epochs, one decoder per variant "
             f"and seed {', '.join(seeds)}; validation trials seed {args.trial_seed}, {args.trials} per case): mean "
             f"SMAPE over the seeds and its ratio to the EKF on the same trials. By `PYTHONPATH=. python "
             f"benchmarks/accuracy/decoder_pairs.py {args.system} --variants {' '.join(args.variants)} --seeds "
             f"{' '.join(seeds)} --n-traj {args.n_traj} --epochs {args.epochs} --trial-seed {args.trial_seed} --trials "
             f"{args.trials} --noise-levels {' '.join(f'{n:g}' for n in args.noise_levels)}"
             + (f" --copies {' '.join(f'{w:g}' for w in args.copies)}"
                if set(args.variants) & set(LATENT_VARIANTS) else "")
             + (f" --copy-substeps {args.copy_substeps}" if args.copy_substeps is not None else "")
             + f" --out {args.out}`.", "",
             "| case | EKF | " + " | ".join(args.variants) + " |", "|---|---|" + "---|" * len(args.variants)]
    for label in labels:
        means = [np.mean([smape[v][s][label] for s in seeds]) for v in args.variants]
        lines.append(f"| {label} | {ekf[label]:.3f} | "
                     + " | ".join(f"{m:.3f} ({m / ekf[label]:.3f}x)" for m in means) + " |")
    lines += ["", "Geometric mean over the cases of variant / plain, per seed:", "",
              "| variant | " + " | ".join(f"seed {s}" for s in seeds) + " |", "|---|" + "---|" * len(seeds)]
    for variant in args.variants[1:]:
        lines.append(f"| {variant} | " + " | ".join(
            f"{geometric_mean([smape[variant][s][lab] / smape['plain'][s][lab] for lab in labels]):.4f}"
            for s in seeds) + " |")
    files = {written[".json"].name: json.dumps(provenance.json_record(record, stamp), indent=1) + "\n",
             written[".md"].name: provenance.markdown("\n".join(lines) + "\n", stamp)}
    write_dir(args.out.parent, files, argument="--out")          # the two as one, after everything is computed
    print("\n".join(lines))


if __name__ == "__main__":
    main()
