"""``jax.jit`` and ``jax.vmap`` of every public function the README's Python section names.

Each function is jitted with its arguments passed and with them closed over (closed-over values
are concrete, so validation looks at them: the statistics check once broke exactly there), and
vmapped over a batch of two; all three must equal the eager call(s). The functions that cannot
be transformed (files, host-side drivers whose sizes come from the data) must be exactly the ones
the README says so of.
"""

import re
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jface import detail, faces, mesh, pyramid, render, wrinkles

README = Path(__file__).resolve().parents[1] / "README.md"

#: Named in the README's Python section but not transformable, with the README's reason.
HOST_SIDE = {
    "io.read_map": "files",
    "io.write_png": "files",
    "io.read_mesh": "files",
    "io.exr_rows": "files",
    "io.provenance": "a dict of metadata",
    "detail.load_stats": "files",
    "detail.save_stats": "files",
    "detail.compare_methods": "a table of Python numbers",
    "mesh.remesh": "ray casting and sparse least squares on the host",
    "wrinkles.synthesize": "sizes each level from the pores it samples",
    "wrinkles.synthesize_bands": "a generator of bands",
    "wrinkles.extract_pores": "as many pores as the scan holds",
    "wrinkles.fit_wrinkles": "a driver of trials with progress",
    "wrinkles.radius_map_from_mesh": "rasterises a mesh on the host",
}


class Case(NamedTuple):
    fn: Callable[..., Any]  # the function under test, on the arguments below
    args: tuple  # one call's arguments
    batch: tuple  # arguments of two calls: a leading axis of 2 where in_axes says 0
    in_axes: tuple


def _python_section() -> str:
    text = README.read_text()
    return text[text.index("## In Python") : text.index("## Layout")]


def _named_in_readme() -> set[str]:
    section = _python_section()
    pattern = r"(?<![\w/.])(io|detail|pyramid|render|mesh|wrinkles|faces)\.([A-Za-z_]\w*)"
    names = {m.group(0) for m in re.finditer(pattern, section)}
    if re.search(r"\w+\.detailed\(", section):
        names.add("detail.Face.detailed")
    return names


def _stack(*trees):
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


def _close(a, b, what: str) -> None:
    leaves_a, tree_a = jax.tree.flatten(a)
    leaves_b, tree_b = jax.tree.flatten(b)
    assert tree_a == tree_b, what
    for x, y in zip(leaves_a, leaves_b, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            continue
        np.testing.assert_allclose(x, y, rtol=2e-4, atol=2e-5, err_msg=what)


@pytest.fixture(scope="module")
def cases() -> dict[str, Case]:
    rng = np.random.default_rng(0)
    key = jax.random.key(0)
    keys = jax.random.split(key, 2)
    maps = rng.standard_normal((2, 32, 32)).astype(np.float32)
    m = maps[0]
    stats = detail.analyze(m, grid=2, n_scales=2)
    both_stats = _stack(stats, detail.analyze(maps[1], grid=2, n_scales=2))

    scan = mesh.synthetic_scan(key, n_subdivisions=1)
    remeshed = mesh.remesh(
        scan.scan.vertices, np.asarray(scan.scan.faces), scan.landmarks, image_size=32,
        n_linear=1, n_loop=1, n_smooth=1,
    )  # fmt: skip
    face = detail.Face.from_remeshed(remeshed)
    face_stats = detail.analyze(face.image, grid=2, n_scales=2)
    images = np.stack([np.asarray(face.image), 2 * np.asarray(face.image)])

    params = wrinkles.WrinkleParams(d=0.05, theta=0.6, s=0.2)
    both_params = wrinkles.stack_params([params, params.replace(theta=1.2)])
    pores = wrinkles.sample_pores(key, 0.05)
    capacity, reach = pores.capacity, (0.04, 0.05)
    spec = wrinkles.graph_spec(pores, radius_range=reach, max_degree=24, max_crossings=64,
                               edge_cell_capacity=64)  # fmt: skip
    graph = wrinkles.build_graph(pores, spec)
    both_pores = jax.vmap(
        lambda k, d: wrinkles.sample_pores(k, d, capacity=capacity, radius_range=reach)
    )(keys, jnp.array([0.04, 0.05]))
    coarse = rng.standard_normal((2, 64, 64)).astype(np.float32)

    train = rng.random((2, 12, 12, 12)).astype(np.float32)
    library = faces.build_library(train[0], 3)
    mask = np.zeros((12, 12), bool)
    mask[4:8, 4:8] = True

    def quilt(k, lib, target):
        return faces.quilt(k, lib, target, blend=False).image

    def fitted_model(x):
        """What identifies a factor analyser (its loadings only up to sign and rotation)."""
        fit = faces.fit_factor_analyser(x, 2, n_iter=3)
        model = fit.model
        return model.mean, model.noise, model.factors @ model.factors.T, fit.log_likelihood

    return {
        "pyramid.build": Case(lambda x: pyramid.build(x, 2, 4), (m,), (maps,), (0,)),
        "detail.analyze": Case(
            lambda x: detail.analyze(x, grid=2, n_scales=2), (m,), (maps,), (0,)
        ),
        "detail.synthesize": Case(
            lambda k, x, s: detail.synthesize(k, x, s, n_iter=2),
            (key, m, stats),
            (keys, maps, both_stats),
            (0, 0, 0),
        ),
        "render.shade": Case(render.shade, (m,), (maps,), (0,)),
        "detail.remove_detail": Case(
            lambda x: detail.remove_detail(x, 2, n_scales=2), (m,), (maps,), (0,)
        ),
        "detail.age": Case(
            lambda k, young, old: detail.age(k, young, old, face_stats, n_iter=1).image,
            (key, face, face),
            (keys, face, face),
            (0, None, None),
        ),
        # the mesh's topology is static (it sizes the subdivision): close over it, map images
        "detail.Face.detailed": Case(
            lambda image: eqx.tree_at(lambda f: f.image, face, image).detailed().vertices,
            (images[0],),
            (images,),
            (0,),
        ),
        "wrinkles.WrinkleParams": Case(
            lambda theta, s: wrinkles.WrinkleParams(d=0.05, theta=theta, s=s),
            (jnp.float32(0.5), jnp.float32(0.2)),
            (jnp.array([0.5, 1.0]), jnp.array([0.2, 0.3])),
            (0, 0),
        ),
        "wrinkles.sample_pores": Case(
            lambda k, d: wrinkles.sample_pores(k, d, capacity=capacity, radius_range=reach),
            (key, jnp.float32(0.05)),
            (keys, jnp.array([0.04, 0.05])),
            (0, 0),
        ),
        "wrinkles.build_graph": Case(
            lambda p: wrinkles.build_graph(p, spec).edge_mask,
            (jax.tree.map(lambda x: x[0], both_pores),),
            (both_pores,),
            (0,),
        ),
        "wrinkles.simulate": Case(
            lambda k, g, p: wrinkles.simulate(k, g, p, n_steps=3),
            (key, graph, params),
            (keys, graph, both_params),
            (0, None, 0),
        ),
        "wrinkles.perlin_variation": Case(
            lambda k, p: wrinkles.perlin_variation(k, p, {"d": 0.2}, resolution=16).d,
            (key, params),
            (keys, params),
            (0, None),
        ),
        "wrinkles.extract_orientation": Case(
            lambda x: wrinkles.extract_orientation(x, crop=32).theta,
            (coarse[0],),
            (coarse,),
            (0,),
        ),
        "wrinkles.blend_with_scan": Case(
            wrinkles.blend_with_scan, (coarse[0], coarse[1]), (coarse, coarse[::-1]), (0, 0)
        ),
        "faces.build_library": Case(
            lambda x: faces.build_library(x, 3).patches, (train[0],), (train,), (0,)
        ),
        "faces.quilt": Case(
            quilt, (key, library, train[0, 0]), (keys, library, train[0, :2]), (0, None, 0)
        ),
        "faces.inpaint": Case(
            lambda k, x: faces.inpaint(k, library, x, mask, train[0, 1]).image,
            (key, train[0, 0]),
            (keys, train[0, :2]),
            (0, 0),
        ),
        "faces.sample": Case(
            lambda k: faces.sample(k, faces.fit_factor_analyser(train[0], 2, n_iter=3).model, 2),
            (key,),
            (keys,),
            (0,),
        ),
        # the case: one factor analyser per population (or bootstrap resample)
        "faces.fit_factor_analyser": Case(
            fitted_model,
            (train[0],),
            (train,),
            (0,),
        ),
    }


TRANSFORMABLE = (
    "pyramid.build",
    "detail.analyze",
    "detail.synthesize",
    "render.shade",
    "detail.remove_detail",
    "detail.age",
    "detail.Face.detailed",
    "wrinkles.WrinkleParams",
    "wrinkles.sample_pores",
    "wrinkles.build_graph",
    "wrinkles.simulate",
    "wrinkles.perlin_variation",
    "wrinkles.extract_orientation",
    "wrinkles.blend_with_scan",
    "faces.build_library",
    "faces.quilt",
    "faces.inpaint",
    "faces.fit_factor_analyser",
    "faces.sample",
)


def test_every_function_of_the_readme_is_covered():
    named = _named_in_readme()
    assert named == set(TRANSFORMABLE) | set(HOST_SIDE), (
        f"untested: {sorted(named - set(TRANSFORMABLE) - set(HOST_SIDE))}; "
        f"no longer in the README: {sorted((set(TRANSFORMABLE) | set(HOST_SIDE)) - named)}"
    )
    # the README says which ones run on the host, and why
    section = _python_section()
    host = section[section.index("run on the host") :]
    for name in HOST_SIDE:
        assert f"`{name.split('.', 1)[1]}`" in host, f"{name} is not listed as host-side"


@pytest.mark.parametrize("name", TRANSFORMABLE)
def test_jit_and_vmap(name, cases):
    case = cases[name]
    eager = case.fn(*case.args)
    _close(jax.jit(case.fn)(*case.args), eager, f"{name}: jit, arguments passed")
    _close(jax.jit(lambda: case.fn(*case.args))(), eager, f"{name}: jit, arguments closed over")
    mapped = jax.vmap(case.fn, in_axes=case.in_axes)(*case.batch)
    calls = [
        case.fn(*[arg if axis is None else jax.tree.map(lambda x: x[i], arg)  # noqa: B023
                  for arg, axis in zip(case.batch, case.in_axes, strict=True)])
        for i in range(2)
    ]  # fmt: skip
    _close(mapped, _stack(*calls), f"{name}: vmap")


def test_statistics_closed_over_under_jit_are_still_checked(cases, unchecked):
    """Closed-over values are concrete: a jitted closure over bad statistics is refused with
    the library's message, not a tracer error."""
    case = cases["detail.synthesize"]
    key, image, stats = case.args
    bad = detail.DetailStats(
        stats.std.at[0, 0, 0].set(jnp.nan), None, None, 2, 4, stats.image_shape
    )
    with pytest.raises(ValueError, match=r"target\.std must be finite"):
        jax.jit(lambda k, x: detail.synthesize(k, x, bad, n_iter=1))(key, image)
    ints = detail.DetailStats(stats.std.astype(jnp.int32), None, None, 2, 4, stats.image_shape)
    with pytest.raises(TypeError, match=r"target\.std must be floating point"):
        jax.jit(lambda k, x: detail.synthesize(k, x, ints, n_iter=1))(key, image)


def test_constant_data_under_jit_fails_when_run(cases):
    """Under tracing the constant-data check of fit_factor_analyser cannot look at values; it
    becomes a runtime error of the compiled fit instead of a silent NaN model."""
    flat = jnp.ones((8, 4, 4), jnp.float32)
    with pytest.raises(Exception, match="data is constant"):
        jax.jit(lambda x: faces.fit_factor_analyser(x, 2, n_iter=2).model.mean)(flat)
