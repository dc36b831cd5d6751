"""The report's statistics over runs: the interquartile mean and the probability of improvement
(Agarwal et al. 2021, ``rliable``), their percentile-bootstrap CIs, the permutation test of a
difference of means (``scipy``), Holm's correction, the smallest shift that corrected test would
call, and the paired count of a run's two policies.

Bootstrap CIs are percentile intervals. They are exact where the resamples are few: every one of
the n^n resamples of a row of n runs (3,125 for 5 runs; n^n x m^m pairs of resamples for the
probability of improvement of two rows, 9,765,625 for 5 and 5, taken as the distinct multisets of
runs weighted by how many resamples give each) is enumerated, and the CI ends are the 2.5% and
97.5% quantiles of the statistic over them (the smallest value with at least that share of the
resamples at or below it: numpy's ``inverted_cdf``). rliable and ``scipy.stats.bootstrap`` only
draw resamples at random, hence the enumeration here. Where the resamples are more than
``EXACT_BOOTSTRAP_LIMIT``, ``BOOTSTRAP_DRAWS`` random resamples (rliable's default) are drawn from
a fixed seed; across tasks (:func:`stratified_interval`) the runs are resampled within each task,
as rliable's ``StratifiedBootstrap`` does, but vectorised: rliable calls the statistic once per
resample in Python, minutes for 50,000 resamples.
"""
from __future__ import annotations

import itertools
import math
import warnings

import numpy as np

EXACT_BOOTSTRAP_LIMIT = 10_000_000  # resamples (pairs of resamples for two rows) enumerated; beyond, random draws
BOOTSTRAP_DRAWS = 50_000  # rliable's default
EXACT_PERMUTATIONS = 1_000_000  # up to this many relabelings the permutation test enumerates them all
SIGNIFICANCE = 0.05  # a difference is called one when its Holm-corrected p is below this
QUANTILES = (0.025, 0.975)
QUANTILE_METHOD = "inverted_cdf"


def _rliable():
    from rliable import library, metrics

    return library, metrics


def exact_resamples(n: int) -> np.ndarray:
    """Every resample with replacement of n runs, as indices: the n^n rows of ``itertools.product(range(n), repeat=n)``."""
    return np.stack(np.unravel_index(np.arange(n ** n), (n,) * n), axis=1)


def resample_multisets(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The distinct resamples of n runs as counts (how often each run appears; C(2n - 1, n) rows,
    126 for 5 runs) and how many of the n^n ordered resamples give each."""
    indices = exact_resamples(n)
    counts = (indices[:, :, None] == np.arange(n)).sum(axis=1)
    return np.unique(counts, axis=0, return_counts=True)


def weighted_quantiles(values, weights, quantiles=QUANTILES) -> np.ndarray:
    """Quantiles of a discrete distribution with integer ``weights``: the smallest value with at
    least q of the weight at or below it (``np.quantile(np.repeat(values, weights), q,
    method="inverted_cdf")`` without repeating)."""
    values, weights = np.ravel(values), np.ravel(weights)
    order = np.argsort(values, kind="stable")
    cumulative = np.cumsum(weights[order])
    positions = [np.searchsorted(cumulative, q * cumulative[-1], side="left") for q in quantiles]
    return values[order][positions]


def _is_exact(*sizes: int) -> bool:
    return math.prod(n ** n for n in sizes) <= EXACT_BOOTSTRAP_LIMIT


def bootstrap_method(*sizes: int) -> str:
    """How a CI over rows of these sizes is computed, for the tables' notes."""
    total = math.prod(n ** n for n in sizes)
    return f"exact, all {total:,} resamples" if total <= EXACT_BOOTSTRAP_LIMIT else f"{BOOTSTRAP_DRAWS:,} random resamples"


def interquartile_mean(values) -> float:
    """Mean of the middle 50% of the runs (rliable's ``aggregate_iqm``)."""
    _, metrics = _rliable()
    return float(metrics.aggregate_iqm(np.asarray(values, dtype=float).reshape(-1, 1)))


def iqm_confidence_interval(values, seed: int = 0) -> tuple[float, float]:
    """95% percentile-bootstrap CI of the IQM over runs: exact (every resample) up to
    ``EXACT_BOOTSTRAP_LIMIT`` resamples, else ``BOOTSTRAP_DRAWS`` random ones. NaN with fewer than 2 distinct values."""
    from scipy import stats

    values = np.asarray(values, dtype=float).ravel()
    if values.size < 2 or np.unique(values).size < 2:
        return math.nan, math.nan
    if _is_exact(values.size):
        iqms = stats.trim_mean(values[exact_resamples(values.size)], 0.25, axis=1)  # rliable's aggregate_iqm, per resample
        low, high = np.quantile(iqms, QUANTILES, method=QUANTILE_METHOD)
        return float(low), float(high)
    _, low, high = stratified_interval([values.reshape(-1, 1)], aggregate_iqm, seed)
    return low, high


def probability_of_improvement(x, y, seed: int = 0) -> tuple[float, float, float]:
    """P(X > Y) for a run of X and a run of Y drawn at random (ties count half; rliable's
    Mann-Whitney statistic), with its 95% percentile-bootstrap CI: exact over every pair of
    resamples of x and y up to ``EXACT_BOOTSTRAP_LIMIT`` pairs, else ``BOOTSTRAP_DRAWS`` random
    ones. NaN CI with fewer than 2 runs on either side."""
    x, y = (np.asarray(v, dtype=float).ravel() for v in (x, y))
    _, metrics = _rliable()
    point = float(metrics.probability_of_improvement(x.reshape(-1, 1), y.reshape(-1, 1)))
    if len(x) < 2 or len(y) < 2:
        return point, math.nan, math.nan
    if _is_exact(len(x), len(y)):
        wins = (x[:, None] > y[None, :]) + 0.5 * (x[:, None] == y[None, :])  # run of x against run of y
        (a, wa), (b, wb) = resample_multisets(len(x)), resample_multisets(len(y))
        # a pair of resamples with counts a (of x) and b (of y) has P = a @ wins @ b / (n m)
        low, high = weighted_quantiles(a @ wins @ b.T / (len(x) * len(y)), np.outer(wa, wb))
        return point, float(low), float(high)
    _, low, high = stratified_interval([x.reshape(-1, 1), y.reshape(-1, 1)], aggregate_probability_of_improvement, seed)
    return point, low, high


def stratified_interval(matrices, statistic, seed: int = 0) -> tuple[float, float, float]:
    """Point estimate and 95% percentile CI of ``statistic(*matrices)`` (each runs x tasks) over
    ``BOOTSTRAP_DRAWS`` stratified resamples: within each matrix, the runs of each task are drawn
    with replacement, independently per task. ``statistic`` takes arrays (draws x runs x tasks)
    and gives one value per draw."""
    rng = np.random.default_rng(seed)
    matrices = [np.asarray(m, dtype=float) for m in matrices]
    point = float(statistic(*(m[None] for m in matrices))[0])
    resampled = []
    for m in matrices:
        indices = rng.integers(0, m.shape[0], size=(BOOTSTRAP_DRAWS, *m.shape))
        resampled.append(np.take_along_axis(np.broadcast_to(m, indices.shape), indices, axis=1))
    low, high = np.quantile(statistic(*resampled), QUANTILES)
    return point, float(low), float(high)


def aggregate_iqm(scores: np.ndarray) -> np.ndarray:
    """rliable's ``aggregate_iqm`` of each of a stack of score matrices (draws x runs x tasks): the
    25%-trimmed mean of all runs x tasks."""
    from scipy import stats

    return stats.trim_mean(scores.reshape(len(scores), -1), 0.25, axis=1)


def aggregate_probability_of_improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """rliable's ``probability_of_improvement`` of stacks of score matrices (draws x runs x tasks):
    per task P(run of x > run of y), ties counting half, averaged over tasks."""
    above = (x[:, :, None, :] > y[:, None, :, :]) + 0.5 * (x[:, :, None, :] == y[:, None, :, :])
    return above.mean(axis=(1, 2, 3))


def paired_comparison(x, y) -> dict:
    """Two policies of the same runs (run i gives ``x[i]`` and ``y[i]``): how many runs have x
    above, equal to (bit for bit) and below y, and the share of runs with x above, ties counting
    half. A count, not a test."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if x.shape != y.shape:
        raise ValueError(f"paired samples need one value each per run: {x.shape} vs {y.shape}")
    above, ties = int(np.sum(x > y)), int(np.sum(x == y))
    below = len(x) - above - ties
    return {"runs": len(x), "above": above, "ties": ties, "below": below, "probability": (above + ties / 2) / len(x) if len(x) else math.nan}


def _mean_difference(x, y, axis=-1):
    return np.mean(x, axis=axis) - np.mean(y, axis=axis)


def permutation_test(x, y, seed: int = 0) -> tuple[float, int, bool]:
    """Two-sided permutation test of the difference of means of two independent samples
    (``scipy.stats.permutation_test``, ``permutation_type="independent"``). Exact, over every
    one of the C(n + m, n) relabelings, when they number at most ``EXACT_PERMUTATIONS`` (252 for
    5 vs 5); else 100,000 random relabelings. Returns (p, relabelings used, exact). scipy's
    two-sided p is twice the smaller one-sided p, capped at 1: 2/252 for two fully separated
    5-vs-5 samples. A sample of one run is not tested (scipy needs two): (NaN, 0, False)."""
    from scipy import stats

    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if len(x) < 2 or len(y) < 2:
        return math.nan, 0, False
    relabelings = math.comb(len(x) + len(y), len(x))
    exact = relabelings <= EXACT_PERMUTATIONS
    result = stats.permutation_test((x, y), _mean_difference, permutation_type="independent", vectorized=True,
                                    n_resamples=np.inf if exact else 100_000, alternative="two-sided", rng=np.random.default_rng(seed))
    return float(result.pvalue), relabelings if exact else 100_000, exact


def smallest_called_shift(x, y, others=(), alpha: float = SIGNIFICANCE) -> float:
    """What the exact test of :func:`permutation_test` could have called, given the runs: the
    smallest shift d (signed, smallest in size) such that adding d to every run of ``x`` makes the
    test, Holm-corrected together with the family's other p-values ``others`` as they are, call
    the difference (corrected p < ``alpha``). Every shift beyond d (further from 0, same sign) is
    called too; d itself may not be (the boundary is where one relabeling ties the observed
    statistic). 0 where the difference is called as it is; inf where no shift can be (the
    smallest possible p, corrected, is not below ``alpha``); NaN where the test is not exact or
    not run (a row of one run).

    Shifting x by d moves each relabeling's difference of means by d (n_x_in_A / n - n_x_in_B / m),
    the observed one by d: the one-sided counts change only where a relabeling's statistic crosses
    the observed one, at d_i = (T_i - T_obs) / (1 - c_i). scipy's two-sided p is 2 min(G, L) / N
    (G, L: relabelings at or above, at or below the observed); the corrected test calls when
    min(G, L) <= k, the largest k whose p = 2k / N Holm calls. G <= k beyond the k-th largest d_i,
    L <= k below the k-th smallest."""
    x, y = np.asarray(x, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()
    n, m = len(x), len(y)
    total = math.comb(n + m, n)
    if n < 2 or m < 2 or total > EXACT_PERMUTATIONS:
        return math.nan
    others = np.asarray(others, dtype=float).ravel()
    called = [k for k in range(1, total // 2 + 1) if holm(np.r_[2 * k / total, others])[0] < alpha]
    if not called:
        return math.inf
    k = max(called)  # Holm's adjusted p grows with the raw p: every count up to k is called
    pooled = np.r_[x, y]
    groups = np.array(list(itertools.combinations(range(n + m), n)))  # group A of each relabeling: the identity first
    in_a = np.zeros((total, n + m), dtype=bool)
    np.put_along_axis(in_a, groups, True, axis=1)
    statistic = (in_a @ pooled) / n - (~in_a @ pooled) / m
    slope = in_a[:, :n].sum(axis=1) / n - (~in_a[:, :n]).sum(axis=1) / m  # 1 for the identity only
    crossings = np.sort((statistic[1:] - statistic[0]) / (1 - slope[1:]))
    up, down = crossings[-k] if k <= len(crossings) else -math.inf, crossings[k - 1] if k <= len(crossings) else math.inf
    if up < 0 or down > 0:
        return 0.0
    return float(up) if up <= -down else float(down)


def holm(pvalues) -> np.ndarray:
    """Holm's step-down adjusted p-values (Holm 1979): the i-th smallest of m p-values times
    (m - i + 1), made non-decreasing in that order, capped at 1. Rejecting where the adjusted p is
    below alpha controls the family-wise error rate at alpha."""
    p = np.asarray(pvalues, dtype=float)
    order = np.argsort(p, kind="stable")
    adjusted = np.minimum(1.0, np.maximum.accumulate(p[order] * (len(p) - np.arange(len(p)))))
    out = np.empty_like(adjusted)
    out[order] = adjusted
    return out


def mean_band(values: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean over seeds (axis 0) and its 95% percentile-bootstrap CI: exact over every resample of
    the seeds up to ``EXACT_BOOTSTRAP_LIMIT``, else ``scipy.stats.bootstrap`` with
    ``BOOTSTRAP_DRAWS`` resamples. The band is the mean itself where the seeds agree or there is one seed."""
    from scipy import stats

    values = np.asarray(values, dtype=float)
    mean = values.mean(axis=0)
    if len(values) < 2:
        return mean, mean, mean
    if _is_exact(len(values)):
        means = values[exact_resamples(len(values))].mean(axis=1)  # resamples x iterations
        low, high = np.quantile(means, QUANTILES, axis=0, method=QUANTILE_METHOD)
    else:
        with warnings.catch_warnings(), np.errstate(invalid="ignore"):
            warnings.simplefilter("ignore")
            ci = stats.bootstrap((values,), np.mean, axis=0, vectorized=True, method="percentile", n_resamples=BOOTSTRAP_DRAWS, rng=np.random.default_rng(seed)).confidence_interval
        low, high = np.where(np.isfinite(ci.low), ci.low, mean), np.where(np.isfinite(ci.high), ci.high, mean)
    return mean, np.minimum(low, mean), np.maximum(high, mean)
