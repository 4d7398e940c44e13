"""``kklcasadi resign``: check a model whose card was edited by hand (or written before cards carried a digest)
and sign its card, saying what changed (:func:`kklcasadi.model.files.resign_model`)."""

from __future__ import annotations

import argparse

from .flags import flagged, out_path


def add_parser(sub: argparse._SubParsersAction) -> None:
    r = sub.add_parser("resign", help="check an edited model card and sign it (its digest), saying what changed",
                       description="A model refuses to load when its card.json changed after it was written. Check "
                       "the change, then run this to accept it: the model is validated as on load (the card against "
                       "its method and weights), and the card's digest written anew. The weights are not touched.")
    r.add_argument("models", nargs="+", metavar="MODEL", help="model directories")
    r.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..model.files import resign_model

    for model in args.models:
        out_path(model, "MODEL", directory=True)            # the shipped models are read-only here
        found = flagged("MODEL", resign_model, model)
        print(f"{model}: " + ("signed; " + "; ".join(found) if found else "unchanged, nothing to sign"))
    return 0
