"""Patch libraries, non-stationary quilting, Poisson blending and editing (Mohammed et al. 2009)."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.fft
import scipy.sparse
import scipy.sparse.linalg

from jface import faces
from jface.faces import _poisson

GRID = 5  # 25×25 faces: 6×6 patches overlapping by 1 px on a 26×26 canvas


@pytest.fixture(scope="module")
def lfw() -> np.ndarray:
    """The first 100 aligned 25×25 greyscale faces of scikit-image's LFW subset, float32."""
    from skimage import data

    return np.asarray(data.lfw_subset()[:100], np.float32)


@pytest.fixture(scope="module")
def library(lfw):
    return faces.build_library(lfw, GRID)


@pytest.fixture(scope="module")
def exact_library(lfw):
    """No augmentation: every patch is a verbatim window of a training image."""
    return faces.build_library(lfw, GRID, translations=0, angles=())


@pytest.fixture(scope="module")
def pca_target(lfw):
    """A global target of our own: a sample of a 10-component PCA model of the faces."""
    flat = lfw.reshape(len(lfw), -1).astype(np.float64)
    mean = flat.mean(0)
    _, s, vt = np.linalg.svd(flat - mean, full_matrices=False)
    z = np.random.default_rng(1).standard_normal(10)
    sample = mean + (z * s[:10] / np.sqrt(len(lfw))) @ vt[:10]
    return np.clip(sample, 0, 1).reshape(lfw.shape[1:]).astype(np.float32)


# --- Poisson --------------------------------------------------------------------------------


def sparse_reference(guide: np.ndarray, boundary: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Eq. 7 of Pérez et al. assembled as a sparse matrix and solved directly (scipy)."""
    h, w = boundary.shape
    index = -np.ones((h, w), int)
    ys, xs = np.nonzero(region)
    index[ys, xs] = np.arange(len(ys))
    rows, cols, vals = [], [], []
    rhs = np.zeros(len(ys))
    for k, (y, x) in enumerate(zip(ys, xs, strict=True)):
        for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            yy, xx = y + dy, x + dx
            if not (0 <= yy < h and 0 <= xx < w):
                continue
            rows.append(k), cols.append(k), vals.append(1.0)
            rhs[k] += guide[y, x] - guide[yy, xx]
            if region[yy, xx]:
                rows.append(k), cols.append(index[yy, xx]), vals.append(-1.0)
            else:
                rhs[k] += boundary[yy, xx]
    a = scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(len(ys), len(ys)))
    out = boundary.copy()
    out[ys, xs] = scipy.sparse.linalg.spsolve(a, rhs)
    return out


def test_dst1_matches_scipy():
    x = np.random.default_rng(0).standard_normal((5, 11))
    for axis in (0, 1):
        np.testing.assert_allclose(
            _poisson.dst1(jnp.asarray(x), axis), scipy.fft.dst(x, type=1, axis=axis) / 2, atol=1e-12
        )


def test_poisson_matches_sparse_direct_solve():
    rng = np.random.default_rng(1)
    guide, boundary = rng.standard_normal((2, 17, 23))
    gx, gy = faces.gradients(jnp.asarray(guide))
    # the whole rectangle, exact DST solve
    ring = np.zeros(boundary.shape, bool)
    ring[1:-1, 1:-1] = True
    u = np.asarray(faces.poisson_solve(gx, gy, boundary))
    np.testing.assert_allclose(u, sparse_reference(guide, boundary, ring), atol=1e-5)
    np.testing.assert_array_equal(u[~ring], boundary[~ring])
    # an irregular region touching the image edge, conjugate gradients
    region = np.zeros(boundary.shape, bool)
    region[0:9, 4:15] = True
    region[7:14, 2:6] = True
    v = np.asarray(faces.poisson_solve(gx, gy, boundary, region, tol=1e-10))
    np.testing.assert_allclose(v, sparse_reference(guide, boundary, region), atol=1e-5)
    np.testing.assert_array_equal(v[~region], boundary[~region])


def test_poisson_float32_and_blend_reproduces_source(lfw):
    face = lfw[3]
    np.testing.assert_allclose(faces.poisson_blend(face, face), face, atol=1e-5)
    assert faces.poisson_blend(face, face).dtype == jnp.float32


def test_poisson_bad_input(unchecked):
    img = np.zeros((8, 9))
    gx, gy = faces.gradients(jnp.asarray(img))
    with pytest.raises(ValueError, match="grad_x must have shape"):
        faces.poisson_solve(gy, gy, img)
    with pytest.raises(ValueError, match="mask is empty"):
        faces.poisson_solve(gx, gy, img, np.zeros((8, 9), bool))
    with pytest.raises(ValueError, match="mask must have shape"):
        faces.poisson_solve(gx, gy, img, np.ones((9, 8), bool))
    with pytest.raises(TypeError, match="mask must be a boolean"):
        faces.poisson_solve(gx, gy, img, np.ones((8, 9)))


# --- libraries ------------------------------------------------------------------------------


def test_library_layout(lfw, library):
    g = library.geometry
    assert g.grid == (5, 5) and g.patch == (6, 6) and g.overlap == (1, 1)
    assert g.canvas == (26, 26)
    assert faces.make_geometry((70, 70)).patch == (10, 10)  # the paper's 70×70, 9×9 grid
    n_aug = 9 * 3  # 3×3 shifts × 3 angles
    assert library.patches.shape == (5, 5, 100 * n_aug, 6, 6, 1)
    np.testing.assert_array_equal(library.sources, np.repeat(np.arange(100), n_aug))
    # entry i * n_aug is image i's own patch, unmoved
    np.testing.assert_allclose(library.patches[2, 3, 7 * n_aug, :, :, 0], lfw[7, 10:16, 15:21])
    # quadratic cost terms: Σ P² and Σ P² over the overlaps with the left and upper neighbours
    p64 = np.asarray(library.patches, np.float64)[..., 0]
    np.testing.assert_allclose(library.norms, (p64**2).sum(axis=(-2, -1)), rtol=1e-5)
    seam = np.zeros((6, 6), bool)
    seam[0], seam[:, 0] = True, True  # an inner position overlaps its neighbours by 1 px
    inner = (p64[2, 3][:, seam] ** 2).sum(1)
    np.testing.assert_allclose(library.seam_norms[2, 3], inner, rtol=1e-5)
    assert float(jnp.max(jnp.abs(library.seam_norms[0, 0]))) == 0.0


def test_library_rgb_and_bad_input(lfw, unchecked):
    rgb = np.stack([lfw[:4], lfw[:4] ** 2, 1 - lfw[:4]], axis=-1)
    lib = faces.build_library(rgb, 3, translations=0, angles=())
    assert lib.patches.shape[-1] == 3 and not lib.grey
    with pytest.raises(ValueError, match=r"images must be \(n, H, W\)"):
        faces.build_library(lfw[0], 3)
    with pytest.raises(ValueError, match="covers 16 px, less than"):
        faces.build_library(lfw[:2], 3, patch=6, overlap=1)
    with pytest.raises(ValueError, match="would lie outside"):
        faces.build_library(lfw[:2], 3, patch=20)
    with pytest.raises(TypeError, match="floating-point"):
        faces.build_library((lfw[:2] * 255).astype(np.uint8), 3)


# --- quilting -------------------------------------------------------------------------------


def test_one_image_and_no_target_weight_reproduces_it(lfw):
    lib = faces.build_library(lfw[:1], GRID, translations=0, angles=())
    out = faces.quilt(jax.random.key(0), lib, lfw[0], lam=0.0, n_best=1)
    np.testing.assert_allclose(out.quilted, lfw[0], atol=1e-6)
    np.testing.assert_allclose(out.image, lfw[0], atol=1e-5)
    assert (np.asarray(out.sources) == 0).all()


def test_patches_from_their_own_position_and_symmetric(lfw, exact_library, pca_target):
    out = faces.quilt(jax.random.key(1), exact_library, pca_target, lam=1.0, n_best=20)
    src = np.asarray(out.sources)
    np.testing.assert_array_equal(src, src[:, ::-1])  # horizontally opposite: same person
    np.testing.assert_array_equal(np.asarray(out.ids), src)  # no augmentation: id == image
    g = exact_library.geometry
    sy, sx = g.step
    quilted = np.asarray(out.quilted)
    for r in range(GRID):
        for c in range(GRID):
            # the part of each window no later patch covers is verbatim from the same window of
            # the chosen training image: the patch came from this position's library
            y, x = r * sy, c * sx
            h = g.patch[0] - (g.overlap[0] if r < GRID - 1 else 0)
            w = g.patch[1] - (g.overlap[1] if c < GRID - 1 else 0)
            h, w = min(h, 25 - y), min(w, 25 - x)
            np.testing.assert_array_equal(
                quilted[y : y + h, x : x + w], lfw[src[r, c], y : y + h, x : x + w]
            )
    assert faces.distinct_sources(out) > 3
    smap = np.asarray(faces.source_map(out, exact_library))
    assert smap.shape == (25, 25) and smap[0, 0] == src[0, 0] and smap[-1, -1] == src[-1, -1]


def replay_costs(library, result, target, image=None, region=None, lam=1.0):
    """Float64 numpy reference of the quilting cost (§2.2), replayed along the patches jface
    chose: at each synthesised position, the costs of the whole library given the canvas so far
    (masked SSD to the known pixels + λ SSD to the target, symmetry restriction applied) and the
    chosen entry. Returns ``[(costs, chosen), ...]`` in raster order."""
    g = library.geometry
    rows, cols = g.grid
    (ph, pw), (sy, sx) = g.patch, g.step
    hc, wc = g.canvas
    patches = np.asarray(library.patches, np.float64)
    sources = np.asarray(library.sources)
    ids = np.asarray(result.ids)

    def pad(x):
        x = np.asarray(x, np.float64)
        return np.pad(x, ((0, hc - x.shape[0]), (0, wc - x.shape[1])), "symmetric")[..., None]

    tgt = pad(target)
    if region is None:
        canvas, known = np.zeros((hc, wc, 1)), np.zeros((hc, wc), bool)
    else:
        hole = pad(region)[..., 0] > 0
        canvas, known = np.where(hole[..., None], tgt, pad(image)), ~hole
    observed = known.copy()
    chosen_src = -np.ones((rows, cols), int)
    out = []
    for r in range(rows):
        for c in range(cols):
            if ids[r, c] < 0:
                continue
            y, x = r * sy, c * sx
            lib = patches[r, c]
            win, m = canvas[y : y + ph, x : x + pw], known[y : y + ph, x : x + pw, None]
            cost = (((lib - win) ** 2) * m).sum(axis=(1, 2, 3))
            cost += lam * ((lib - tgt[y : y + ph, x : x + pw]) ** 2).sum(axis=(1, 2, 3))
            mirror = chosen_src[r, cols - 1 - c]
            if mirror >= 0:
                cost = np.where(sources == mirror, cost, np.inf)
            out.append((cost, ids[r, c]))
            chosen_src[r, c] = sources[ids[r, c]]
            o = observed[y : y + ph, x : x + pw, None]
            canvas[y : y + ph, x : x + pw] = np.where(o, win, lib[ids[r, c]])
            known[y : y + ph, x : x + pw] = True
    return out


def test_choices_match_a_numpy_reference_of_the_cost(lfw, library, pca_target):
    """Every chosen patch is among the N cheapest under an independent float64 cost, for whole
    faces (library quadratic terms) and for an inpainted region (arbitrary known pixels)."""
    n_best = 11  # the default for 2,700 patches: the compiled scans are shared with other tests
    mask = np.zeros((25, 25), bool)
    mask[6:15, 4:20] = True
    runs = [
        (faces.quilt(jax.random.key(12), library, pca_target), {}),
        (
            faces.inpaint(jax.random.key(13), library, lfw[50], mask, pca_target),
            {"image": lfw[50], "region": mask},
        ),
    ]
    for result, extra in runs:
        steps = replay_costs(library, result, pca_target, **extra)
        assert len(steps) == int((np.asarray(result.ids) >= 0).sum()) > 4
        for cost, chosen in steps:
            kth = np.partition(cost, n_best - 1)[n_best - 1]
            assert cost[chosen] <= kth + 1e-4 * max(1.0, abs(kth))


def test_same_key_same_face_and_vmap(library, pca_target):
    keys = jax.random.split(jax.random.key(2), 3)
    batch = jax.vmap(lambda k: faces.quilt(k, library, pca_target))(keys)
    one = faces.quilt(keys[1], library, pca_target)
    np.testing.assert_allclose(batch.image[1], one.image, atol=1e-5)
    np.testing.assert_array_equal(batch.ids[1], one.ids)
    again = faces.quilt(keys[1], library, pca_target)
    np.testing.assert_array_equal(again.image, one.image)
    assert not np.array_equal(batch.ids[0], batch.ids[2])


def test_novel_but_close_to_target(lfw, library, pca_target):
    """§5: new faces, not copies. The RMS distance of a result to its nearest training face is
    inherited from the global target (the target carries identity, the patches detail): on
    these 25×25 faces a low-rank sample lies at ~0.6–1.1 of the median training
    nearest-neighbour distance, and so do the results. Asserted: every result is farther from
    every training face than the closest training pair, keeps at least 90% of its target's
    distance to the training set (the patches do not collapse onto one training face), and is
    much closer to its target than to any training face."""
    nn = np.asarray(faces.training_nn_distances(lfw))
    _, target_nn = faces.nearest_training(pca_target, lfw)
    keys = jax.random.split(jax.random.key(3), 3)
    out = jax.vmap(lambda k: faces.quilt(k, library, pca_target))(keys)
    for image in out.image:
        _, dist = faces.nearest_training(image, lfw)
        assert float(dist) > nn.min()
        assert float(dist) > 0.9 * float(target_nn)
        assert float(faces.target_distance(image, pca_target)) < 0.8 * float(dist)
    # the local-only model (λ = 0) ignores the target
    local = jax.vmap(lambda k: faces.quilt(k, library, pca_target, lam=0.0))(keys)
    far = jax.vmap(faces.target_distance, in_axes=(0, None))
    assert far(local.image, pca_target).mean() > far(out.image, pca_target).mean()


def test_allowed_sources(library, pca_target):
    allowed = np.zeros(100, bool)
    allowed[::3] = True
    out = faces.quilt(jax.random.key(4), library, pca_target, allowed=allowed)
    assert allowed[np.asarray(out.sources)].all()


def test_quilt_bad_input(library, lfw, pca_target, unchecked):
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="target must have the library's image shape"):
        faces.quilt(key, library, lfw[0, :24])
    with pytest.raises(ValueError, match="n_best=10000 is more than"):
        faces.quilt(key, library, pca_target, n_best=10000)
    with pytest.raises(TypeError, match="key must be a JAX random key"):
        faces.quilt(0, library, pca_target)
    with pytest.raises(ValueError, match="lam must be in"):
        faces.quilt(key, library, pca_target, lam=-1.0)
    with pytest.raises(ValueError, match="allowed must allow"):
        faces.quilt(key, library, pca_target, allowed=np.zeros(100, bool))
    with pytest.raises(ValueError, match="one entry per training image"):
        faces.quilt(key, library, pca_target, allowed=np.ones(7, bool))


# --- editing --------------------------------------------------------------------------------


def test_inpaint_keeps_observed_and_follows_target(lfw, library):
    face = lfw[100 - 1]
    others = lfw[:-1]
    mask = np.zeros((25, 25), bool)
    mask[:9, :] = True  # the top of the head, touching the image edge (Fig. 10B)
    mean = others.mean(0)
    out = faces.inpaint(jax.random.key(5), library, face, mask, face, lam=2.0)
    img = np.asarray(out.image)
    np.testing.assert_array_equal(img[~mask], face[~mask])
    assert np.isfinite(img).all()
    ids = np.asarray(out.ids)
    assert (ids[:2] >= 0).all() and (ids[3:] == -1).all()
    err = np.sqrt(np.mean((img[mask] - face[mask]) ** 2))
    assert err < np.sqrt(np.mean((mean[mask] - face[mask]) ** 2))
    # several hypotheses from several keys
    other = faces.inpaint(jax.random.key(6), library, face, mask, face, lam=2.0)
    assert not np.array_equal(np.asarray(other.image), img)


def test_guided_edit_changes_only_the_painted_region(lfw, library, unchecked):
    face = lfw[10]
    painted = face.copy()
    painted[16:18, 8:17] = 0.05  # a painted mustache
    out = faces.guided_edit(jax.random.key(7), library, face, painted)
    img = np.asarray(out.image)
    region = np.zeros((25, 25), bool)
    region[15:19, 7:18] = True
    np.testing.assert_array_equal(img[~region], face[~region])
    assert img[16:18, 8:17].mean() < face[16:18, 8:17].mean()
    with pytest.raises(ValueError, match="nothing to edit"):
        faces.guided_edit(jax.random.key(7), library, face, face)
    with pytest.raises(ValueError, match="mask must have shape"):
        faces.inpaint(jax.random.key(7), library, face, np.ones((5, 5), bool), face)
    with pytest.raises(ValueError, match="mask is empty"):
        faces.inpaint(jax.random.key(7), library, face, np.zeros((25, 25), bool), face)
    with pytest.raises(ValueError, match="selects every pixel"):
        faces.inpaint(jax.random.key(7), library, face, np.ones((25, 25), bool), face)


def test_ict_render_pairs_for_restyling():
    """The example's Fig. 12 pairs: the same identities, poses and noise, neutral and smiling;
    the smile changes the lower face, not the forehead."""
    from jface.cli._faces import face_renders

    neutral, smiling = face_renders(3, 2, 32), face_renders(3, 2, 32, smile=1.0)
    np.testing.assert_array_equal(neutral, face_renders(3, 2, 32))
    change = np.abs(smiling - neutral).mean(axis=(0, 2))
    assert change[16:23].mean() > 0.05
    assert change[16:23].mean() > 10 * change[:6].mean()


# --- command line ---------------------------------------------------------------------------


def test_cli_sample_inpaint_edit(lfw, tmp_path, capsys):
    from jface import io
    from jface.cli import main

    folder = tmp_path / "faces"
    for i in range(40):
        io.write_png(folder / f"{i:03d}.png", lfw[i])
    common = ["--grid", "5", "--translations", "0", "--angles", "--seed", "1"]
    out = tmp_path / "sample"
    assert main(["faces", "synth", str(folder), "--n", "2", "--out", str(out), *common]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["nn_distance"]) == 2 and all(d > 0 for d in summary["nn_distance"])
    assert io.read_image(out / "face_001.png").shape == (25, 25)
    assert (out / "sources.png").is_file() and (out / "faces.png").is_file()

    mask = np.zeros((25, 25), np.float32)
    mask[:8] = 1.0
    io.write_png(tmp_path / "mask.png", mask)
    face = folder / "039.png"
    args = ["--image", str(face), "--mask", str(tmp_path / "mask.png"), "--n", "2", *common]
    out = tmp_path / "inpaint"
    assert main(["faces", "inpaint", str(folder), "--out", str(out), *args]) == 0
    inpainted = io.read_image(out / "inpainted_001.png")
    np.testing.assert_array_equal(inpainted[8:], io.read_image(face)[8:])

    painted = io.read_image(face)
    painted[16:18, 8:17] = 0.0
    io.write_png(tmp_path / "painted.png", painted)
    out = tmp_path / "edit"
    edit = ["--image", str(face), "--painted", str(tmp_path / "painted.png"), *common]
    assert main(["faces", "edit", str(folder), "--out", str(out), *edit]) == 0
    assert io.read_image(out / "edited.png").shape == (25, 25)

    io.write_png(tmp_path / "small.png", lfw[0, :20])
    capsys.readouterr()
    bad = ["--image", str(tmp_path / "small.png"), "--mask", str(tmp_path / "mask.png")]
    assert main(["faces", "inpaint", str(folder), "--out", str(out), *bad, *common]) == 2
    assert "--image must have the training faces' shape" in capsys.readouterr().err


# --- with the global factor models ------------------------------------------------------------


@pytest.fixture(scope="module")
def factor_models(lfw):
    fa = faces.fit_factor_analyser(lfw, 8, n_iter=20).model
    mofa = faces.fit_mixture(jax.random.key(0), lfw, 2, 4, n_iter=10).model
    return fa, mofa


def test_synthesis_from_factor_models(lfw, library, factor_models):
    fa, mofa = factor_models
    out, target, comp = faces.synthesize(jax.random.key(8), library, fa)
    assert int(comp) == 0 and target.shape == (25, 25)
    assert float(faces.target_distance(out.image, target)) < 0.2
    assignment = faces.assign_components(mofa, lfw)
    out, target, comp = faces.synthesize(jax.random.key(9), library, mofa, assignment=assignment)
    src = np.asarray(out.sources)
    assert (np.asarray(assignment)[src] == int(comp)).all()  # only the component's images
    results, targets = faces.inpaint_hypotheses(
        jax.random.key(10), library, fa, lfw[5], np.arange(25)[:, None] < np.full((25, 25), 8), 2
    )
    assert results.image.shape == (2, 25, 25) and targets.shape == (2, 25, 25)
    np.testing.assert_array_equal(
        np.asarray(results.image)[:, 8:], np.broadcast_to(lfw[5, 8:], (2, 17, 25))
    )


def test_restyle_with_bilinear_model(lfw, factor_models):
    # two "styles" of every individual: as photographed, and darker with more contrast
    styled = np.clip(1.3 * lfw - 0.25, 0, 1).astype(np.float32)
    model = faces.fit_bilinear(np.stack([lfw, styled], axis=1), 8, n_iter=20).model
    library = faces.build_library(styled, GRID, translations=0, angles=())
    out, prediction = faces.restyle(jax.random.key(11), library, model, lfw[7], n_best=2)
    assert prediction.shape == (25, 25)
    # the result is in the target style: nearer the styled face than the original face
    to_styled = float(faces.target_distance(out.image, styled[7]))
    assert to_styled < float(faces.target_distance(out.image, lfw[7]))
    mouth = np.zeros((25, 25), bool)
    mouth[15:21, 6:19] = True
    part, _ = faces.restyle(jax.random.key(11), library, model, lfw[7], mouth, n_best=2)
    np.testing.assert_array_equal(np.asarray(part.image)[~mouth], lfw[7][~mouth])


def test_cli_with_a_model_file(lfw, factor_models, tmp_path):
    from jface import io
    from jface.cli import main

    folder = tmp_path / "faces"
    for i in range(40):
        io.write_png(folder / f"{i:03d}.png", lfw[i])
    model = tmp_path / "fa.npz"
    faces.save_model(model, factor_models[0])
    out = tmp_path / "sample"
    common = ["--grid", "5", "--translations", "0", "--angles", "--seed", "2"]
    assert (
        main(
            [
                "faces",
                "synth",
                str(folder),
                "--model",
                str(model),
                "--n",
                "1",
                "--out",
                str(out),
                *common,
            ]
        )
        == 0
    )
    assert io.read_image(out / "face_000.png").shape == (25, 25)
