"""``kklcasadi export``: an observer as C code and/or a serialised CasADi Function."""

from __future__ import annotations

import argparse
from pathlib import Path

from .flags import CommandError, add_plant, c_name, columns, load, plant_of


def add_parser(sub: argparse._SubParsersAction) -> None:
    x = sub.add_parser("export", help="export an observer as C code and/or a serialised CasADi Function")
    x.add_argument("model", metavar="MODEL", help="a model directory, or a shipped model's name SYSTEM/METHOD "
                                                  "(e.g. duffing/bank)")
    add_plant(x, "for a model of a plant that kklcasadi does not ship")
    x.add_argument("--c", metavar="OUT_DIR", help="write C code of the observer step here")
    x.add_argument("--name", type=c_name, default="kkl_obs", help="C name prefix (a C identifier)")
    x.add_argument("--time-col", default="time", help="with --c: the column of times the C main reads by name "
                   "(default time)")
    x.add_argument("--y-cols", type=columns, metavar="NAMES", help="with --c: the outputs' columns the C main reads "
                   "by name, comma-separated, in the plant's output order (default y1,...)")
    x.add_argument("--u-cols", type=columns, metavar="NAMES", help="with --c: the inputs' columns (default u1,...)")
    x.add_argument("--state-names", type=columns, metavar="NAMES", help="with --c: the estimates' columns the C main "
                   "writes (default x1,...)")
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
        names = {"time_col": "--time-col", "y_cols": "--y-cols", "u_cols": "--u-cols", "state_names": "--state-names"}
        try:
            files = generate_c(obs, args.c, name=args.name, overwrite=args.overwrite, time_col=args.time_col,
                               y_cols=args.y_cols, u_cols=args.u_cols, state_names=args.state_names)
        except (ValueError, TypeError) as exc:
            head, sep, rest = str(exc).partition(": ")
            if sep and head in names:
                raise CommandError(f"{names[head]}: {rest}") from exc
            raise
        for path in files:
            print(f"wrote {path}")
    if args.casadi:
        target = Path(args.casadi)
        if target.exists() and not args.overwrite:
            raise CommandError(f"--casadi {target}: the file exists; pass --overwrite to replace it")
        obs.step.save(str(target))
        print(f"wrote {target} (ca.Function.load it: {obs.step.name_in()} -> {obs.step.name_out()})")
    return 0
