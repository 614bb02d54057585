"""Drawing (§3.2 of Weiss et al. 2023): Eq. 9 profile, mellowmax (Eq. 10), blending (Eq. 11),
pore strength (Eq. 12–13); the tiled rasteriser against a brute-force float64 reference; jit,
vmap, determinism, gradients; bad input."""

import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

import jface
from jface.wrinkles import (
    WrinkleParams,
    build_graph,
    draw,
    draw_bands,
    make_pores,
    mellowmax,
    pore_strength,
    radius_map_from_mesh,
    sample_pores,
    shape_function,
    simulate,
)
from jface.wrinkles._drawing import (
    BETA,
    FOOTPRINT,
    N_HAT,
    N_VERTICES,
    DrawOptions,
    _draw_flagged,
    _fragments,
    _render_tiles,
    _static_sizes,
    _tile_pixels,
    _Tiling,
    bin_primitives,
    needed_entries,
    needed_span,
    primitives,
    render,
)

N = 64


@pytest.fixture(scope="module")
def level():
    key = jax.random.key(3)
    params = WrinkleParams(d=0.05, theta=0.7, s=0.3, wrinkle_width=0.5, pore_width=0.3,
                           dmin=0.3, blend=0.6, skew=0.5, cushion=0.4, sperturb=1.0,
                           fperturb=150.0, snoise=0.05, fnoise=200.0)  # fmt: skip
    graph = build_graph(sample_pores(key, params.d, periodic=True))
    # the extraction tests' settings: compiled functions are shared across the two modules
    weights = simulate(key, graph, params, n_steps=60, n_samples=3000)
    return graph, weights, params


# ---------------------------------------------------------------- Eq. 9–11 on a straight wrinkle


def _straight(n_hat, bulge=True):
    """One wrinkle of weight 1 from (0.3, 0.5) to (0.7, 0.5). Perturbation and additive noise are
    Perlin noise sampled exactly at lattice points (where gradient noise is zero): the vertices lie
    at multiples of 1/140 and the pixel centres of a 128² map at odd multiples of 1/256."""
    graph = build_graph(make_pores(np.array([[0.3, 0.5], [0.7, 0.5]], np.float32), radius=0.4), k=1)
    params = WrinkleParams(d=0.05, wrinkle_width=0.6, pore_width=0.01, fperturb=140.0,
                           fnoise=256.0, scale=0.5)  # fmt: skip
    weights = jnp.zeros(graph.edge_mask.shape, jnp.float32).at[0].set(1.0)
    out = draw(jax.random.key(0), graph, weights, params, (128, 128), n_hat=n_hat, bulge=bulge)
    column = np.asarray(out, np.float64)[:, 64]  # x = 0.504, far from both pores
    # drawn at the pixel footprint: widened to sqrt(w² + f²), depth lowered by w / sqrt(w² + f²)
    width = np.hypot(0.6 * 0.05, FOOTPRINT / 128)
    dist = np.abs((np.arange(128) + 0.5) / 128 - 0.5) / width  # in valley half-widths
    return column, dist, 0.5 * (0.6 * 0.05) / width  # α_scale times the footprint's fade


def _eq9(x, bulge):
    if bulge:
        return np.where(x < 3, (x - 3) ** 2 * (x - 1) / 9, 0.0)
    return np.where(x < 1.5, -((1 - 2 * x / 3) ** 3), 0.0)


@pytest.mark.parametrize("bulge", [True, False])
def test_straight_wrinkle_has_the_eq9_profile(bulge):
    column, dist, depth = _straight(n_hat=1, bulge=bulge)  # standard mellowmax: one = value
    np.testing.assert_allclose(column, depth * _eq9(dist, bulge), atol=2e-6)
    assert column.min() < -0.75 * depth and (
        column.max() > 0.13 * depth if bulge else column.max() == 0
    )


def test_straight_wrinkle_blends_per_eq10_11():
    column, dist, depth = _straight(n_hat=16)
    s = depth * _eq9(dist, True)  # α_scale multiplies the fragments before the blend
    beta = 20.0

    def mm16(v):  # Eq. 10 with one fragment of value v ≥ 0 and N̂_f = 16
        return np.log((15 + np.exp(beta * v)) / 16) / beta

    np.testing.assert_allclose(column, mm16(np.maximum(s, 0)) - mm16(np.maximum(-s, 0)), atol=2e-6)


def test_shape_function_matches_eq9():
    x = np.linspace(0, 4, 101)
    np.testing.assert_allclose(shape_function(x), _eq9(x, True), atol=1e-6)
    np.testing.assert_allclose(shape_function(x, bulge=False), _eq9(x, False), atol=1e-6)
    assert float(shape_function(0.0)) == -1.0 and float(shape_function(1.0)) == 0.0


# ---------------------------------------------------------------- mellowmax (Eq. 10)


def _standard(x, beta=20.0):
    return np.log(np.mean(np.exp(beta * x), axis=-1)) / beta


def test_mellowmax_one_fragment_and_bounds():
    x = np.random.default_rng(0).uniform(0, 1, (50, 5))
    np.testing.assert_allclose(mellowmax(x[:, :1], n_hat=1), x[:, 0], rtol=1e-6)
    mm = np.asarray(mellowmax(x, n_hat=1), np.float64)
    np.testing.assert_allclose(mm, _standard(x), rtol=1e-5)
    assert np.all(mm >= x.mean(-1) - 1e-6) and np.all(mm <= x.max(-1) + 1e-6)
    # the modified version is the standard one of the fragments padded with zeros to N̂ = 16
    padded = np.concatenate([x, np.zeros((50, 11))], axis=-1)
    modified = np.asarray(mellowmax(x), np.float64)
    np.testing.assert_allclose(modified, _standard(padded), rtol=1e-5)
    assert np.all(modified >= padded.mean(-1) - 1e-6) and np.all(modified <= x.max(-1) + 1e-6)
    # more fragments than N̂: the standard mellowmax; masked fragments are absent
    many = np.random.default_rng(1).uniform(0, 2, (4, 40))
    np.testing.assert_allclose(mellowmax(many), _standard(many), rtol=1e-5)
    mask = np.arange(40) < 25
    np.testing.assert_allclose(mellowmax(many, mask=np.broadcast_to(mask, many.shape)),
                               _standard(many[:, :25]), rtol=1e-5)  # fmt: skip
    assert float(mellowmax(np.zeros(3), mask=np.zeros(3, bool))) == 0.0
    assert np.isfinite(float(mellowmax(np.array([30.0, 1.0]))))  # no float32 overflow


def test_pore_strength_eq12_13(level):
    graph, weights, _ = level
    got = np.asarray(pore_strength(graph, weights, 0.3, 0.6))
    w, ht, hm = (np.asarray(a) for a in (weights, graph.half_edge, graph.half_mask))
    for v in range(int(graph.node_count)):
        inc = w[ht[v][hm[v]]]
        wmax, wsum = inc.max(initial=0.0), inc.sum()
        assert got[v] == pytest.approx(max(wmax + 0.3, wmax + 0.6 * (wsum - wmax)), abs=1e-6)


# ---------------------------------------------------------------- rasteriser vs brute force


def _brute_force(key, graph, weights, params, shape):
    """Every primitive against every pixel in float64 numpy, blended with Eq. 10–11 directly."""
    k_perturb, _ = jax.random.split(key)
    p = primitives(k_perturb, graph, weights, params, shape)
    p = p._replace(**{f: np.asarray(getattr(p, f), np.float64) for f in p._fields if f != "valid"})
    p = p._replace(valid=np.asarray(p.valid))
    h, w = shape
    ys, xs = np.meshgrid((np.arange(h) + 0.5) / h, (np.arange(w) + 0.5) / w, indexing="ij")
    q = np.stack([xs, ys], -1).reshape(-1, 1, 2)
    rel = q - p.p0[None]
    rel -= np.round(rel)
    len2 = np.sum(p.delta**2, -1)
    t = np.clip(np.sum(rel * p.delta, -1) / np.where(len2 > 0, len2, 1), 0, 1)
    perp = rel - t[..., None] * p.delta
    normal = (
        np.stack([-p.delta[:, 1], p.delta[:, 0]], -1)
        / np.sqrt(np.where(len2 > 0, len2, 1))[:, None]
    )
    vert = np.linspace(0, 1, N_VERTICES)
    offset = np.stack([np.interp(t[:, i], vert, p.offsets[i]) for i in range(len(len2))], -1)
    perp -= offset[..., None] * normal
    along = np.sum(perp * p.axis, -1)
    across = perp[..., 0] * p.axis[:, 1] - perp[..., 1] * p.axis[:, 0]
    x = np.sqrt((along / p.stretch) ** 2 + across**2) / np.where(p.valid, p.width, 1)
    covered = p.valid & (x < 3)

    def smooth(u):
        return u * u * (3 - 2 * u)

    strength = p.strength + p.cushion[:, 0] * (1 - smooth(np.minimum(t, 0.5) * 2))
    strength += p.cushion[:, 1] * (1 - smooth(np.minimum(1 - t, 0.5) * 2))
    s = np.where(covered, strength * _eq9(x, True), 0.0)
    n = covered.sum(-1)
    n_hat = np.maximum(16, n)

    def mm(v):
        return np.log((n_hat - n + np.sum(np.where(covered, np.exp(20 * v), 0), -1)) / n_hat) / 20

    return (mm(np.maximum(s, 0)) - mm(np.maximum(-s, 0))).reshape(h, w)


def test_tiled_rasteriser_matches_brute_force(level):
    graph, weights, params = level
    key = jax.random.key(5)
    quiet = params.replace(snoise=0.001, scale=0.9)
    got = np.asarray(draw(key, graph, weights, quiet, (N, N), tile=8, capacity=4), np.float64)
    ref = _brute_force(key, graph, weights, quiet, (N, N))
    noise_bound = 0.001 * 1.5  # α_scale is in the primitives: only the additive noise is left
    assert np.max(np.abs(got - ref)) < noise_bound + 1e-5
    assert ref.min() < -0.2 and ref.max() > 0.005  # there is something to compare
    # another tile size and capacity give the same map (performance settings only)
    other = draw(key, graph, weights, quiet, (N, N), tile=N, capacity=7)
    np.testing.assert_allclose(other, got, atol=1e-5)


def test_packed_bins_and_passes_as_needed_draw_the_same_map(level):
    """Packing the (primitive, tile) pairs before sorting, and drawing each tile with as many
    passes as it needs (the swarm's fast path), change nothing but the cost."""
    graph, weights, params = level
    key = jax.random.key(5)
    prims = primitives(key, graph, weights, params, (N, N))
    sizes = {"tile": 8, "bulge": True, "periodic": True}
    span = needed_span(prims, (N, N), **sizes)
    pairs = needed_entries(prims, (N, N), **sizes)
    full = bin_primitives(prims, (N, N), span=span, **sizes)
    packed = bin_primitives(prims, (N, N), span=span, entries=pairs, **sizes)
    assert not bool(full.overflow) and not bool(packed.overflow)
    np.testing.assert_array_equal(packed.count, full.count)
    np.testing.assert_array_equal(packed.start, full.start)
    np.testing.assert_array_equal(packed.order[:pairs], full.order[:pairs])
    assert bool(bin_primitives(prims, (N, N), span=span, entries=pairs - 1, **sizes).overflow)

    passes = -(-int(jnp.max(full.count)) // 4)
    opts = DrawOptions(tile=8, capacity=4, span=span, passes=passes)
    static = render(key, prims, full, params, (N, N), opts, True)
    as_needed = jax.jit(
        lambda p, b: render(key, p, b, params, (N, N), opts._replace(passes=None), True)
    )(prims, packed)
    np.testing.assert_allclose(as_needed, static, atol=1e-6)
    assert float(jnp.std(static)) > 0.01


@pytest.mark.parametrize("periodic", [True, False])
def test_bins_list_each_tiles_primitives_in_order(level, periodic):
    """Every tile's bin holds exactly the valid primitives whose reach (width × profile extent ×
    stretch, plus the largest centre-line offset) overlaps it, in primitive order, against a
    loop over the primitives' pixel boxes; on a periodic map a box wraps round, on a plain one it
    is cut at the border."""
    graph, weights, params = level
    key = jax.random.key(5)
    prims = primitives(key, graph, weights, params, (N, N))
    # some invalid primitives among the valid ones: they take no slot
    prims = prims._replace(valid=prims.valid & (jnp.arange(prims.valid.shape[0]) % 5 != 0))
    tile, grid = 8, N // 8
    bins = bin_primitives(prims, (N, N), tile=tile, span=grid, bulge=True, periodic=periodic)
    p = jax.tree.map(np.asarray, prims)
    reach = p.width * 3.0 * p.stretch + np.abs(p.offsets).max(-1)
    ends = np.stack([p.p0, p.p0 + p.delta])
    lo, hi = ends.min(0) - reach[:, None], ends.max(0) + reach[:, None]
    first, last = np.floor(lo * N / tile).astype(int), np.floor(hi * N / tile).astype(int)
    expected = [[] for _ in range(grid * grid)]
    for i in np.flatnonzero(p.valid):
        xs, ys = range(first[i, 0], last[i, 0] + 1), range(first[i, 1], last[i, 1] + 1)
        cells = {(x % grid, y % grid) for x in xs for y in ys}
        if not periodic:
            cells = {(x, y) for x in xs for y in ys if 0 <= x < grid and 0 <= y < grid}
        for x, y in cells:
            expected[y * grid + x].append(i)
    order, start, count = map(np.asarray, (bins.order, bins.start, bins.count))
    assert not bool(bins.overflow)
    np.testing.assert_array_equal(count, [len(e) for e in expected])
    for t, e in enumerate(expected):
        np.testing.assert_array_equal(order[start[t] : start[t] + count[t]], e)
    assert count.max() > 1 and count.min() < count.max()  # there is something to sort


def test_passes_beyond_the_need_change_neither_map_nor_gradient(level):
    """A tile batch skips the passes beyond its fullest tile: a static bound four times the need
    (as the fit's refinement sets one bound for every answer) gives the same map and the same
    gradient, bit for bit."""
    graph, weights, params = level
    key = jax.random.key(5)
    prims = primitives(key, graph, weights, params, (N, N))
    sizes = {"tile": 8, "bulge": True, "periodic": True}
    span = needed_span(prims, (N, N), **sizes)
    bins = bin_primitives(prims, (N, N), span=span, **sizes)
    need = -(-int(jnp.max(bins.count)) // 4)

    def drawn(passes):
        opts = DrawOptions(tile=8, capacity=4, span=span, passes=passes)

        def energy(scale):  # through the strengths of every wrinkle and pore
            scaled = prims._replace(strength=scale * prims.strength)
            return jnp.sum(render(key, scaled, bins, params, (N, N), opts, True) ** 2)

        return jax.jit(jax.value_and_grad(energy))(jnp.float32(1.0))

    exact, bound = drawn(need), drawn(4 * need)
    assert need > 1 and float(exact[1]) != 0.0
    np.testing.assert_array_equal(bound, exact)


@pytest.mark.parametrize("bulge", [True, False])
def test_the_drawings_gradient_is_reverse_mode_through_every_fragment_at_once(level, bulge):
    """The differentiable drawing's own gradient (the fragments recomputed pass by pass, each
    weighted by its softmax share on its side of Eq. 11) equals reverse-mode autodiff of a
    dense reference: every pixel against every primitive, blended with ``mellowmax``."""
    graph, weights, params = level
    prims = primitives(jax.random.key(5), graph, weights, params, (N, N))
    floats, valid = prims._replace(valid=None), prims.valid
    sizes = {"tile": 8, "bulge": bulge, "periodic": True}
    bins = bin_primitives(prims, (N, N), span=needed_span(prims, (N, N), **sizes), **sizes)
    tids = jnp.arange((N // 8) ** 2, dtype=jnp.int32)
    q = jax.vmap(lambda t: _tile_pixels(_Tiling((N, N), 8, 4, None, bulge, True, 0, 0), t))(tids)
    mix = jax.random.normal(jax.random.key(6), (tids.shape[0], 8, 8), jnp.float32)  # per pixel

    def tiled(fl):
        opts = {"tile": 8, "capacity": 4, "passes": 64, "bulge": bulge, "periodic": True}
        return _render_tiles(fl._replace(valid=valid), bins, tids, (N, N), beta=BETA,
                             n_hat=N_HAT, **opts)  # fmt: skip

    def dense(fl):
        s, covered = _fragments(fl._replace(valid=valid), q.reshape(-1, 2), True, bulge)
        side = [mellowmax(jnp.maximum(sign * s, 0.0), covered) for sign in (1.0, -1.0)]
        return (side[0] - side[1]).reshape(mix.shape)

    energy = [
        jax.jit(jax.value_and_grad(lambda fl, f=f: jnp.sum(f(fl) * mix))) for f in (tiled, dense)
    ]
    (got, grad), (want, grad_ref) = (e(floats) for e in energy)
    assert float(got) == pytest.approx(float(want), rel=1e-5)
    for name, g, r in zip(floats._fields, grad, grad_ref, strict=True):
        if r is not None:
            assert float(jnp.max(jnp.abs(r))) > 0, name  # every field moves the map
            np.testing.assert_allclose(g, r, atol=2e-5 * float(jnp.max(jnp.abs(r))), err_msg=name)


def test_jit_eager_vmap_determinism_and_grad(level):
    graph, weights, params = level
    key = jax.random.key(1)
    eager = draw(key, graph, weights, params, (N, N))
    jitted = jax.jit(lambda k, p: draw(k, graph, weights, p, (N, N)))
    np.testing.assert_allclose(jitted(key, params), eager, atol=1e-5)
    np.testing.assert_array_equal(draw(key, graph, weights, params, (N, N)), eager)
    assert not np.array_equal(draw(jax.random.key(2), graph, weights, params, (N, N)), eager)

    # a batch of agents with different drawing parameters and α_d
    agents = [params.replace(wrinkle_width=ww, d=d) for ww, d in ((0.2, 0.04), (0.6, 0.05))]
    batch = jax.tree.map(lambda *xs: jnp.stack(xs), *agents)
    keys = jax.random.split(key, 2)
    vm = jax.vmap(lambda k, p: draw(k, graph, weights, p, (N, N)))(keys, batch)
    for i, p in enumerate(agents):
        np.testing.assert_allclose(vm[i], draw(keys[i], graph, weights, p, (N, N)), atol=1e-5)

    names = ("wrinkle_width", "pore_width", "dmin", "blend", "skew", "cushion", "sperturb",
             "snoise", "scale")  # fmt: skip

    def loss(values):
        p = params.replace(**dict(zip(names, values, strict=True)))
        return jnp.sum(draw(key, graph, weights, p, (32, 32)) ** 2)

    grads = jax.grad(loss)([getattr(params, n) for n in names])
    assert all(np.isfinite(float(g)) for g in grads)
    g = dict(zip(names, (float(g) for g in grads), strict=True))
    # Eq. 13 is a max: only one of α_dmin, α_blend moves a given pore
    assert all(v != 0 for n, v in g.items() if n not in ("dmin", "blend"))
    assert g["dmin"] != 0 or g["blend"] != 0


def test_textured_params_and_skew_orientation(level):
    graph, weights, params = level
    texture = jnp.broadcast_to(jnp.linspace(0.1, 0.9, 16, dtype=jnp.float32), (16, 16))
    out = draw(jax.random.key(0), graph, weights, params.replace(scale=texture), (N, N))
    flat = draw(jax.random.key(0), graph, weights, params.replace(scale=0.5), (N, N))
    # α_scale grows along x: the right half carries more displacement than the left
    assert np.abs(out[:, N // 2 :]).sum() > np.abs(out[:, : N // 2]).sum()
    assert not np.allclose(out, flat)


def test_bad_input(level, unchecked):
    graph, weights, params = level
    key = jax.random.key(0)
    with pytest.raises(ValueError, match=r"shape\[0\]"):
        draw(key, graph, weights, params, (0, 8))
    with pytest.raises(ValueError, match=r"shape\[1\]"):
        draw(key, graph, weights, params, (8, 10**6))
    with pytest.raises(ValueError, match="weights must lie in"):
        draw(key, graph, weights + 2.0, params, (8, 8))
    with pytest.raises(ValueError, match="weights must have shape"):
        draw(key, graph, weights[:3], params, (8, 8))
    with pytest.raises(TypeError, match="shape must be a pair"):
        draw(key, graph, weights, params, 8)
    with pytest.raises(TypeError, match="params must be WrinkleParams"):
        draw(key, graph, weights, {"d": 0.01}, (8, 8))
    with pytest.raises(ValueError, match=r"WrinkleParams.scale must be in \[0.1, 0.9\]"):
        params.replace(scale=2.0)
    with pytest.raises(ValueError, match=r"WrinkleParams.fnoise must be in \[100.0, 150000.0\]"):
        WrinkleParams(fnoise=0.05)
    with pytest.raises(ValueError, match="tile must divide"):
        draw(key, graph, weights, params, (N, N), tile=5)
    with pytest.raises(Exception, match="span=1"):
        draw(key, graph, weights, params, (N, N), tile=4, span=1)


def test_a_crowded_tile_is_an_error_eager_and_under_jit(level):
    """Concrete inputs draw with a program that holds no host callback (JAX's persistent
    compilation cache keeps it) and raise here; under jit the check runs in the program."""
    graph, weights, params = level
    key, shape = jax.random.key(0), (N, N)
    few = {"tile": 32, "capacity": 1, "passes": 1}
    with pytest.raises(ValueError, match="passes·capacity=1 wrinkles"):
        draw(key, graph, weights, params, shape, **few)
    jitted = jax.jit(lambda w: draw(key, graph, w, params, shape, **few))
    with pytest.raises(Exception, match="passes·capacity=1 wrinkles"):
        jax.block_until_ready(jitted(weights))
    prims = primitives(key, graph, weights, params, shape)
    opts = _static_sizes(prims, shape, DrawOptions(True, 16, 16, None, None, BETA, N_HAT), True)
    program = jax.make_jaxpr(lambda: _draw_flagged(key, prims, params, shape, opts, True))()
    assert "callback" not in str(program)


def test_old_json_without_drawing_fields_loads():
    from jface.wrinkles import params_from_json

    (p,) = params_from_json('{"kind": "WrinkleParams", "levels": [{"d": 0.02}]}', frame="uv")
    assert float(p.scale) == pytest.approx(0.5) and float(p.wrinkle_width) == pytest.approx(0.3)
    assert math.isclose(float(p.d), 0.02, rel_tol=1e-6)


# ---------------------------------------------------------------- maps larger than memory


def test_bands_join_to_the_whole_map(level):
    graph, weights, params = level
    key = jax.random.key(1)
    whole = draw(key, graph, weights, params, (N, N))  # compiled once for this module
    parts = list(draw_bands(key, graph, weights, params, (N, N), band=20))
    # bands of whole tiles (16 px) top to bottom, the last one cut at the map's edge
    assert [(r, x.shape) for r, x in parts] == [(0, (32, N)), (32, (32, N))]
    joined = np.concatenate([np.asarray(x) for _, x in parts])
    np.testing.assert_allclose(joined, whole, atol=1e-7)  # the same arithmetic, fused otherwise
    assert np.ptp(np.asarray(whole)) > 0.01  # there is a map to compare


def test_exr_rows_writes_in_pieces_atomically(tmp_path):
    from jface.io import exr_rows, read_exr

    image = np.random.default_rng(0).normal(size=(40, 24)).astype(np.float32)
    out = tmp_path / "m.exr"
    with exr_rows(out, (40, 24), metadata={"seed": 7, "levels": [{"d": 0.01}]}) as write:
        for r in range(0, 40, 16):
            write(image[r : r + 16])
    got = read_exr(out)
    np.testing.assert_array_equal(got.channels["Y"], image)
    assert got.metadata["seed"] == 7 and got.metadata["levels"] == [{"d": 0.01}]
    # too few rows, a wrong width, too many rows: an error and no file (an old one is kept)
    short = pytest.raises(ValueError, match="only 16 of the map's 40 rows")
    with short, exr_rows(out, (40, 24)) as w:
        w(image[:16])
    np.testing.assert_array_equal(read_exr(out).channels["Y"], image)
    for bad, message in (
        (image[:8, :20], r"rows must have shape \(n, 24\)"),
        (np.concatenate([image, image[:1]]), "more than the map's 40 rows"),
    ):
        with pytest.raises(ValueError, match=message), exr_rows(tmp_path / "w.exr", (40, 24)) as w:
            w(bad)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.exr"]
    with pytest.raises(ValueError, match="shape must be two"), exr_rows(tmp_path / "x", (0, 4)):
        pass


def test_cli_renders_large_maps_band_by_band(tmp_path, monkeypatch, level):
    """Above BANDED_ABOVE the command draws (synthesize_bands), blends with the scan and writes
    band by band: the same EXR as the whole-map path, with provenance and a preview PNG. (The
    fixture's settings, so that the compiled simulation and drawing are shared.)"""
    import argparse

    from jface.cli import _wrinkles
    from jface.io import read_exr, read_image, write_exr
    from jface.wrinkles import save_params

    params = tmp_path / "p.json"
    save_params(params, [level[2]], "uv")
    write_exr(tmp_path / "scan.exr", np.random.default_rng(3).normal(size=(N, N)).astype("f4"))
    parser = argparse.ArgumentParser()
    _wrinkles.register(parser.add_subparsers())

    def render(out):
        args = parser.parse_args(["wrinkles", "render", "--params", str(params), "--size",
                                  str(N), "--base", str(tmp_path / "scan.exr"), "--out",
                                  str(tmp_path / out), "--seed", "4", "--periodic",
                                  "--steps", "60", "--samples", "3000"])  # fmt: skip
        args.run(args)
        return read_exr(tmp_path / out)

    whole = render("whole.exr")
    monkeypatch.setattr(_wrinkles, "BANDED_ABOVE", N // 2)
    monkeypatch.setattr(_wrinkles, "_PREVIEW", N // 2)
    monkeypatch.setattr("jface.wrinkles._synthesis.default_band", lambda shape: 20)
    banded = render("banded.exr")
    np.testing.assert_allclose(banded.channels["Y"], whole.channels["Y"], atol=1e-6)
    assert banded.metadata["seed"] == 4 and banded.metadata["size"] == N
    assert read_image(tmp_path / "banded.png").shape[:2] == (N // 2, N // 2)  # the preview


# ---------------------------------------------------------------- radius map from UV stretch


def _two_charts(n=8):
    """A UV atlas of two charts: u < 0.5 maps to a plane 2× larger in 3-D (UV squashed, stretch
    σ = 2), u > 0.5 to one of the same size (σ = 1)."""
    g = np.linspace(0.0, 1.0, n + 1)
    uu, vv = np.meshgrid(g, g)
    i = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None]).ravel()
    quad = np.concatenate([[i, i + 1, i + n + 2], [i, i + n + 2, i + n + 1]], axis=1).T
    verts, faces, uvs = [], [], []
    for k, (u0, scale) in enumerate(((0.0, 2.0), (0.5, 1.0))):
        uv = np.stack([u0 + 0.5 * uu.ravel(), vv.ravel()], 1)
        verts.append(np.concatenate([scale * uv + [3.0 * k, 0.0], np.zeros((len(uv), 1))], 1))
        faces.append(quad + k * len(uv))
        uvs.append(uv)
    from jface.io import MeshData

    return MeshData(np.concatenate(verts), np.concatenate(faces), np.concatenate(uvs))


def test_radius_map_from_known_uv_stretch():
    mesh = _two_charts()
    r = np.asarray(radius_map_from_mesh(mesh, 64, smooth=1.0), np.float64)
    assert r.shape == (64, 64)
    # R = σ̄ / σ with σ̄ the geometric mean: 1/√2 on the squashed chart, √2 on the other
    np.testing.assert_allclose(r[:, :26], 2**-0.5, rtol=1e-5)
    np.testing.assert_allclose(r[:, 38:], 2**0.5, rtol=1e-5)
    # pores sampled with it are evenly spaced on the surface: the same 3-D spacing in both charts
    pores = sample_pores(jax.random.key(0), 0.04, r, periodic=False)
    uv = np.asarray(pores.positions)[: int(pores.count)]
    xyz = uv * np.where(uv[:, :1] < 0.5, 2.0, 1.0)
    spacing = []
    for chart in (uv[:, 0] < 0.45, uv[:, 0] > 0.55):
        d, _ = cKDTree(xyz[chart]).query(xyz[chart], k=2)
        spacing.append(np.median(d[:, 1]))
    assert 0.85 < spacing[0] / spacing[1] < 1.15, spacing  # uniform UV spacing would give 2
    # a real mesh: positive, finite, geometric mean 1 where the face covers the map
    from jface.io import read_mesh

    face = read_mesh(Path(jface.__file__).parent / "data" / "mediapipe_canonical_face.obj")
    r = np.asarray(radius_map_from_mesh(face, 128, smooth=0.0))
    assert np.all(np.isfinite(r)) and r.min() > 0 and np.ptp(r) > 0.5
    covered = r != 1.0
    assert covered.mean() > 0.3 and abs(np.mean(np.log(r[covered]))) < 1e-3


def test_radius_map_bad_input(unchecked):
    mesh = _two_charts()
    with pytest.raises(ValueError, match="no UV coordinates"):
        radius_map_from_mesh(mesh._replace(uv=None), 64)
    with pytest.raises(TypeError, match="mesh must have vertices, faces and uv"):
        radius_map_from_mesh(np.zeros((3, 3)), 64)
    with pytest.raises(ValueError, match="size"):
        radius_map_from_mesh(mesh, 0)
    with pytest.raises(ValueError, match="maps every triangle to a point"):
        radius_map_from_mesh(mesh._replace(uv=np.zeros_like(mesh.uv)), 64)


# ---------------------------------------------------------------- α_scale, perturbation, seams


def test_scale_multiplies_the_fragments_before_the_blend(level):
    """α_scale scales every wrinkle and pore strength (and the cushion) before Eq. 10–11: a map
    drawn with α_scale is the map of primitives drawn at another α_scale and pre-scaled."""
    graph, weights, params = level
    key = jax.random.key(2)
    low, high = params.replace(scale=0.3), params.replace(scale=0.9)
    p_low = primitives(key, graph, weights, low, (N, N))
    p_high = primitives(key, graph, weights, high, (N, N))
    np.testing.assert_allclose(p_high.strength, 3.0 * p_low.strength, rtol=1e-5)
    np.testing.assert_allclose(p_high.cushion, 3.0 * p_low.cushion, rtol=1e-5)
    prescaled = p_low._replace(strength=3.0 * p_low.strength, cushion=3.0 * p_low.cushion)
    opts = DrawOptions(tile=8, span=N // 8, passes=64, capacity=16)
    bins = bin_primitives(prescaled, (N, N), tile=8, span=N // 8, bulge=True, periodic=True)
    drawn = render(key, p_high, bins, high, (N, N), opts, True)
    np.testing.assert_allclose(drawn, render(key, prescaled, bins, high, (N, N), opts, True),
                               atol=1e-6)  # fmt: skip
    assert float(jnp.std(drawn)) > 0.01
    # the blend is non-linear: scaling the finished map instead gives another map
    quiet = params.replace(snoise=0.001)
    m_low = np.asarray(draw(key, graph, weights, quiet.replace(scale=0.3), (N, N), tile=8))
    m_high = np.asarray(draw(key, graph, weights, quiet.replace(scale=0.9), (N, N), tile=8))
    assert np.max(np.abs(m_high - 3.0 * m_low)) > 0.05


def test_wrinkles_stay_joined_at_their_pores(level):
    """One perturbation field moves the pores and the wrinkle ends with them: every drawn
    wrinkle starts and ends exactly at its pores' drawn centres, while the field does move
    the geometry (by up to α_sperturb · α_wrinkle-width · α_d)."""
    graph, weights, params = level
    prims = primitives(jax.random.key(7), graph, weights, params, (N, N))
    e, n = int(graph.edge_count), int(graph.node_count)
    m = graph.edge_mask.shape[0]
    pore = np.asarray(prims.p0)[m : m + n]
    start = np.asarray(prims.p0)[:e]
    end = start + np.asarray(prims.delta)[:e]
    nodes = np.asarray(graph.edge_nodes)[:e]

    def gap(a, b):  # periodic distance
        d = a - b
        return np.abs(d - np.round(d)).max()

    assert gap(start, pore[nodes[:, 0]]) < 1e-6  # float32 rounding, far below a valley width
    assert gap(end, pore[nodes[:, 1]]) < 1e-6
    assert np.all(np.asarray(prims.offsets)[:e][:, [0, -1]] == 0)
    moved = np.linalg.norm(pore - np.asarray(graph.positions)[:n], axis=-1)
    reach = float(params.sperturb * params.wrinkle_width * params.d)
    assert 0.1 * reach < moved.max() <= 1.5 * reach
    assert np.abs(np.asarray(prims.offsets)[:e]).max() > 0.05 * reach


def test_periodic_map_tiles_without_a_seam(level):
    """Perturbation and additive noise are periodic on periodic maps: the squared difference
    across the wrap-around edges is within 10 % of that between neighbouring interior pixels."""
    graph, weights, params = level
    seam, inner = [], []
    for seed in range(4):  # 2048 pixel pairs across the seams: a few % sampling noise
        m = np.asarray(draw(jax.random.key(seed), graph, weights, params, (256, 256)), np.float64)
        seam += [m[:, 0] - m[:, -1], m[0] - m[-1]]
        inner += [np.diff(m, axis=1).ravel(), np.diff(m, axis=0).ravel()]
    ratio = np.mean(np.concatenate(seam) ** 2) / np.mean(np.concatenate(inner) ** 2)
    assert abs(ratio - 1) < 0.1


def test_sub_pixel_wrinkle_fades_instead_of_a_hairline():
    """A wrinkle far narrower than a pixel, through a row of pixel centres, is drawn at the
    pixel footprint with its depth × width kept: a faint valley, not a full-depth hairline."""
    y = 64.5 / 128  # the centres of pixel row 64
    graph = build_graph(make_pores(np.array([[0.3, y], [0.7, y]], np.float32), radius=0.4), k=1)
    params = WrinkleParams(d=0.002, wrinkle_width=0.1, pore_width=0.01, sperturb=0.001,
                           snoise=0.001, scale=0.9)  # fmt: skip
    weights = jnp.zeros(graph.edge_mask.shape, jnp.float32).at[0].set(1.0)
    out = np.asarray(draw(jax.random.key(0), graph, weights, params, (128, 128), n_hat=1))
    half_width = 1.0 * 0.1 * 0.002 * 128  # 0.026 px
    fade = half_width / np.hypot(half_width, FOOTPRINT)
    column = out[:, 64]
    assert column[64] == pytest.approx(-0.9 * fade, abs=0.0015)  # ≈ 3 % of the full depth 0.9
    assert abs(column[63]) > 1e-3 and abs(column[65]) > 1e-3  # spread over the footprint
