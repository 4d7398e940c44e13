"""The C step's cost with the covariance head against the same model without it (issue 49: at most 1.2x).

    python benchmarks/covariance_cost.py MODEL_WITHOUT MODEL_WITH [--steps 2000]

Both models go through :func:`kklcasadi.observer.codegen.generate_c` (the defaults: axpy kernels, vector exp/tanh,
AVX2 dispatch) and the timing loop of ``kklcasadi bench observer``
(:func:`kklcasadi.evaluation.bench.observer_step.loop_source`, which also fills the covariance output where the
model has a head), built with ``gcc -std=c99 -O3``. Printed: instructions per step under ``valgrind
--tool=callgrind`` (repeatable on a loaded machine) and the best wall time per step of 3 x 20 runs, and their
ratios.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

from kklcasadi.evaluation.bench.observer_step import loop_source
from kklcasadi.observer.codegen import generate_c
from kklcasadi.observer.kkl import load_observer


def measure(model: str, folder: Path, steps: int) -> tuple[float, float]:
    """Instructions per step and the best seconds per step of ``model``'s generated C step."""
    obs = load_observer(model)
    files = generate_c(obs, folder, "kkl_bench")
    (folder / "loop.c").write_text(loop_source("kkl_bench"))
    binary = folder / "loop"
    subprocess.run(["gcc", "-std=c99", "-O3", str(files[0]), str(folder / "loop.c"), "-lm", "-o", str(binary)],
                   check=True)
    out = subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={folder / 'cg.out'}", str(binary),
                          str(steps), "1"], capture_output=True, text=True, check=True)
    instructions = int(re.search(r"Collected : (\d+)", out.stderr).group(1)) / steps
    best = min(float(subprocess.run([str(binary), str(10 * steps), "20"], capture_output=True, text=True,
                                    check=True).stdout.split()[0]) for _ in range(3))
    return instructions, best


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("without", help="the model without a covariance head (e.g. the bank before its head)")
    p.add_argument("with_head", metavar="with", help="the same model with its head")
    p.add_argument("--steps", type=int, default=2000)
    args = p.parse_args()
    if shutil.which("valgrind") is None or shutil.which("gcc") is None:
        raise SystemExit("error: needs gcc and valgrind")
    with tempfile.TemporaryDirectory() as tmp:
        a = measure(args.without, Path(tmp) / "without", args.steps)
        b = measure(args.with_head, Path(tmp) / "with", args.steps)
    for label, (ir, s) in (("without", a), ("with", b)):
        print(f"{label:8s} {ir:12.0f} instructions/step   best {1e6 * s:8.2f} us/step")
    print(f"ratio    {b[0] / a[0]:12.4f} (instructions)     {b[1] / a[1]:8.3f} (best wall time)")


if __name__ == "__main__":
    main()
