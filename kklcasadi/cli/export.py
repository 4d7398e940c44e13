"""``kklcasadi export``: an observer as C code and/or a serialised CasADi Function."""

from __future__ import annotations

import argparse
from pathlib import Path

from .flags import CommandError, add_plant, c_name, load, plant_of


def add_parser(sub: argparse._SubParsersAction) -> None:
    x = sub.add_parser("export", help="export an observer as C code and/or a serialised CasADi Function")
    x.add_argument("model", metavar="MODEL", help="a model directory, or a shipped model's name SYSTEM/METHOD "
                                                  "(e.g. duffing/bank)")
    add_plant(x, "for a model of a plant that kklcasadi does not ship")
    x.add_argument("--c", metavar="OUT_DIR", help="write C code of the observer step here")
    x.add_argument("--name", type=c_name, default="kkl_obs", help="C name prefix (a C identifier)")
    x.add_argument("--precision", choices=("float64", "float32"), default="float64",
                   help="the C type of every value: double (default), or float for a microcontroller's "
                   "single-precision FPU (docs/design.md, 'float32 C')")
    x.add_argument("--casadi", metavar="FILE", help="write the step as a ca.Function (Function.save)")
    x.add_argument("--overwrite", action="store_true", help="replace files that exist")
    x.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..observer.codegen import generate_c

    if not (args.c or args.casadi):
        raise CommandError("export: nothing to export; give --c OUT_DIR and/or --casadi FILE")
    obs = load(args.model, plant_of(args), "MODEL")
    if args.c:
        existing = Path(args.c)
        if existing.exists() and any(existing.iterdir()) and not args.overwrite:
            raise CommandError(f"--c {existing}: the directory is not empty; pass --overwrite to replace its files")
        for path in generate_c(obs, args.c, name=args.name, overwrite=args.overwrite,
                               precision=args.precision):
            print(f"wrote {path}")
    if args.casadi:
        target = Path(args.casadi)
        if target.exists() and not args.overwrite:
            raise CommandError(f"--casadi {target}: the file exists; pass --overwrite to replace it")
        obs.step.save(str(target))
        print(f"wrote {target} (ca.Function.load it: {obs.step.name_in()} -> {obs.step.name_out()})")
    return 0
