"""Vectorised particle swarm optimisation (§4.2.1 of Weiss et al. 2023).

The swarm works in normalised coordinates: every parameter is mapped to ``[0, 1]`` by its bounds,
so one step size, one velocity scale and one boundary rule serve parameters of any unit. The loss
sees the parameters in their own units. All agents are evaluated at once with ``jax.vmap`` and a
whole trial (initialisation and every epoch) is one jitted ``lax.scan``; trials run one after the
other with ``lax.map`` so memory holds one swarm at a time.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jface import _checks
from jface._compilation import QUICK_COMPILE
from jface.noise import counter_uniform

Topology = Literal["lbest", "gbest"]
Boundary = Literal["random_absorb", "nearest_absorb", "reflect", "periodic"]
#: ``progress(trial, epoch, best_loss)``, called from inside the jitted run after each epoch.
Progress = Callable[[int, int, float], None]


class PSOResult(eqx.Module):
    """What a swarm found.

    Attributes:
        params: best parameter vector over all trials, in the caller's units, ``(P,)``.
        loss: its loss.
        history: best-so-far loss of each trial after initialisation and after every epoch,
            ``(n_trials, n_epochs + 1)`` (non-increasing along the epoch axis).
        trial_params: best parameters of each trial, ``(n_trials, P)``.
        trial_losses: best loss of each trial, ``(n_trials,)``.
        n_nonfinite: loss evaluations per trial that gave NaN or infinity; they count as
            ``+inf`` (never a personal or neighbourhood best), so a bad agent cannot pull the
            swarm towards it.
        best_trial: index of the trial that gave ``params``.
    """

    params: Float[Array, " P"]
    loss: Float[Array, ""]
    history: Float[Array, "T E"]
    trial_params: Float[Array, "T P"]
    trial_losses: Float[Array, " T"]
    n_nonfinite: Int[Array, " T"]
    best_trial: Int[Array, ""]


class _Settings(eqx.Module):
    n_agents: int = eqx.field(static=True)
    n_epochs: int = eqx.field(static=True)
    topology: str = eqx.field(static=True)
    boundary: str = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    c1: float = eqx.field(static=True)
    c2: float = eqx.field(static=True)
    inertia: tuple[float, float, float] = eqx.field(static=True)
    batched: bool = eqx.field(static=True)


def pso(
    key: Any,
    loss_fn: Callable[[Float[Array, " P"]], Float[Array, ""]],
    bounds: Any,
    *,
    n_agents: int = 50,
    n_epochs: int = 100,
    n_trials: int = 1,
    topology: Topology = "lbest",
    boundary: Boundary = "random_absorb",
    cyclic: Any = None,
    dt: float = 0.2,
    c1: float = 2.0,
    c2: float = 2.0,
    inertia: tuple[float, float, float] = (0.4, 0.6, 0.98),
    batched: bool = False,
    progress: Progress | None = None,
) -> PSOResult:
    """Minimise ``loss_fn`` over a box with a particle swarm (Eq. 14–15 of Weiss et al. 2023).

    Each epoch every agent ``i`` moves by

        v ← w_t v + c1 r1 (p_i − x) + c2 r2 (g_i − x)      (Eq. 14)
        x ← x + Δt v                                      (Eq. 15)

    with ``r1, r2 ~ U[0, 1]`` drawn per agent and per dimension, ``p_i`` the agent's best
    position, ``g_i`` the best position of its neighbourhood and the inertia
    ``w_t = a + b · c^t`` (``inertia=(a, b, c)``; the paper's exponential decay 0.4 + 0.6 · 0.98^t).
    Positions start uniform in ``[0, 1]`` (normalised units) and velocities at half the way to
    another uniform point, ``v = (u − x) / 2`` (the "half-diff" start of Standard PSO 2007):
    on Rastrigin-10D it beats starting from zero or from uniform ``[−1, 1]`` velocities in every
    topology and constant set of ``benchmarks/bench_pso.py``.

    Topologies [KM02]: "lbest" — agents on an index ring see themselves and their two ring
    neighbours (fixed at initialisation; the paper's choice, it keeps several minima explored);
    "gbest" — every agent sees the whole swarm.

    Boundary handling [HBM13], per violated coordinate of a non-cyclic parameter:
    "random_absorb" (the paper's) — a uniformly random in-bounds value, velocity zero;
    "nearest_absorb" — the nearest bound, velocity zero; "reflect" — mirrored back into the box,
    velocity reversed; "periodic" — wrapped into the box, velocity kept (pyswarms' default).
    Cyclic parameters (orientations) use the shortest signed distance modulo the period
    ``high − low`` in Eq. 14 and wrap their position.

    Non-finite losses are treated as ``+inf`` and counted in ``PSOResult.n_nonfinite``.

    Args:
        key: JAX random key; ``n_trials`` trials use independent keys split from it.
        loss_fn: maps one parameter vector ``(P,)`` in the caller's units to a scalar loss; it is
            vmapped over agents and traced once. Close over arrays through
            ``jax.tree_util.Partial`` or an ``equinox.Module`` to keep them traced inputs.
        bounds: ``(low, high)``, each of shape ``(P,)`` (or an array of shape ``(2, P)``).
        n_agents, n_epochs, n_trials: swarm size, epochs per trial, independent trials (the best
            is kept). Each trial evaluates ``n_agents · (n_epochs + 1)`` losses.
        topology: "lbest" or "gbest".
        boundary: "random_absorb", "nearest_absorb", "reflect" or "periodic".
        cyclic: ``None`` or a boolean mask ``(P,)`` of periodic parameters.
        dt, c1, c2, inertia: Δt of Eq. 15, the coefficients and the inertia schedule of Eq. 14.
        batched: ``loss_fn`` maps the whole swarm ``(n_agents, P)`` to ``(n_agents,)`` itself
            instead of being vmapped (e.g. to evaluate agents one after the other with
            ``lax.map`` when each agent's cost depends on its parameters).
        progress: optional ``progress(trial, epoch, best_loss)`` called after every epoch from
            inside the jitted run (for a progress bar on long runs).

    Returns:
        A :class:`PSOResult`.

    Raises:
        TypeError: a non-callable ``loss_fn``, or one that does not return a scalar float.
        ValueError: malformed bounds (wrong shape, non-finite, beyond float32,
            ``low >= high``), a bad count, unknown topology/boundary, or a malformed ``cyclic``
            mask.
    """
    key = _checks.key(key)
    if not callable(loss_fn):
        raise TypeError(f"loss_fn must be callable, got {_checks.describe(loss_fn)}")
    low, high = _check_bounds(bounds)
    n = low.shape[0]
    cyclic = _check_cyclic(cyclic, n)
    settings = _Settings(
        n_agents=_checks.integer(n_agents, "n_agents", low=2 if topology == "gbest" else 3),
        n_epochs=_checks.integer(n_epochs, "n_epochs", low=1),
        topology=_checks.choice(topology, "topology", ("lbest", "gbest")),
        boundary=_checks.choice(
            boundary, "boundary", ("random_absorb", "nearest_absorb", "reflect", "periodic")
        ),
        dt=_checks.real(dt, "dt", low=0.0, open_low=True),
        c1=_checks.real(c1, "c1", low=0.0),
        c2=_checks.real(c2, "c2", low=0.0),
        inertia=tuple(_checks.real(v, "inertia", low=0.0) for v in _triple(inertia)),
        batched=bool(batched),
    )
    n_trials = _checks.integer(n_trials, "n_trials", low=1)
    return _run(key, n_trials, loss_fn, low, high, cyclic, settings, progress)


def _triple(inertia: Any) -> tuple:
    if not isinstance(inertia, (tuple, list)) or len(inertia) != 3:
        raise ValueError(f"inertia must be (a, b, c) for w_t = a + b·c^t, got {inertia!r}")
    return tuple(inertia)


def _check_bounds(bounds: Any) -> tuple[np.ndarray, np.ndarray]:
    try:
        arr = np.asarray(bounds, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise TypeError(f"bounds must be (low, high) arrays of shape (P,), got {bounds!r}") from err
    if arr.ndim != 2 or arr.shape[0] != 2 or arr.shape[1] == 0:
        raise ValueError(f"bounds must be (low, high), each of shape (P,), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("bounds must be finite")
    # the swarm runs in float32 on (x - low) / (high - low): both must be float32 numbers
    big = float(np.finfo(np.float32).max)
    wide = np.flatnonzero((np.abs(arr).max(axis=0) > big) | (arr[1] - arr[0] > big))
    if wide.size:
        i = int(wide[0])
        raise ValueError(
            f"bounds must be float32 numbers whose span high - low is at most {big:.4g}, got "
            f"low={arr[0, i]}, high={arr[1, i]} in dimension {i}"
        )
    bad = np.flatnonzero(arr[0] >= arr[1])
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"bounds must have low < high in every dimension, got low={arr[0, i]} >= "
            f"high={arr[1, i]} in dimension {i}"
        )
    # numpy, not jax arrays: the jitted run takes them as inputs without a device_put each call
    return arr[0].astype(np.float32), arr[1].astype(np.float32)


def _check_cyclic(cyclic: Any, n: int) -> np.ndarray:
    if cyclic is None:
        return np.zeros(n, bool)
    mask = np.asarray(cyclic)
    if mask.dtype != bool or mask.shape != (n,):
        raise ValueError(
            f"cyclic must be a boolean mask of shape ({n},), got {_checks.describe(mask)}"
        )
    return mask


@eqx.filter_jit
def _run(key, n_trials: int, loss_fn, low, high, cyclic, settings, progress) -> PSOResult:
    def trial(args):
        index, key = args
        return _trial(key, index, loss_fn, low, high, cyclic, settings, progress)

    keys = jax.random.split(key, n_trials)
    best_x, best_s, history, nonfinite = jax.lax.map(trial, (jnp.arange(n_trials), keys))
    winner = jnp.argmin(best_s)
    to_units = low + best_x * (high - low)
    return PSOResult(
        params=to_units[winner],
        loss=best_s[winner],
        history=history,
        trial_params=to_units,
        trial_losses=best_s,
        n_nonfinite=nonfinite,
        best_trial=winner,
    )


def _trial(key, index, loss_fn, low, high, cyclic, settings: _Settings, progress):
    m, n = settings.n_agents, low.shape[0]

    def evaluate(x: Float[Array, "M P"]) -> tuple[Float[Array, " M"], Int[Array, ""]]:
        return _evaluate(loss_fn, low, high, x, settings)

    x, v, seed = _start(key, m, n)
    s, bad = evaluate(x)

    def epoch(state, t):
        x, v, p, ps, bad = state
        x, v = _move(x, v, p, ps, t, seed, cyclic, settings)
        s, new_bad = evaluate(x)
        p, ps = _keep_better(x, s, p, ps)
        best = jnp.min(ps)
        if progress is not None:
            jax.debug.callback(_report, progress, index, t + 1, best)
        return (x, v, p, ps, bad + new_bad), best

    init = (x, v, x, s, bad)
    (_, _, p, ps, bad), history = jax.lax.scan(epoch, init, jnp.arange(settings.n_epochs))
    i = jnp.argmin(ps)
    return p[i], ps[i], jnp.concatenate([jnp.min(s)[None], history]), bad


def _start(key, m: int, n: int):
    """Initial positions, velocities (half-diff) and the seed of the per-epoch random numbers."""
    k_x, k_v, k_run = jax.random.split(key, 3)
    x = jax.random.uniform(k_x, (m, n), jnp.float32)
    v = 0.5 * (jax.random.uniform(k_v, (m, n), jnp.float32) - x)  # half-diff
    return x, v, jax.random.bits(k_run, (), jnp.uint32)


def _evaluate(loss_fn, low, high, x, settings: _Settings):
    """Losses of the swarm at normalised positions ``x`` (non-finite → +inf) and their count."""
    m, n = x.shape
    units = low + x * (high - low)
    s = loss_fn(units) if settings.batched else jax.vmap(_scalar(loss_fn))(units)
    if s.shape != (m,) or s.dtype.kind != "f":  # checked once, while tracing
        raise TypeError(
            f"loss_fn must return one loss per agent for a {(m, n)} input, got "
            f"{_checks.describe(s)}"
        )
    s = s.astype(jnp.float32)
    finite = jnp.isfinite(s)
    return jnp.where(finite, s, jnp.inf), jnp.sum(~finite)


def _move(x, v, p, ps, t, seed, cyclic, settings: _Settings):
    """One step of Eq. 14-15 (epoch ``t``, counting from 0) and the boundary rule."""
    m, n = x.shape
    # cheaper than threefry; the barrier keeps XLA from recomputing the hash in every user
    r1, r2, r3 = jax.lax.optimization_barrier(counter_uniform(seed, t, (3, m, n)))
    g = _neighbourhood_best(p, ps, settings.topology)
    a, b, c = settings.inertia
    w = a + b * jnp.power(jnp.float32(c), jnp.asarray(t).astype(jnp.float32))
    v = w * v + settings.c1 * r1 * _delta(p, x, cyclic) + settings.c2 * r2 * _delta(g, x, cyclic)
    return _bound(r3, x + settings.dt * v, v, cyclic, settings.boundary)


def _keep_better(x, s, p, ps):
    better = s < ps
    return jnp.where(better[:, None], x, p), jnp.where(better, s, ps)


class Swarm(eqx.Module):
    """A swarm advanced one epoch at a time from Python (:func:`swarm_start`,
    :func:`swarm_epoch`), for callers that stop early, compare trials between epochs or change
    the loss on the way. Positions are normalised to ``[0, 1]``; the moves are :func:`pso`'s.

    Attributes:
        x, v: positions and velocities ``(M, P)``; p, ps: personal bests and their losses.
        seed: seed of the per-epoch random numbers; epoch: epochs done.
        n_nonfinite: evaluations that gave NaN or infinity.
    """

    x: Float[Array, "M P"]
    v: Float[Array, "M P"]
    p: Float[Array, "M P"]
    ps: Float[Array, " M"]
    seed: Array
    epoch: Int[Array, ""]
    n_nonfinite: Int[Array, ""]

    @property
    def best(self) -> Float[Array, ""]:
        return jnp.min(self.ps)

    def best_params(self, low, high) -> Float[Array, " P"]:
        """The best personal position in the caller's units."""
        return low + self.p[jnp.argmin(self.ps)] * (high - low)


def swarm_settings(n_agents: int, **options) -> _Settings:
    """Settings of :func:`swarm_start` / :func:`swarm_epoch` (options as in :func:`pso`, with
    its defaults; ``n_epochs`` is unused)."""
    defaults = {"topology": "lbest", "boundary": "random_absorb", "dt": 0.2, "c1": 2.0,
                "c2": 2.0, "inertia": (0.4, 0.6, 0.98), "batched": False}  # fmt: skip
    return _Settings(n_agents=n_agents, n_epochs=1, **(defaults | options))


@eqx.filter_jit
def _positions(key, n_agents: int, n: int):
    return _start(key, n_agents, n)


@functools.partial(eqx.filter_jit, compiler_options=QUICK_COMPILE)
def swarm_evaluate(loss_fn, low, high, x, settings: _Settings):
    """:func:`pso`'s evaluation of normalised positions: the one compile that holds the loss
    (compiled quickly: a stepped swarm is for large losses, whose compile is a fit's fixed
    cost)."""
    return _evaluate(loss_fn, low, high, x, settings)


def swarm_start(key, loss_fn, low, high, settings: _Settings) -> Swarm:
    """The initial swarm of :func:`pso`'s trial with this key, evaluated."""
    x, v, seed = _positions(key, settings.n_agents, low.shape[0])
    s, bad = swarm_evaluate(loss_fn, low, high, np.asarray(x), settings)
    return Swarm(x, v, x, s, seed, jnp.int32(0), bad)


@eqx.filter_jit
def _moved(swarm: Swarm, cyclic, settings: _Settings):
    return _move(swarm.x, swarm.v, swarm.p, swarm.ps, swarm.epoch, swarm.seed, cyclic, settings)


@eqx.filter_jit
def _absorbed(swarm: Swarm, x, v, s, bad) -> Swarm:
    p, ps = _keep_better(x, s, swarm.p, swarm.ps)
    return Swarm(x, v, p, ps, swarm.seed, swarm.epoch + 1, swarm.n_nonfinite + bad)


def swarm_epoch(swarm: Swarm, loss_fn, low, high, cyclic, settings: _Settings) -> Swarm:
    """``swarm`` one epoch on (the same moves as :func:`pso`)."""
    x, v = _moved(swarm, cyclic, settings)
    # the positions reach the loss from the host, so that it compiles once: a loss sharded over
    # devices leaves its losses, and so the next moves, on its mesh
    s, bad = swarm_evaluate(loss_fn, low, high, np.asarray(x), settings)
    return _absorbed(swarm, x, v, s, bad)


def _scalar(loss_fn: Callable) -> Callable:
    """``loss_fn``, raising a clear error (while tracing) unless it returns a scalar float."""

    def checked(x):
        out = loss_fn(x)
        if not hasattr(out, "shape") or out.shape != () or out.dtype.kind != "f":
            raise TypeError(
                f"loss_fn must return a scalar float for a {x.shape} input, got "
                f"{_checks.describe(out)}"
            )
        return out

    return checked


def _report(progress: Progress, trial, epoch, best) -> None:
    progress(int(trial), int(epoch), float(best))


def _neighbourhood_best(p: Array, ps: Array, topology: str) -> Array:
    """Best personal position each agent sees: the swarm's (gbest) or its ring's (lbest)."""
    if topology == "gbest":
        return jnp.broadcast_to(p[jnp.argmin(ps)], p.shape)
    ring = jnp.stack([jnp.roll(ps, 1), ps, jnp.roll(ps, -1)])  # agents i-1, i, i+1
    shift = jnp.argmin(ring, axis=0) - 1
    return p[(jnp.arange(ps.shape[0]) + shift) % ps.shape[0]]


def _delta(target: Array, x: Array, cyclic: Bool[Array, " P"]) -> Array:
    """``target - x``, for cyclic dimensions the shortest signed distance modulo the period 1."""
    d = target - x
    return jnp.where(cyclic, d - jnp.round(d), d)


def _bound(r: Array, x: Array, v: Array, cyclic: Array, boundary: str) -> tuple[Array, Array]:
    """Bring positions back into ``[0, 1]`` (Helwig et al. 2013) and wrap cyclic ones."""
    wrapped = x - jnp.floor(x)
    out = ((x < 0) | (x > 1)) & ~cyclic
    if boundary == "random_absorb":
        inside = r
        v = jnp.where(out, 0.0, v)
    elif boundary == "nearest_absorb":
        inside = jnp.clip(x, 0.0, 1.0)
        v = jnp.where(out, 0.0, v)
    elif boundary == "periodic":  # wrapped into the box, velocity kept (pyswarms' default)
        inside = wrapped
    else:  # reflect: fold the overshoot back (period 2 handles overshoots beyond one box width)
        folded = jnp.mod(x, 2.0)
        inside = jnp.where(folded > 1.0, 2.0 - folded, folded)
        v = jnp.where(out, -v, v)
    x = jnp.where(cyclic, wrapped, jnp.where(out, inside, x))
    return x, v
