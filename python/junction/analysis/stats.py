"""Intervals: Student's t over seeds (exact quantiles, as `core/src/confidence.rs`), paired
differences against a baseline of the same seed, and Wilson's score interval for a share of
agent episodes. Standard library only."""

from __future__ import annotations

import math
from typing import Iterable, Mapping, Sequence

# Two-sided 95 % quantiles of Student's t by degrees of freedom, as printed tables give them
# (kept for readers of the tables; the intervals use `t_quantile_975`, exact).
T975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306,
        9: 2.262, 10: 2.228, 15: 2.131, 20: 2.086, 30: 2.042}

# The 97.5 % point of the standard normal, and the df above which the quantile comes from
# the Cornish-Fisher expansion (as core/src/confidence.rs).
Z_95 = 1.959963984540054
EXACT_T_MAX_DF = 2000


def _central_probability(t: float, df: int) -> float:
    """P(|T| <= t) for Student's t with integer df (Abramowitz & Stegun 26.7.3-4)."""
    theta = math.atan(t / math.sqrt(df))
    sin, cos = math.sin(theta), math.cos(theta)
    cos2 = cos * cos
    total = 0.0
    if df % 2 == 1:
        term = cos
        for k in range(1, (df - 1) // 2 + 1):
            total += term
            term *= cos2 * (2 * k) / (2 * k + 1)
        return 2 / math.pi * (theta + sin * total)
    term = 1.0
    for k in range(1, df // 2 + 1):
        total += term
        term *= cos2 * (2 * k - 1) / (2 * k)
    return sin * total


def _cornish_fisher_975(df: float) -> float:
    z = Z_95
    return (z + (z ** 3 + z) / (4 * df)
            + (5 * z ** 5 + 16 * z ** 3 + 3 * z) / (96 * df ** 2)
            + (3 * z ** 7 + 19 * z ** 5 + 17 * z ** 3 - 15 * z) / (384 * df ** 3)
            + (79 * z ** 9 + 776 * z ** 7 + 1482 * z ** 5 - 1920 * z ** 3 - 945 * z)
            / (92160 * df ** 4))


def t_quantile_975(df: int) -> float:
    """The 97.5 % quantile of Student's t with df >= 1 degrees of freedom (the half-width
    multiplier of a 95 % interval), by bisection on the exact distribution function."""
    df = max(1, int(df))
    if df > EXACT_T_MAX_DF:
        return _cornish_fisher_975(df)
    low, high = 0.0, 1.0
    while _central_probability(high, df) < 0.95:
        high *= 2
    for _ in range(200):
        mid = 0.5 * (low + high)
        if _central_probability(mid, df) < 0.95:
            low = mid
        else:
            high = mid
        if high - low < 1e-13 * high:
            break
    return 0.5 * (low + high)


def t_quantile(df: int) -> float:
    """The two-sided 95 % quantile of Student's t at df degrees of freedom (exact)."""
    return t_quantile_975(df)


def mean_ci(values: Iterable[float | None]) -> tuple[float | None, float | None]:
    """Mean and half-width of the 95 % t interval over the values that are not None (a
    half-width of None where a single value gives none; (None, None) for no value)."""
    values = [v for v in values if v is not None]
    if not values:
        return None, None
    mean = sum(values) / len(values)
    if len(values) < 2:
        return mean, None
    var = sum((v - mean) ** 2 for v in values) / (len(values) - 1)
    return mean, t_quantile_975(len(values) - 1) * math.sqrt(var / len(values))


def t_interval(values: Sequence[float]) -> tuple[float, float]:
    """`mean_ci` for at least one value, with a half-width of 0 for a single one."""
    mean, half = mean_ci(values)
    if mean is None:
        raise ValueError("t_interval of no values")
    return mean, half or 0.0


def paired(arm: Mapping[int, float | None], base: Mapping[int, float | None]) -> list[float]:
    """arm − base for every seed both have a value for, in seed order."""
    return [arm[s] - base[s] for s in sorted(arm)
            if s in base and arm[s] is not None and base[s] is not None]


def paired_difference(arm: Mapping[int, float | None], base: Mapping[int, float | None]
                      ) -> tuple[float | None, float | None, int]:
    """Mean ± 95 % t half-width of arm − base over the seeds both have, and their number."""
    diffs = paired(arm, base)
    mean, half = mean_ci(diffs)
    return mean, half, len(diffs)


def wilson(successes: float, n: float, z: float = Z_95) -> tuple[float, float]:
    """Wilson's score interval for a share of n trials (n > 0)."""
    if n <= 0:
        raise ValueError("wilson of no trials")
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def fmt(values: Iterable[float | None], digits: int = 2, signed: bool = False) -> str:
    """`mean ± half-width` over the values (a dash for none, the mean alone for one)."""
    mean, half = mean_ci(values)
    if mean is None:
        return "–"
    text = f"{mean:{'+' if signed else ''}.{digits}f}"
    return text if half is None else f"{text} ± {half:.{digits}f}"


def format_number(value: float) -> str:
    """Four significant digits or so, as the report's Table 1 prints its numbers."""
    if not math.isfinite(value):
        return str(value)
    if value == 0:
        return "0"
    magnitude = math.floor(math.log10(abs(value)))
    if magnitude >= 5:
        return f"{value:.3e}"
    decimals = min(max(3 - magnitude, 0), 4)
    return f"{value:.{decimals}f}"
