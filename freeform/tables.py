"""Tables of figures, the one copy every writer of results uses (``freeform-control``, the figure commands, the
lab): the 99 % bands of the paper's statistics and CSV rows in and out.

A band is ``mean ± z·sd/√n`` (sd with Bessel's correction): normal (the paper's "99 % Normal confidence interval",
over thousands of episodes) for a mean, Student's t for paired differences over tens of bodies.
"""

from __future__ import annotations

import csv
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

Z_99 = 2.576
"""Two-sided 99 % quantile of the standard normal: the paper's "99 % Normal confidence interval"."""


def mean_band(values: np.ndarray, axis: int = 0, z: float = Z_99, ddof: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Mean and confidence half-width ``z·sd/√n`` along ``axis``.

    ``values``: any shape; NaNs are ignored (a trial that has fewer epochs than the others). With one sample the
    half-width is 0 (no spread can be estimated), never NaN.
    """
    values = np.asarray(values, dtype=np.float64)
    n = np.sum(np.isfinite(values), axis=axis)
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        # An epoch with fewer than ddof+1 finite samples has no spread; its half-width is set to 0 below.
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(values, axis=axis) if values.size else np.zeros(np.delete(values.shape, axis))
        sd = np.nanstd(values, axis=axis, ddof=ddof) if values.size else np.zeros_like(mean)
        half = np.where(n > ddof, z * sd / np.sqrt(np.maximum(n, 1)), 0.0)
    return mean, np.nan_to_num(half)


def paired_band(differences: np.ndarray) -> tuple[float, float]:
    """Mean and 99 % half-width of paired differences ``[n]`` (one per body: two controllers on the same body, same
    headings and noise streams), Student's t with n − 1 degrees of freedom — tens of bodies, where the normal band
    of :func:`mean_band` (the paper's, over thousands of episodes) is 30 % too narrow at n = 9 and 2 % at n = 93.
    Every "paired" figure of the held-out tables is this band. One body: its difference, half-width 0 (as
    :func:`mean_band`: no spread to estimate)."""
    from scipy import stats

    d = np.asarray(differences, dtype=np.float64)
    d = d[np.isfinite(d)] if d.ndim == 1 else d
    if d.ndim != 1 or len(d) == 0:
        raise ValueError(f"paired differences: need a 1-d array of at least one finite value, got shape {d.shape}")
    if len(d) == 1:
        return float(d[0]), 0.0
    mean, half = mean_band(d, z=float(stats.t.ppf(0.995, len(d) - 1)))
    return float(mean), float(half)


def ratio_band(values: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """A fraction of a reference and its 99 % half-width: ``mean(values) / mean(reference)`` over paired bodies
    ``[n]`` (each body's figure and its own reference), the band by the delta method — the fraction's error is
    ``mean(values − R·reference) / mean(reference)``, a mean of paired residuals, so :func:`paired_band`'s Student's t
    over them (Cochran's ratio estimator). A body without both figures is left out."""
    x, r = np.asarray(values, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    if x.shape != r.shape or x.ndim != 1:
        raise ValueError(f"a fraction pairs each body's figure with its reference: shapes {x.shape} and {r.shape}")
    both = np.isfinite(x) & np.isfinite(r)
    x, r = x[both], r[both]
    if not len(x) or r.mean() <= 0:
        raise ValueError(f"a fraction needs bodies with a positive mean reference (got {len(x)} bodies, reference "
                         f"mean {r.mean() if len(r) else float('nan'):g})")
    ratio = x.mean() / r.mean()
    _, half = paired_band((x - ratio * r) / r.mean())
    return float(ratio), half


def summary_row(name: str, values: np.ndarray, paired: bool = False) -> dict:
    """A summary.csv row: ``values``' mean over its first axis and 99 % band (``mean_band``; ``paired``: per-body
    differences, :func:`paired_band`), low and high."""
    mean, band = paired_band(values) if paired else mean_band(values)
    return {"what": name, "n": len(values), "mean": float(mean), "band99": float(band),
            "low": float(mean - band), "high": float(mean + band)}


def write_rows(path: Path, rows: Sequence[dict[str, Any]]) -> Path:
    """Write ``rows`` (dicts) as a CSV table, its columns every key in the order first met. An empty table is
    refused (``ValueError``), the file untouched: without rows a CSV has no header, and it would read back as
    nothing where a table was meant."""
    path = Path(path)
    if not rows:
        raise ValueError(f"no rows to write to {path} (an empty table has no columns); nothing written")
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(dict.fromkeys(k for row in rows for k in row)))
        writer.writeheader()
        writer.writerows(rows)
    return path


def missing_figure(value: str) -> bool:
    """Whether a table's cell holds no figure: an empty cell, or the ``nan`` :func:`write_rows` writes for one (a
    body without per-body control)."""
    return value in ("", "nan")


def read_rows(path: Path) -> list[dict[str, str]]:
    """Inverse of :func:`write_rows`: the table's rows as dicts of strings."""
    with open(path, newline="") as f:
        return list(csv.DictReader(f))
