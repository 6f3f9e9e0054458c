"""The batched round of the Mitra et al. family (:mod:`estimation.lfre`): every member's own
``begin`` and ``finish``, one fusion over all of them."""

from __future__ import annotations

import numpy as np

from .batching import Batch
from .trimmed_mean import fuse_blocks


class FusionBatch(Batch):
    """LFRE / SW-LFRE agents of one fusion rule and ``f``: every member's :meth:`~_ModalFusion.begin`,
    one :func:`~estimation.trimmed_mean.fuse_blocks` over all their values, every
    :meth:`~_ModalFusion.finish` (the per-agent code itself: bit-identical to ``step``).

    Members go in slices of at most :attr:`CHUNK_VALUES` (262,144) values to fuse (a 1,024-agent team
    on 5,120 states fuses 42 M values a round: one stacked copy alone would be 335 MB)."""

    CHUNK_VALUES = 1 << 18

    def __init__(self, members, **kw) -> None:
        super().__init__(members, **kw)
        self._slices, start, size = [], 0, 0
        for m, est in enumerate(self.members):
            size += est._F.size * max(1, est._nb.size)
            if size > self.CHUNK_VALUES and m > start:
                self._slices.append(slice(start, m))
                start, size = m, est._F.size * max(1, est._nb.size)
        self._slices.append(slice(start, len(self.members)))

    def step(self, k: int, measurements, inboxes) -> list[np.ndarray]:
        ms = self.members
        fusion, f = ms[0].fusion, ms[0].f
        out: list[np.ndarray] = []
        for sl in self._slices:
            vals = [m.begin(k, inbox) for m, inbox in zip(ms[sl], inboxes[sl])]
            fused = fuse_blocks(vals, fusion=fusion, f=f)
            del vals
            out += [m.finish(k, y, g) for m, y, g in zip(ms[sl], measurements[sl], fused)]
        return out

    def estimates(self) -> np.ndarray | list[np.ndarray]:
        ms = self.members
        if ms[0].design.modal.is_identity:  # x_hat = z: the read-only modal estimates themselves
            return [m._z for m in ms]
        return np.array([m.estimate for m in ms])
