"""Trail simulation: the behaviours of §3.1.2 / Fig. 5–6, weights in [0, 1], determinism, vmap,
exact compounding of deposits; parameters: ranges, textures, JSON, Perlin variation."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jface.wrinkles import (
    WrinkleParams,
    build_graph,
    load_params,
    make_pores,
    params_from_json,
    params_to_json,
    perlin_variation,
    sample_pores,
    save_params,
    simulate,
    stack_params,
)
from jface.wrinkles._simulation import CHUNK, converged_steps

STEPS, SAMPLES = 60, 2000


@pytest.fixture(scope="module")
def graph():
    return build_graph(sample_pores(jax.random.key(0), 0.02, periodic=True))


def run(graph, seed=1, **changes):
    return np.asarray(
        simulate(
            jax.random.key(seed), graph, WrinkleParams(**changes), n_steps=STEPS, n_samples=SAMPLES
        )
    )


def _valid(graph, w):
    return w[: int(graph.edge_count)]


def test_weights_in_unit_interval_and_deterministic(graph):
    w = run(graph)
    assert w.min() >= 0 and w.max() <= 1 and w.max() > 0.3
    assert not w[int(graph.edge_count) :].any()
    np.testing.assert_array_equal(w, run(graph))
    assert not np.array_equal(w, run(graph, seed=2))
    np.testing.assert_array_equal(
        run(graph, deposit=1.0, decay=0.0).clip(0, 1), run(graph, deposit=1.0, decay=0.0)
    )


def _axial(graph, w):
    w = _valid(graph, w)
    z = np.sum(w * np.exp(2j * np.asarray(graph.edge_angle)[: len(w)])) / w.sum()
    return np.angle(z) / 2, abs(z)


def test_orientation_concentrates_around_primary_angle(graph):
    mean, strength = _axial(graph, run(graph, s=0.0, theta=1.0))
    assert abs(mean - 1.0) < 0.1 and strength > 0.6
    _, uniform = _axial(graph, run(graph, s=1.0, theta=1.0))
    assert uniform < 0.5 * strength


def _crossing_weight(graph, w):
    e = int(graph.edge_count)
    cr, cm = np.asarray(graph.crossings)[:e], np.asarray(graph.crossing_mask)[:e]
    return float(np.sum(w[:e, None] * np.where(cm, w[cr], 0.0)))


def test_crossing_penalty_lowers_crossing_weight(graph):
    # against the printed orientation term (at most 1 + α_s) the penalty acts strongly on a
    # directional sampler and less on an even one
    assert _crossing_weight(graph, run(graph, cross=1.0, s=0.0)) < 0.3 * _crossing_weight(
        graph, run(graph, s=0.0)
    )
    assert _crossing_weight(graph, run(graph, cross=1.0)) < 0.9 * _crossing_weight(
        graph, run(graph)
    )


def test_distance_exponent_favours_short_edges(graph):
    length = np.asarray(graph.edge_length)[: int(graph.edge_count)]

    def mean_length(w):
        w = _valid(graph, w)
        return np.sum(w * length) / np.sum(w)

    assert mean_length(run(graph, dist=5.0)) < 0.95 * mean_length(run(graph))


def test_similarity_penalty_and_continuation(graph):
    # α_sim penalises similar directions at a pore: fewer same-side pairs of strong edges
    assert _crossing_weight(graph, run(graph, sim=2.0)) < _crossing_weight(graph, run(graph))
    w0, w1 = run(graph), run(graph, cont=0.01)
    assert not np.array_equal(w0, w1)


def test_texture_parameter_sets_orientation_locally(graph):
    theta = np.zeros((8, 8), np.float32)
    theta[:, 4:] = math.pi / 2
    w = run(graph, s=0.0, theta=theta)
    mid = np.asarray(graph.edge_midpoints())[: int(graph.edge_count)]
    ang = np.asarray(graph.edge_angle)[: int(graph.edge_count)]
    w = _valid(graph, w)
    left = (mid[:, 0] > 0.1) & (mid[:, 0] < 0.4)
    right = (mid[:, 0] > 0.6) & (mid[:, 0] < 0.9)
    for sel, target in ((left, 0.0), (right, math.pi / 2)):
        z = np.sum(w[sel] * np.exp(2j * ang[sel]))
        assert abs(np.angle(z * np.exp(-2j * target))) / 2 < 0.15  # axial: modulo π


def test_vmap_over_parameter_sets_equals_loop(graph):
    sets = [WrinkleParams(deposit=0.3, cross=0.5), WrinkleParams(deposit=0.8, dist=2.0)]
    keys = jax.random.split(jax.random.key(4), 2)
    batch = jax.vmap(lambda k, p: simulate(k, graph, p, n_steps=20, n_samples=SAMPLES))(
        keys, stack_params(sets)
    )
    for i, p in enumerate(sets):
        np.testing.assert_allclose(
            batch[i], simulate(keys[i], graph, p, n_steps=20, n_samples=SAMPLES), atol=1e-6
        )


def test_scoring_every_pore_equals_scoring_the_samples(graph):
    # the simulation scores every pore once per step when there are fewer pores than samples
    from jface.wrinkles import half_edge_scores
    from jface.wrinkles._simulation import _scores, _static_terms

    params = WrinkleParams(theta=0.4, s=0.2, dist=1.5, cont=0.006, sim=0.5, cross=0.7)
    w = jnp.where(
        graph.edge_mask,
        jax.random.uniform(jax.random.key(3), graph.edge_mask.shape, jnp.float32),
        0.0,
    )
    nodes = jax.random.randint(jax.random.key(4), (500,), 0, int(graph.node_count))
    every = jnp.arange(graph.half_mask.shape[0])
    terms = _static_terms(graph, params, every)
    all_scores = _scores(graph, params, terms, w, every, None, per_edge=True)
    expected = half_edge_scores(graph, params, w, nodes)
    assert float(jnp.max(expected)) > 0
    np.testing.assert_allclose(all_scores[nodes], expected, rtol=1e-5, atol=1e-7)
    # and a run where N exceeds the pore count takes that path and stays a valid simulation
    n = int(graph.node_count) + 100
    w = simulate(jax.random.key(1), graph, params, n_steps=10, n_samples=n)
    assert float(w.min()) >= 0 and float(w.max()) <= 1 and float(w.max()) > 0


def test_deposits_on_one_edge_compound_exactly():
    pores = make_pores(np.array([[0.3, 0.5], [0.6, 0.5]], np.float32), radius=0.2)
    graph = build_graph(pores, k=1)
    assert int(graph.edge_count) == 1
    params = WrinkleParams(deposit=0.5, decay=0.0)
    w = simulate(jax.random.key(0), graph, params, n_steps=1, n_samples=37)
    np.testing.assert_allclose(w[0], 1 - (1 - 0.03 * 0.5) ** 37, rtol=1e-5)
    w = simulate(
        jax.random.key(0), graph, WrinkleParams(deposit=0.5, decay=0.2), n_steps=3, n_samples=10
    )
    expect = 0.0
    for _ in range(3):
        expect = (1 - (1 - expect) * (1 - 0.015) ** 10) * (1 - 0.03 * 0.2 * 10)
    np.testing.assert_allclose(w[0], expect, rtol=1e-5)


def test_parameters_validated_and_json_round_trip(tmp_path, unchecked):
    with pytest.raises(ValueError, match=r"WrinkleParams.cross must be in \[0.0, 1.0\]"):
        WrinkleParams(cross=1.5)
    with pytest.raises(ValueError, match=r"WrinkleParams\.d must be in"):
        WrinkleParams(d=np.full((4, 4), 0.2, np.float32))
    with pytest.raises(ValueError, match="scalar or a 2-D texture"):
        WrinkleParams(theta=np.zeros(3, np.float32))
    with pytest.raises(ValueError, match="unknown"):
        WrinkleParams().replace(speed=1.0)
    levels = [
        WrinkleParams(d=0.02, theta=np.full((2, 3), 0.5, np.float32)),
        WrinkleParams(d=0.01, sim=1.0),
    ]
    back = params_from_json(params_to_json(levels, "uv"))
    for a, b in zip(levels, back, strict=True):
        jax.tree.map(np.testing.assert_array_equal, a, b)
    save_params(tmp_path / "p.json", levels, "uv")
    jax.tree.map(np.testing.assert_array_equal, levels[1], load_params(tmp_path / "p.json")[1])
    with pytest.raises(ValueError, match="not a WrinkleParams"):
        params_from_json('{"kind": "other"}')
    defaults = WrinkleParams()
    assert float(defaults.deposit) == 0.25 and float(defaults.decay) == 0.5
    assert all(float(getattr(defaults, n)) == 0 for n in ("dist", "cont", "sim", "cross"))


def test_perlin_variation_gives_textures_in_range(key):
    varied = perlin_variation(key, WrinkleParams(), {"d": 0.05, "cont": 0.3}, resolution=32)
    assert varied.d.shape == (32, 32) and varied.cont.shape == (32, 32)
    assert float(varied.d.min()) >= 0.001 and float(varied.d.max()) <= 0.05
    assert float(jnp.std(varied.d)) > 1e-4
    assert varied.theta.shape == ()


def test_bad_simulation_input(graph, unchecked):
    with pytest.raises(ValueError, match="decay factor"):
        simulate(jax.random.key(0), graph, WrinkleParams(decay=1.0), n_samples=10**7)
    with pytest.raises(TypeError, match="WrinkleParams"):
        simulate(jax.random.key(0), graph, {"deposit": 0.3})
    with pytest.raises(TypeError, match="random key"):
        simulate(0, graph, WrinkleParams())
    with pytest.raises(ValueError, match="weights must"):
        simulate(
            jax.random.key(0),
            graph,
            WrinkleParams(),
            weights=np.full(graph.edge_mask.shape, 2.0, np.float32),
        )


def test_default_run_is_converged(graph):
    """The default step count reaches equilibrium: a run 8× longer changes the weights' mean by
    under 5 % and the share of strong edges by under 0.02 (N/|E| as on a 130k-edge graph)."""
    params = WrinkleParams(d=0.02, s=0.2)
    n = int(0.38 * int(graph.edge_count))  # the ratio N/|E| of 50,000 samples on 130k edges
    steps = converged_steps(graph, params, n)
    short = _valid(graph, np.asarray(simulate(jax.random.key(3), graph, params, n_samples=n)))
    long = _valid(
        graph,
        np.asarray(simulate(jax.random.key(3), graph, params, n_samples=n, n_steps=8 * steps)),
    )
    assert abs(short.mean() - long.mean()) < 0.05 * long.mean()
    assert abs((short > 0.5).mean() - (long > 0.5).mean()) < 0.02
    # 50 steps (the old default) are far from it
    fifty = _valid(graph, np.asarray(simulate(jax.random.key(3), graph, params, n_samples=n,
                                              n_steps=50)))  # fmt: skip
    assert fifty.mean() < 0.6 * long.mean()


def test_default_run_in_chunks_equals_one_scan(graph):
    params = WrinkleParams(d=0.02, theta=0.4, s=0.3, cross=0.3)
    steps = converged_steps(graph, params)
    assert steps > CHUNK  # the default run goes in several chunks
    chunked = simulate(jax.random.key(4), graph, params, progress=True)
    whole = simulate(jax.random.key(4), graph, params, n_steps=steps)
    np.testing.assert_allclose(np.asarray(chunked), np.asarray(whole), atol=1e-6)


def test_fixed_steps_with_progress_move_the_bar_and_give_the_same_weights(capsys):
    graph = build_graph(sample_pores(jax.random.key(7), 0.05, periodic=True))
    params = WrinkleParams(d=0.05, theta=0.4)
    shown = simulate(jax.random.key(8), graph, params, n_steps=CHUNK + 10, progress=True)
    assert "2/2" in capsys.readouterr().err  # chunk by chunk, not 0/1 for the whole run
    whole = simulate(jax.random.key(8), graph, params, n_steps=CHUNK + 10)
    np.testing.assert_allclose(np.asarray(shown), np.asarray(whole), atol=1e-6)


def test_weights_do_not_depend_on_capacity():
    """The same pores stored with 1× and 2× the capacity, same key: the same weights (N is the
    paper's or |E|, never the array size), eagerly and under jit."""
    pores = sample_pores(jax.random.key(5), 0.03, periodic=True)
    n = int(pores.count)
    positions = np.asarray(pores.positions)[:n]
    small = build_graph(make_pores(positions, radius=0.03, periodic=True))
    large = build_graph(make_pores(positions, radius=0.03, capacity=2 * n, periodic=True))
    assert large.edge_mask.shape[0] > small.edge_mask.shape[0]
    assert int(large.edge_count) == int(small.edge_count)
    params = WrinkleParams(d=0.03, theta=1.0, s=0.2, cont=0.01, cross=0.2)
    e = int(small.edge_count)
    w_small = np.asarray(simulate(jax.random.key(6), small, params, n_steps=40))[:e]
    w_large = np.asarray(simulate(jax.random.key(6), large, params, n_steps=40))[:e]
    np.testing.assert_allclose(w_small, w_large, atol=1e-6)
    jitted = jax.jit(lambda g: simulate(jax.random.key(6), g, params, n_steps=40))
    np.testing.assert_allclose(np.asarray(jitted(large))[:e], w_small, atol=1e-6)
    np.testing.assert_allclose(np.asarray(jitted(small))[:e], w_small, atol=1e-6)


def test_orientation_term_as_printed(graph):
    """Without reward or penalty terms Eq. 3 is ``d^(−α_dist) (1 − α_cont)(α_s + exp(−|θ −
    α_θ|²_π / σ²))`` exactly as printed (not a normalised density), per pore up to the
    distance normalisation."""
    from jface.wrinkles import half_edge_scores, orientation_density, orientation_weight

    params = WrinkleParams(theta=0.8, s=0.7, dist=0.0)
    nodes = jnp.arange(int(graph.node_count))
    w = jnp.zeros(graph.edge_mask.shape, jnp.float32)
    got = np.asarray(half_edge_scores(graph, params, w, nodes))
    angle = np.asarray(graph.half_angle)[: len(nodes)]
    diff = np.abs((angle - 0.8 + np.pi / 2) % np.pi - np.pi / 2)
    want = np.where(np.asarray(graph.half_mask)[: len(nodes)], 0.7 + np.exp(-(diff**2) / 0.09), 0)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    # the density form integrates to one over [0, 2π)
    theta = np.linspace(0, 2 * np.pi, 20001, dtype=np.float32)[:-1]
    dens = np.asarray(orientation_density(theta, 0.8, 0.7, 0.3))
    assert np.mean(dens) * 2 * np.pi == pytest.approx(1.0, rel=1e-4)
    np.testing.assert_allclose(
        np.asarray(orientation_weight(theta, 0.8, 0.7, 0.3)) / dens, 2 * np.pi * 0.7
        + 2 * 0.3 * np.sqrt(np.pi) * math.erf(np.pi / 0.6), rtol=1e-5,
    )  # fmt: skip
