"""Known answers for the numbered equations, each against a hand value or an independent
few-line reference on a tiny case: the half-edge scores of Eq. 1–6, the deposit and decay of
Eq. 7–8 and their distribution against a slow reference loop, the drawing of Eq. 9–10, and one
swarm run of Eq. 14–15 replayed in numpy."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate

from jface.noise import counter_uniform
from jface.optim import pso
from jface.wrinkles import WrinkleParams, build_graph, make_pores, mellowmax, shape_function
from jface.wrinkles._drawing import pore_strength
from jface.wrinkles._simulation import (
    continuation_kernel,
    half_edge_scores,
    orientation_density,
    orientation_weight,
    simulate,
)

# six pores: a zig-zag whose kNN graph has pores of degree 2–4 and at least one crossing pair
PORES = np.array(
    [[0.2, 0.2], [0.5, 0.25], [0.8, 0.2], [0.3, 0.6], [0.55, 0.5], [0.75, 0.7]], np.float32
)
PARAMS = WrinkleParams(
    theta=0.7, s=0.2, sigma=0.5, dist=1.5, cont=0.6, sim=0.3, cross=0.8, sigma_cont=0.4
)


@pytest.fixture(scope="module")
def graph():
    return build_graph(make_pores(PORES, radius=0.2, capacity=8), k=4)


def _gauss(x, sigma):
    return math.exp(-x * x / (2 * sigma * sigma)) / (sigma * math.sqrt(2 * math.pi))


def _wrap(a, period):
    """|a| with wrap-around at ``period``."""
    return abs((a + period / 2) % period - period / 2)


def _reference_scores(graph, p, w):
    """Eq. 3 per pore and half-edge by plain loops over the graph's lists."""
    g = jax.tree.map(np.asarray, graph)
    n, d = g.half_mask.shape
    out = np.zeros((n, d))
    for i in range(int(g.node_count)):
        slots = [j for j in range(d) if g.half_mask[i, j]]
        shortest = min(g.half_length[i, j] for j in slots)
        for j in slots:
            th = g.half_angle[i, j]
            p_pref = p["s"] + math.exp(-(_wrap(th - p["theta"], math.pi) ** 2) / p["sigma"] ** 2)
            p_cont = 0.0
            for k in slots:
                if k != j:
                    same = _wrap(th - g.half_angle[i, k], 2 * math.pi)
                    kern = p["cont"] * _gauss(math.pi - same, p["sigma_cont"])
                    kern -= p["sim"] * _gauss(same, p["sigma_cont"])
                    p_cont += kern * w[g.half_edge[i, k]]
            e = g.half_edge[i, j]
            p_cross = float(np.sum(w[g.crossings[e]], where=g.crossing_mask[e]))
            dist = (g.half_length[i, j] / shortest) ** -p["dist"]
            score = dist * ((1 - p["cont"]) * p_pref + p_cont - p["cross"] * p_cross)
            out[i, j] = max(score, 0.0)
    return out


def _as_dict(params):
    return {k: float(getattr(params, k)) for k in ("theta", "s", "sigma", "dist", "cont", "sim",
                                                    "cross", "sigma_cont")}  # fmt: skip


def test_orientation_density_values_and_normalisation():
    # Eq. 1–2 by hand: at α_θ the weight is α_s + 1, a quarter turn away α_s + exp(−(π/2)²/σ²)
    assert float(orientation_weight(0.7, 0.7, 0.2, 0.5)) == pytest.approx(1.2, abs=1e-6)
    far = 0.2 + math.exp(-((math.pi / 2) ** 2) / 0.25)
    assert float(orientation_weight(0.7 + math.pi / 2, 0.7, 0.2, 0.5)) == pytest.approx(far, 1e-5)
    # undirected: θ and θ + π weigh the same; the density integrates to one over [0, 2π)
    assert float(orientation_weight(0.7 + math.pi, 0.7, 0.2, 0.5)) == pytest.approx(1.2, abs=1e-6)
    for s, sigma in [(0.0, 0.3), (0.2, 0.5), (1.0, 2.0)]:
        total, _ = integrate.quad(
            lambda a, s=s, sigma=sigma: float(orientation_density(a, 0.7, s, sigma)),
            0.0, 2 * math.pi, limit=200, points=[0.7, 0.7 + math.pi],
        )  # fmt: skip
        assert total == pytest.approx(1.0, abs=1e-4)


def test_continuation_kernel_matches_eq4_by_hand(graph):
    g = jax.tree.map(np.asarray, graph)
    nodes = np.arange(int(g.node_count))
    kern = np.asarray(continuation_kernel(graph, PARAMS, nodes))
    d = g.half_mask.shape[1]
    for i in nodes:
        for j in range(d):
            for k in range(d):
                if j == k or not (g.half_mask[i, j] and g.half_mask[i, k]):
                    assert kern[i, j, k] == 0.0
                    continue
                same = _wrap(g.half_angle[i, j] - g.half_angle[i, k], 2 * math.pi)
                want = 0.6 * _gauss(math.pi - same, 0.4) - 0.3 * _gauss(same, 0.4)
                assert kern[i, j, k] == pytest.approx(want, abs=1e-5)


def test_half_edge_scores_match_a_loop_over_eq3(graph):
    assert int(np.sum(np.asarray(graph.crossing_mask))) > 0  # the crossing term takes part
    w = np.asarray(jax.random.uniform(jax.random.key(3), (graph.edge_mask.shape[0],)))
    w = np.where(np.asarray(graph.edge_mask), w, 0.0).astype(np.float32)
    nodes = np.arange(int(graph.node_count))
    got = np.asarray(half_edge_scores(graph, PARAMS, jnp.asarray(w), nodes))
    want = _reference_scores(graph, _as_dict(PARAMS), w)[nodes]
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6)
    assert (want > 0).sum() >= 10  # the scores are mostly positive, not all clipped to zero


def test_decay_alone_is_geometric_in_the_valid_edge_count(graph):
    # Eq. 8 with no deposit: W ← W (1 − Δt α_decay N/|E|) per step, |E| the valid edges (not
    # the capacity), also under jit where the graph is not trimmed
    n_edges = int(graph.edge_count)
    assert graph.edge_mask.shape[0] > n_edges
    w0 = np.where(np.asarray(graph.edge_mask), 0.5, 0.0).astype(np.float32)
    # no deposit (below Table 1's range, so set past the constructor's check)
    params = eqx.tree_at(lambda p: p.deposit, WrinkleParams(decay=0.5, dt=0.1), jnp.float32(0))
    fade = 1.0 - 0.1 * 0.5 * 4 / n_edges
    want = np.where(np.asarray(graph.edge_mask), 0.5 * fade**3, 0.0)

    def run(g, w):
        return simulate(jax.random.key(0), g, params, n_steps=3, n_samples=4, weights=w)

    np.testing.assert_allclose(np.asarray(run(graph, w0)), want, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(jax.jit(run)(graph, w0)), want, rtol=1e-6)


def _hits(w0, w1, keep):
    """Deposits per edge from Eq. 7: 1 − W is multiplied by ``keep`` once per hit."""
    return np.log((1.0 - w1) / (1.0 - w0)) / math.log(keep)


def test_deposits_count_one_hit_per_sample(graph):
    # Eq. 7 with no decay: every sampled pore with a positive score deposits exactly once
    params = WrinkleParams(deposit=0.5, decay=0.0, dt=0.2)
    w = simulate(jax.random.key(1), graph, params, n_steps=1, n_samples=7)
    hits = _hits(np.zeros(w.shape), np.asarray(w, np.float64), 1 - 0.2 * 0.5)
    np.testing.assert_allclose(hits, np.round(hits), atol=1e-3)
    assert round(float(hits.sum())) == 7


def test_one_step_hits_follow_eq3_in_distribution(graph):
    # E[hits of edge e] = N/n Σ_pores P(pore picks e), P from the reference loop of Eq. 3
    n_edges = graph.edge_mask.shape[0]
    mask = np.asarray(graph.edge_mask)
    w0 = np.where(mask, np.linspace(0.1, 0.7, n_edges), 0.0).astype(np.float32)
    params = PARAMS.__class__(**{**_as_dict(PARAMS), "decay": 0.0, "deposit": 0.5, "dt": 0.2})
    scores = _reference_scores(graph, _as_dict(PARAMS), w0)
    g = jax.tree.map(np.asarray, graph)
    n, samples, runs = int(g.node_count), 5, 4000
    expected = np.zeros(n_edges)
    for i in range(n):
        np.add.at(expected, g.half_edge[i], samples / n * scores[i] / scores[i].sum())

    def one(key):
        return simulate(key, graph, params, n_steps=1, n_samples=samples, weights=w0)

    w1 = np.asarray(jax.jit(jax.vmap(one))(jax.random.split(jax.random.key(2), runs)), np.float64)
    hits = _hits(w0.astype(np.float64), w1, 1 - 0.2 * 0.5)[:, mask]
    mean, sd = hits.mean(0), hits.std(0) / math.sqrt(runs)
    assert np.all(np.abs(mean - expected[mask]) < 4 * sd + 1e-3)
    assert hits.sum(1) == pytest.approx(samples, abs=1e-2)


def test_shape_function_and_mellowmax_by_hand():
    # Eq. 9: S_bulge(0) = −1 (valley floor), S(1) = 0, peak of the bulge at x = 5/3
    s = np.asarray(shape_function(np.array([0.0, 1.0, 5 / 3, 3.0, 4.0])))
    np.testing.assert_allclose(s, [-1.0, 0.0, (4 / 3) ** 2 * (2 / 3) / 9, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(shape_function(0.75, bulge=False), -((1 - 0.5) ** 3), atol=1e-6)
    # Eq. 10: (1/β) log((N̂ − N_f + Σ e^{β x}) / N̂)
    x = np.array([0.3, 0.1, -0.2])
    want = math.log((8 - 3 + np.exp(5 * x).sum()) / 8) / 5
    assert float(mellowmax(x, beta=5.0, n_hat=8)) == pytest.approx(want, rel=1e-5)
    masked = math.log((8 - 2 + np.exp(5 * x[:2]).sum()) / 8) / 5
    got = float(mellowmax(x, np.array([True, True, False]), beta=5.0, n_hat=8))
    assert got == pytest.approx(masked, rel=1e-5)
    standard = math.log(np.exp(5 * x).mean()) / 5  # N_f > N̂: the standard mellowmax
    assert float(mellowmax(x, beta=5.0, n_hat=2)) == pytest.approx(standard, rel=1e-5)


def _numpy_swarm(key, loss, m, n, epochs, dt, c1, c2, inertia):
    """Eq. 14–15 with lbest ring, random absorb and the inertia schedule, in float64 numpy,
    drawing the same random numbers as the library."""
    (trial_key,) = jax.random.split(key, 1)
    k_x, k_v, k_run = jax.random.split(trial_key, 3)
    x = np.asarray(jax.random.uniform(k_x, (m, n), jnp.float32), np.float64)
    v = 0.5 * (np.asarray(jax.random.uniform(k_v, (m, n), jnp.float32), np.float64) - x)
    seed = jax.random.bits(k_run, (), jnp.uint32)
    p, ps = x.copy(), loss(x)
    history = [ps.min()]
    a, b, c = inertia
    for t in range(epochs):
        r1, r2, r3 = np.asarray(counter_uniform(seed, jnp.uint32(t), (3, m, n)), np.float64)
        best = [min([(i - 1) % m, i, (i + 1) % m], key=lambda j: ps[j]) for i in range(m)]
        v = (a + b * c**t) * v + c1 * r1 * (p - x) + c2 * r2 * (p[best] - x)
        x = x + dt * v
        out = (x < 0) | (x > 1)
        x, v = np.where(out, r3, x), np.where(out, 0.0, v)
        s = loss(x)
        better = s < ps
        p[better], ps[better] = x[better], s[better]
        history.append(ps.min())
    return p[np.argmin(ps)], np.array(history)


def test_swarm_epochs_replay_eq14_15_in_numpy():
    target = np.array([0.3, 0.8, 0.55], np.float32)

    def loss(x):
        return np.sum((x - target) ** 2 * np.array([1.0, 3.0, 0.5]), axis=-1)

    settings = dict(dt=0.6, c1=1.5, c2=1.2, inertia=(0.3, 0.5, 0.7))
    key = jax.random.key(4)

    def jax_loss(u):
        return jnp.sum((u - target) ** 2 * jnp.array([1.0, 3.0, 0.5], jnp.float32), axis=-1)

    res = pso(key, jax_loss, (np.zeros(3), np.ones(3)), n_agents=6, n_epochs=5, **settings)
    best, history = _numpy_swarm(key, loss, 6, 3, 5, **settings)
    np.testing.assert_allclose(np.asarray(res.history[0]), history, rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(np.asarray(res.params), best, atol=1e-5)


def test_pore_strength_by_hand(graph):
    # Eq. 12–13: w_v = max(w_max + α_dmin, w_max + α_blend (Σ w − w_max)) over incident edges
    g = jax.tree.map(np.asarray, graph)
    w = np.where(g.edge_mask, np.linspace(0.05, 0.9, g.edge_mask.shape[0]), 0.0)
    got = np.asarray(pore_strength(graph, jnp.asarray(w), 0.1, 0.4))
    for i in range(int(g.node_count)):
        incident = w[g.half_edge[i][g.half_mask[i]]]
        top, total = incident.max(), incident.sum()
        assert got[i] == pytest.approx(max(top + 0.1, top + 0.4 * (total - top)), rel=1e-6)


def test_free_flight_follows_the_inertia_schedule():
    # with c1 = c2 = 0 each step is Δt w_t v (Eq. 14–15), so successive steps of an agent shrink
    # by w_t = a + b c^t (to float32 rounding of the tiny steps that keep the agents in the box)
    seen = []

    def loss(x):
        jax.debug.callback(lambda p: seen.append(np.asarray(p, np.float64)), x)
        return jnp.sum(x, axis=-1)

    a, b, c = 0.3, 0.5, 0.7
    pso(jax.random.key(5), loss, (np.zeros(2), np.ones(2)), n_agents=4, n_epochs=5,
        dt=1e-3, c1=0.0, c2=0.0, inertia=(a, b, c), batched=True)  # fmt: skip
    steps = np.diff(np.stack(seen), axis=0)  # (epochs, agents, dims)
    ratios = steps[1:] / steps[:-1]
    want = a + b * c ** np.arange(1, 5)
    np.testing.assert_allclose(ratios, np.broadcast_to(want[:, None, None], ratios.shape), 1e-2)


def test_random_absorb_stops_a_coordinate_where_it_left_the_box():
    # w = 1, c1 = c2 = 0, Δt = 1: each coordinate moves by its constant velocity until it leaves
    # [0, 1]; random_absorb then puts it at a random in-box value with zero velocity, so it
    # never moves again (Helwig et al. 2013, the paper's boundary handling)
    seen = []

    def loss(x):
        jax.debug.callback(lambda p: seen.append(np.asarray(p, np.float64)), x)
        return jnp.sum(x, axis=-1)

    pso(
        jax.random.key(6),
        loss,
        (np.zeros(3), np.ones(3)),
        n_agents=8,
        n_epochs=8,
        dt=1.0,
        c1=0.0,
        c2=0.0,
        inertia=(1.0, 0.0, 0.5),
        boundary="random_absorb",
        batched=True,
    )
    path = np.stack(seen)  # (evaluations, agents, dims)
    assert np.all((path >= 0) & (path <= 1))
    steps = np.diff(path, axis=0)
    left = 0
    for agent, dim in np.ndindex(steps.shape[1:]):
        d = steps[:, agent, dim]
        jumps = np.flatnonzero(np.abs(d - d[0]) > 1e-6)
        if jumps.size:  # the absorbing step, then no more motion
            left += 1
            np.testing.assert_array_equal(d[jumps[0] + 1 :], 0.0)
    assert left >= steps.shape[1] * steps.shape[2] // 2


def test_full_continuation_weight_leaves_no_orientation_term(graph):
    # Eq. 3 with α_cont = 1: (1 − α_cont) p_pref vanishes, so from zero weights (p_cont = 0) no
    # half-edge has a positive score and nothing is deposited
    params = WrinkleParams(cont=1.0, sim=0.0, cross=0.0)
    nodes = np.arange(int(graph.node_count))
    zeros = jnp.zeros(graph.edge_mask.shape[0], jnp.float32)
    assert not np.asarray(half_edge_scores(graph, params, zeros, nodes)).any()
    assert not np.asarray(simulate(jax.random.key(0), graph, params, n_steps=3, n_samples=5)).any()
