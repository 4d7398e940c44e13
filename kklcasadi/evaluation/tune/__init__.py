"""Observer design searches on Optuna (``kklcasadi tune``): the search space, the validation score,
the study, and the best trial as a model directory.

A study searches one method's training configuration (:func:`kklcasadi.train.default_config`)
against a validation score measured on trials that no training and no benchmark uses: input
families and parameter ranges the configuration does not fit on (:func:`validation_cells`),
simulated with their own seed, scored as the observer's mean SMAPE over the EKF's on the same
trials (:func:`score`). The engine is Optuna, with nothing of our own around it:

* the storage is an Optuna RDB storage: a SQLite file by default, a PostgreSQL URL to join one
  study from several machines (every ``kklcasadi tune`` started with the same ``--study`` and
  ``--storage`` is one more worker);
* a worker killed mid-trial stops beating its RDB heartbeat; after the grace period the next
  worker to start a trial marks it failed and Optuna's ``RetryHeartbeatStaleTrialCallback``
  queues it again with the same parameters, which that worker then runs;
* the study stops at ``n_trials`` complete trials (``MaxTrialsCallback``), so running ``tune``
  again resumes it, and a larger ``n_trials`` extends it;
* TPE samples the space (multivariate, constant liar for parallel workers).

The search space of every method is one entry of :data:`SPACES`: dimensions that name the
configuration's dataclass fields by dotted path (``"decoder.loop.epochs"``), so a renamed or new
field is one line there. Budget dimensions (:class:`Budget`) search up to a cap, default the
method's own default budget; the recipe's baseline is trained at the caps.

Optuna (``pip install 'kklcasadi[tune]'``) and torch are imported inside the functions that use
them.

The rooms: :mod:`.space` (the search space), :mod:`.validation` (the validation cells and the score),
:mod:`.storage` (Optuna and the study's storage), :mod:`.study` (a worker: :func:`tune`, :func:`export_best`)
and :mod:`.report` (the summary table and the plot).
"""

from .report import search_plot, summary_table
from .space import SPACES, Budget, Filters, Float, Int, Layers, MaybeRate, Space, search_space
from .storage import storage_url
from .study import TuneResult, export_best, tune
from .validation import (
    VALIDATION_FAMILIES,
    VALIDATION_SEED,
    Validation,
    ValidationCell,
    fitted_families,
    score,
    validation_cells,
)

__all__ = ["Float", "Int", "Filters", "Layers", "MaybeRate", "Budget", "Space", "SPACES", "search_space",
           "ValidationCell", "validation_cells", "fitted_families", "Validation", "score", "TuneResult", "tune",
           "export_best", "summary_table", "search_plot", "storage_url", "VALIDATION_SEED", "VALIDATION_FAMILIES"]
