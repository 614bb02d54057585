"""Wrinkle parameter fitting: recovery of known parameters (Fig. 12 of Weiss et al. 2023), the
gradient refinement, the CLI, bad input. A small setting (64², α_d near its top, few agents):
the fitted pipeline compiles once per module."""

import dataclasses
import inspect
import json
import logging
from pathlib import Path
from types import SimpleNamespace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from conftest import TINY_FIT

from jface import _compilation
from jface._compilation import kept_arrays, kept_path
from jface.cli import main
from jface.io import write_exr
from jface.optim import texture_stats
from jface.optim._pso import Swarm, swarm_settings
from jface.wrinkles import WrinkleParams, _fit, fit_budget, fit_wrinkles, heldout_key_count
from jface.wrinkles._drawing import needed_entries
from jface.wrinkles._fit import (
    _bfgs,
    _draw,
    _drawing_fields,
    _layout,
    _levels_from,
    _refine,
    _simulate,
    _SwarmLoss,
)

D_RANGE = (0.04, 0.05)
# α_wrinkle-width is not fitted: its loss profile (the others at truth, two simulation keys) moves
# by 4 % over its whole Table 1 range [0.1, 0.6] (minimum at 0.25-0.35), less than the losses of
# a swarm's trials differ, so no fit here could recover it
NAMES = ("1.deposit", "1.theta")
TRUE = (
    WrinkleParams(d=0.045, theta=1.0, s=0.2, deposit=0.6, wrinkle_width=0.3),
    WrinkleParams(d=0.0225, theta=1.0, s=0.2, deposit=0.6, snoise=0.001),
)
SMALL = {"d_range": D_RANGE, "n_agents": 10, "n_epochs": 10, "n_steps": 30, "d_levels": 4}
# held-out simulation keys for scores outside a fit (as many as a default fit's)
HELDOUT = jax.random.split(jax.random.key(5), _fit.HELDOUT_KEYS)


def synthesize(key, levels, layout):
    sims, levels = _simulate(key, levels, layout)
    return _draw(key, sims, levels, layout)


@pytest.fixture(scope="module")
def target():
    """A 64² map drawn with TRUE from other pores and another simulation key than the fit's."""
    layout = _layout(jax.random.key(7), (64, 64), D_RANGE, SMALL["n_steps"], SMALL["d_levels"])
    return np.asarray(synthesize(jax.random.key(123), TRUE, layout))


@pytest.fixture(scope="module")
def layout():
    """The fits' pores and graphs (every fit's, whatever its seed)."""
    return _layout(_fit.layout_key(), (64, 64), D_RANGE, SMALL["n_steps"], SMALL["d_levels"])


@pytest.fixture(scope="module")
def fit(target):
    return fit_wrinkles(
        jax.random.key(0), target, names=NAMES, base=TRUE, n_trials=1, refine_steps=4, **SMALL
    )


def test_recovers_deposit_and_orientation(fit, target, layout):
    loss = eqx.filter_jit(_SwarmLoss(fit.sim_key, texture_stats(target), TRUE, layout, NAMES))
    # the truth and α_deposit 0.3 / 0.9 with α_θ at truth (one compiled call)
    points = jnp.array([[0.6, 1.0], [0.3, 1.0], [0.9, 1.0]], jnp.float32)
    true_loss, low, high = (float(v) for v in loss(points))
    # α_deposit is identifiable with this loss: its profile (the others at truth, this target,
    # 30 steps, α_d on the 4-value grid; measured on a grid of 0.05) has its minimum at
    # 0.60-0.65, stays within 10 % of it only over [0.55, 0.72] and is 2.8x / 1.7x higher at
    # 0.3 / 0.9. The α_θ profile has its minimum at 1.0 and stays within 10 % over [0.64, 1.05].
    # Tolerances: those bands.
    assert low > 2.0 * true_loss and high > 1.3 * true_loss
    assert float(fit.swarm_loss) <= 1.1 * true_loss
    deposit, theta = float(fit.swarm.params[0]), float(fit.swarm.params[1])
    assert abs(deposit - 0.6) < 0.15
    # wrinkle orientations are axial: α_θ and α_θ + π give the same pattern
    assert abs((theta - 1.0 + np.pi / 2) % np.pi - np.pi / 2) < 0.4


def test_refinement_never_worsens_and_history_is_monotone(fit, target, layout):
    # the fit's answer with the widest α_wrinkle-width, refined by gradient on that field
    names = (*NAMES, "1.wrinkle_width")
    x = jnp.concatenate([fit.swarm.params, jnp.array([0.6], jnp.float32)])
    start = _SwarmLoss(fit.sim_key, texture_stats(target), TRUE, layout, names)(x[None])[0]
    levels = _levels_from(x, names, TRUE)
    fields = _drawing_fields(names, *_fit._bounds(names, D_RANGE, {})[:2])
    args = (layout, texture_stats(target), fields, 4)
    assert float(_refine(fit.sim_key, levels, start, *args).loss) <= float(start)
    assert float(fit.loss) <= float(fit.swarm_loss)
    assert np.all(np.diff(np.asarray(fit.swarm.history), axis=1) <= 0)
    assert fit.fitted.shape == (64, 64) and np.all(np.isfinite(fit.fitted))
    assert float(fit.levels[1].d) == pytest.approx(float(fit.levels[0].d) / 2)


def test_heldout_losses_score_the_answer_with_other_simulation_keys(fit, target, layout):
    """The answer's held-out losses are its swarm losses with the held-out keys (folded into
    the fit's simulation key), which differ from its own key's: the search's least loss
    flatters the parameters on other keys."""
    k_sim = jax.random.split(jax.random.key(0))[0]
    count = heldout_key_count(SMALL["n_agents"], SMALL["n_epochs"], 1)
    assert count == 10  # a tenth of the budget's 100 evaluations
    keys = jax.random.split(jax.random.fold_in(k_sim, _fit._HELDOUT_STREAM), count)
    stats = texture_stats(target)
    answer = jnp.array([[getattr(fit.levels[0], n[2:]) for n in NAMES]], jnp.float32)
    expected = [eqx.filter_jit(_SwarmLoss(k, stats, TRUE, layout, NAMES))(answer)[0] for k in keys]
    # the fit scores in a batch of its agents, which reduces in another order than one agent
    # alone (up to 1e-4 of the loss)
    np.testing.assert_allclose(fit.heldout_losses, expected, rtol=5e-4)
    assert np.all(np.isfinite(fit.heldout_losses)) and len(set(np.asarray(expected))) == len(keys)
    assert fit.heldout_loss == pytest.approx(float(np.mean(expected)), rel=5e-4)
    assert fit.heldout_loss > float(fit.loss)


def test_the_refinement_keeps_its_answer_and_map_only_when_it_beats_the_start(fit, target, layout):
    """The refinement returns its answer, with that answer's loss and map (the solve's last
    accepted step, the same as drawn anew), when it beats the start's loss (100); else the start
    (loss 0) with no map, which the fit draws only if it reports that start."""
    names = (*NAMES, "1.wrinkle_width")
    x = jnp.concatenate([fit.swarm.params, jnp.array([0.6], jnp.float32)])
    stats = texture_stats(target)
    fields = _drawing_fields(names, *_fit._bounds(names, D_RANGE, {})[:2])
    levels = _levels_from(x, names, TRUE)
    answer = _refine(fit.sim_key, levels, 100.0, layout, stats, fields, 4)
    assert float(answer.levels[0].wrinkle_width) != float(x[-1])
    image = _fit._fitted_map(fit.sim_key, answer.levels, layout)
    np.testing.assert_allclose(answer.image, image, atol=1e-5)
    assert float(answer.loss) == pytest.approx(float(_fit._loss(image, stats)), rel=1e-5)
    kept = _refine(fit.sim_key, levels, 0.0, layout, stats, fields, 4)
    assert float(kept.loss) == 0.0 and kept.image is None
    assert float(kept.levels[0].wrinkle_width) == float(x[-1])
    assert float(kept.levels[0].d) in np.asarray(layout.d_values)  # α_d snapped, as simulated


def test_heldout_losses_are_one_agents_swarm_losses_with_each_key(fit, target, layout):
    """:func:`_fit._heldout` scores one agent with each held-out key through the trial's swarm
    loss (its compiled program), the agent in the first row and the other rows skipped: the
    same losses as that agent alone with each key."""
    stats = texture_stats(target)
    low, high, cyclic = (np.asarray(a, np.float32) for a in _fit._bounds(NAMES, D_RANGE, {}))
    search = (low, high, cyclic, swarm_settings(3, batched=True))
    params = np.asarray(fit.swarm.params)
    heldout = _fit._heldout(_SwarmLoss(fit.sim_key, stats, TRUE, layout, NAMES), params,
                            HELDOUT, search)  # fmt: skip
    expected = [
        eqx.filter_jit(_SwarmLoss(k, stats, TRUE, layout, NAMES))(params[None])[0] for k in HELDOUT
    ]
    # a batch of three reduces in another order than one agent alone (up to 1e-4 of the loss);
    # the keys' losses lie further apart than that, so a wrong key cannot pass
    np.testing.assert_allclose(heldout, expected, rtol=5e-4)
    assert np.min(np.abs(np.diff(np.sort(expected))) / np.sort(expected)[1:]) > 5e-4


def test_the_noise_table_gives_the_swarms_bits(fit, target, layout):
    """A large fit's swarm takes the perturbation's noise from its trial's table
    (:func:`_fit._noise_table`) instead of computing it: the same losses to the bit, and a key
    other than the table's (a held-out one) computes its own (a wrong noise moves the loss)."""
    stats = texture_stats(target)
    points = jnp.array([[0.6, 1.0], [0.3, 1.0], [0.9, 1.0]], jnp.float32)
    table = _fit._noise_table(fit.sim_key, layout, TRUE)
    plain = _SwarmLoss(fit.sim_key, stats, TRUE, layout, NAMES)
    tabled = dataclasses.replace(plain, table=table)
    np.testing.assert_array_equal(eqx.filter_jit(tabled)(points), eqx.filter_jit(plain)(points))
    other = eqx.filter_jit(dataclasses.replace(tabled, key=HELDOUT[0]))(points)
    expected = eqx.filter_jit(dataclasses.replace(plain, key=HELDOUT[0]))(points)
    np.testing.assert_allclose(other, expected, rtol=1e-6)
    misread = eqx.filter_jit(
        dataclasses.replace(tabled, table=_fit._noise_table(HELDOUT[0], layout, TRUE))
    )
    assert np.all(np.abs(np.asarray(misread(points)) / np.asarray(expected) - 1) > 1e-4)


def test_heldout_maps_the_static_draw_sizes_cannot_hold_are_drawn_with_room(
    fit, target, layout, monkeypatch
):
    """A held-out map that overflows the fit's static draw sizes (bins cut to one tile per
    primitive and one (primitive, tile) pair, which no map fits) is drawn again on bins sized to
    it: the losses the fit's own sizes give, not NaN."""
    stats = texture_stats(target)
    low, high, cyclic = (np.asarray(a, np.float32) for a in _fit._bounds(NAMES, D_RANGE, {}))
    search = (low, high, cyclic, swarm_settings(3, batched=True))
    params = np.asarray(fit.swarm.params)
    keys = HELDOUT[:2]
    redrawn = []  # one `_primitives_of` call per redrawn key
    primitives_of = _fit._primitives_of
    monkeypatch.setattr(_fit, "_primitives_of", lambda *a: redrawn.append(1) or primitives_of(*a))
    cramped = dataclasses.replace(layout, span=(1, 1), entries=(1, 1))
    heldout = _fit._heldout(_SwarmLoss(fit.sim_key, stats, TRUE, cramped, NAMES), params,
                            keys, search)  # fmt: skip
    expected = [
        eqx.filter_jit(_SwarmLoss(k, stats, TRUE, layout, NAMES))(params[None])[0] for k in keys
    ]
    assert len(redrawn) == len(keys)
    np.testing.assert_allclose(heldout, expected, rtol=5e-4)


@pytest.fixture(scope="module")
def overflowing(fit, target, layout):
    """The fit's answer, two held-out keys and their losses on the fit's bins, and bins
    (``cramped``) of half the most (primitive, tile) pairs either key's map makes, and a
    margin: every key overflows them on some level."""
    stats = texture_stats(target)
    low, high, cyclic = (np.asarray(a, np.float32) for a in _fit._bounds(NAMES, D_RANGE, {}))
    params = np.asarray(fit.swarm.params)
    keys = HELDOUT[:2]
    levels = _levels_from(jnp.asarray(params), NAMES, TRUE)
    needed = np.array([
        [needed_entries(p, layout.shape, tile=_fit._TILE, bulge=i == 0, periodic=True)
         for i, p in enumerate(_fit._primitives_of(k, levels, layout))]
        for k in keys
    ])  # fmt: skip
    entries = np.max(needed, axis=0) // 2 + 16
    assert np.all(np.any(needed > entries, axis=1))
    expected = [
        eqx.filter_jit(_SwarmLoss(k, stats, TRUE, layout, NAMES))(params[None])[0] for k in keys
    ]
    return SimpleNamespace(
        stats=stats, search=(low, high, cyclic, swarm_settings(3, batched=True)), params=params,
        keys=keys, expected=expected,
        cramped=dataclasses.replace(layout, entries=tuple(map(int, entries))),
    )  # fmt: skip


def test_heldout_maps_that_overflow_the_static_draw_sizes_by_less_than_twice_need_no_sizing(
    fit, overflowing, monkeypatch
):
    """A held-out map with more (primitive, tile) pairs than the fit's bins hold, but fewer than
    twice as many, is drawn on bins of twice the pairs, a program compiled beside the other
    keys' losses: none of its primitives are sized first, and the losses are the fit's own
    sizes'."""
    o = overflowing
    sized, ahead = [], []
    monkeypatch.setattr(_fit, "_primitives_of", lambda *a: sized.append(1))
    compile_ahead = _fit.compile_ahead
    monkeypatch.setattr(_fit, "compile_ahead", lambda *a: ahead.append(1) or compile_ahead(*a))
    loss = _SwarmLoss(fit.sim_key, o.stats, TRUE, o.cramped, NAMES)
    heldout = _fit._heldout(loss, o.params, o.keys, o.search)
    assert not sized and ahead == [1]
    np.testing.assert_allclose(heldout, o.expected, rtol=5e-4)


def test_a_swarm_room_below_the_bins_draws_as_its_bins_and_scores_held_out_maps_past_it(
    fit, layout, overflowing, monkeypatch
):
    """A small fit's swarm loss has bins of twice the (primitive, tile) pairs its ``room`` lets
    it draw: its losses are those of bins of that room, to the bit (NaN where a map needs
    more), and held-out maps that need more than the room but fit the bins are scored by the
    same program with all the room of its bins: no other program compiled, none sized."""
    o = overflowing
    twice = [bins.roomier() for bins in (layout, o.cramped)]
    x = jnp.asarray(o.params[None])
    # drawn within the room (the fit's key, all its layout's pairs) and past it (held-out keys)
    cases = [(fit.sim_key, layout, twice[0])] + [(k, o.cramped, twice[1]) for k in o.keys]
    for k, bins, more in cases:
        room = jnp.asarray(bins.entries, jnp.int32)
        plain = eqx.filter_jit(_SwarmLoss(k, o.stats, TRUE, bins, NAMES))(x)
        capped = eqx.filter_jit(_SwarmLoss(k, o.stats, TRUE, more, NAMES, None, room))(x)
        np.testing.assert_array_equal(np.asarray(capped), np.asarray(plain))
        assert np.isfinite(float(plain[0])) == (bins is layout)
    sized, ahead = [], []
    monkeypatch.setattr(_fit, "_primitives_of", lambda *a: sized.append(1))
    monkeypatch.setattr(_fit, "compile_ahead", lambda *a: ahead.append(1))
    room = jnp.asarray(o.cramped.entries, jnp.int32)
    loss = _SwarmLoss(fit.sim_key, o.stats, TRUE, twice[1], NAMES, None, room)
    heldout = _fit._heldout(loss, o.params, o.keys, o.search)
    assert not sized and not ahead
    np.testing.assert_allclose(heldout, o.expected, rtol=5e-4)


def test_the_refinement_takes_optimistix_bfgs_steps_and_stops_where_they_no_longer_gain():
    """The refinement's solve is optimistix's BFGS, step for step (the same answer as
    ``optimistix.minimise`` on a smooth loss). It stops once the line search has halved a step
    ``REFINE_BACKTRACKS`` times in a row (on a loss whose gradient points uphill every step after
    the first is a backtrack, and optimistix's own loop would run all of them), and once
    ``REFINE_FLAT_STEPS`` accepted steps in a row each gained less than ``REFINE_GAIN`` of the
    loss (the smooth loss lifted by a constant: the same steps, tiny relative gains)."""

    def smooth(z, _):
        scales = jnp.arange(1, 5, dtype=jnp.float32)
        return jnp.sum((z - 1.0) ** 2 * scales) + 0.1 * jnp.sum(z**4), 2 * z

    def counted(loss, calls):
        def f(z, _):
            jax.debug.callback(lambda: calls.append(1))
            return loss(z, _)

        return f

    def optimistix_minimise(loss, steps):
        solver = optx.BFGS(rtol=1e-4, atol=1e-6)
        return optx.minimise(loss, solver, z0, max_steps=steps, has_aux=True, throw=False)

    z0 = jnp.array([0.3, -0.5, 2.0, 0.0], jnp.float32)
    for steps in (3, 40):
        sol = optimistix_minimise(smooth, steps)
        calls = []
        z, value, aux = jax.jit(_bfgs, static_argnums=(0, 2))(counted(smooth, calls), z0, steps)
        jax.effects_barrier()  # every counted call has run
        np.testing.assert_array_equal(z, sol.value)
        np.testing.assert_array_equal(aux, sol.state.aux)
        assert float(value) == float(sol.state.f_info.f)
    assert float(value) < float(smooth(z0, None)[0]) / 10 and len(calls) > 10

    def lifted(z, _):
        value, aux = smooth(z, _)
        return value + 1e6, aux

    calls = []
    z, value, aux = _bfgs(counted(lifted, calls), z0, 40)
    jax.effects_barrier()
    # it stopped at the step that accepted the second flat one (the first accepts the start),
    # where optimistix's own loop stands after as many steps
    sol, before = (optimistix_minimise(lifted, n) for n in (len(calls), len(calls) - 1))
    assert sol.state.num_accepted_steps == 1 + _fit.REFINE_FLAT_STEPS
    assert before.state.num_accepted_steps == _fit.REFINE_FLAT_STEPS
    np.testing.assert_array_equal(z, sol.value)
    assert float(value) == float(sol.state.f_info.f) < float(lifted(z0, None)[0])

    @jax.custom_jvp
    def uphill(z):
        return jnp.sum(z**2)

    uphill.defjvp(lambda z, t: (uphill(z[0]), -2 * jnp.sum(z[0] * t[0])))
    calls = []
    z, value, _ = _bfgs(counted(lambda z, _: (uphill(z), None), calls), z0, 100)
    jax.effects_barrier()
    np.testing.assert_array_equal(z, z0)
    # the start, then the backtracks
    assert len(calls) == 1 + _fit.REFINE_BACKTRACKS and float(value) == float(uphill(z0))


def test_the_refinement_keeps_to_the_search_range_a_user_gives(fit, target, layout, monkeypatch):
    """A loss that wants α_wrinkle-width small (minus the map's spread: this target's texture
    loss hardly depends on it): refined from 0.35, it reaches near Table 1's low end in a wide
    range and stops at the low end of a user's (0.3, 0.4). Ranges no other test uses, so that
    no other test's refinement is this stand-in's compiled program."""
    monkeypatch.setattr(_fit, "_loss", lambda image, stats: 10.0 - 100.0 * jnp.std(image))
    names = (*NAMES, "1.wrinkle_width")
    x = jnp.concatenate([fit.swarm.params, jnp.array([0.35], jnp.float32)])
    levels, refined = _levels_from(x, names, TRUE), []
    for bounds in ((0.1, 0.59), (0.3, 0.4)):
        fields = _drawing_fields(names, *_fit._bounds(names, D_RANGE, {names[-1]: bounds})[:2])
        args = (layout, texture_stats(target), fields, 4)
        refined.append(float(_refine(fit.sim_key, levels, 100.0, *args).levels[0].wrinkle_width))
    assert refined[0] < 0.2 and refined[1] == pytest.approx(0.3, abs=1e-3), refined


def test_refinement_compiles_once_while_the_swarm_runs(target, layout, caplog, monkeypatch):
    """The refinement's program is compiled ahead, in a background thread, for the types of the
    answer the swarm will give: the fit then finds it compiled (one compile, not in the main
    thread; the coordinate search's answer is refined by it too). Its held-out losses are the
    answer's swarm losses with the fit's held-out keys, scored by the swarm's own program (one
    compile): a fit this small gives its swarm bins of twice the pairs of the refinement's
    layout, and lets it draw as many as the refinement's."""
    names = (*NAMES, "1.wrinkle_width")
    small = dict(SMALL, n_agents=3, n_epochs=1)
    swarm_losses = []
    trial = _fit._Trial
    monkeypatch.setattr(_fit, "_Trial", lambda k, loss: swarm_losses.append(loss) or trial(k, loss))
    # compiled here (not read from the persistent cache), each compile logged
    settings = {"jax_enable_compilation_cache": False, "jax_log_compiles": True}
    before = {name: getattr(jax.config, name) for name in settings}
    try:
        for name, value in settings.items():
            jax.config.update(name, value)
        with caplog.at_level(logging.WARNING):
            fit = fit_wrinkles(jax.random.key(1), target, names=names, base=TRUE, n_trials=1,
                               refine_steps=2, refine_starts=3, **small)  # fmt: skip
    finally:
        for name, value in before.items():
            jax.config.update(name, value)
    compiles = [r for r in caplog.records if "XLA compilation of jit(_refined)" in r.getMessage()]
    # one program for every start: the swarm's best and its two other agents' personal bests
    assert len(compiles) == 1 and compiles[0].threadName != "MainThread"
    swarm = [
        r for r in caplog.records if "XLA compilation of jit(swarm_evaluate)" in r.getMessage()
    ]
    assert len(swarm) == 1
    (loss,) = swarm_losses
    merged = layout.merged()
    assert loss.layout.entries == merged.roomier().entries
    np.testing.assert_array_equal(loss.room, merged.entries)
    assert float(fit.loss) <= float(fit.swarm_loss) and not fit.interrupted
    assert len(fit.refined_losses) == 3 and float(fit.loss) <= float(min(fit.refined_losses))
    assert float(fit.refined_losses[0]) <= float(fit.swarm_loss)
    k_sim = jax.random.split(jax.random.key(1))[0]
    keys = jax.random.split(jax.random.fold_in(k_sim, _fit._HELDOUT_STREAM), _fit.HELDOUT_MIN_KEYS)
    answer = jnp.array([[getattr(fit.levels[0], n[2:]) for n in names]], jnp.float32)
    stats = texture_stats(target)
    expected = [eqx.filter_jit(_SwarmLoss(k, stats, TRUE, layout, names))(answer)[0] for k in keys]
    np.testing.assert_allclose(fit.heldout_losses, expected, rtol=1e-5)


def test_paper_mode_keeps_another_trials_answer_with_its_own_key(target, monkeypatch):
    """Each start is refined with its own trial's simulation key: made to refine best, the
    second start (the other trial's best) gives the fit's answer, key and trial. The fit takes
    as many starts as its evaluations allow (made 3 here: 1 for so few)."""
    keys = []

    def refine(sim_key, levels, start, *args):
        refined = _refine(sim_key, levels, start, *args)
        keys.append(jax.random.key_data(sim_key))
        return refined._replace(loss=refined.loss - (1.0 if len(keys) == 2 else 0.0))

    monkeypatch.setattr(_fit, "_refine", refine)
    monkeypatch.setattr(_fit, "_refine_starts", lambda *a: 3)
    monkeypatch.setattr(_fit, "_coordinate_search", None)  # the paper's procedure has none
    small = dict(SMALL, n_agents=3, n_epochs=1, refine_steps=2)
    fit = fit_wrinkles(jax.random.key(1), target, names=(*NAMES, "1.wrinkle_width"), base=TRUE,
                       n_trials=2, mode="paper", **small)  # fmt: skip
    assert fit.answer_trial == 1 - int(fit.swarm.best_trial) and len(keys) == 3
    assert not jnp.array_equal(keys[0], keys[1])
    assert jnp.array_equal(keys[1], jax.random.key_data(fit.sim_key))
    assert jnp.array_equal(keys[0], keys[2])  # the best trial's next agent
    assert float(fit.loss) == float(fit.refined_losses[1]) == float(min(fit.refined_losses))


def test_refinement_starts_are_the_finished_trials_bests_then_the_best_ones_next():
    """Hand-worked: trial 1 (unfinished) is left out although it is the best; the finished
    trials' bests come first (best first), then trial 0's next personal bests by loss, without
    the agent whose personal best repeats its best nor the one that never had a finite loss."""
    low, high = np.zeros(2, np.float32), np.full(2, 2.0, np.float32)

    def trial(ps, p):
        run = _fit._Trial(jax.random.key(0), _Bowl(jax.random.key(0), jnp.zeros(2)))
        p, zero = jnp.asarray(p, jnp.float32), jnp.zeros((), jnp.int32)
        run.swarm = Swarm(p, p, p, jnp.asarray(ps, jnp.float32), zero, zero, zero)
        return run

    a, b, c, d = [0.1, 0.1], [0.2, 0.2], [0.3, 0.3], [0.4, 0.4]
    runs = [trial([2.0, 1.0, 1.5, 1.0, np.inf], [a, b, c, b, d]), trial([0.5], [a]),
            trial([1.2, 3.0], [d, a])]  # fmt: skip
    starts = _fit._starts(runs, [0, 2], low, high, 10)
    assert [t for t, _, _ in starts] == [0, 2, 0, 0]
    np.testing.assert_array_equal([loss for _, _, loss in starts], np.float32([1, 1.2, 1.5, 2]))
    for (_, params, _), point in zip(starts, [b, d, c, a], strict=True):
        np.testing.assert_allclose(params, 2 * np.asarray(point))  # the caller's units
    assert [t for t, _, _ in _fit._starts(runs, [0, 2], low, high, 3)] == [0, 2, 0]
    assert len(_fit._starts(runs, [2], low, high, 0)) == 1


def test_coordinate_search_hand_worked():
    """A greedy pass over the fitted simulation parameters (level 1's α_θ, cyclic on [0, 2π),
    and α_deposit on [0.01, 1]), steps of ±5 % and ±10 % of the range, the best step kept where
    it gains. Loss: squared distance to α_θ 2.95 (axial: mod π) and α_deposit 0.62, plus terms
    in α_d and a drawing parameter, which the search leaves alone. Pass 1: α_θ 0.1 → 0.1 − 0.1π
    + 2π (wrapped; 0.023 from 2.95 against 0.29), α_deposit 0.5 → 0.599 (0.021 from 0.62;
    0.6485 is 0.0285 off); pass 2 gains nothing from either, so the search stops there (4
    batches of 4). With the finer steps after it (half: ±2.5 % and ±5 %, then a quarter),
    α_deposit goes on to 0.599 + 0.02475 = 0.62375 (0.00375 off); the next half-step pass and
    the quarter-step pass gain nothing (6 more batches); α_θ's finer steps (±0.157, ±0.314 and
    ±0.079, ±0.157) all land farther than its 0.023."""
    names = ("d", "1.theta", "1.deposit", "1.wrinkle_width", "fnoise")
    low, high, cyclic = _fit._bounds(names, D_RANGE, {})
    search = (low, high, cyclic, None)

    def loss(p):
        axial = np.abs((p[:, 1] - 2.95 + np.pi / 2) % np.pi - np.pi / 2)
        return axial**2 + (p[:, 2] - 0.62) ** 2 + (p[:, 0] - 0.045) ** 2 + (p[:, 3] - 0.5) ** 2

    seen = []

    def losses_of(rows):
        seen.append(rows.copy())
        return loss(rows)

    start = np.array([0.04, 0.1, 0.5, 0.3, 500.0])
    params, value = _fit._coordinate_search(losses_of, start, loss(start[None])[0], names,
                                            search, passes=3, scales=(1.0,))  # fmt: skip
    theta = 0.1 - 0.1 * np.pi + 2 * np.pi
    np.testing.assert_allclose(params, [0.04, theta, 0.599, 0.3, 500])
    assert value == pytest.approx(loss(params[None])[0])
    assert len(seen) == 4 and all(r.shape == (4, 5) for r in seen)
    seen.clear()
    params, value = _fit._coordinate_search(losses_of, start, loss(start[None])[0], names,
                                            search, passes=3)  # fmt: skip
    np.testing.assert_allclose(params, [0.04, theta, 0.62375, 0.3, 500])
    assert value == pytest.approx(loss(params[None])[0])
    assert len(seen) == 10 and all(r.shape == (4, 5) for r in seen)
    np.testing.assert_allclose(seen[5][:, 2], 0.599 + 0.99 * np.array([-0.05, -0.025, 0.025, 0.05]))
    moved = np.concatenate(seen)
    assert np.all(moved[:, [0, 3, 4]] == start[[0, 3, 4]])  # only the simulation parameters
    # one pass; near a bound only the steps inside the range (α_deposit 0.97: 0.871, 0.9205)
    start = np.array([0.04, 3.0, 0.97, 0.3, 500.0])
    seen.clear()
    params, _ = _fit._coordinate_search(losses_of, start, 0.0, names, search, passes=1,
                                        scales=(1.0,))  # fmt: skip
    assert [len(r) for r in seen] == [4, 2] and np.all(params == start)  # nothing beats 0
    np.testing.assert_allclose(seen[1][:, 2], [0.871, 0.9205])
    assert _fit.coordinate_evaluations("fast") == 1 + 3 * 2 * 4 * 12
    assert _fit.coordinate_evaluations("paper") == 0


class _RowLoss(eqx.Module):
    """A batched loss that gives each drawable agent its row's index (NaN elsewhere), with a
    stand-in for a mesh of ``devices`` devices."""

    devices: int = eqx.field(static=True)

    @property
    def mesh(self):
        return None if self.devices == 1 else type("Mesh", (), {"size": self.devices})()

    def __call__(self, units):
        rows = jnp.arange(units.shape[0], dtype=jnp.float32)
        return jnp.where(jnp.all(jnp.isfinite(units), axis=1), rows, jnp.nan)


@pytest.mark.parametrize(
    ("agents", "devices", "slots"),
    [(50, 1, [0, 1, 2, 3]), (50, 2, [0, 25, 1, 26]), (5, 2, [0, 3, 1, 4, 2, 0, 3])],
)
def test_agent_losses_deal_the_agents_to_every_devices_share(agents, devices, slots):
    """A sharded swarm loss evaluates each device's rows side by side: the agents scored alone
    (held-out keys, the coordinate search) go to the devices in turn (rows 0, 25, 1, 26 of 50 on
    two devices; 5 rows on two: shares 0-2 and 3-4), more than a swarm's in further calls."""
    low, high = np.zeros(2, np.float32), np.ones(2, np.float32)
    search = (low, high, np.zeros(2, bool), swarm_settings(agents, batched=True))
    rows = np.full((len(slots), 2), 0.5)
    np.testing.assert_array_equal(_fit._agent_losses(_RowLoss(devices), rows, search), slots)


def test_fast_mode_ends_with_a_coordinate_search_from_the_refined_answer(
    target, layout, monkeypatch
):
    """The search starts from the best refined start (its loss there the swarm program's, equal
    to the refinement's up to the last bits); its answer, refined once more, is the fit's, with
    the loss of the map the fit reports. A fit this small skips it unless asked: by default it
    runs only where it costs at most a tenth of the budget (``fit_budget``)."""
    search = _fit._coordinate_search
    calls = []

    def spy(losses_of, params, loss, *args):
        calls.append((loss, search(losses_of, params, loss, *args)))
        return calls[-1][-1]

    monkeypatch.setattr(_fit, "_coordinate_search", spy)
    small = dict(SMALL, n_agents=3, n_epochs=1)
    fit = fit_wrinkles(jax.random.key(1), target, names=(*NAMES, "1.wrinkle_width"), base=TRUE,
                       n_trials=1, refine_steps=2, coordinate_search=True, **small)  # fmt: skip
    ((start_loss, (moved, loss)),) = calls
    assert start_loss == pytest.approx(float(min(fit.refined_losses)), rel=1e-4)
    assert loss < start_loss  # it gained here: 1 epoch of 3 agents leaves easy descents
    assert float(fit.loss) <= loss and not fit.interrupted
    assert float(fit.levels[0].deposit) == pytest.approx(moved[0], abs=1e-6)
    assert float(fit.levels[0].theta) == pytest.approx(moved[1], abs=1e-6)
    stats = texture_stats(target)
    image = _fit._fitted_map(fit.sim_key, fit.levels, layout.merged().narrowed(0))
    np.testing.assert_allclose(fit.fitted, image, atol=1e-5)
    assert float(fit.loss) == pytest.approx(float(_fit._loss(image, stats)), rel=1e-4)
    plain = fit_wrinkles(jax.random.key(1), target, names=(*NAMES, "1.wrinkle_width"), base=TRUE,
                         n_trials=1, refine_steps=2, **small)  # fmt: skip
    assert len(calls) == 1  # not searched: the refined starts' best is the answer
    np.testing.assert_array_equal(plain.refined_losses, fit.refined_losses)
    assert float(plain.loss) == float(min(plain.refined_losses)) > float(fit.loss)


def test_size_classes_give_the_whole_grids_losses(target, layout):
    """The swarm evaluates each agent on its α_d's size class (the graphs cut to that class's
    slots): the same losses as drawn on the whole grid's slots, with fewer slots for the sparse
    class, and as drawn with the classes merged into one."""
    dense, sparse = layout.slots
    assert 0 < layout.split < 4
    assert sparse[1] < dense[1]  # the finer level's pores fewer where α_d is larger
    names = ("d", *NAMES)
    x = jnp.array([[float(d), 0.6, 1.0] for d in layout.d_values], jnp.float32)
    assert set(np.asarray(jax.vmap(layout.size_class)(x[:, 0])).tolist()) == {0, 1}
    key, stats = jax.random.key(3), texture_stats(target)
    classed = _SwarmLoss(key, stats, TRUE, layout, names)(x)

    @jax.jit
    def whole(x):  # every agent on the whole grid's slots
        return _fit._loss(synthesize(key, _levels_from(x, names, TRUE), layout), stats)

    np.testing.assert_allclose(classed, [whole(a) for a in x], rtol=1e-5)
    # one class over the whole grid (small swarms, the refinement): the same losses
    merged = layout.merged()
    assert merged.slots == (tuple(map(tuple, np.maximum(dense, sparse).tolist())),)
    assert set(np.asarray(jax.vmap(merged.size_class)(x[:, 0])).tolist()) == {0}
    merged_losses = _SwarmLoss(key, stats, TRUE, merged, names)(x.at[0, 0].set(jnp.nan))
    np.testing.assert_allclose(merged_losses[1:], classed[1:], rtol=1e-5)
    assert np.isnan(merged_losses[0])  # a non-finite α_d is undrawable


@pytest.mark.parametrize(
    ("patch", "kwargs", "error", "match"),
    [
        (np.full((64, 64), 0.5, np.float32), {}, ValueError, "constant"),
        (np.full((64, 64), np.nan, np.float32), {}, ValueError, "finite"),
        (np.zeros((32, 32), np.float32), {}, ValueError, "64"),
        (np.eye(64, 96, dtype=np.float32), {}, ValueError, "square"),
        (np.eye(64, dtype=np.float32), {"names": ("1.bogus",)}, ValueError, "names"),
        (np.eye(64, dtype=np.float32), {"names": ("1.d",)}, ValueError, "names"),
        (np.eye(64, dtype=np.float32), {"d_range": (0.05, 0.02)}, ValueError, "d_range"),
        (np.eye(64, dtype=np.float32), {"refine_starts": 0}, ValueError, "refine_starts"),
        (np.eye(64, dtype=np.float32), {"coordinate_search": 1}, ValueError, "coordinate_search"),
        (
            np.eye(64, dtype=np.float32),
            {"coordinate_search": True, "mode": "paper"},
            ValueError,
            "coordinate_search",
        ),
    ],
)
def test_bad_input(patch, kwargs, error, match, unchecked):
    with pytest.raises(error, match=match):
        fit_wrinkles(jax.random.key(0), patch, **kwargs)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"mode": "quick"}, "mode"), ({"n_agents": 2}, "n_agents"), ({"n_trials": 0}, "n_trials"),
     ({"n_epochs": 2.5}, "n_epochs"), ({"refine_steps": -1}, "refine_steps")],
)  # fmt: skip
def test_fit_budget_bad_input(kwargs, match):
    with pytest.raises((TypeError, ValueError), match=match):
        fit_budget(**kwargs)


def test_heldout_keys_cost_at_most_a_tenth_of_the_budget():
    """Worked by hand: a tenth of the budget's evaluations, between 8 and 32 keys. The default
    fast budget, 136 epochs × 50 agents = 6,800 evaluations, and a race of 39 epochs × 20
    (780): 32; 10 × 10 in one trial: 10; the exploratory 8 × 5 = 40 and 3 × 1: 8; paper mode
    counts every trial's epochs (10 × 10 × 3 = 300: 30), as does fast mode's race of 16 trials of
    2 epochs (30 epochs × 10). Fewer keys are the first of more."""
    assert heldout_key_count() == 32 and heldout_key_count(20, 30, 3) == 32
    assert heldout_key_count(10, 10, 1) == 10
    assert heldout_key_count(8, 5, 1) == 8 == heldout_key_count(3, 1, 1)
    assert heldout_key_count(10, 10, 3, mode="paper") == 30 == heldout_key_count(10, 2, 16)
    key = jax.random.key(3)
    np.testing.assert_array_equal(
        jax.random.key_data(_fit.heldout_keys(key, 8)),
        jax.random.key_data(_fit.heldout_keys(key)[:8]),
    )
    with pytest.raises(ValueError, match="mode"):
        heldout_key_count(mode="quick")


def test_fast_mode_is_deterministic_and_halves_the_trials(target, monkeypatch):
    looked_up = []
    monkeypatch.setattr(_fit, "_LAYOUTS", {})
    monkeypatch.setattr(_fit, "_DESIGNS", {})
    monkeypatch.setattr(_fit, "kept_arrays", lambda *a: looked_up.append(a) or kept_arrays(*a))
    inertias = []  # of every epoch's move
    swarm_epoch = _fit.swarm_epoch
    monkeypatch.setattr(_fit, "swarm_epoch",
                        lambda *a: inertias.append(a[-1].inertia) or swarm_epoch(*a))  # fmt: skip
    kwargs = dict(SMALL, n_trials=3, names=NAMES, base=TRUE, refine_steps=0)
    runs = [fit_wrinkles(jax.random.key(0), target, **kwargs) for _ in range(2)]
    # the fast mode's swarm moves with its faster decay, the paper mode's with the paper's
    assert set(inertias) == {_fit.INERTIA["fast"]} and _fit.INERTIA["fast"][2] < 0.98
    assert np.array_equal(runs[0].swarm.params, runs[1].swarm.params)
    assert len(looked_up) == 2  # the first fit's design and layout; the second kept them
    # rungs of n_epochs // 8 = 1 epoch: three trials run one, the better two another, the best
    # goes on to n_epochs = 10 unless it stalls (10 epochs without a 1 % gain)
    epochs = sorted(runs[0].epochs_run)
    assert epochs[:2] == [1, 2] and 2 < epochs[2] <= 10
    # at most: three rungs of one epoch, two more, the last trial's eight; no polishes
    assert sum(epochs) <= fit_budget(10, 10, 3, refine_steps=0)[0] == 1 + 2 + 10
    # worked by hand: the defaults; either side of POLISH_FROM (rungs of 12 × 24 or 25 agents);
    # rungs of 2 with an odd rest; one trial; rungs that add up to more than n_epochs. Polishes: one
    # per rung (the last trial's last may be cut short at n_epochs). Starts of the final refinement
    # (7 evaluations a BFGS step, 210 for the default 30): up to 4 within a tenth of the evaluations
    # (none extra in an exploratory fit of 40 nor in one of 39 × 20 = 780, one with 10 steps; one in
    # 136 × 24 = 3,264), and one more for each start's cost in the epochs after the race, which
    # a last trial that stalls there leaves unspent (76 × 50 = 3,800 evaluations: 18 more). The
    # last trial of 100 epochs stops at FAST_EPOCHS = 48: it runs 24 more after the race's 24, the
    # fit at most 36 + 24 + 24 = 84 epochs in 7 rungs of 12, its budget still 136 epochs. The
    # coordinate search (289 evaluations, then a refinement of 210) runs where that is at most a
    # tenth of the budget's evaluations: 136 × 50 = 6,800 (3,590 with 10 steps), 100 × 50 = 5,000
    # in one trial, not 100 × 49 = 4,900, 136 × 25 = 3,400 nor any smaller budget below
    assert fit_budget() == (84, 7, 4 + 18, 289) and fit_budget(24) == (84, 0, 2 + 8, 0)
    assert fit_budget(25) == (84, 7, 2 + 9, 0)
    assert fit_budget(50, refine_steps=10) == (84, 7, 58, 289)
    assert fit_budget(50, 100, 1)[3] == 289 and fit_budget(49, 100, 1)[3] == 0
    assert fit_budget(150, 21, 3) == (27, 14, 2 + 12, 0)
    assert fit_budget(150, 20, 1) == (20, 10, 2 + 14, 0)
    assert fit_budget(10, 2, 16, refine_steps=0) == (30, 0, 1, 0)
    assert fit_budget(8, 5, 1) == (5, 0, 1, 0) and fit_budget(20, 30, 3) == (39, 0, 1 + 2, 0)
    assert fit_budget(20, 30, 3, refine_steps=10) == (39, 0, 2 + 6, 0)
    paper = fit_wrinkles(jax.random.key(1), target, mode="paper", **kwargs)
    assert paper.epochs_run == (10, 10, 10)
    assert set(inertias[-30:]) == {_fit.INERTIA["paper"]} == {swarm_settings(3).inertia}
    assert fit_budget(10, 10, 3, mode="paper") == (30, 0, 1, 0)
    assert len(looked_up) == 2  # another seed: the same layout (and so the same programs)
    assert not np.array_equal(paper.swarm.trial_params, runs[0].swarm.trial_params)


class _Bowl(eqx.Module):
    """A cheap stand-in for a trial's loss: a quadratic bowl around ``centre``, lifted by
    ``floor`` (``key``: the trial's simulation key, which a polish receives)."""

    key: jax.Array
    centre: jax.Array
    floor: float = 0.0

    def __call__(self, xs):
        return jnp.sum((xs - self.centre) ** 2, axis=-1) + self.floor


def test_polished_bests_join_their_swarms_and_the_race():
    """A polish that finds the bowl's minimum: after the first rung every trial's best is that
    point (its best agent's personal best, and the history's last entry), the race compares the
    polished losses, and the last trial stalls once the polish gains nothing more (10 epochs
    after the first polish). A worse or out-of-box polish changes nothing."""
    low, high = np.zeros(2, np.float32), np.full(2, 2.0, np.float32)
    search = (low, high, np.zeros(2, bool), swarm_settings(4, batched=True))
    centre = np.array([0.5, 1.5], np.float32)
    keys = jax.random.split(jax.random.key(0), 3)
    runs = [_fit._Trial(k, _Bowl(jax.random.key(t), jnp.asarray(centre))) for t, k in
            enumerate(keys)]  # fmt: skip
    calls = []

    def polish(sim_key, best, start):
        calls.append(sim_key)
        return centre, 0.0

    finished = _fit._halve(runs, 16, search, None, polish)
    # rungs of 2 epochs: 3 trials, then 2 (ties keep the order), then trial 0 polished every 2
    # epochs until its best (0 from epoch 2 on) has not fallen for 10 epochs; the race's other
    # 4 epochs (of 3 × 2 + 2 × 2 + 16 - 4 = 22) are left to refinement starts: the trials it
    # beat do not run on
    assert [len(r.history) - 1 for r in runs] == [12, 4, 2] and finished == [0]
    assert _fit._race_epochs(3, 16)[0] - sum(len(r.history) - 1 for r in runs) == 22 - 18
    assert len(calls) == 3 + 2 + 4
    for r in runs:
        assert float(r.swarm.best) == 0.0 and r.history[-1] == 0.0
        np.testing.assert_array_equal(r.swarm.best_params(low, high), centre)
    trial = _fit._Trial(keys[0], _Bowl(jax.random.key(0), jnp.asarray(centre)))
    trial.advance(1, search, 0, None)
    before = (trial.swarm, list(trial.history))
    best = float(trial.swarm.best)
    trial.polish(lambda *a: (centre, best + 1.0), search)  # worse
    trial.polish(lambda *a: (np.array([0.5, 2.5], np.float32), 0.0), search)  # out of the box
    assert trial.swarm is before[0] and trial.history == before[1]
    trial.polish(None, search)
    assert trial.swarm is before[0]


def test_the_last_trial_stops_at_fast_epochs_and_leaves_the_rest_to_refinement_starts(
    monkeypatch,
):
    """A last trial that never stalls (a tolerance below any gain) runs to FAST_EPOCHS, here 7
    of 16, not to n_epochs: 3 trials × 2 epochs, 2 × 2, then the winner on to 7 (a rung of 2,
    then one cut at 7), polished after each rung, as :func:`fit_budget` counts. The budget's
    other 9 epochs (of 6 + 4 + 12 = 22) are left unspent: they buy refinement starts."""
    monkeypatch.setattr(_fit, "FAST_EPOCHS", 7)
    monkeypatch.setattr(_fit, "STALL_TOLERANCE", -1.0)
    monkeypatch.setattr(_fit, "POLISH_FROM", 1)
    low, high = np.zeros(2, np.float32), np.full(2, 2.0, np.float32)
    search = (low, high, np.zeros(2, bool), swarm_settings(4, batched=True))
    keys = jax.random.split(jax.random.key(0), 3)
    centre = jnp.float32([0.5, 1.5])
    runs = [_fit._Trial(k, _Bowl(jax.random.key(t), centre, 1.0)) for t, k in enumerate(keys)]
    polished = []

    def polish(sim_key, best, start):  # no gain: the swarm goes on as it was
        polished.append(sim_key)
        return best, start

    (t,) = _fit._halve(runs, 16, search, None, polish)
    epochs = [len(r.history) - 1 for r in runs]
    assert sorted(epochs) == [2, 4, 7] and epochs[t] == 7 and not runs[t].stalled()
    assert len(polished) == 3 + 2 + 2
    assert fit_budget(4, 16, 3, refine_steps=1)[:2] == (sum(epochs), len(polished)) == (13, 7)
    assert _fit._race_epochs(3, 16) == (22, 12, 13) and _fit._budget_epochs("fast", 3, 16) == 22
    # 9 unspent epochs of 4 agents: 5 starts' worth at 7 evaluations each, after 2 within a tenth
    assert _fit._refine_starts(4, 22, 1, 22 - sum(epochs)) == 2 + 5


def test_a_gaining_polish_shares_its_refined_entries_with_every_personal_best():
    """Hand-worked on the bowl around (0.5, 1.5): the best agent (0.6, 1.0) is polished to
    (0.6, 1.4); the changed entry, 1.4, is tried on every other personal best, and the agents
    it brings nearer the centre take it (losses 1.25 → 0.26, 0.74 → 0.5) while the one it does
    not keeps its own (1.5, 1.5), loss 1.0."""
    low, high = np.zeros(2, np.float32), np.full(2, 2.0, np.float32)
    search = (low, high, np.zeros(2, bool), swarm_settings(4, batched=True))
    trial = _fit._Trial(jax.random.key(0), _Bowl(jax.random.key(1), np.float32([0.5, 1.5])))
    p = jnp.asarray([[0.6, 1.0], [1.0, 0.5], [1.5, 1.5], [1.2, 2.0]], jnp.float32) / 2
    trial.advance(0, search, 0, None)  # started, then given these personal bests
    trial.swarm = eqx.tree_at(lambda w: (w.p, w.ps), trial.swarm, (p, trial.loss(2 * p)))
    trial.history = [float(trial.swarm.best)]
    trial.polish(lambda sim_key, best, start: (np.float32([best[0], 1.4]), 0.02), search)
    expected = np.float32([[0.6, 1.4], [1.0, 1.4], [1.5, 1.5], [1.2, 1.4]]) / 2
    np.testing.assert_allclose(trial.swarm.p, expected, rtol=1e-6)
    np.testing.assert_allclose(trial.swarm.ps, [0.02, 0.26, 1.0, 0.5], rtol=1e-5)
    assert trial.history == [float(trial.swarm.best)]


def test_a_trial_stalls_when_its_best_gains_under_one_percent_over_ten_epochs():
    """The fast mode's stall rule: less than 1 % over the last 10 epochs (0.1 % ran a full fit's
    last trial 24 epochs longer for 0.4 % on other simulation keys); never before 10 epochs."""
    run = _fit._Trial(jax.random.key(0), lambda xs: jnp.zeros(xs.shape[0]))
    for history, stalled in (
        ([1.0] * 10, False),  # 9 epochs: too soon to judge
        ([1.0] + [0.995] * 10, True),  # 0.5 %
        ([1.0] + [0.98] * 10, False),  # 2 %
        ([0.5, 1.0] + [0.995] * 10, True),  # judged over the last 10 epochs only
    ):
        run.history = history
        assert run.stalled() is stalled, history


def test_a_stalled_trial_goes_on_after_a_gaining_polish_and_stops_after_one_that_is_not():
    """The last trial's swarm stalls on the lifted bowl, judged at the ends of its rungs of 10
    epochs, after their polishes: the first stalled polish gains (a half) and sends it on; it
    stalls again 10 epochs later, where the polish gains nothing, and it stops there, with one
    polish per rung, as :func:`fit_budget` counts them."""
    low, high = np.zeros(2, np.float32), np.full(2, 2.0, np.float32)
    search = (low, high, np.zeros(2, bool), swarm_settings(4, batched=True))
    centre = np.array([0.5, 1.5], np.float32)
    (run,) = runs = [_fit._Trial(jax.random.key(0), _Bowl(jax.random.key(1), centre, 1.0))]
    polished, gains = [], []

    def polish(sim_key, best, start):
        polished.append(len(run.history) - 1)
        gain = run.stalled() and not gains  # the first stalled polish halves the loss
        gains.append(gain) if gain else None
        return centre, start * (0.5 if gain else 2.0)

    _fit._halve(runs, 80, search, None, polish)  # rungs of 10 epochs
    epochs = len(run.history) - 1
    assert run.stalled() and 20 < epochs < 80 and epochs % 10 == 0
    assert polished == list(range(10, epochs + 1, 10)) and gains == [True]
    revived = epochs - 10  # where the gaining polish was: the history's only halving
    # (its swarm had stalled: the epoch before was as good within the stall's tolerance)
    halved = 0.5 * run.history[revived - 1]
    assert run.history[revived] == pytest.approx(halved, rel=_fit.STALL_TOLERANCE)
    assert run.history[revived] == run.history[-1]  # nothing beat the polished best since
    assert len(polished) == -(-epochs // 10) <= fit_budget(30, 80, 1, refine_steps=1)[1] == 5


def test_fast_mode_polishes_each_rungs_bests(target, monkeypatch):
    """With rungs large enough (here: any), fast mode refines every trial's best after each rung
    and keeps what the refinement found: a polish of the winning trial that gained is its best
    from that epoch on, and the fit's swarm loss is at most every polish's loss. No start is
    solved twice (a polish that gained nothing, on a best that did not change since, nor as the
    final refinement's first start)."""
    solved, polishes = [], []

    def bits(key):
        return np.asarray(jax.random.key_data(key)).tobytes()

    def refine(sim_key, levels, start, *args):
        solved.append((bits(sim_key), float(start)))
        return _refine(sim_key, levels, start, *args)

    def polish(run, *args):
        before = run.history[-1]
        real_polish(run, *args)
        polishes.append((bits(run.loss.key), len(run.history) - 1, before, run.history[-1]))

    real_polish = _fit._Trial.polish
    monkeypatch.setattr(_fit, "POLISH_FROM", 1)
    # the paper's inertia: on its path some polishes come back to a best that did not change
    monkeypatch.setitem(_fit.INERTIA, "fast", _fit.INERTIA["paper"])
    monkeypatch.setattr(_fit, "_refine", refine)
    monkeypatch.setattr(_fit._Trial, "polish", polish)
    names = (*NAMES, "1.wrinkle_width")
    small = dict(SMALL, n_agents=3, n_epochs=8)  # rungs of one epoch
    fit = fit_wrinkles(jax.random.key(1), target, names=names, base=TRUE, n_trials=2,
                       refine_steps=2, refine_starts=3, **small)  # fmt: skip
    assert sorted(fit.epochs_run) == [1, 8]
    # two after the first rung, seven after the last trial's epochs 2-8
    assert len(polishes) == 2 + 7
    assert fit_budget(3, 8, 2, refine_steps=2)[:2] == (1 + 8, 2 + 7)  # what the fit ran
    winner = [p for p in polishes if p[0] == bits(fit.sim_key)]
    assert [epoch for _, epoch, *_ in winner] == list(range(1, 9))
    # the polishes and the final refinement's three starts, each solved once: some repeated
    assert len(solved) == len(set(solved)) < 2 + 7 + 3
    # a polish that gained became the trial's best at that epoch (and stays in the history)
    history = np.asarray(fit.swarm.history)[int(fit.swarm.best_trial)]
    gained = [(epoch, after) for _, epoch, before, after in winner if after < before]
    assert gained
    for epoch, loss in gained:
        assert history[epoch] == pytest.approx(loss, rel=1e-6)
    assert float(fit.swarm_loss) <= min(after for *_, after in winner) * (1 + 1e-6)


def test_epochs_the_stalled_race_left_buy_more_refinement_starts(target, monkeypatch):
    """Made to stall at once (any loss stalls after one epoch), both trials stop after the
    race's first rung, leaving 7 of its 1 + 1 + 7 epochs unspent: 35 evaluations of 5 agents,
    two starts' worth at 7 × 2 each, so the final refinement takes 1 + 2 starts (the winner's
    best and its next two personal bests) where the budget alone gives 1."""
    monkeypatch.setattr(_fit, "STALL_TOLERANCE", 1e9)
    monkeypatch.setattr(_fit, "PATIENCE", 1)
    small = dict(SMALL, n_agents=5, n_epochs=8)  # rungs of one epoch, no polishes
    fit = fit_wrinkles(jax.random.key(2), target, names=(*NAMES, "1.wrinkle_width"), base=TRUE,
                       n_trials=2, refine_steps=2, **small)  # fmt: skip
    assert fit.epochs_run == (1, 1) and fit_budget(5, 8, 2, refine_steps=2) == (9, 0, 1 + 2, 0)
    assert _fit._refine_starts(5, 9, 2) == 1 and len(fit.refined_losses) == 1 + 2
    assert float(fit.loss) <= float(min(fit.refined_losses))


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="Linux's memory mappings")
def test_a_fit_drops_compiled_programs_near_the_memory_mapping_limit(target, monkeypatch):
    """Past vm.max_map_count the next compile crashes the interpreter: a fit drops JAX's
    compiled programs first once the process holds more than MAPPINGS_LIMIT mappings."""
    dropped = []
    monkeypatch.setattr(jax, "clear_caches", lambda: dropped.append(True))
    assert not _compilation.spare_memory_mappings(limit=10**9) and not dropped
    monkeypatch.setattr(_compilation, "MAPPINGS_LIMIT", 10)  # any process holds more
    fit_wrinkles(jax.random.key(0), target, names=NAMES, base=TRUE, n_trials=1, refine_steps=0,
                 **dict(SMALL, n_agents=3, n_epochs=1))  # fmt: skip
    assert dropped == [True]


def test_interrupt_keeps_the_best_so_far(target):
    seen = []

    def stop_after_two(trial, epoch, best):
        seen.append(best)
        if len(seen) == 2:
            raise KeyboardInterrupt

    fit = fit_wrinkles(
        jax.random.key(0), target, names=NAMES, base=TRUE, n_trials=1, refine_steps=4,
        progress=stop_after_two, **SMALL,
    )  # fmt: skip
    assert fit.interrupted and fit.epochs_run == (2,)
    assert float(fit.loss) == pytest.approx(seen[-1])
    assert fit.fitted.shape == (64, 64)


def test_interrupt_while_refining_keeps_the_starts_refined_so_far(target, layout, monkeypatch):
    """Ctrl-C during the final refinement's second start: the fit reports the first start's
    refined answer (not the swarm's unrefined one), interrupted, with its map (drawn anew when
    the refinement kept the start)."""
    refined = []

    def refine(*args):
        if refined:
            raise KeyboardInterrupt
        refined.append(_refine(*args))
        return refined[-1]

    monkeypatch.setattr(_fit, "_refine", refine)
    small = dict(SMALL, n_agents=3, n_epochs=1)  # no polish: the first call is the first start
    fit = fit_wrinkles(jax.random.key(1), target, names=(*NAMES, "1.wrinkle_width"), base=TRUE,
                       n_trials=1, refine_steps=2, refine_starts=2, **small)  # fmt: skip
    assert fit.interrupted and len(fit.refined_losses) == 1
    levels, loss, image = refined[0]
    assert float(fit.loss) == float(loss) <= float(fit.swarm_loss)
    if image is None:
        image = _fit._fitted_map(fit.sim_key, levels, layout.merged().narrowed(0))
    np.testing.assert_array_equal(fit.fitted, image)
    assert float(fit.levels[0].wrinkle_width) == float(levels[0].wrinkle_width)


def test_cli_interrupt_writes_the_best_so_far(tmp_path, monkeypatch, target):
    from jface.cli import _fit as cli_fit

    def interrupted_fit(*args, progress, **kwargs):
        def stop(trial, epoch, best):
            progress(trial, epoch, best)
            raise KeyboardInterrupt

        return fit_wrinkles(*args, progress=stop, **kwargs)

    monkeypatch.setattr(cli_fit, "fit_wrinkles", interrupted_fit)
    np.save(tmp_path / "patch.npy", target)
    out = tmp_path / "p.json"
    argv = ["fit", str(tmp_path / "patch.npy"), "--out", str(out), *TINY_FIT, "--iters", "3"]
    assert main(argv) == 130
    document = json.loads(out.read_text())
    assert document["fit"]["interrupted"] is True and document["fit"]["epochs_run"] == [1]


def test_cli_bad_input_exits_2(tmp_path, capsys):
    path = tmp_path / "flat.exr"
    write_exr(path, {"Y": np.zeros((64, 64), np.float32)})
    assert main(["fit", str(path), "--out", str(tmp_path / "p.json")]) == 2
    assert "constant" in capsys.readouterr().err
    assert main(["fit", str(path), "--out", str(tmp_path / "p.txt")]) == 2


def test_layout_programs_are_cacheable_and_report_their_errors():
    """The α_d grid's programs hold no host callback (JAX's persistent compilation cache keeps
    no program that has one), so its sampling and graph errors come back as flags, which the
    fit raises as clear errors."""
    keys = tuple(jax.random.split(jax.random.key(0)))
    ranges = ((0.04, 0.05), (0.02, 0.025))
    caps = _fit._capacities(0.04)
    args = (keys, jnp.asarray([0.04, 0.05]), ranges, caps)
    assert "callback" not in str(jax.make_jaxpr(_fit._grid_pores, static_argnums=(2, 3))(*args))
    pores, pore_flags = _fit._grid_pores(*args)
    specs = tuple(
        _fit.covering_spec([jax.tree.map(lambda a: a[0], p)], r)
        for p, r in zip(pores, ranges, strict=True)
    )
    jaxpr = jax.make_jaxpr(_fit._grid_graphs, static_argnums=1)(pores, specs)
    assert "callback" not in str(jaxpr)
    _, graph_flags = _fit._grid_graphs(pores, specs)
    assert not any(np.any(np.asarray(f)) for f in jax.tree.leaves((pore_flags, graph_flags)))
    _, flags = _fit._pores(keys, 0.04, ranges, (16, caps[1]))  # too few slots
    with pytest.raises(ValueError, match="more pores than capacity"):
        _fit._checked(None, flags, _fit.SAMPLING_ERRORS)


def test_a_rerun_reads_the_layout_kept_on_disk(monkeypatch):
    """Where compiled programs are kept (as in this suite and on the command line), so is the
    layout: its design (the pores and graphs, the same for every patch size) and its draw sizes.
    A rerun (a new process: nothing kept in memory) reads the same arrays back without building,
    a damaged file is built anew and replaced, and a fit of another size builds only its draw
    sizes."""
    key, rest = jax.random.key(7), (D_RANGE, SMALL["n_steps"], SMALL["d_levels"])
    paths = [
        kept_path("designs", _fit._design_name(key, D_RANGE, SMALL["d_levels"])),
        kept_path("layouts", _fit._layout_name(key, (64, 64), *rest)),
    ]
    if None in paths:
        pytest.skip("compiled programs are not kept (JFACE_CACHE_DIR=off)")
    fresh = _layout(key, (64, 64), *rest)  # the target's (compiled already)
    built = []
    design, draw_entries = _fit._design, _fit._draw_entries
    monkeypatch.setattr(_fit, "_design", lambda *a: built.append("design") or design(*a))
    monkeypatch.setattr(_fit, "_draw_entries", lambda *a: built.append("sizes") or draw_entries(*a))

    def same(a, b):
        assert jax.tree.structure(a) == jax.tree.structure(b)
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
            assert x.dtype == y.dtype and np.array_equal(x, y)

    def rerun():
        monkeypatch.setattr(_fit, "_LAYOUTS", {})
        monkeypatch.setattr(_fit, "_DESIGNS", {})
        same(_fit._kept_layout(key, (64, 64), *rest), fresh)
        return built.copy()

    rerun()  # built and written unless an earlier run of the suite wrote them
    assert all(p.is_file() for p in paths)
    built.clear()
    assert rerun() == []  # read back
    for path, what in zip(paths, ("design", "sizes"), strict=True):
        path.write_bytes(path.read_bytes()[:200])  # truncated
        built.clear()
        assert rerun() == [what]
        built.clear()
        assert rerun() == []  # the damaged file was replaced
    kept_path("layouts", _fit._layout_name(key, (72, 72), *rest)).unlink(missing_ok=True)
    other = _fit._kept_layout(key, (72, 72), *rest)  # a size no earlier run may have kept
    assert built == ["sizes"]  # the design kept in memory
    same(other, _layout(key, (72, 72), *rest))


def test_the_shipped_layouts_are_what_a_build_gives(monkeypatch):
    """jface ships the default fast fit's design and its draw sizes at common patch sizes (a
    first fit spent half a minute building them): a default fit of those sizes builds nothing,
    and a build now gives the same arrays (else ``python -m jface.wrinkles._ship`` rebuilds the
    file)."""
    key, d_levels, n_steps = _fit.layout_key(), _fit.D_LEVELS["fast"], 50
    assert inspect.signature(fit_wrinkles).parameters["n_steps"].default == n_steps
    monkeypatch.setattr(_fit, "_LAYOUTS", {})
    monkeypatch.setattr(_fit, "_DESIGNS", {})
    monkeypatch.setattr(_compilation, "kept_path", lambda *a: pytest.fail("looked for a kept file"))
    for build in ("_design", "_draw_entries"):
        monkeypatch.setattr(_fit, build, lambda *a: pytest.fail("built a shipped layout"))
    shipped = {
        n: _fit._kept_layout(key, (n, n), _fit.D_RANGE, n_steps, d_levels)
        for n in _fit.SHIPPED_SIZES
    }
    monkeypatch.undo()
    design = _fit._design(key, _fit.D_RANGE, d_levels)
    for n, layout in shipped.items():
        entries = _fit._draw_entries(key, design, (n, n), n_steps)
        fresh = _fit._sized(design, (n, n), n_steps, entries)
        assert jax.tree.structure(layout) == jax.tree.structure(fresh)
        for a, b in zip(jax.tree.leaves(layout), jax.tree.leaves(fresh), strict=True):
            assert a.dtype == b.dtype and np.array_equal(a, b)
        assert _fit.layout_shipped((n, n), _fit.D_RANGE, n_steps, d_levels)
    assert not _fit.layout_shipped((72, 72), _fit.D_RANGE, n_steps, d_levels)
    assert not _fit.layout_shipped((256, 256), _fit.D_RANGE, n_steps, _fit.D_LEVELS["paper"])
