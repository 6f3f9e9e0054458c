"""Resilient scalar fusion rules: the (weighted) trimmed mean and the median.

Mitra et al. 2019, step 2 of SW-LFRE (eq. (14)) and LFRE (eq. (21)): sort the
neighbours' values, discard the ``f`` largest and the ``f`` smallest, and take a convex
combination of the rest. Remark 7: the median may be used instead. With at least
``2f + 1`` values of which at most ``f`` are adversarial, both results lie in the
interval spanned by the regular values (the basis of the proofs of Theorems 1 and 2).

All functions reduce along ``axis`` and broadcast over every other axis, so a batch of
modes (or agents) is fused in one call. ``NaN`` marks a missing entry (no message from
that neighbour, or a neighbour that is not in the mode's MEDAG); trimming counts only
the present entries of each row.
"""

from __future__ import annotations

import numpy as np

from .errors import DesignError

_SHORT = ("raise", "nan")
#: names of the fusion rules of :func:`fuse` / :func:`fuse_block`
FUSIONS = ("trimmed", "median", "average")


def _check_f(f: int) -> int:
    if isinstance(f, bool) or not isinstance(f, (int, np.integer)) or f < 0:
        raise DesignError(f"attack budget f must be a non-negative integer, got {f!r}")
    return int(f)


def _short(result: np.ndarray, short_rows: np.ndarray, short: str, need: int, what: str) -> np.ndarray:
    if short not in _SHORT:
        raise DesignError(f"short must be one of {_SHORT}, got {short!r}")
    if short_rows.any():
        if short == "raise":
            raise DesignError(f"{what} needs at least {need} present values per row; {int(np.sum(short_rows))} row(s) have fewer")
        result = np.where(short_rows, np.nan, result)
    return result


def trimmed_mean(
    values: np.ndarray,
    *,
    f: int,
    weights: np.ndarray | None = None,
    axis: int = -1,
    short: str = "raise",
) -> np.ndarray | float:
    """Trimmed mean: drop the ``f`` largest and ``f`` smallest present values, average the rest.

    Eqs. (14) and (21): ``sum_{l in M} w_l v_l`` with ``M`` the values left after trimming
    and the weights renormalised over ``M`` (uniform when ``weights`` is None).

    Parameters
    ----------
    values : (..., d, ...) array
        Values to fuse along ``axis``; ``NaN`` = missing. ``+-inf`` are ordinary (extreme)
        values and are trimmed first.
    f : int >= 0
        Attack budget: the number of values trimmed at each end.
    weights : array broadcastable to ``values``, optional
        Positive weight of each entry (attached to the entry, i.e. to the sender, and
        carried through the sort). Renormalised over the kept entries of each row.
    axis : int
        Axis to reduce.
    short : {"raise", "nan"}
        What to do with a row with fewer than ``2f + 1`` present values: raise
        :class:`DesignError`, or return ``NaN`` for that row (batch use; the caller then
        runs open loop, eq. (22)).

    Returns
    -------
    array of the batch shape (``values`` without ``axis``), or a float for 1-D input.
    """
    f = _check_f(f)
    v = np.asarray(values, dtype=float)
    if axis != -1 and axis != v.ndim - 1:
        v = np.moveaxis(v, axis, -1)
    d = v.shape[-1]
    present = ~np.isnan(v)
    count = present.sum(axis=-1)
    rank = np.arange(d)
    if weights is None:  # fast path: a plain sort (NaN sort last)
        vs = np.sort(v, axis=-1)
        keep = (rank >= f) & (rank < (count - f)[..., None])
        short_rows = count < 2 * f + 1
        den = np.where(short_rows, 1, keep.sum(axis=-1))
        kept = np.where(keep, vs, 0.0)
        # a running sum in sorted order: trailing padding (NaN columns of a batch of rows
        # with fewer senders) adds exact zeros, so a row's result never depends on the
        # width of the batch it is fused in (numpy's pairwise .sum() regroups with width)
        total = np.cumsum(kept, axis=-1)[..., -1] if d else np.zeros(kept.shape[:-1])
        out = total / den
        out = _short(out, short_rows, short, 2 * f + 1, "trimmed_mean")
        return float(out) if out.ndim == 0 else out
    order = np.argsort(v, axis=-1, kind="stable")
    vs = np.take_along_axis(v, order, axis=-1)
    keep = (rank >= f) & (rank < (count - f)[..., None])
    vals = np.asarray(values, dtype=float)
    wa = np.moveaxis(np.broadcast_to(np.asarray(weights, dtype=float), vals.shape), axis, -1)
    if np.any(wa[present] <= 0) or not np.all(np.isfinite(wa[present])):
        raise DesignError("trimmed_mean weights must be finite and > 0 for present values")
    w = np.where(keep, np.take_along_axis(wa, order, axis=-1), 0.0)
    den = w.sum(axis=-1)
    num = np.where(keep, vs, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (num * w).sum(axis=-1) / den
    out = _short(out, count < 2 * f + 1, short, 2 * f + 1, "trimmed_mean")
    return float(out) if out.ndim == 0 else out


def median(values: np.ndarray, *, f: int = 0, axis: int = -1, short: str = "raise") -> np.ndarray | float:
    """Median of the present values (Remark 7 of Mitra et al.).

    With at least ``2f + 1`` present values and at most ``f`` adversarial ones, the median
    lies between two regular values. An even count gives the mean of the two middle
    values.

    Parameters
    ----------
    values : array, ``NaN`` = missing
    f : int >= 0
        Attack budget; only used for the minimum count ``2f + 1`` (``short``).
    axis, short : as in :func:`trimmed_mean`
    """
    f = _check_f(f)
    v = np.asarray(values, dtype=float)
    if axis != -1 and axis != v.ndim - 1:
        v = np.moveaxis(v, axis, -1)
    count = (~np.isnan(v)).sum(axis=-1)
    need = max(2 * f + 1, 1)
    short_rows = count < need
    if v.shape[-1] == 0:
        out = np.full(v.shape[:-1], np.nan)
    else:
        vs = np.sort(v, axis=-1)  # NaN sort last
        c = np.maximum(count, 1)[..., None]
        lo = np.take_along_axis(vs, (c - 1) // 2, axis=-1)[..., 0]
        hi = np.take_along_axis(vs, c // 2, axis=-1)[..., 0]
        out = 0.5 * (lo + hi) if np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) else np.where(lo == hi, lo, 0.5 * lo + 0.5 * hi)
    out = _short(np.asarray(out, dtype=float), short_rows, short, need, "median")
    return float(out) if out.ndim == 0 else out


def average(values: np.ndarray, *, weights: np.ndarray | None = None, axis: int = -1, short: str = "raise") -> np.ndarray | float:
    """Plain (weighted) average of the present values: the non-resilient baseline.

    This is the convex-combination update of Mitra & Sundaram (2018a) used in Fig. 13 of
    Mitra et al.; one adversarial value moves it arbitrarily.
    """
    return trimmed_mean(values, f=0, weights=weights, axis=axis, short=short)


def fuse(values: np.ndarray, *, fusion: str, f: int) -> np.ndarray:
    """Fused value per row of ``values (..., F, d)`` (NaN = missing); NaN if too few present."""
    if fusion == "trimmed":
        return np.asarray(trimmed_mean(values, f=f, short="nan"))
    if fusion == "median":
        return np.asarray(median(values, f=f, short="nan"))
    if fusion == "average":
        return np.asarray(average(values, short="nan"))
    raise DesignError(f"unknown fusion {fusion!r}; expected one of {', '.join(FUSIONS)}")


def fuse_block(block: np.ndarray, *, fusion: str, f: int) -> np.ndarray:
    """Fuse a complete block ``(d, g)`` column-wise (no missing values): ``(g,)``.

    The fast path of :func:`fuse` for ``d`` neighbours that all delivered; ``d >= 2f + 1``
    (``>= 1`` for ``"average"``) is the caller's responsibility.
    """
    d = block.shape[0]
    if fusion == "trimmed":
        if f == 0:
            return block.sum(axis=0) / d
        srt = np.array(block)  # a copy: never sort the caller's array
        srt.sort(axis=0)
        return srt[f : d - f].sum(axis=0) / (d - 2 * f)
    if fusion == "median":
        srt = np.sort(block, axis=0)
        return srt[d // 2] if d % 2 else 0.5 * (srt[d // 2 - 1] + srt[d // 2])
    if fusion == "average":
        return block.sum(axis=0) / d
    raise DesignError(f"unknown fusion {fusion!r}; expected one of {', '.join(FUSIONS)}")


def fuse_blocks(values: list[np.ndarray | None], *, fusion: str, f: int) -> list[np.ndarray | None]:
    """:func:`fuse` of each ``(F_i, d_i)`` block (None: nothing), in one call over the
    blocks stacked row-wise and padded to the widest with NaN (a missing value). Every
    row's result is exactly what the per-block call gives (each row is fused alone)."""
    present = [v for v in values if v is not None]
    if not present:
        return [None] * len(values)
    width = max(v.shape[1] for v in present)
    stacked = np.full((sum(v.shape[0] for v in present), width), np.nan)
    row = 0
    for v in present:
        stacked[row:row + v.shape[0], :v.shape[1]] = v
        row += v.shape[0]
    got = fuse(stacked, fusion=fusion, f=f)
    out: list[np.ndarray | None] = []
    row = 0
    for block in values:
        if block is None:
            out.append(None)
        else:
            out.append(got[row:row + block.shape[0]])
            row += block.shape[0]
    return out
