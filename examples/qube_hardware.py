"""A real rig, end to end: the six logged free swings of a Quanser Qube Servo 2 (``examples/qube/``).

1. **The split, fixed before anything was looked at.** Runs 1, 3 and 5 are the development runs (the
   logs the training reads, and where any setting was chosen); runs 7, 9 and 11 are scored and chose
   nothing.
2. **Train** with the one command, for ``y = (theta, alpha)`` and for ``y = alpha``
   (``make_plant_alpha``), its Python path: the configuration
   :func:`kklcasadi.cli.train.training_config` builds from the command's flags, trained by
   ``train_observer`` as the command does::

       kklcasadi train --plant examples/qube/qube_plant.py:make_plant --dt 0.004 \
           --like examples/qube/data/free_swing_1.csv --like .../free_swing_3.csv --like .../free_swing_5.csv \
           --time-col time --y-cols theta,alpha --u-zero --out DIR

   (the ``like`` recipe: the rig's envelope from the development runs' logs, its measurement and process
   noise estimated from them, nothing chosen by hand; the bank recipe's budget for a new plant, 1000
   runs of 60 / 13.3 = 4.5 s, 15 epochs). ``--recipe chosen`` trains the earlier command instead, whose
   flags were chosen by hand on the development runs (:data:`CHOSEN`, ``benchmarks/accuracy/qube.py``).
3. **Estimate every log** with :func:`kklcasadi.evaluation.logged.estimate_log` (the log put on the
   4 ms grid, angles unwrapped), beside the EKF with the noise the log estimation gives on the
   development runs (:func:`kklcasadi.estimators.noise.rig_envelope`; the ``like`` model's card holds the
   same), the EKF of ``examples/qube/check_logs.py`` (``R = 1e-6 I``, process variance ``1e-3`` per step on
   the velocities) and a filtered finite difference of the angles (the backward difference low-passed at
   50 rad/s, ``50 s / (s + 50)``), and score them for ``t >= 2 s``: the angles against the measured ones
   (wrapped), the velocities against the zero-phase reference
   :func:`kklcasadi.plant.logs.savgol_derivative` (window 15, cubic).
4. **Plot** the angles and velocities of a scored run against the reference (``OUT/qube_<y>.png``),
   and write every score to ``OUT/qube_hardware.json`` (or ``--results FILE``).

Nothing is overwritten: where a model, a plot or the scores' file it would write exists, the script says so
before any work, naming the flag; the plots and the scores are rendered first and then written exclusively
(:func:`kklcasadi.writes.write_files`), so a run that fails leaves none of them half written.

Run: ``python examples/qube_hardware.py [--out DIR] [--results FILE] [--cases ...] [--recipe like|chosen]``;
``--epochs``, ``--runs`` and ``--horizon`` (in units of the plant's time scale) shrink the recipe's budget, as
``tests/test_qube_hardware.py`` does.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np
from scipy.signal import savgol_filter

import kklcasadi as kc
from kklcasadi import provenance
from kklcasadi.estimators.noise import rig_envelope
from kklcasadi.evaluation.logged import estimate_log
from kklcasadi.metrics import rmse
from kklcasadi.plant.logs import Log, read_log, savgol_derivative
from kklcasadi.writes import refuse_existing, write_files

HERE = Path(__file__).resolve().parent / "qube"
sys.path.insert(0, str(HERE))
from qube_plant import BOX, STATES  # noqa: E402

DT = 0.004
#: The split, fixed before anything was fitted: settings chosen on these runs only ...
FIT_RUNS = (1, 3, 5)
#: ... and scores on these.
SCORED_RUNS = (7, 9, 11)
#: Scores leave out the first seconds (every estimator starts from its prior).
SETTLE = 2.0
#: The filtered finite difference: the backward difference low-passed at this rate (rad/s).
FFD_RATE = 50.0
#: The measured outputs per case: (label, plant factory in examples/qube/qube_plant.py, y columns).
CASES = {"theta_alpha": ("y = (theta, alpha)", "make_plant", ("theta", "alpha")),
         "alpha": ("y = alpha", "make_plant_alpha", ("alpha",))}
#: The flags of ``kklcasadi train`` per case beyond ``--plant``, ``--dt`` and ``--out``, chosen on
#: FIT_RUNS (velocity RMSE of both velocities, mean over runs 1, 3, 5; the EKF's 0.054 / 0.170):
#: y = (theta, alpha) process std 4 / 8 / 16 / 32 -> 0.088 / 0.067 / 0.053 / 0.057 with half the box,
#: 0.109 with process std 8 and the whole box; y = alpha 16 / 32 -> 0.171 / 0.158.
CHOSEN = {"theta_alpha": {"--measurement-std": 1e-3, "--process-std": 16.0, "--box-scale": 0.5},
          "alpha": {"--measurement-std": 1e-3, "--process-std": 32.0, "--box-scale": 0.5}}
#: The training recipes: ``like`` (the default: the rig's envelope from the development runs' logs) and
#: ``chosen`` (the flags of :data:`CHOSEN`).
RECIPES = ("like", "chosen")


def run_path(k: int) -> Path:
    return HERE / "data" / f"free_swing_{k}.csv"


def read_angles(k: int) -> Log:
    """Run ``k``'s two angles on the 4 ms grid, unwrapped, alpha on the box's branch (hanging at pi)."""
    return read_log(run_path(k), time_col="time", y_cols=("theta", "alpha"), angle_cols=("theta", "alpha"), dt=DT,
                    box={"theta": BOX[0], "alpha": BOX[1]})


def encoder_noise(runs: tuple[int, ...]) -> float:
    """The std of the logged angles about their Savitzky-Golay smoothing (window 15, cubic) on ``runs``."""
    residuals = [log.y - savgol_filter(log.y, 15, 3, axis=0) for log in map(read_angles, runs)]
    return float(np.std(np.concatenate(residuals)))


def filtered_difference(t: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """``(theta_k - theta_k-1) / dt`` low-passed by ``v_k = a v_k-1 + (1 - a) d_k``, ``a = exp(-FFD_RATE dt)``."""
    h = float(t[1] - t[0])
    d = np.vstack([np.zeros((1, angles.shape[1])), np.diff(angles, axis=0) / h])
    a = np.exp(-FFD_RATE * h)
    v = np.zeros_like(d)
    for k in range(1, len(d)):
        v[k] = a * v[k - 1] + (1 - a) * d[k]
    return v


def command(case: str, out: Path, plant: Path = HERE / "qube_plant.py", seed: int = 0,
            recipe: str = "like", data: Path = HERE / "data") -> list[str]:
    """The one command that trains ``case``'s observer into ``out`` with ``recipe``, as its argument list
    (``plant``, ``data``: the plant file and the logs' folder as the command names them; ``seed``: the
    command's ``--seed``, shown where it is not 0)."""
    if recipe == "like":
        flags = [part for k in FIT_RUNS for part in ("--like", str(data / f"free_swing_{k}.csv"))]
        flags += ["--time-col", "time", "--y-cols", ",".join(CASES[case][2]), "--u-zero"]
    else:
        flags = [str(part) for flag, value in CHOSEN[case].items() for part in (flag, value)]
    seeded = ["--seed", str(seed)] if seed else []
    return ["train", "--plant", f"{plant}:{CASES[case][1]}", "--dt", str(DT), *flags, *seeded, "--out", str(out)]


def train(case: str, out: Path, *, epochs: Optional[int] = None, runs: Optional[int] = None,
          horizon: Optional[float] = None, seed: int = 0, recipe: str = "like") -> Path:
    """``kklcasadi train`` of :func:`command` in Python: the command's configuration
    (:func:`kklcasadi.cli.train.training_config`), trained as the command trains it; ``epochs``,
    ``runs`` and ``horizon`` (runs' length in units of the plant's time scale) shrink the budget."""
    from kklcasadi.cli import build_parser
    from kklcasadi.cli.flags import plant_of
    from kklcasadi.cli.train import RECOMMENDED, rig_of, training_config
    from kklcasadi.train import train_observer, with_field

    args = build_parser().parse_args(command(case, out / case, seed=seed, recipe=recipe))
    plant = plant_of(args)
    config = training_config(plant, RECOMMENDED, args, rig_of(plant, args))
    for name, value in (("n_traj", runs), ("T", horizon)):      # a smaller budget than the recipe's, when asked
        if value is not None:
            config = with_field(config, name, value)
    if runs is not None and runs < 100:                          # batches a tiny budget's few samples can fill
        config = with_field(config, "decoder", with_field(config.decoder, "batch_size", 64))
    return train_observer(plant, RECOMMENDED, Path(args.out), config=config, dt=args.dt, seed=args.seed,
                          epochs=epochs, threads=1)


def score(case: str, model: Path) -> tuple[dict, dict]:
    """Every run's errors for ``t >= SETTLE``: ``{run: {estimator: [theta, alpha, theta_dot, alpha_dot]}}``,
    and the traces of the first scored run for the plot."""
    label, factory, y_cols = CASES[case]
    plant = kc.systems.load_plant(f"{HERE / 'qube_plant.py'}:{factory}")
    obs = kc.load_observer(model, system=plant)
    rig = rig_envelope(plant, [run_path(k) for k in FIT_RUNS], dt=DT, time_col="time", y_cols=y_cols)
    ekf = kc.EKF.for_noise(plant, DT, process_std=rig.process_std, measurement_std=rig.measurement_std)
    check_logs = kc.EKF(plant, DT, Q=np.diag([0.0, 0.0, 1e-3, 1e-3]), R=1e-6 * np.eye(plant.ny))
    table, traces = {}, {}
    for k in FIT_RUNS + SCORED_RUNS:
        # the reference: the measured angles (both, whatever y is) and their zero-phase derivative
        both = read_angles(k)
        # free swings (zero input); every run is scored, inside the training domain or not (the reduced test's
        # tiny training covers less than a swing), so the range check is off and the domain monitor reports
        result = estimate_log(obs, run_path(k), y_cols=y_cols, u_zero=True, range_check=False, ekf=ekf)
        reference = np.column_stack([both.y, savgol_derivative(both.t, both.y)])
        keep = both.t - both.t[0] >= SETTLE
        u0 = np.zeros((result.t.size, plant.nu))
        # the filtered difference gives the angles it measures and their velocities, nothing else
        ffd = np.column_stack([both.y, filtered_difference(both.t, both.y)])
        for i in (0, 1):
            if STATES[i] not in y_cols:
                ffd[:, [i, i + 2]] = np.nan
        estimates = {"KKL (bank)": result.xhat, "EKF": result.ekf,
                     "EKF (check_logs)": check_logs.simulate(result.t, result.log.y, u0).xhat,
                     "filtered difference": ffd}
        table[k] = {name: [rmse(reference[keep, i:i + 1], x[keep, i:i + 1], angles=(0,) if i < 2 else ())
                           for i in range(4)] for name, x in estimates.items()}
        if k == SCORED_RUNS[0]:
            traces = {"t": both.t - both.t[0], "reference": reference, **estimates, "in_domain": result.in_domain,
                      "run": k, "label": label}
    return table, traces


#: The estimators scored: the observer, the EKF with the noise the log estimation gives on the development runs,
#: the EKF of examples/qube/check_logs.py, the filtered difference.
ESTIMATORS = ("KKL (bank)", "EKF", "EKF (check_logs)", "filtered difference")


def scored_mean(table: dict) -> dict:
    """``{estimator: [theta, alpha, theta_dot, alpha_dot]}``: the mean RMSE over SCORED_RUNS (NaN: not given)."""
    return {name: np.mean([table[k][name] for k in SCORED_RUNS], axis=0).tolist() for name in ESTIMATORS}


def markdown(case: str, table: dict) -> str:
    """Per run and the mean over the scored runs; ``-`` where an estimator cannot give a state."""
    head = ("| " + CASES[case][0] + " | run | " + " | ".join(f"{s} RMSE" for s in STATES) + " |\n"
            + "|---|---|" + "---|" * len(STATES) + "\n")
    rows = []
    means = scored_mean(table)
    label = "mean " + ", ".join(map(str, SCORED_RUNS))
    for name in ESTIMATORS:
        for k in FIT_RUNS + SCORED_RUNS:
            values = " | ".join("-" if np.isnan(v) else f"{v:.3f}" for v in table[k][name])
            rows.append(f"| {name} | {k}{' (fit)' if k in FIT_RUNS else ''} | {values} |")
        rows.append(f"| **{name}** | **{label}** | " + " | ".join("-" if np.isnan(v) else f"**{v:.3f}**"
                                                                  for v in means[name]) + " |")
    ratio = np.array(means["KKL (bank)"]) / np.array(means["EKF"])
    rows.append(f"| bank / EKF | {label} | " + " | ".join("" if i < 2 else f"{v:.2f}x" for i, v in enumerate(ratio))
                + " |")                                          # velocities: the EKF's angles are the measured ones
    return head + "\n".join(rows)


def summary(records: dict) -> str:
    """The README's table: per case of ``records`` (``{case: the record main writes}``), the mean RMSE over
    the scored runs of each estimator and the bank's velocities over the EKF's."""
    head = "| y | estimator | " + " | ".join(STATES) + " |\n" + "|---|---|" + "---|" * len(STATES) + "\n"
    rows = []
    for case, record in records.items():
        means = record["scored_mean"]
        for j, name in enumerate(name for name in ESTIMATORS if name in means):     # older records: fewer
            label = CASES[case][0].removeprefix("y = ") if j == 0 else ""
            shown = f"**{name}**" if j == 0 else name
            cells = ["-" if v is None else f"{v:.{4 if i < 2 else 3}f}" for i, v in enumerate(means[name])]
            rows.append("| " + " | ".join([label, shown, *cells]) + " |")
        ratio = [f"{b / e:.2f}x" for b, e in zip(means["KKL (bank)"][2:], means["EKF"][2:])]
        rows.append("| " + " | ".join(["", "bank / EKF", "", "", *ratio]) + " |")
    return head + "\n".join(rows)


def plot(traces: dict, stamp: provenance.Stamp) -> bytes:
    """The angles and velocities of the traced run against the reference (a PNG with ``stamp``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 1, figsize=(10, 9), sharex=True)
    t = traces["t"]
    for i, ax in enumerate(axes):
        ax.plot(t, traces["reference"][:, i], "k", lw=1.4, label="measured" if i < 2 else "zero-phase reference")
        for j, name in enumerate(ESTIMATORS):
            if not np.all(np.isnan(traces[name][:, i])):
                ax.plot(t, traces[name][:, i], color=f"C{j}", lw=0.9, ls="--" if j else "-", label=name)
        ax.axvline(SETTLE, color="0.7", lw=0.8)
        ax.set_ylabel(STATES[i] + (" [rad]" if i < 2 else " [rad/s]"))
        ax.legend(fontsize=7, ncol=4, loc="upper right")
    axes[0].set_title(f"Qube Servo 2, free swing {traces['run']} (scored), {traces['label']}")
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    png = io.BytesIO()
    fig.savefig(png, format="png", dpi=110, metadata=provenance.png_metadata(stamp))
    plt.close(fig)
    return png.getvalue()


def _json(values: list) -> list:
    """RMSEs for JSON: None where an estimator does not give the state (NaN)."""
    return [None if np.isnan(v) else float(v) for v in values]


def main(out: Path, *, epochs: Optional[int] = None, runs: Optional[int] = None, horizon: Optional[float] = None,
         cases: tuple[str, ...] = tuple(CASES), results: Optional[Path] = None, seed: int = 0,
         recipe: str = "like") -> dict:
    """Train with ``recipe``, estimate, score and plot every case; writes the scores to ``results`` (default
    ``OUT/qube_hardware.json``) and returns ``{case: (table, markdown)}``.

    Raises
    ------
    FileExistsError
        Before any work, where one of the files it writes exists (the one line names the flag)."""
    results = out / "qube_hardware.json" if results is None else results
    refuse_existing({**{path: "--out" for case in cases for path in (out / case, out / f"qube_{case}.png")},
                     results: "--results"})
    stamp = provenance.stamp(seeds={"training": seed})                # the command line, commit and versions
    out.mkdir(parents=True, exist_ok=True)
    print(f"encoder noise on runs {FIT_RUNS}: std {encoder_noise(FIT_RUNS):.2g} rad about a smoothing "
          f"(the quantisation)")
    record, done, plots = {}, {}, {}
    for case in cases:
        print("kklcasadi " + " ".join(command(case, out / case, seed=seed, recipe=recipe)), flush=True)
        t0 = time.perf_counter()
        model = train(case, out, epochs=epochs, runs=runs, horizon=horizon, seed=seed, recipe=recipe)
        seconds = time.perf_counter() - t0
        print(f"{CASES[case][0]}: trained {model} in {seconds:.0f} s")
        table, traces = score(case, model)
        text = markdown(case, table)
        print(text)
        plots[out / f"qube_{case}.png"] = plot(traces, stamp)
        done[case] = (table, text)
        shown = command(case, Path("DIR"), Path("examples/qube/qube_plant.py"), seed, recipe,
                        Path("examples/qube/data"))
        record[case] = {"command": "kklcasadi " + " ".join(shown), "recipe": recipe, "train_s": round(seconds),
                        "budget": {"epochs": epochs, "runs": runs, "horizon": horizon}, "fit_runs": FIT_RUNS,
                        "scored_runs": SCORED_RUNS, "states": STATES, "settle_s": SETTLE,
                        "runs": {str(k): {name: _json(v) for name, v in row.items()} for k, row in table.items()},
                        "scored_mean": {name: _json(v) for name, v in scored_mean(table).items()}}
    # everything rendered first: each file whole, never over another one
    write_files({**plots, results: json.dumps(provenance.json_record(record, stamp), indent=1) + "\n"},
                argument="--results")
    print("plots " + ", ".join(map(str, plots)) + f"\nscores {results}")
    return done


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/qube"),
                        help="where the models go (default: runs/qube, ignored by git)")
    parser.add_argument("--results", type=Path, help="the scores' JSON file (default OUT/qube_hardware.json)")
    parser.add_argument("--epochs", type=int, help="decoder epochs (default: the recipe's)")
    parser.add_argument("--runs", type=int, help="training runs of the bank (default: the recipe's)")
    parser.add_argument("--horizon", type=float, help="length of each training run in units of the plant's time "
                        "scale (default: the recipe's 60)")
    parser.add_argument("--cases", nargs="+", choices=tuple(CASES), default=list(CASES))
    parser.add_argument("--seed", type=int, default=0, help="the train command's --seed")
    parser.add_argument("--recipe", choices=RECIPES, default="like", help="like (default: the rig's envelope from the "
                        "development runs' logs) or chosen (the earlier flags chosen by hand on them)")
    args = parser.parse_args()
    main(args.out, epochs=args.epochs, runs=args.runs, horizon=args.horizon, cases=tuple(args.cases),
         results=args.results, seed=args.seed, recipe=args.recipe)
