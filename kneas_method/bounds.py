"""Per-material attenuation bounds ``(α_k, β_k)`` from a Gaussian mixture (SPEC §4).

Units: every value here is an attenuation in the units of the model's attenuation
output, which kneas keeps in **data units** (1/m, what the NAF volume stores; see
``model.py``), because ``α_k`` and ``β_k`` bound the model's raw attenuation
``μ̄_k = α_k · sigmoid(·) + β_k``. The mathematics is unit-free (values are
rescaled internally before fitting). Sample the prior
(NeAS-1M) model's ``mu`` at the voxel centres and pass those values to
:meth:`GMMBounds.fit`.

The paper's procedure (``method="gmm"``, the default):

1. keep the values above the air threshold;
2. fit 1-D Gaussian mixtures for K = 1..``max_components`` (scikit-learn, fixed
   ``random_state``, on at most ``max_samples`` values), pick K by the lowest BIC
   unless ``n_components`` is given; sort the components by mean;
3. ``b_0 = 0``; between adjacent components ``b_k`` is the minimum of the
   *mixture* density on the interval between their two means (dense grid);
   ``b_K = upper_factor ×`` the ``upper_percentile`` percentile of the kept values
   (with ``cover_percentile``, at least that percentile of the kept values);
4. ``β_k = b_k``, ``α_k = b_{k+1} − b_k``.

Alternatives (options beside it, never silently instead of it; SPEC §4):

* ``method="quantile"``: inner boundaries at equal-mass quantiles ``k/K`` of the
  kept values (K still from BIC unless given). Simple and robust when the
  histogram has no clear valleys (the Jaw failure of the paper).
* ``method="bayes"``: inner boundary where the two adjacent *weighted component*
  densities cross (the Bayes decision boundary between the two materials)
  instead of the mixture's minimum; it stays meaningful when a broad component
  swamps the valley.

If a boundary cannot be placed (no interior minimum / crossing), the midpoint of
the two means is used and a warning is recorded in ``warnings_`` and ``to_dict``.

Choosing K on a reconstruction rather than a trained prior (options beside the
paper's, used by the cpu preset; ``k_rule`` and ``min_std``):

* ``k_rule="bic-valleys"``: the lowest-BIC K among those whose every boundary can
  be placed by the boundary rule (for ``gmm``: a valley of the mixture density). A
  K that splits one material into two overlapping components has no valley
  between them, so it is not a K of distinct materials.
* ``k_rule="peaks"``: the materials are the peaks of the values' histogram
  (:func:`histogram_peaks`): K is their number and each inner boundary the histogram's
  lowest point between two adjacent peaks, SPEC §4's valley rule applied to the
  histogram rather than to a fitted mixture. No mixture is fitted, so nothing depends on
  ``random_state`` (the GMM rules' K can change with it). A TV-regularised
  reconstruction flattens each material into a plateau, a narrow spike in its histogram,
  so the peaks are the materials' levels; a noisy or textured volume smears them: with
  fewer than two peaks the rule falls back to ``bic-valleys`` (``k_rule_used_`` says
  which decided). With ``n_components`` given the rule is not used (as for the others).
* ``min_std``: the smallest component standard deviation, as a fraction of the
  ``upper_percentile`` value (sklearn's ``reg_covar``). A regularised reconstruction
  (TV) flattens a large material into a spike that a component of near-zero width
  fits far better in likelihood than any material boundary is worth; with a floor
  the components follow the materials instead.
"""

from __future__ import annotations

import json
import math
import warnings as _warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import ConfigError, KneasError

__all__ = ["GMMBounds", "Bounds", "load_bounds", "histogram_peaks", "DEFAULT_AIR_FRACTION", "K_RULES"]

DEFAULT_AIR_FRACTION = 0.05  # "auto" air threshold = this × the 99.5th percentile of all values
_MIN_VALUES = 50  # fewer non-air samples than this: the prior model looks empty
_GRID = 4001
K_RULES = ("bic", "bic-valleys", "peaks")
PEAK_BIN_WIDTH = 1 / 500  # histogram bin, in units of the upper percentile
PEAK_MIN_PROMINENCE = 1.5  # in log(1 + count): a peak stands >= e^1.5 ~ 4.5x above the valleys beside it
PEAK_MIN_FRACTION = 1e-4  # a peak's bin holds at least this fraction of the values


def histogram_peaks(z, *, top: float, bin_width: float = PEAK_BIN_WIDTH, min_prominence: float = PEAK_MIN_PROMINENCE,
                    min_fraction: float = PEAK_MIN_FRACTION) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Peaks of the histogram of ``z`` and the lowest points between them.

    The histogram has bins of ``bin_width`` from 0 to ``top``; its ``log(1 + count)`` is
    smoothed by ``[1, 2, 1] / 4``. A peak is a local maximum of that curve whose
    prominence (``scipy.signal.find_peaks``, the curve taken as 0 outside the range) is at
    least ``min_prominence`` and whose bin holds at least ``min_fraction`` of ``z``.

    Args:
        z: values [N], in any unit (``bin_width`` and ``top`` in the same unit).
        top: the histogram's upper end; values above it are left out.

    Returns:
        ``(peaks [P], valleys [P - 1], prominences [P])``: the peaks' bin centres
        (ascending), the bin centre of the smoothed curve's minimum between each two
        adjacent peaks (the middle one where several bins share it, e.g. an empty gap), and
        each peak's prominence.
    """
    from scipy.signal import find_peaks

    z = np.asarray(z, dtype=np.float64).reshape(-1)
    edges = np.arange(0.0, float(top) + bin_width, bin_width)
    count, _ = np.histogram(z, edges)
    centre = 0.5 * (edges[1:] + edges[:-1])
    h = np.log1p(count)
    h = np.convolve(np.r_[h[0], h, h[-1]], [0.25, 0.5, 0.25], mode="valid")
    idx, props = find_peaks(np.r_[0.0, h, 0.0], prominence=min_prominence)
    idx, prom = idx - 1, props["prominences"]
    keep = count[idx] >= min_fraction * z.size
    idx, prom = idx[keep], prom[keep]
    valleys = []
    for i, j in zip(idx[:-1], idx[1:]):
        lowest = np.flatnonzero(h[i:j + 1] == h[i:j + 1].min())
        valleys.append(i + int(lowest[lowest.size // 2]))  # the middle of a flat (e.g. empty) valley
    return centre[idx], centre[np.array(valleys, dtype=int)], prom


@dataclass(frozen=True)
class Bounds:
    """Validated per-material bounds in data units.

    Attributes:
        alphas: ``(α_1, ..., α_K)``, widths, > 0.
        betas: ``(β_1, ..., β_K)``, lower bounds, ≥ 0, strictly increasing.
    """

    alphas: tuple[float, ...]
    betas: tuple[float, ...]

    def __post_init__(self):
        a, b = self.alphas, self.betas
        if len(a) == 0 or len(a) != len(b):
            raise ConfigError(f"bounds need as many alphas as betas (at least one each), got {len(a)} alphas and {len(b)} betas")
        if not all(math.isfinite(v) for v in (*a, *b)):
            raise ConfigError("bounds contain NaN or infinite values; give finite numbers")
        if any(v <= 0 for v in a):
            raise ConfigError(f"every alpha (bound width) must be > 0, got alphas {list(a)}")
        if any(v < 0 for v in b):
            raise ConfigError(f"every beta (lower bound) must be >= 0, got betas {list(b)}")
        if any(b[k + 1] <= b[k] for k in range(len(b) - 1)):
            raise ConfigError(f"betas must be strictly increasing (materials ordered by attenuation), got {list(b)}")

    @property
    def K(self) -> int:
        return len(self.alphas)

    @property
    def boundaries(self) -> tuple[float, ...]:
        """``b_0..b_K`` when the intervals tile (``b_k = β_k``, ``b_K = β_K + α_K``)."""
        return (*self.betas, self.betas[-1] + self.alphas[-1])

    def to_dict(self) -> dict:
        return {"K": self.K, "alphas": list(self.alphas), "betas": list(self.betas)}


def _as_bounds(d) -> Bounds:
    if not isinstance(d, dict):
        raise ConfigError(f"bounds must be a JSON object with 'alphas' and 'betas' (or 'boundaries'), got {type(d).__name__}")
    try:
        if "alphas" in d and "betas" in d:
            alphas = tuple(float(v) for v in d["alphas"])
            betas = tuple(float(v) for v in d["betas"])
        elif "boundaries" in d:
            bnd = [float(v) for v in d["boundaries"]]
            if len(bnd) < 2:
                raise ConfigError(f"'boundaries' needs at least 2 values (b_0 < b_1), got {bnd}")
            if any(bnd[k + 1] <= bnd[k] for k in range(len(bnd) - 1)):
                raise ConfigError(f"'boundaries' must be strictly increasing, got {bnd}")
            betas = tuple(bnd[:-1])
            alphas = tuple(bnd[k + 1] - bnd[k] for k in range(len(bnd) - 1))
        else:
            raise ConfigError("bounds need 'alphas' and 'betas' lists (or one 'boundaries' list); add them to the bounds file")
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"bounds values must be lists of numbers ({exc}); fix the bounds file") from None
    if "K" in d and int(d["K"]) != len(alphas):
        raise ConfigError(f"bounds say K = {d['K']} but list {len(alphas)} materials; make them agree")
    return Bounds(alphas, betas)


def load_bounds(path) -> Bounds:
    """Read and validate a user-given bounds JSON file (``{"alphas": [...], "betas": [...]}``
    or ``{"boundaries": [...]}``, data units), e.g. one written by ``GMMBounds.to_dict``."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"bounds file {p} does not exist; give the path of a JSON file with 'alphas' and 'betas'")
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"bounds file {p} is not valid JSON ({exc.__class__.__name__}); fix or regenerate it") from None
    return _as_bounds(d)


def _normal_pdf(x, mean, std):
    return np.exp(-0.5 * ((x - mean) / std) ** 2) / (std * math.sqrt(2 * math.pi))


class GMMBounds:
    """GMM attenuation-bound estimator (scikit-learn estimator shape).

    Args:
        n_components: K to use; ``None`` picks K by the lowest BIC over 1..max_components.
        max_components: the largest K tried.
        air_threshold: values ≤ this are air and dropped, data units; ``"auto"``
            uses ``DEFAULT_AIR_FRACTION`` (5 %) of the 99.5th percentile of all
            values (scale-free, so it works in any unit).
        upper_percentile, upper_factor: ``b_K = upper_factor × percentile``.
        cover_percentile: ``b_K`` is at least this percentile of the kept values (0 = no floor), so
            the last material holds what the volume shows: a real scan's bone and contrast are a thin
            tail, 0.1-0.3 % of its values, reaching twice ``upper_factor`` x the 99.5th percentile, while
            on a piecewise-constant volume only its edges' overshoot (under 0.05 %) lies above that. The
            histogram's unit (``unit_``) stays the ``upper_percentile`` value.
        random_state: seed for subsampling and for the GaussianMixture fits.
        max_samples: at most this many kept values are used for the fits.
        method: ``"gmm"`` (paper: mixture-density valleys), ``"quantile"`` or
            ``"bayes"`` (see module docstring).
        n_init: GaussianMixture restarts per K.
        k_rule: ``"bic"`` (paper: the lowest BIC), ``"bic-valleys"`` (the lowest BIC
            among K whose boundaries can all be placed) or ``"peaks"`` (the histogram's
            peaks and the valleys between them, no mixture; see module docstring).
        min_std: smallest component standard deviation as a fraction of the
            ``upper_percentile`` value (scale-free); 0 = sklearn's default regulariser.

    Fitted attributes: ``n_components_``, ``boundaries_ [K+1]``, ``alphas_ [K]``,
    ``betas_ [K]``, ``means_ [K]``, ``stds_ [K]``, ``weights_ [K]`` (sorted by mean),
    ``bic_`` (``{K: BIC}``, in the units of the input values), ``placeable_`` (``{K: bool}``,
    every boundary placed by the rule; filled for each K tried under ``bic-valleys``), ``gmm_`` (the chosen
    ``sklearn.mixture.GaussianMixture``, fitted on values divided by ``unit_``; None when the
    ``peaks`` rule placed the bounds), ``k_rule_used_`` (the rule that chose K), ``peaks_`` (the
    histogram's peaks, data units, under the ``peaks`` rule), ``cover_`` (the ``cover_percentile`` value of
    the kept values, data units; 0 when none),
    ``air_threshold_``, ``n_values_``, ``n_kept_``, ``warnings_``, ``kept_`` (the
    values used for the fits).
    """

    def __init__(
        self,
        n_components: int | None = None,
        max_components: int = 4,
        air_threshold: float | str = "auto",
        upper_percentile: float = 99.5,
        upper_factor: float = 1.15,
        random_state: int = 0,
        max_samples: int = 200_000,
        method: str = "gmm",
        n_init: int = 1,
        k_rule: str = "bic",
        min_std: float = 0.0,
        cover_percentile: float = 0.0,
    ):
        self.n_components = n_components
        self.max_components = max_components
        self.air_threshold = air_threshold
        self.upper_percentile = upper_percentile
        self.upper_factor = upper_factor
        self.random_state = random_state
        self.max_samples = max_samples
        self.method = method
        self.n_init = n_init
        self.k_rule = k_rule
        self.min_std = min_std
        self.cover_percentile = cover_percentile

    # ------------------------------------------------------------- settings
    def _check_settings(self):
        if self.method not in ("gmm", "quantile", "bayes"):
            raise ConfigError(f"bounds method {self.method!r} is not known; use 'gmm' (paper), 'quantile' or 'bayes'")
        if self.k_rule not in K_RULES:
            raise ConfigError(f"bounds K rule {self.k_rule!r} is not known; use 'bic' (paper), 'bic-valleys' or 'peaks'")
        if self.k_rule == "peaks" and self.n_components is None and self.method != "gmm":
            raise ConfigError(f"the 'peaks' K rule places its own boundaries (the histogram's valleys), so method {self.method!r} "
                              "would not be used; use method 'gmm' with it, or another K rule")
        if not (isinstance(self.min_std, (int, float, np.integer, np.floating)) and not isinstance(self.min_std, bool)
                and math.isfinite(self.min_std) and 0 <= self.min_std < 1):
            raise ConfigError(f"min_std must be a fraction in [0, 1) of the upper percentile, got {self.min_std!r}")
        if not (isinstance(self.max_components, int) and self.max_components >= 1):
            raise ConfigError(f"max_components must be an integer >= 1, got {self.max_components!r}")
        if self.n_components is not None and not (isinstance(self.n_components, (int, np.integer)) and self.n_components >= 1):
            raise ConfigError(f"n_components must be a positive integer or None (pick by BIC), got {self.n_components!r}")
        if not (isinstance(self.cover_percentile, (int, float, np.integer, np.floating)) and not isinstance(self.cover_percentile, bool)
                and 0 <= self.cover_percentile <= 100):
            raise ConfigError(f"cover_percentile must be a percentile in [0, 100] (0 = none), got {self.cover_percentile!r}")
        if not (0 < self.upper_percentile <= 100):
            raise ConfigError(f"upper_percentile must be in (0, 100], got {self.upper_percentile}")
        if not self.upper_factor > 0:
            raise ConfigError(f"upper_factor must be > 0, got {self.upper_factor}")
        if not (self.air_threshold == "auto" or (isinstance(self.air_threshold, (int, float, np.integer, np.floating))
                                                 and not isinstance(self.air_threshold, bool))):
            raise ConfigError(f"air_threshold must be a number (data units) or 'auto', got {self.air_threshold!r}")

    def get_params(self) -> dict:
        return {k: getattr(self, k) for k in ("n_components", "max_components", "air_threshold", "upper_percentile",
                                               "upper_factor", "random_state", "max_samples", "method", "n_init",
                                               "k_rule", "min_std", "cover_percentile")}

    # ------------------------------------------------------------------ fit
    def _keep(self, values) -> np.ndarray:
        """The finite values above the air threshold (sets ``n_values_``, ``air_threshold_``,
        ``n_kept_``); one-line KneasError when none or too few are."""
        if hasattr(values, "detach"):
            values = values.detach().cpu().numpy()
        x = np.asarray(values, dtype=np.float64).reshape(-1)
        x = x[np.isfinite(x)]
        self.n_values_ = int(x.size)
        if x.size == 0:
            raise KneasError("no finite attenuation values to fit bounds on; the prior model output is empty or NaN — "
                             "retrain the single-material prior or give bounds by hand")
        if self.air_threshold == "auto":
            self.air_threshold_ = DEFAULT_AIR_FRACTION * float(np.percentile(x, 99.5))
        else:
            self.air_threshold_ = float(self.air_threshold)
        kept = x[x > self.air_threshold_]
        self.n_kept_ = int(kept.size)
        if kept.size < _MIN_VALUES:
            raise KneasError(
                f"only {kept.size} of {x.size} attenuation values lie above the air threshold {self.air_threshold_:.4g}: "
                "the prior model looks empty — train the single-material prior longer, lower air_threshold, or give bounds by hand")
        return kept

    def fit(self, values, fallback=None, fallback_name: str = "the fallback values") -> "GMMBounds":
        """Fit on attenuation samples (any shape, numpy or torch), data units.

        Args:
            values: the samples.
            fallback: under the ``peaks`` rule, the values the mixtures are fitted on when
                ``values``' histogram has fewer than two peaks (e.g. the same volume after an
                edge-preserving filter, which flattens noise into plateaus), or a function of no
                arguments that returns them (called only then); None = ``values`` themselves.
            fallback_name: what the fallback values are, as ``k_rule_used_`` names them.

        Raises:
            KneasError: when fewer than 50 values lie above the air threshold
                (the prior model looks empty), or boundaries cannot be made
                strictly increasing.
        """
        from sklearn.mixture import GaussianMixture

        self._check_settings()
        kept = self._keep(values)
        self.warnings_: list[str] = []
        self.k_rule_used_ = "given" if self.n_components is not None else self.k_rule
        self.peaks_ = []
        if self.k_rule == "peaks" and self.n_components is None:
            # on every kept value (no subsample), so nothing depends on random_state
            unit = float(np.percentile(kept, self.upper_percentile)) or 1.0
            peaks, valleys, _ = histogram_peaks(kept / unit, top=self.upper_factor)
            self.peaks_ = [float(v) for v in peaks * unit]
            if peaks.size >= 2:
                return self._adopt_peaks(kept, unit, peaks * unit, valleys * unit)
            count = f"the histogram has {peaks.size} peak{'s' if peaks.size != 1 else ''}"
            self.k_rule_used_ = f"bic-valleys ({count})"
            if fallback is not None:
                kept = self._keep(fallback() if callable(fallback) else fallback)
                self.k_rule_used_ = f"bic-valleys on {fallback_name} ({count})"
        self.cover_ = self._cover(kept)
        rng = np.random.default_rng(self.random_state)
        if kept.size > self.max_samples:
            kept = rng.choice(kept, size=self.max_samples, replace=False)
        self.kept_ = kept

        percentile = float(np.percentile(kept, self.upper_percentile))
        upper = self._top(percentile)
        # Fit on values in units of the upper percentile so the sklearn covariance
        # regulariser (1e-6, or min_std squared) means the same whatever the attenuation unit.
        self.unit_ = percentile or 1.0
        z = (kept / self.unit_).reshape(-1, 1)
        n_unique = np.unique(z).size
        ks = [k for k in range(1, self.max_components + 1) if k <= n_unique]
        reg_covar = max(1e-6, float(self.min_std) ** 2)  # z is in units of the upper percentile
        self.bic_: dict[int, float] = {}
        self.placeable_: dict[int, bool] = {}
        models = {}

        def fit_k(k: int):
            gm = GaussianMixture(n_components=k, covariance_type="full", random_state=self.random_state, n_init=self.n_init,
                                 reg_covar=reg_covar)
            with _warnings.catch_warnings():
                _warnings.simplefilter("ignore")  # ConvergenceWarning on tiny inputs; the BIC still compares
                gm.fit(z)
            models[k] = gm
            # BIC in the units of the input values: log-likelihood shifts by -n·log(unit)
            self.bic_[k] = float(gm.bic(z) + 2 * z.shape[0] * math.log(self.unit_))

        for k in ks:
            fit_k(k)
        if self.n_components is not None:
            k = int(self.n_components)
            if k not in models:
                if k > n_unique:
                    raise KneasError(f"n_components={k} but the samples hold only {n_unique} distinct values; choose fewer materials")
                fit_k(k)
            inner = self._adopt(models[k], k, kept)
        elif self.k_rule == "bic":  # the lowest BIC whose boundaries lie below the upper bound (see bic-valleys)
            skipped = []
            for k in sorted(self.bic_, key=self.bic_.get):
                inner = self._adopt(models[k], k, kept)
                if not inner or inner[-1] < upper:
                    break
                skipped.append(k)
            if skipped:
                self.warnings_.append(f"K = {', '.join(map(str, skipped))} (lower BIC) put a boundary above the upper bound "
                                      f"{upper:.4g}; K = {k} used")
        else:  # bic-valleys: the lowest BIC among the K whose boundaries can all be placed
            for k in sorted(self.bic_, key=self.bic_.get):
                inner = self._adopt(models[k], k, kept)
                # every boundary a valley, and below the upper bound (a tail of extreme values, e.g. the end
                # slices of a scan truncated along its axis, can put a component's valley above it)
                self.placeable_[k] = not self.warnings_ and (not inner or inner[-1] < upper)
                if self.placeable_[k]:
                    break

        return self._set_boundaries(np.array([0.0, *inner, upper]))

    def _adopt_peaks(self, kept: np.ndarray, unit: float, peaks: np.ndarray, valleys: np.ndarray) -> "GMMBounds":
        """The ``peaks`` rule's result: one material per histogram peak (data units), the
        valleys between them as inner boundaries; ``means_`` are the peaks, ``weights_`` and
        ``stds_`` the share and spread of the kept values between each material's boundaries."""
        self.gmm_ = None
        self.bic_, self.placeable_ = {}, {}
        self.unit_ = unit
        self.kept_ = kept
        self.n_components_ = int(peaks.size)
        self.cover_ = self._cover(kept)
        b = np.array([0.0, *valleys, self._top(unit)])
        self.means_ = np.asarray(peaks, dtype=np.float64)
        which = np.clip(np.searchsorted(b, kept, side="right") - 1, 0, peaks.size - 1)
        self.weights_ = np.bincount(which, minlength=peaks.size) / kept.size
        self.stds_ = np.array([kept[which == k].std() if np.any(which == k) else 0.0 for k in range(peaks.size)])
        return self._set_boundaries(b)

    def _cover(self, kept: np.ndarray) -> float:
        """The ``cover_percentile`` value of ``kept`` (data units); 0 when the floor is off."""
        return float(np.percentile(kept, self.cover_percentile)) if self.cover_percentile > 0 else 0.0

    def _top(self, percentile: float) -> float:
        """``b_K`` from the ``upper_percentile`` value (data units): ``upper_factor`` times it, at least
        ``cover_`` (the ``cover_percentile`` value of all kept values, before any subsampling)."""
        return max(self.upper_factor * percentile, self.cover_)

    def _set_boundaries(self, b: np.ndarray) -> "GMMBounds":
        if b[-1] <= b[-2]:
            raise KneasError(
                f"upper bound {b[-1]:.4g} does not exceed the last inner boundary {b[-2]:.4g}; "
                "use fewer materials (n_components) or a larger upper_factor")
        if np.any(np.diff(b) <= 0):
            raise KneasError(f"bound boundaries are not strictly increasing ({np.round(b, 6).tolist()}); "
                             "raise the air threshold or use fewer materials (n_components)")
        self.boundaries_ = b
        self.betas_ = b[:-1].copy()
        self.alphas_ = np.diff(b)
        for w in self.warnings_:
            _warnings.warn(w, stacklevel=3)
        return self

    def _adopt(self, gm, k: int, kept: np.ndarray) -> list[float]:
        """Make ``gm`` (K = ``k``, fitted on values / ``unit_``) the chosen mixture: sets
        ``gmm_``, ``n_components_``, ``means_``, ``stds_``, ``weights_`` (sorted by mean) and
        ``warnings_``; returns its inner boundaries (data units)."""
        self.gmm_ = gm
        self.n_components_ = k
        order = np.argsort(gm.means_[:, 0])
        self.means_ = gm.means_[order, 0] * self.unit_
        self.stds_ = np.sqrt(gm.covariances_[order, 0, 0]) * self.unit_
        self.weights_ = gm.weights_[order].copy()
        self.warnings_ = []
        return self._inner_boundaries(kept)

    def _inner_boundaries(self, kept: np.ndarray) -> list[float]:
        K = self.n_components_
        if K == 1:
            return []
        if self.method == "quantile":
            q = np.quantile(kept, np.arange(1, K) / K)
            out = []
            for k, v in enumerate(q):
                lo = out[-1] if out else 0.0
                if not v > lo:
                    v = 0.5 * (self.means_[k] + self.means_[k + 1])
                    self.warnings_.append(f"quantile boundary {k + 1} coincided with the previous one; used the midpoint of the means")
                out.append(float(v))
            return out
        out = []
        for k in range(K - 1):
            m0, m1 = self.means_[k], self.means_[k + 1]
            grid = np.linspace(m0, m1, _GRID)
            if self.method == "gmm":
                dens = self.density(grid)
                i = int(np.argmin(dens))
                ok = 0 < i < _GRID - 1
                what = "the mixture density has no valley between"
            else:  # bayes: the weighted densities of components k and k+1 cross
                diff = (self.weights_[k] * _normal_pdf(grid, m0, self.stds_[k])
                        - self.weights_[k + 1] * _normal_pdf(grid, m1, self.stds_[k + 1]))
                cross = np.nonzero(np.diff(np.sign(diff)) != 0)[0]
                i = int(cross[0]) + 1 if cross.size else 0
                ok = cross.size > 0 and 0 < i < _GRID - 1
                what = "the weighted component densities do not cross between"
            if ok:
                out.append(float(grid[i]))
            else:
                out.append(float(0.5 * (m0 + m1)))
                self.warnings_.append(f"{what} components {k + 1} and {k + 2} (means {m0:.4g}, {m1:.4g}); boundary {k + 1} set to their midpoint")
        return out

    # ------------------------------------------------------------- queries
    def _check_fitted(self):
        if not hasattr(self, "boundaries_"):
            raise KneasError("GMMBounds is not fitted yet; call fit(values) first")

    def density(self, x) -> np.ndarray:
        """Mixture density at ``x`` (data units) -> same shape, 1/(model attenuation unit).
        Under the ``peaks`` rule (no mixture) it is the normal mixture of the materials'
        shares, peaks and spreads, a summary rather than a fit."""
        x = np.asarray(x, dtype=np.float64)
        return sum(w * _normal_pdf(x, m, s) for w, m, s in zip(self.weights_, self.means_, self.stds_))

    def to_dict(self) -> dict:
        """JSON-able summary: K, alphas, betas, boundaries, bic, means, stds, weights,
        warnings, settings (all attenuations in data units)."""
        self._check_fitted()
        return {
            "K": int(self.n_components_),
            "alphas": [float(v) for v in self.alphas_],
            "betas": [float(v) for v in self.betas_],
            "boundaries": [float(v) for v in self.boundaries_],
            "bic": {str(k): float(v) for k, v in sorted(self.bic_.items())},
            "placeable": {str(k): bool(v) for k, v in sorted(self.placeable_.items())},
            "k_rule_used": self.k_rule_used_,
            "peaks": list(self.peaks_),
            "means": [float(v) for v in self.means_],
            "stds": [float(v) for v in self.stds_],
            "weights": [float(v) for v in self.weights_],
            "warnings": list(self.warnings_),
            "units": "data units (1/m)",
            "settings": {**self.get_params(), "air_threshold_used": self.air_threshold_, "n_values": self.n_values_,
                         "n_kept": self.n_kept_},
        }

    @staticmethod
    def from_dict(d) -> Bounds:
        """Validated :class:`Bounds` from a ``to_dict`` result or a user bounds dict
        (``alphas``/``betas`` or ``boundaries``); one-line ``ConfigError`` if invalid."""
        return _as_bounds(d)

    def plot(self, path, values=None, *, bins: int = 200, title: str | None = None) -> Path:
        """Histogram of the values with the fitted mixture density, its weighted
        components and the boundaries; writes a PNG (matplotlib Agg) and returns its path.

        Args:
            path: output PNG path.
            values: values to histogram (default: the kept values used for the fit);
                values at or below the air threshold are left out.
        """
        self._check_fitted()
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        if values is None:
            v = self.kept_
        else:
            if hasattr(values, "detach"):
                values = values.detach().cpu().numpy()
            v = np.asarray(values, dtype=np.float64).reshape(-1)
            v = v[np.isfinite(v) & (v > self.air_threshold_)]
        fig = Figure(figsize=(7, 4), dpi=110)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot()
        hi = max(float(self.boundaries_[-1]), float(v.max()) if v.size else 1.0)
        ax.hist(v, bins=bins, range=(0, hi), density=True, color="0.75", label="samples (non-air)")
        grid = np.linspace(0, hi, 1000)
        if self.gmm_ is None:  # the peaks rule: no mixture, the materials are the histogram's peaks
            for k, m in enumerate(self.means_):
                ax.axvline(m, color="tab:blue", lw=1, ls="--", label="histogram peaks" if k == 0 else None)
        else:
            ax.plot(grid, self.density(grid), "k", lw=2.5, alpha=0.6, label=f"mixture (K={self.n_components_})")
            for k, (w, m, s) in enumerate(zip(self.weights_, self.means_, self.stds_)):
                ax.plot(grid, w * _normal_pdf(grid, m, s), lw=1.2, ls="--", label=f"component {k + 1}")
        for k, b in enumerate(self.boundaries_):
            ax.axvline(b, color="tab:red", lw=1, alpha=0.8, label="boundaries $b_k$" if k == 0 else None)
        ax.set_xlabel("attenuation (data units)")
        ax.set_ylabel("density")
        ax.set_title(title or ("attenuation bounds (histogram peaks)" if self.gmm_ is None else f"GMM attenuation bounds ({self.method})"))
        ax.legend(fontsize=7)
        fig.tight_layout()
        out = Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, format="png")
        return out
