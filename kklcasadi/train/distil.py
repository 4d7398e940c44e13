"""Distillation of a ``bank``: a teacher bank's estimates as the targets of a student's decoder.

A ``bank``'s decoder is the minimum-mean-square estimator of the state given its latent on the runs it was fit
on (docs/design.md, "Decoder under noise"); a large ensemble with model copies approximates it best and costs
the most per step. A student (one small decoder, perhaps on a cheaper latent) fit to the teacher's estimate on
many operational runs learns that estimator from targets without the noise of the true state's deviation from
it (docs/design.md, "A compact observer").

* :func:`teacher_estimates` -- a teacher bank's estimates along the runs of a student's operational samples.
"""

from __future__ import annotations

import os
from typing import Callable, Optional

import numpy as np

from ..model.files import load_model
from ..model.operational import OperationalData
from ..model.shipped import is_shipped, resolve
from ..model.variants import BankSpec
from ..model.variants import filterbank as fb
from ..model.variants.copies import ModelCopies
from ..plant.systems import System
from ..validation import Text, error

__all__ = ["teacher_estimates"]


#: Relative difference under which two latents' arrays are the same design (a copy's Kalman gain solved again
#: differs from the stored one in the last bits).
SAME_LATENT_RTOL = 1e-12


def _same_arrays(a: dict, b: dict) -> bool:
    return set(a) == set(b) and all(np.shape(a[k]) == np.shape(b[k])
                                    and np.allclose(a[k], b[k], rtol=SAME_LATENT_RTOL, atol=0.0) for k in a)


def _same_latent(a: fb.FilterBank, a_copies: Optional[ModelCopies], b: fb.FilterBank,
                 b_copies: Optional[ModelCopies]) -> bool:
    """Whether two latents (filter banks and model copies) are the same map of ``(y, u)`` (arrays within
    :data:`SAME_LATENT_RTOL`)."""
    if not _same_arrays(fb.bank_arrays(a), fb.bank_arrays(b)) or (a_copies is None) != (b_copies is None):
        return False
    return a_copies is None or (a_copies.substeps == b_copies.substeps
                                and _same_arrays(a_copies.arrays(), b_copies.arrays()))


def teacher_estimates(system: System, teacher: str | os.PathLike, data: OperationalData, bank: fb.FilterBank,
                      copies: Optional[ModelCopies], *, dt: float,
                      rerun: Callable[[fb.FilterBank, Optional[ModelCopies]], OperationalData],
                      chunk: int = 65536) -> tuple[np.ndarray, dict]:
    """The teacher bank's estimates at the samples ``data`` of a student's operational runs.

    Parameters
    ----------
    system : System
        The plant both observers are for.
    teacher : path
        A ``bank`` model directory of ``system`` at the sample time ``dt``, or a shipped model's name
        (``duffing/bank``).
    data : OperationalData
        The student's samples (its latent ``bank`` and ``copies`` in ``data.z``).
    bank, copies : FilterBank, ModelCopies or None
        The student's latent.
    dt : float
        The student's sample time.
    rerun : callable ``(bank, copies) -> OperationalData``
        The same runs with another latent (same seed and recipe): where the teacher's latent is not the
        student's, its own latent is run over them; their true states must be ``data.x``.
    chunk : int
        Samples decoded at a time.

    Returns
    -------
    estimates : numpy.ndarray, shape (S, nx)
        The teacher's ``xhat`` at each of ``data``'s samples (its ensemble's mean).
    record : dict
        For the card: the teacher's path (a shipped model's name ``SYSTEM/METHOD``), weights digest, decoder,
        members and latent, and the RMSE of its estimates against the true states per state.
    """
    model = load_model(resolve(teacher))
    where = f"teacher {str(teacher)!r}"
    if model.method != "bank":
        raise error("teacher", "a bank model directory (its decoder's estimates are the targets)",
                    Text(f"{where}: a {model.method!r} model"))
    if model.spec.system.name != system.name or model.dt != dt:
        raise error("teacher", f"a bank model of {system.name!r} at dt = {dt}",
                    Text(f"{where}: {model.spec.system.name!r} at dt = {model.dt}"))
    spec: BankSpec = model.spec.architecture
    full = spec.filter_arrays(model.arrays)
    t_bank, t_copies = fb.bank_from_arrays(full), spec.model_copies(model.arrays, system)
    if _same_latent(t_bank, t_copies, bank, copies):
        z, source = data.z, f"the student's (its arrays within a relative {SAME_LATENT_RTOL:g})"
    else:
        again = rerun(t_bank, t_copies)
        if again.x.shape != data.x.shape or not np.array_equal(again.x, data.x):
            raise ValueError("rerun: expected the student's runs again (same seed and recipe), received others: "
                             f"{again.x.shape} samples against {data.x.shape}.")
        z, source = again.z, "its own, run over the same runs"
    arch = spec.decoder.to_card()
    xhat = np.concatenate([fb.decode(full, arch, z[i:i + chunk], data.y[i:i + chunk], data.u[i:i + chunk],
                                     angles=spec.angles, members=spec.members)
                           for i in range(0, len(z), chunk)] or [np.empty((0, system.nx))])
    name = "/".join(model.path.resolve().parts[-2:]) if is_shipped(model.path) else str(teacher)
    record = {"path": name, "weights_sha256": model.card.get("weights_sha256"),
              "decoder": list(spec.decoder.sizes), "members": spec.members,
              "copies": model.card["architecture"]["bank"].get("copies"), "latent": source,
              "rmse_to_truth": np.sqrt(np.mean((xhat - data.x) ** 2, axis=0)).tolist()}
    return xhat, record
