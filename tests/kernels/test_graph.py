import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from pipeline.kernels.graph import connect_components, laplacian, radius_graph, valence_radius
from tests.conftest import sphere_patch


def test_radius_gives_the_requested_average_valence():
    pts = sphere_patch(2000)
    for valence in (6, 12, 24):
        a = radius_graph(pts, valence_radius(pts, valence))
        assert abs(a.nnz / len(pts) - valence) <= 2.0 / len(pts) * 10


def test_radius_graph_is_symmetric_binary_without_loops():
    pts = sphere_patch(800)
    a = radius_graph(pts, valence_radius(pts, 12))
    assert (a != a.T).nnz == 0
    assert set(np.unique(a.data)) == {1.0}
    assert a.diagonal().sum() == 0


def test_components_and_isolated_points_are_joined():
    pts = np.vstack([sphere_patch(400), sphere_patch(400) + 10.0, [[50.0, 0, 0]]])
    a = radius_graph(pts, valence_radius(pts[:400], 12))
    joined, before = connect_components(pts, a)
    assert before >= 3
    assert connected_components(joined, directed=False)[0] == 1
    # only a few bridges were added
    assert joined.nnz - a.nnz <= 2 * 2 * before


def test_laplacian_is_degree_minus_adjacency():
    pts = sphere_patch(300)
    a = radius_graph(pts, valence_radius(pts, 12))
    k = laplacian(a)
    assert np.allclose(k @ np.ones(len(pts)), 0.0)
    assert np.allclose(k.diagonal(), np.asarray(a.sum(axis=1)).ravel())
    assert sp.issparse(k)
