"""One-off migration of model cards written before plant fingerprints and training domains.

Adds ``system.fingerprint`` (:attr:`kklcasadi.System.fingerprint` of the registered plant of the
card's name) and ``domain`` (where the maps were trained) to every ``card.json`` under the given
directories. The weights, and so ``weights_sha256``, are unchanged; cards are rewritten
atomically and each model is loaded again afterwards.

The domain of an ``autonomous`` model is recomputed from its own training recipe: the states of
the Phase-1 box (scaled by the card's ``box_scale``) and of 10 s autonomous trajectories from it,
and their latents under the model's encoder. Models built on a base take the base's domain
(``curriculum`` recomputes it with its own encoder).

Usage::

    python benchmarks/migrate_cards.py models            # every models/<system>/<method>/
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

import numpy as np

import kklcasadi as kc
from kklcasadi.model.card import Domain
from kklcasadi.model.files import CARD_FILE, load_model

PHASE1_STATES = 2000
PHASE1_TRAJECTORIES = 200


def phase1_domain(model: kc.model.files.Model, plant: kc.System) -> Domain:
    """States of the box and of autonomous trajectories from it, and their latents."""
    config = model.card["training"].get("config", {})
    scale = float(config.get("box_scale", 1.0)) if isinstance(config, dict) else 1.0
    starts = plant.sample_box(PHASE1_TRAJECTORIES, 1, scale=scale)
    runs = kc.simulate_batch(plant, starts, [kc.signals.Zero(plant.nu)] * len(starts), 10.0, model.dt, method="rk")
    x = np.vstack([plant.sample_box(PHASE1_STATES, 0, scale=scale), runs.x[runs.ok].reshape(-1, plant.nx)])
    encoder = kc.load_observer(model.path, system=plant).encoder
    return Domain.of(x, np.asarray(encoder.map(len(x))(x.T)).T)


def write_card(directory: Path, card: dict) -> None:
    handle, name = tempfile.mkstemp(dir=directory, prefix=".tmp-", suffix=".json")
    with os.fdopen(handle, "w", encoding="utf-8") as stream:
        stream.write(json.dumps(card, indent=2) + "\n")
    os.replace(name, directory / CARD_FILE)


def migrate(root: Path) -> None:
    cards = sorted(root.glob(f"*/*/{CARD_FILE}"))
    domains: dict[Path, Domain] = {}
    # bases first: the autonomous models, then what is built on them
    for path in sorted(cards, key=lambda p: json.loads(p.read_text())["method"] != "autonomous"):
        directory = path.parent.resolve()
        card = json.loads(path.read_text())
        plant = kc.systems.get(card["system"]["name"])
        card["system"]["fingerprint"] = plant.fingerprint
        if card["method"] in ("autonomous", "curriculum"):
            write_card(directory, card)                  # the fingerprint first: the observer checks it
            domain = phase1_domain(load_model(directory), plant)
        else:
            domain = domains[(directory / card["base"]["path"]).resolve()]
        domains[directory] = domain
        card["domain"] = domain.to_card()
        write_card(directory, card)
        print(f"{directory}: fingerprint {plant.fingerprint[:12]}..., domain x in "
              f"{np.round(domain.x_lo, 2).tolist()} .. {np.round(domain.x_hi, 2).tolist()}")
    for path in cards:                                   # every model and its base load again
        load_model(path.parent)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="directory holding <system>/<method>/card.json")
    migrate(parser.parse_args().root)
