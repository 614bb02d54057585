"""Maps that read as skin: weak edges fade out, pores are pits that the extraction finds, and a
non-periodic map's border is carved like its interior."""

import jax
import numpy as np
import pytest
from scipy.spatial import cKDTree

from jface.wrinkles import WrinkleParams, find_pores, synthesize
from jface.wrinkles._drawing import DrawOptions, bin_primitives, primitives, render

D = 0.04  # 20 px between pores on a 512² map


@pytest.fixture(scope="module")
def patch():
    params = WrinkleParams(d=D, theta=0.5, s=0.05, cross=0.5)  # directional: many weak edges
    return params, synthesize(jax.random.key(3), params, (512, 512), periodic=True)


def _render(key, graph, weights, params, keep):
    """The map with only the primitives in ``keep`` drawn (pores keep their Eq. 13 strength)."""
    k_perturb, k_noise = jax.random.split(key)
    prims = primitives(k_perturb, graph, weights, params, (512, 512))
    prims = prims._replace(valid=prims.valid & keep)
    opts = DrawOptions(tile=16, span=32, capacity=16)
    bins = bin_primitives(prims, (512, 512), tile=16, span=32, bulge=True, periodic=True)
    return np.asarray(render(k_noise, prims, bins, params, (512, 512), opts, True))


def test_weak_edges_fade_out(patch):
    """Wrinkles with W < 0.1 contribute under 5 % of the drawn depth (no hairline floor)."""
    params, syn = patch
    level = syn.levels[0]
    w = np.asarray(level.weights)
    weak = np.mean(w[: int(level.graph.edge_count)] < 0.1)
    assert 0.2 < weak < 0.9  # a directional pattern: many weak edges
    quiet = params.replace(snoise=0.001)
    n = level.graph.node_mask.shape[0]
    everything = np.ones(w.shape[0] + n, bool)
    strong = np.concatenate([w >= 0.1, np.ones(n, bool)])
    key = jax.random.key(4)
    full = _render(key, level.graph, level.weights, quiet, everything)
    without = _render(key, level.graph, level.weights, quiet, strong)
    share = np.sum(np.abs(full - without)) / np.sum(np.abs(full))
    assert share < 0.05


def test_pores_are_found_by_the_extraction(patch):
    """At the default widths pores are pits: find_pores (§4.1) finds ≥ 80 % of the sampled pores
    within half a pore distance."""
    _, syn = patch
    pores = syn.levels[0].pores
    sampled = np.asarray(pores.positions)[: int(pores.count)]
    found = find_pores(syn.displacement)
    centres = np.asarray(found.positions)[: int(found.count)]
    dist, _ = cKDTree(centres, boxsize=1.0).query(sampled)
    assert np.mean(dist < 0.5 * D) >= 0.8
    assert len(centres) <= 1.2 * len(sampled)  # and not much else


def test_border_is_carved_like_the_interior():
    """A non-periodic map has no border band: the gradient energy in a strip along each border
    is within 10 % of the interior's."""
    params = WrinkleParams(d=0.02, theta=0.3, s=0.4, snoise=0.001)
    m = np.asarray(synthesize(jax.random.key(5), params, (512, 512), periodic=False).displacement)
    energy = np.diff(m, axis=0)[:, :-1] ** 2 + np.diff(m, axis=1)[:-1] ** 2
    strip = 40  # two pore distances
    border = np.ones(energy.shape, bool)
    border[strip:-strip, strip:-strip] = False
    assert abs(energy[border].mean() / energy[~border].mean() - 1) < 0.1
