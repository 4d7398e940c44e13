"""Grow a shipped ``bank`` model into a decoder ensemble: fit more decoders on its own fitting runs.

    OMP_NUM_THREADS=2 python benchmarks/ensemble_members.py MODEL_DIR --members K --out DIR [--cache C]
        [--member-seeds S1,...]

Re-simulates the model's fitting samples (checked against its card, as
``benchmarks/calibrate_monitors.py`` does; with ``--fresh`` runs of the card's recipe as the current
code simulates them, for a card whose own runs the current code cannot remake), fits K - 1 more
decoders with the card's decoder configuration from the seeds ``seed + 1, ..., seed + K - 1``
(the card's training seed; what ``kklcasadi train --members K`` fits after the first; ``--member-seeds``
names other seeds, e.g. to leave out a member that validation trials found worse than the first), keeps the
model's own decoder as the first member, and writes DIR: the ensemble (``architecture.bank.members = K``)
with its monitor recalibrated on the same runs, the spread test included, at
:class:`kklcasadi.model.operational.MonitorConfig`'s quantiles (choose the spread quantile again with
``benchmarks/monitor_quantiles.py DIR``, apply it with ``benchmarks/calibrate_monitors.py DIR
--spread-quantile Q``). A model that is already an ensemble of K0 < K decoders keeps its K0 members and
gains K - K0 (seeds ``seed + K0, ..., seed + K - 1`` by default). ``--cache C`` keeps each member's fitted
arrays and its fit's summary (``C/<system>_m<seed>.npz``, ``.json``) so that several K reuse them.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import io
import json
import time
from pathlib import Path

import numpy as np
from calibrate_monitors import calibration_source, recalibrate, resimulate

from kklcasadi.model.files import MODEL_FILES
from kklcasadi.model.variants import bankdecoder as bd
from kklcasadi.model.variants.bankdecoder import ASINH_SCALE, member_prefixes
from kklcasadi.nets.specs import DECODER
from kklcasadi.train.bank import ensemble_arrays
from kklcasadi.train.config import LoopConfig
from kklcasadi.train.decoder import BankFit, DecoderConfig, fit_bank_decoder
from kklcasadi.writes import refuse_existing, write_file


def decoder_config(record: dict) -> DecoderConfig:
    """The card's decoder record (``training.config.decoder``, or the older ``training.decoder``, whose
    sampling entries the runs' configuration now holds) as a DecoderConfig."""
    scale = record["asinh_scale"]
    known = {f.name for f in dataclasses.fields(DecoderConfig)}
    fields = {k: v for k, v in record.items() if k in known}
    return DecoderConfig(**{**fields, "hidden": tuple(record["hidden"]), "loop": LoopConfig(**record["loop"]),
                            "asinh_scale": None if scale is None else tuple(scale)})


def member_arrays(arrays: dict, prefix: str) -> dict:
    """One ensemble member's arrays as a single decoder's: the filter bank's and the output scale's, and
    the member's MLP arrays (``prefix/*``) under ``decoder/``."""
    own = {name: value for name, value in arrays.items() if not name.startswith(DECODER)}
    own[ASINH_SCALE] = arrays[ASINH_SCALE]
    own.update({DECODER + name[len(prefix):]: value for name, value in arrays.items()
                if name.startswith(prefix + "/") and name != ASINH_SCALE})
    return own


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path, help="a bank model directory (one decoder or an ensemble of fewer than K)")
    parser.add_argument("--members", type=int, required=True, help="decoders of the ensemble (>= 2)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--cache", type=Path, help="directory of fitted members to reuse")
    parser.add_argument("--member-seeds", help="comma-separated seeds of the K - K0 added decoders (default: the "
                        "card's training seed + K0, ..., + K - 1; K0 the model's decoders)")
    parser.add_argument("--fresh", action="store_true", help="fit the new members (and calibrate the monitor) on "
                        "runs of the card's recipe from the current code, unchecked against the card's domain")
    args = parser.parse_args()
    if args.members < 2:
        parser.error(f"--members: expected at least 2, received {args.members}")
    refuse_existing({args.out / name: "--out" for name in MODEL_FILES})         # before any fit, never over a model
    t0 = time.perf_counter()
    model, bank, data = resimulate(args.model, fresh=args.fresh)
    have = model.spec.architecture.members
    if have >= args.members:
        parser.error(f"--members: expected more than the {have} decoders of {args.model}, received {args.members}")
    card, seed = copy.deepcopy(model.card), int(model.card["training"]["seed"])
    one = bd.DecoderSpec.from_card(card["architecture"]["decoder"], angles=model.spec.architecture.angles)
    fits = [BankFit(member_arrays(model.arrays, prefix), one, None, len(data), 0.0, {})
            for prefix in member_prefixes(have)]
    training = card["training"]
    config = decoder_config(training["config"]["decoder"] if "config" in training else training["decoder"])
    summaries = list(training.get("member_fits", []))
    kept = len(summaries)
    seeds = list(range(seed + have, seed + args.members))
    if args.member_seeds is not None:
        try:
            seeds = [int(v) for v in args.member_seeds.split(",")]
        except ValueError:
            parser.error(f"--member-seeds: expected comma-separated integers, received {args.member_seeds!r}")
        if len(seeds) != args.members - have or len(set(seeds)) != len(seeds) or seed in seeds:
            parser.error(f"--member-seeds: expected {args.members - have} distinct seeds other than the card's "
                         f"training seed {seed}, received {args.member_seeds!r}")
    for member_seed in seeds:
        path = None if args.cache is None else args.cache / f"{card['system']['name']}_m{member_seed}.npz"
        if path is not None and path.exists():
            arrays = dict(np.load(path))
            record = path.with_suffix(".json")          # the fit's summary, written beside its arrays
            summaries.append(json.loads(record.read_text()) if record.exists()
                             else {"seed": member_seed, "cached": path.name})
        else:
            fit = fit_bank_decoder(bank, data, config, angles=one.angles, seed=member_seed, progress=True)
            arrays = fit.arrays
            summaries.append({"seed": member_seed, **fit.fit.summary()})
            if path is not None:                        # the summary, then the arrays whose file marks it done
                archive = io.BytesIO()
                np.savez(archive, **arrays)
                write_file(path.with_suffix(".json"), json.dumps(summaries[-1]), overwrite=True, argument="--cache")
                write_file(path, archive.getvalue(), overwrite=True, argument="--cache")
        fits.append(BankFit(arrays, one, None, len(data), 0.0, {}))
    arrays = {k: v for k, v in ensemble_arrays(fits).items() if not k.startswith(("bank/A", "bank/By"))}
    card["architecture"]["bank"]["members"] = args.members
    card["training"]["member_fits"] = summaries
    card["training"]["members_added_by"] = "benchmarks/ensemble_members.py" + (" --fresh" if args.fresh else "")
    source = calibration_source("benchmarks/ensemble_members.py", args.fresh)
    card = recalibrate(args.out, model, bank, data, arrays, card, source)
    print(f"{args.out}: {args.members} members ({json.dumps(summaries[kept:])} added), monitor threshold "
          f"{card['monitor']['threshold']:.4g}, spread threshold {card['monitor']['spread']['threshold']:.4g}, "
          f"{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
