"""The named plants of Mitra et al. 2019, Section 8: ``cells`` and ``diffusion``.

Both are ``K`` decoupled cells with ``R = 10`` sensing locations each (:class:`CellModel`).
The diagonal ``A`` of ``cells`` is a ``scipy.sparse`` CSR array from ``SPARSE_FROM`` states
on (a 1,024-agent team's dense ``5120 x 5120`` ``A`` would be 200 MB for 40 kB of
non-zeros; ``A.toarray()`` is the dense matrix), a dense array below. Its product with a state is the dense product bit for bit (one non-zero
per row). The ``diffusion`` cells' ``A`` stays a dense array: a row there has several
non-zeros, which a sparse product adds in another order than the dense one (the plant's
trajectory would differ in the last bits, and the paper scenario's estimates with it).

Map (the paper gives no dimensions): each cell is a square of side ``cell_size = 30``
distance units; the cells sit on a grid of ``ceil(sqrt(K))`` columns, numbered in
boustrophedon order (row 0 left to right, row 1 right to left, ...), so for ``K = 4``
cell 1 is top-left, 2 top-right, 3 bottom-right, 4 bottom-left: cell 1 borders cells 2
and 4 but not 3, as in Fig. 5. Locations are uniform in their cell's square, drawn from
the ``numpy.random.Generator`` passed in (cell by cell, ``R`` points of 2 coordinates).

* ``cells`` (Section 8.1): per cell a 20-state diagonal ``A`` with eigenvalues
  ``linspace(0.5, 1.2, 20)`` (state ``q`` has the ``q``-th smallest), location ``r``
  (1-based within its cell) measures ``x_{2r-1} + x_{2r}`` of its cell; initial state
  of every state of cell ``c`` is ``(0.07, 0.05, 0.03, 0.01)[(c - 1) mod 4]`` (the
  paper's values for cells 1..4, cycled for ``K > 4``).
* ``diffusion`` (Section 8.2): per cell ``A = I - eps L`` with ``eps = 0.01`` and ``L`` the
  Laplacian of the graph joining locations closer than ``radius = 15``; location ``i``
  measures state ``i`` of its cell. The paper states this graph is connected; a cell's
  positions are redrawn (same generator) until the graph is connected and ``A``'s
  eigenvalues in that cell are distinct (Assumption 1; a gap > 1e-6), at most
  ``max_draws`` times. Initial states as for ``cells`` (all states of a cell equal, which
  is the consensus direction and hence constant in time), plus optional uniform noise
  ``x0_noise * U(-1, 1)`` drawn after the positions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .errors import DesignError

if TYPE_CHECKING:  # scipy is imported when a plant is built, not with the package
    from scipy import sparse

#: from this many states on, the ``cells`` plant's diagonal ``A`` is kept sparse (dense it
#: would be at least 8 MB); below, dense, so that a small team's plant and monitor
#: processes need not import scipy.sparse (about 18 MB each)
SPARSE_FROM = 1024
#: initial state of the states of cells 1..4 (Section 8.1), cycled for more cells
PAPER_X0 = (0.07, 0.05, 0.03, 0.01)
LOCATIONS_PER_CELL = 10


@dataclass(frozen=True, eq=False)
class CellModel:
    """A plant ``x[k+1] = A x[k]`` with sensing locations, split into named cells.

    Attributes
    ----------
    A : (n, n) array  block diagonal, one block per cell (``cells`` from ``SPARSE_FROM`` states: a scipy.sparse CSR array)
    positions : (N, 2) array  2-D position of every location
    loc_C : tuple of (1, n) arrays  measurement row(s) of every location (eq. (2))
    loc_cell : (N,) int array  cell (0-based) of every location
    block_names : tuple of str  ``"cell1" .. "cellK"``
    state_block : (n,) int array  cell (0-based) of every state
    x0 : (n,) array  initial state
    cell_origin : (K, 2) array  lower-left corner of every cell's square
    cell_size : float  side of a cell's square
    """

    A: sparse.csr_array | np.ndarray
    positions: np.ndarray
    loc_C: tuple[np.ndarray, ...]
    loc_cell: np.ndarray
    block_names: tuple[str, ...]
    state_block: np.ndarray
    x0: np.ndarray
    cell_origin: np.ndarray
    cell_size: float

    @property
    def n(self) -> int:
        return int(self.A.shape[0])

    @property
    def C(self) -> np.ndarray:
        """All locations' rows stacked, ``(N, n)``."""
        return np.vstack(self.loc_C)

    @property
    def blocks(self) -> tuple[np.ndarray, ...]:
        """State indices of every cell (usable as ``modal_form(..., blocks=...)``)."""
        return tuple(np.flatnonzero(self.state_block == b) for b in range(len(self.block_names)))


def cell_origins(K: int, *, cell_size: float) -> np.ndarray:
    """Lower-left corners ``(K, 2)`` of the cells on the boustrophedon grid."""
    cols = max(1, math.ceil(math.sqrt(K)))
    out = np.zeros((K, 2))
    for c in range(K):
        row, j = divmod(c, cols)
        col = j if row % 2 == 0 else cols - 1 - j
        out[c] = (col * cell_size, -row * cell_size)
    return out


def _check(K: int, rng: np.random.Generator, cell_size: float) -> None:
    if isinstance(K, bool) or not isinstance(K, (int, np.integer)) or K < 1:
        raise DesignError(f"number of cells K must be an integer >= 1, got {K!r}")
    if not isinstance(rng, np.random.Generator):
        raise DesignError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    if not cell_size > 0:
        raise DesignError(f"cell_size must be > 0, got {cell_size}")


def _assemble(blocks_A, positions, rows, x0_cells, origins, cell_size, *, sparse_A: bool) -> CellModel:
    K = len(blocks_A)
    sizes = [b.shape[0] for b in blocks_A]
    n = sum(sizes)
    offs = np.concatenate([[0], np.cumsum(sizes)])
    parts: tuple[np.ndarray, ...]
    if sparse_A:
        from scipy import sparse

        A = sparse.csr_array(sparse.block_diag([np.asarray(b, dtype=float) for b in blocks_A], format="csr"))
        A.eliminate_zeros()
        A.sort_indices()
        parts = (A.data, A.indices, A.indptr)
    else:
        A = np.zeros((n, n))
        for c in range(K):
            A[offs[c] : offs[c + 1], offs[c] : offs[c + 1]] = blocks_A[c]
        parts = (A,)
    state_block = np.repeat(np.arange(K), sizes)
    loc_C, loc_cell = [], []
    for c in range(K):
        for row in rows[c]:
            full = np.zeros((1, n))
            full[0, offs[c] : offs[c + 1]] = row
            full.setflags(write=False)
            loc_C.append(full)
            loc_cell.append(c)
    x0 = np.concatenate(x0_cells)
    pos = np.vstack(positions)
    for arr in (*parts, pos, x0, state_block, origins):
        arr.setflags(write=False)
    lc = np.asarray(loc_cell, dtype=int)
    lc.setflags(write=False)
    return CellModel(
        A=A,
        positions=pos,
        loc_C=tuple(loc_C),
        loc_cell=lc,
        block_names=tuple(f"cell{c + 1}" for c in range(K)),
        state_block=state_block,
        x0=x0,
        cell_origin=origins,
        cell_size=float(cell_size),
    )


def cells(K: int, rng: np.random.Generator, *, cell_size: float = 30.0, states: int = 20, lam_range: tuple[float, float] = (0.5, 1.2)) -> CellModel:
    """The unstable cells of Section 8.1.

    Parameters
    ----------
    K : int >= 1, number of cells
    rng : numpy.random.Generator, draws the location positions
    cell_size : float, side of a cell's square (distance units)
    states : int, states per cell (even; ``states / 2`` locations per cell)
    lam_range : (lo, hi), eigenvalues ``linspace(lo, hi, states)`` per cell

    Returns
    -------
    CellModel with ``n = K * states`` and ``N = K * states / 2`` locations.
    """
    _check(K, rng, cell_size)
    if states < 2 or states % 2:
        raise DesignError(f"states per cell must be even and >= 2, got {states}")
    R = states // 2
    lam = np.linspace(lam_range[0], lam_range[1], states)
    origins = cell_origins(K, cell_size=cell_size)
    rows = []
    for r in range(R):
        row = np.zeros(states)
        row[2 * r : 2 * r + 2] = 1.0  # 1-based positions 2r-1 and 2r
        rows.append(row)
    positions = [origins[c] + rng.uniform(0.0, cell_size, size=(R, 2)) for c in range(K)]
    x0 = [np.full(states, PAPER_X0[c % len(PAPER_X0)]) for c in range(K)]
    return _assemble([np.diag(lam)] * K, positions, [rows] * K, x0, origins, cell_size,
                     sparse_A=K * states >= SPARSE_FROM)


def proximity_laplacian(points: np.ndarray, *, radius: float) -> np.ndarray:
    """Laplacian ``(R, R)`` of the graph joining points closer than ``radius``."""
    d = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=-1)
    adj = ((d < radius) & ~np.eye(points.shape[0], dtype=bool)).astype(float)
    return np.diag(adj.sum(axis=1)) - adj


def diffusion(
    K: int,
    rng: np.random.Generator,
    *,
    eps: float = 0.01,
    radius: float = 15.0,
    cell_size: float = 30.0,
    locations: int = LOCATIONS_PER_CELL,
    x0_noise: float = 0.0,
    max_draws: int = 1000,
) -> CellModel:
    """The diffusion cells of Section 8.2: ``A_c = I - eps L_c`` per cell.

    Parameters
    ----------
    K : int >= 1;  rng : numpy.random.Generator
    eps : float, the step of the discretised Laplacian dynamics (paper: 0.01)
    radius : float, connection distance between locations (paper: 15)
    cell_size : float;  locations : int, locations (= states) per cell
    x0_noise : float >= 0, amplitude of uniform noise added to the paper's initial states
    max_draws : int, redraws per cell before giving up (DesignError)
    """
    from scipy.sparse.csgraph import connected_components

    _check(K, rng, cell_size)
    if not (0 < eps) or not (radius > 0) or locations < 1 or x0_noise < 0:
        raise DesignError(f"diffusion: need eps > 0, radius > 0, locations >= 1, x0_noise >= 0; got {eps}, {radius}, {locations}, {x0_noise}")
    origins = cell_origins(K, cell_size=cell_size)
    blocks, positions = [], []
    for c in range(K):
        for _ in range(max_draws):
            pts = rng.uniform(0.0, cell_size, size=(locations, 2))
            L = proximity_laplacian(pts, radius=radius)
            ncomp, _ = connected_components((L != 0).astype(np.int8), directed=False)
            if ncomp != 1:
                continue
            ev = np.sort(np.linalg.eigvalsh(L))
            if locations > 1 and np.min(np.diff(ev)) * eps <= 1e-6:
                continue
            break
        else:
            raise DesignError(f"diffusion: cell {c + 1}: no connected location graph with distinct eigenvalues "
                              f"in {max_draws} draws (radius {radius}, cell_size {cell_size})")
        blocks.append(np.eye(locations) - eps * L)
        positions.append(origins[c] + pts)
    rows = [list(np.eye(locations))] * K
    x0 = [np.full(locations, PAPER_X0[c % len(PAPER_X0)]) for c in range(K)]
    if x0_noise > 0:
        x0 = [v + x0_noise * rng.uniform(-1.0, 1.0, size=locations) for v in x0]
    return _assemble(blocks, positions, rows, x0, origins, cell_size, sparse_A=False)
