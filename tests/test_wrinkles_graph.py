"""Pore graph: kNN edges vs scipy, crossing lists vs brute force, half-edge consistency."""

import jax
import numpy as np
import pytest
from scipy.spatial import cKDTree

from jface.wrinkles import build_graph, graph_spec, make_pores, sample_pores
from jface.wrinkles._graph import (
    covering_spec,
    graph_from_tables,
    graph_tables,
    stack_graphs,
)


@pytest.fixture(scope="module", params=[False, True], ids=["open", "periodic"])
def pores_graph(request):
    pores = sample_pores(jax.random.key(0), 0.02, periodic=request.param)
    return pores, build_graph(pores)


def _brute_crossings(x, nodes, delta, periodic):
    """All properly crossing edge pairs, in float64, by a direct O(E²) test."""

    def cross(u, v):
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    def opposite(s, t):
        return ((s > 0) & (t < 0)) | ((s < 0) & (t > 0))

    a = x[nodes[:, 0]]
    out = []
    for lo in range(0, len(nodes), 1000):
        q1 = a[None, :, :] - a[lo : lo + 1000, None, :]
        if periodic:
            q1 -= np.round(q1)
        q2 = q1 + delta[None]
        p2 = delta[lo : lo + 1000, None]
        hit = opposite(cross(p2, q1), cross(p2, q2)) & opposite(
            cross(q2 - q1, -q1), cross(q2 - q1, p2 - q1)
        )
        e = nodes[lo : lo + 1000]
        shared = (e[:, None, :, None] == nodes[None, :, None, :]).any(axis=(-1, -2))
        out.append(hit & ~shared)
    return np.concatenate(out)


def test_edges_are_symmetric_knn(pores_graph):
    pores, graph = pores_graph
    n = int(pores.count)
    x = np.asarray(pores.positions, np.float64)[:n]
    _, nn = cKDTree(x, boxsize=1.0 if pores.periodic else None).query(x, 7)
    ref = {(min(i, j), max(i, j)) for i in range(n) for j in nn[i, 1:]}
    e = int(graph.edge_count)
    nodes = np.asarray(graph.edge_nodes)[:e]
    assert {tuple(p) for p in nodes.tolist()} == ref and len(ref) == e
    assert np.all(nodes[:, 0] < nodes[:, 1])
    assert int(graph.degree[:n].min()) >= 6


def test_crossing_lists_equal_brute_force(pores_graph):
    pores, graph = pores_graph
    e = int(graph.edge_count)
    x = np.asarray(pores.positions, np.float64)
    nodes = np.asarray(graph.edge_nodes)[:e]
    ref = _brute_crossings(x, nodes, np.asarray(graph.edge_delta, np.float64)[:e], pores.periodic)
    lists, mask = np.asarray(graph.crossings)[:e], np.asarray(graph.crossing_mask)[:e]
    assert ref.sum() > 100
    for i in range(e):
        assert set(lists[i][mask[i]].tolist()) == set(np.nonzero(ref[i])[0].tolist())
    assert not np.asarray(graph.crossing_mask)[e:].any()


def test_half_edges_match_edges(pores_graph):
    pores, graph = pores_graph
    n = int(pores.count)
    hm = np.asarray(graph.half_mask)
    assert hm.sum() == 2 * int(graph.edge_count) and not hm[n:].any()
    v, slot = np.nonzero(hm)
    t = np.asarray(graph.half_target)[v, slot]
    e = np.asarray(graph.half_edge)[v, slot]
    nodes = np.asarray(graph.edge_nodes)[e]
    np.testing.assert_array_equal(np.sort(np.stack([v, t], 1), 1), nodes)
    x = np.asarray(pores.positions, np.float64)
    delta = x[t] - x[v]
    if pores.periodic:
        delta -= np.round(delta)
    np.testing.assert_allclose(
        np.asarray(graph.half_length)[v, slot], np.hypot(*delta.T), atol=1e-6
    )
    ang = np.mod(np.arctan2(delta[:, 1], delta[:, 0]), 2 * np.pi)
    diff = np.angle(np.exp(1j * (np.asarray(graph.half_angle)[v, slot] - ang)))
    np.testing.assert_allclose(diff, 0, atol=1e-4)
    np.testing.assert_allclose(np.asarray(graph.edge_length)[e], np.hypot(*delta.T), atol=1e-6)


def test_capacity_overflow_raises(unchecked):
    pores = sample_pores(jax.random.key(0), 0.02)
    with pytest.raises(ValueError, match="max_crossings"):
        build_graph(pores, graph_spec(pores, max_crossings=1))


def test_tiny_graph_and_bad_input(unchecked):
    pores = make_pores(np.array([[0.2, 0.2], [0.4, 0.3], [0.3, 0.6]], np.float32), radius=0.1)
    graph = build_graph(pores, k=2)
    assert int(graph.edge_count) == 3
    with pytest.raises(TypeError, match="Pores"):
        build_graph(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="k must be"):
        graph_spec(pores, k=0)


def test_covering_spec_and_stack_graphs_keep_every_graph():
    # one measured spec serves pore sets between the densest and the sparsest; stacking trims
    # the slots to the data without changing any graph
    key = jax.random.key(5)
    sets = [sample_pores(key, d, periodic=True, capacity=1300, radius_range=(0.03, 0.05))
            for d in (0.03, 0.04, 0.05)]  # fmt: skip
    spec = covering_spec([sets[0], sets[2]], (0.03, 0.05))
    bound = graph_spec(sets[0], radius_range=(0.03, 0.05))
    assert (
        spec.edge_cell_capacity / spec.edge_grid**2 < bound.edge_cell_capacity / bound.edge_grid**2
    )
    graphs = [build_graph(p, spec) for p in sets]
    stacked = stack_graphs(graphs)
    for i, p in enumerate(sets):
        auto = build_graph(p)
        n, e = int(auto.node_count), int(auto.edge_count)
        np.testing.assert_array_equal(stacked.edge_nodes[i, :e], auto.edge_nodes[:e])
        np.testing.assert_array_equal(stacked.edge_count[i], e)
        pairs = {tuple(sorted(c)) for c in np.argwhere(np.asarray(auto.crossing_mask[:e]))}
        got = {tuple(sorted(c)) for c in np.argwhere(np.asarray(stacked.crossing_mask[i, :e]))}
        assert len(got) == len(pairs)
        np.testing.assert_array_equal(
            np.sort(np.where(auto.crossing_mask[:e], auto.crossings[:e], -1), -1)[:, -1],
            np.sort(np.where(stacked.crossing_mask[i, :e], stacked.crossings[i, :e], -1), -1)[
                :, -1
            ],
        )
        np.testing.assert_array_equal(
            np.sum(stacked.half_mask[i, :n], -1), np.sum(auto.half_mask[:n], -1)
        )
    assert stacked.half_mask.shape[-1] == max(int(g.degree.max()) for g in graphs)
    # slots are trimmed to the batch's use, rounded up by at most an eighth (shared shapes)
    most = max(int(p.count) for p in sets)
    assert most <= stacked.positions.shape[1] <= most * 9 // 8 < 1300


def test_a_graph_is_rebuilt_from_its_tables_bit_for_bit(pores_graph):
    """A graph stored as its tables (indices narrowed as a stored layout narrows them) comes
    back with every array equal, alone and as a batch."""
    _, graph = pores_graph
    batch = stack_graphs([graph, graph])
    for g in (graph, batch):
        tables = graph_tables(g)
        assert sum(a.nbytes for a in tables.values()) < 0.6 * sum(
            np.asarray(a).nbytes for a in jax.tree.leaves(g)
        )
        tables["half_edge"] = tables["half_edge"].astype(np.int16)
        back = graph_from_tables(tables, periodic=g.periodic)
        assert back.periodic == g.periodic
        for field in g.__dataclass_fields__:
            a, b = np.asarray(getattr(back, field)), np.asarray(getattr(g, field))
            assert a.dtype == b.dtype and np.array_equal(a, b), field
