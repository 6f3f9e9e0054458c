"""r-robustness by enumeration (estimation.graphs.r_robustness), as rse check reports it."""

import numpy as np

from estimation import graphs


def test_known_graphs():
    for N in (2, 3, 6, 7):
        assert graphs.r_robustness(graphs.complete(N)) == (N + 1) // 2  # K_N is ceil(N/2)-robust (LeBlanc et al. 2013)
    assert graphs.r_robustness(graphs.ring(6)) == 1
    path = graphs.from_edges(4, [(0, 1), (1, 2), (2, 3)])
    assert graphs.r_robustness(path) == 1
    two_cliques = np.zeros((6, 6))
    two_cliques[:3, :3] = two_cliques[3:, 3:] = 1 - np.eye(3)
    assert graphs.r_robustness(two_cliques) == 0  # each clique is 0-reachable from the other
    assert graphs.r_robustness(graphs.complete(graphs.ROBUSTNESS_MAX_N + 1)) is None
