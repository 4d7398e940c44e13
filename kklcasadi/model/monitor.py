"""The decoder's domain monitor: how far the decoder's input is from what it was fit on.

The decoder of an observer reads ``f_k = [z_k; vec(w_k)]`` (for ``bank``: ``[z_k; y_k; u_k]``). The
monitor keeps ``K`` prototypes, samples of ``f`` drawn from the fitting runs, each with its radius
``r_j``, and a metric ``L``; a sample is in the domain when its distance to the prototypes, in
units of their radii, ``min_j ||L f_k - P_j|| / r_j`` (``P_j = L p_j``), is at most the threshold.
The metric whitens the spread of fitting samples around their nearest prototype (the residual
covariance), so a direction the fitting data fill with measurement noise counts little and a
direction they never leave (an input filter of a noise-free input) counts a lot. A prototype's
radius is the median distance of the fitting samples nearest to it, so that sparse and dense parts
of the fitting data are flagged alike. The threshold is a quantile of the distances of validation
samples (runs of the fitting distribution that gave no prototype) after the settle time, so that
share of fitting-distribution samples is flagged.

A decoder ensemble (``bank`` with ``members`` > 1) adds a second test: a sample is in the domain
only where the members' spread (:func:`kklcasadi.model.variants.bankdecoder.spread`) is at most the
``spread`` threshold, a quantile of the spreads of the same validation samples: the members agree
where the fitting runs pinned the map down and part where they did not, also inside the region the
prototypes cover.

Stored in the model file (``docs/model-format.md``): the card entry ``monitor`` (kind, feature size,
prototypes, threshold, quantile, settle time, calibration record, and optionally ``spread``:
``{"threshold": t, "quantile": q}``) and the arrays ``monitor/metric`` (d, d), ``monitor/prototypes``
(K, d) and ``monitor/radii`` (K,).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import casadi as ca
import numpy as np

from ..nets.specs import field_error
from ..validation import Text, error, is_int, is_number, nonnegative_int, positive_int

__all__ = ["FeatureMonitor", "MonitorSpec", "calibrate", "calibrate_runs", "parse_monitor", "check_radii", "KIND",
           "METRIC", "PROTOTYPES", "RADII", "DEFAULT_PROTOTYPES", "DEFAULT_QUANTILE", "DEFAULT_SPREAD_QUANTILE",
           "with_spread"]

#: The monitor's kind in the card.
KIND = "nearest_prototype"
#: Array names in ``weights.npz``.
METRIC, PROTOTYPES, RADII = "monitor/metric", "monitor/prototypes", "monitor/radii"
#: Calibration defaults: prototypes kept, and the share of validation samples after the settle time
#: inside the threshold (2 % of fitting-distribution samples are flagged: the target is at most 5 %).
DEFAULT_PROTOTYPES = 2048
DEFAULT_QUANTILE = 0.98
#: A prototype nearest to fewer residual samples than this gets the median radius of all.
MIN_ASSIGNED = 5
_KEYS = ("kind", "features", "prototypes", "threshold", "quantile", "settle_time", "calibration")
_FIX = ('Write "monitor" as {"kind": "nearest_prototype", "features": d, "prototypes": K, "threshold": t > 0, '
        '"quantile": q in (0, 1), "settle_time": s >= 0, "calibration": {...}} (and optionally "spread": '
        '{"threshold": t > 0, "quantile": q in (0, 1)} for a decoder ensemble) with the arrays monitor/metric (d, d), '
        'monitor/prototypes (K, d) and monitor/radii (K,), or remove it.')
#: Calibration default of the ensemble test: the share of validation samples within the spread threshold.
DEFAULT_SPREAD_QUANTILE = 0.99


@dataclass(frozen=True)
class MonitorSpec:
    """The card entry ``monitor``: sizes, threshold and the calibration record."""

    features: int
    prototypes: int
    threshold: float
    quantile: float
    settle_time: float
    calibration: dict = field(default_factory=dict)
    #: ``(threshold, quantile)`` of the decoder ensemble's spread test, or None.
    spread: tuple[float, float] | None = None

    def array_shapes(self) -> dict[str, tuple[int, ...]]:
        """The monitor's arrays in ``weights.npz``."""
        return {METRIC: (self.features, self.features), PROTOTYPES: (self.prototypes, self.features),
                RADII: (self.prototypes,)}

    def to_card(self) -> dict:
        card = {"kind": KIND, "features": self.features, "prototypes": self.prototypes, "threshold": self.threshold,
                "quantile": self.quantile, "settle_time": self.settle_time, "calibration": dict(self.calibration)}
        if self.spread is not None:
            card["spread"] = {"threshold": self.spread[0], "quantile": self.spread[1]}
        return card


def parse_monitor(entry: Any, where: str) -> MonitorSpec | None:
    """The card's ``monitor`` entry, checked (None where the card has none)."""
    if entry is None:
        return None
    if not isinstance(entry, Mapping) or not set(_KEYS) <= set(entry) <= set(_KEYS) | {"spread"}:
        raise field_error(where, "monitor", f"an object with exactly the keys {list(_KEYS)} (and optionally "
                          "'spread')", entry, _FIX)
    if entry["kind"] != KIND:
        raise field_error(where, "monitor.kind", repr(KIND), entry["kind"], _FIX)
    for key in ("features", "prototypes"):
        if not is_int(entry[key]) or entry[key] < 1:
            raise field_error(where, f"monitor.{key}", "a positive integer", entry[key], _FIX)
    checks = {"threshold": lambda v: v > 0, "quantile": lambda v: 0 < v < 1, "settle_time": lambda v: v >= 0}
    for key, ok in checks.items():
        value = entry[key]
        if not (is_number(value) and math.isfinite(value) and ok(value)):
            raise field_error(where, f"monitor.{key}", {"threshold": "a number > 0", "quantile": "a number in (0, 1)",
                                                         "settle_time": "a number >= 0"}[key], value, _FIX)
    if not isinstance(entry["calibration"], Mapping):
        raise field_error(where, "monitor.calibration", "an object", entry["calibration"], _FIX)
    spread = None
    if "spread" in entry:
        value = entry["spread"]
        if not (isinstance(value, Mapping) and set(value) == {"threshold", "quantile"}
                and all(is_number(v) and math.isfinite(v) for v in value.values())
                and value["threshold"] > 0 and 0 < value["quantile"] < 1):
            raise field_error(where, "monitor.spread", '{"threshold": t > 0, "quantile": q in (0, 1)}', value, _FIX)
        spread = (float(value["threshold"]), float(value["quantile"]))
    return MonitorSpec(int(entry["features"]), int(entry["prototypes"]), float(entry["threshold"]),
                       float(entry["quantile"]), float(entry["settle_time"]), dict(entry["calibration"]), spread)


def check_radii(arrays: Mapping[str, Any], where: str) -> None:
    """Refuse a model file whose monitor radii are not all > 0 (the shapes are checked with the other arrays)."""
    radii = np.asarray(arrays[RADII])
    if not np.all(radii > 0):
        raise field_error(where, RADII, "radii > 0", Text(f"min {float(np.min(radii))}"), _FIX)


@dataclass(frozen=True, eq=False)
class FeatureMonitor:
    """The nearest-prototype monitor of the decoder's input.

    Attributes
    ----------
    spec : MonitorSpec
    metric : numpy.ndarray, shape (d, d)
        ``L``: the distance of a feature ``f`` to a prototype ``p`` is ``||L (f - p)||``.
    prototypes : numpy.ndarray, shape (K, d)
        The prototypes in the metric's coordinates, ``P_j = L p_j``.
    radii : numpy.ndarray, shape (K,)
        Each prototype's radius ``r_j > 0``, the unit of distances to it.
    """

    spec: MonitorSpec
    metric: np.ndarray
    prototypes: np.ndarray
    radii: np.ndarray

    def __post_init__(self) -> None:
        if not (np.all(np.isfinite(self.radii)) and np.all(self.radii > 0)):
            raise error("radii", "finite radii > 0", Text(f"min {np.min(self.radii)}"))

    @classmethod
    def from_arrays(cls, spec: MonitorSpec, arrays: Mapping[str, Any]) -> FeatureMonitor:
        """The monitor of a model file's arrays (already checked against ``spec``)."""
        return cls(spec, *(np.asarray(arrays[name], dtype=float) for name in (METRIC, PROTOTYPES, RADII)))

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays to store in ``weights.npz``."""
        return {METRIC: np.array(self.metric), PROTOTYPES: np.array(self.prototypes), RADII: np.array(self.radii)}

    @property
    def features(self) -> int:
        """Feature size d."""
        return self.spec.features

    def _terms(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``a_j = |P_j|^2 / r_j^2``, ``B_j = 2 P_j / r_j^2`` and ``c_j = 1 / r_j^2``: the squared scaled
        distance to prototype j is ``a_j - B_j . g + c_j |g|^2``."""
        c = 1.0 / self.radii ** 2
        return np.einsum("ij,ij->i", self.prototypes, self.prototypes) * c, 2.0 * self.prototypes * c[:, None], c

    def distance(self, features: Any, *, chunk: int = 16384) -> np.ndarray:
        """Distance of each feature vector to the prototypes in units of their radii, ``min_j ||L f - P_j|| / r_j``.

        Parameters
        ----------
        features : array_like, shape (..., d)

        Returns
        -------
        numpy.ndarray, shape (...)
        """
        f = np.asarray(features, dtype=float)
        if f.shape[-1:] != (self.features,):
            raise error("features", f"shape (..., {self.features})", Text(f"shape {f.shape}"))
        flat = f.reshape(-1, self.features) @ self.metric.T
        a, b, c = self._terms()
        out = np.empty(len(flat))
        for start in range(0, len(flat), chunk):
            g = flat[start:start + chunk]
            out[start:start + chunk] = (a[None, :] - g @ b.T + np.einsum("ij,ij->i", g, g)[:, None] * c).min(axis=1)
        return np.sqrt(np.maximum(out, 0.0)).reshape(f.shape[:-1])

    def inside(self, features: Any) -> np.ndarray:
        """Whether each feature vector is within the threshold, shape (...)."""
        return self.distance(features) <= self.spec.threshold

    def expression(self, f: ca.MX) -> ca.MX:
        """The in-domain test of one feature vector ``f`` (d, 1) as a CasADi expression (1 inside, else 0).

        ``min_j (a_j - B_j . g + c_j |g|^2) <= threshold^2`` with ``g = L f`` (:meth:`distance`'s
        terms): one (K, d) mat-vec, one scaled sum and one minimum.
        """
        a, b, c = self._terms()
        g = ca.mtimes(ca.DM(self.metric), f)
        scaled = ca.DM(a) - ca.mtimes(ca.DM(b), g) + ca.DM(c) * ca.sumsqr(g)
        return ca.mmin(scaled) <= self.spec.threshold ** 2


def with_spread(monitor: FeatureMonitor, validation_spread: Any, *,
                quantile: float = DEFAULT_SPREAD_QUANTILE, source: str = "") -> FeatureMonitor:
    """``monitor`` with the decoder ensemble's spread test, its threshold the ``quantile`` of
    ``validation_spread``: the spreads (V,) of calibration samples (the validation samples that set the
    prototype threshold, or runs at the model's nominal noise), described by ``source`` in the card's
    ``monitor.calibration`` (``spread_source``, with ``spread_samples``)."""
    spread = np.asarray(validation_spread, dtype=float)
    if spread.ndim != 1 or not len(spread) or not np.all(np.isfinite(spread)):
        raise error("validation_spread", "finite spreads (V >= 1,)", Text(f"shape {spread.shape}"))
    if not 0 < quantile < 1:
        raise error("quantile", "a number in (0, 1)", quantile)
    threshold = float(np.quantile(spread, quantile))
    if not threshold > 0:
        raise error("validation_spread", "spreads with a positive quantile (members that differ)", threshold)
    spec = monitor.spec
    calibration = {**spec.calibration, "spread_samples": int(len(spread)),
                   **({"spread_source": source} if source else {})}
    spec = MonitorSpec(spec.features, spec.prototypes, spec.threshold, spec.quantile, spec.settle_time,
                       calibration, (threshold, float(quantile)))
    return FeatureMonitor(spec, monitor.metric, monitor.prototypes, monitor.radii)


def _nearest(points: np.ndarray, prototypes: np.ndarray, chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:
    """Index (S,) and distance (S,) of each point's nearest prototype, in blocks of ``chunk`` points."""
    norms = np.einsum("ij,ij->i", prototypes, prototypes)
    index, dist = np.empty(len(points), dtype=int), np.empty(len(points))
    for start in range(0, len(points), chunk):
        g = points[start:start + chunk]
        d2 = norms[None, :] - 2.0 * g @ prototypes.T
        index[start:start + chunk] = j = np.argmin(d2, axis=1)
        dist[start:start + chunk] = d2[np.arange(len(g)), j] + np.einsum("ij,ij->i", g, g)
    return index, np.sqrt(np.maximum(dist, 0.0))


def _inverse_sqrt(cov: np.ndarray) -> np.ndarray:
    values, vectors = np.linalg.eigh(np.atleast_2d(cov))
    values = np.maximum(values, 1e-9 * values.max())
    return (vectors / np.sqrt(values)) @ vectors.T


def calibrate(fit: Any, validation: Any, *, n_prototypes: int | None = None,
              quantile: float = DEFAULT_QUANTILE, settle_time: float = 5.0, seed: int = 0, iterations: int = 2,
              n_residuals: int = 200000, calibration: Mapping[str, Any] | None = None) -> FeatureMonitor:
    """Calibrate the monitor on the decoder's features over the fitting runs.

    Parameters
    ----------
    fit : array_like, shape (S, d)
        Feature samples of the fitting runs (the prototypes and the metric come from them).
    validation : array_like, shape (V, d)
        Feature samples after ``settle_time`` of other runs of the same distribution (the threshold
        is their ``quantile``).
    n_prototypes : int, optional
        Prototypes ``K`` (fewer than S), drawn without replacement from ``fit``; default
        :data:`DEFAULT_PROTOTYPES`, or a quarter of the fitting samples where they are fewer than
        four times that.
    quantile : float
        Share of validation samples inside the threshold.
    settle_time : float
        Recorded: the time after which ``validation`` was sampled (the benchmark scores after it).
    seed : int
        Seeds the draws of prototypes and residual samples.
    iterations : int
        Rounds of the metric: the nearest prototype under the current metric, then the inverse
        square root of the covariance of the residuals to it (the first round starts from the
        global whitening; 0 keeps the global whitening).
    n_residuals : int
        Fitting samples (other than the prototypes) whose residuals to their nearest prototype
        estimate the metric and the radii.
    calibration : Mapping, optional
        Free-form record kept in the card (where the runs came from).

    Returns
    -------
    FeatureMonitor
    """
    fit = np.asarray(fit, dtype=float)
    validation = np.asarray(validation, dtype=float)
    if fit.ndim != 2 or validation.ndim != 2 or validation.shape[1] != fit.shape[1] or not len(validation):
        raise error("fit, validation", "feature samples (S, d) and (V >= 1, d) of one width d",
                    Text(f"shapes {fit.shape} and {validation.shape}"))
    if n_prototypes is None:
        n_prototypes = max(1, min(DEFAULT_PROTOTYPES, len(fit) // 4))
    n_prototypes = positive_int(n_prototypes, "n_prototypes")
    if n_prototypes >= len(fit):
        raise error("n_prototypes", f"fewer than the {len(fit)} fitting samples", n_prototypes)
    if not 0 < quantile < 1:
        raise error("quantile", "a number in (0, 1)", quantile)
    rng = np.random.default_rng(seed)
    picked = rng.choice(len(fit), n_prototypes, replace=False)
    rest = np.setdiff1d(np.arange(len(fit)), picked)
    protos = fit[picked]
    sample = fit[rng.choice(rest, min(n_residuals, len(rest)), replace=False)]
    metric = _inverse_sqrt(np.cov(fit.T))
    for _ in range(nonnegative_int(iterations, "iterations")):
        nearest, _ = _nearest(sample @ metric.T, protos @ metric.T)
        metric = _inverse_sqrt(np.cov((sample - protos[nearest]).T))
    # each prototype's radius: the median distance of the residual samples nearest to it (the median of all
    # of them for a prototype with fewer than MIN_ASSIGNED)
    p = protos @ metric.T
    nearest, dist = _nearest(sample @ metric.T, p)
    radii = np.full(n_prototypes, np.median(dist))
    counts = np.bincount(nearest, minlength=n_prototypes)
    for j in np.flatnonzero(counts >= MIN_ASSIGNED):
        radii[j] = np.median(dist[nearest == j])
    radii = np.maximum(radii, 1e-6 * np.median(dist) + 1e-300)
    spec = MonitorSpec(fit.shape[1], n_prototypes, 1.0, float(quantile), float(settle_time), {})
    monitor = FeatureMonitor(spec, metric, p, radii)
    threshold = float(np.quantile(monitor.distance(validation), quantile))
    record = {**dict(calibration or {}), "fit_samples": int(len(fit)), "validation_samples": int(len(validation)),
              "residual_samples": int(len(sample)), "seed": int(seed), "iterations": int(iterations)}
    spec = MonitorSpec(fit.shape[1], n_prototypes, threshold, float(quantile), float(settle_time), record)
    return FeatureMonitor(spec, metric, p, radii)


def calibrate_runs(features: Any, t: Any, *, validation_share: float = 0.2, stride: int = 2, settle_time: float = 5.0,
                   seed: int = 0, calibration: Mapping[str, Any] | None = None, **options: Any) -> FeatureMonitor:
    """:func:`calibrate` on whole runs: the first runs give the prototypes and the metric, the last the threshold.

    Parameters
    ----------
    features : array_like, shape (R, N, d)
        The decoder's features along each fitting run (for ``bank``: ``[z_k; y_k; u_k]`` from ``z_0 = 0``).
    t : array_like, shape (N,)
        Sample times of the runs.
    validation_share : float
        Share of the runs (the last ones, at least one) whose samples after ``settle_time`` set the
        threshold; the others give the prototypes and the metric.
    stride : int
        Keep every ``stride``-th sample of each run.
    settle_time : float
        See :func:`calibrate`; runs that end before it are read whole (the card records 0).
    seed, calibration, **options
        See :func:`calibrate`.

    Returns
    -------
    FeatureMonitor
    """
    features = np.asarray(features, dtype=float)
    t = np.asarray(t, dtype=float)
    if features.ndim != 3 or t.shape != features.shape[1:2] or features.shape[0] < 2:
        raise error("features, t", "runs (R >= 2, N, d) and their times (N,)",
                    Text(f"shapes {features.shape} and {t.shape}"))
    if not 0 < validation_share < 1:
        raise error("validation_share", "a number in (0, 1)", validation_share)
    stride = positive_int(stride, "stride")
    n_val = max(1, int(round(validation_share * features.shape[0])))
    n_fit = features.shape[0] - n_val
    keep = np.arange(t.size) % stride == 0
    if t[-1] < settle_time:                          # runs shorter than the settle time: all their samples
        settle_time = 0.0
    fit = features[:n_fit, keep].reshape(-1, features.shape[2])
    validation = features[n_fit:, keep & (t >= settle_time)].reshape(-1, features.shape[2])
    record = {**dict(calibration or {}), "fit_runs": int(n_fit), "validation_runs": int(n_val), "stride": stride}
    return calibrate(fit, validation, settle_time=settle_time, seed=seed, calibration=record, **options)
