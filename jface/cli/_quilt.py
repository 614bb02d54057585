"""``jface faces synth|inpaint|edit|restyle``: face synthesis and editing by non-stationary
quilting (the actions are attached to ``jface faces`` by :mod:`jface.cli._faces`).

The training set is a folder (or list) of aligned face images of one size. The global target
is a sample of a trained factor analyser or mixture (``--model``, a file of
``jface.faces.save_model``), or, without one, of a principal-component model of the training
faces (``--global pca``, Gaussian loadings scaled by the singular values, no noise) or their
mean (``--global mean``). ``restyle`` needs a bilinear model.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from jface import faces, io, plots
from jface.faces import _editing, _patches, _quilting

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


def _library_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("images", nargs="+", help="aligned training faces: image files or folders")
    p.add_argument("--grey", action="store_true", help="read the faces as greyscale")
    p.add_argument(
        "--grid",
        type=int,
        default=None,
        help=f"patches per side (default: {_patches.GRID}, or the finest grid below it that "
        "fits the faces' size)",
    )
    p.add_argument(
        "--upscale",
        type=int,
        default=None,
        help="draw the faces of the figures N times larger (default: 1; the face PNGs keep "
        "their size)",
    )
    p.add_argument("--patch", type=int, default=None, help="patch size (default: quarter overlap)")
    p.add_argument("--translations", type=int, default=1, help="largest patch shift, pixels")
    p.add_argument(
        "--angles", type=float, nargs="*", default=[-3.0, 3.0], help="patch rotations, degrees"
    )
    p.add_argument("--lam", type=float, default=_quilting.LAM, help="weight λ of the global target")
    p.add_argument(
        "--n-best",
        type=int,
        default=None,
        help="choose among the N best patches (default: the best one)",
    )
    p.add_argument("--no-symmetry", action="store_true", help="no left/right source constraint")
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="random seed (default %(default)s)",
    )
    p.add_argument("--out", required=True, help="output folder")


def add_actions(actions: argparse._SubParsersAction, sample_name: str = "sample") -> None:
    """Add the quilting actions (sample, inpaint, edit, restyle) to a group of sub-commands, so
    another command (e.g. ``jface faces``) can carry them; ``sample_name`` renames ``sample``."""
    sample = actions.add_parser(
        sample_name, help="synthesise new faces from aligned training faces"
    )
    _library_args(sample)
    sample.add_argument("--n", type=int, default=16, help="number of faces (default 16)")
    sample.add_argument(
        "--global",
        dest="global_model",
        choices=("pca", "mean"),
        default="pca",
        help="global targets: PCA samples or the mean face",
    )
    sample.add_argument(
        "--model", help="global model file (factor analyser or mixture, .npz); overrides --global"
    )
    sample.add_argument("--components", type=int, default=8, help="PCA components (default 8)")
    sample.add_argument("--no-blend", action="store_true", help="skip the Poisson blending")
    sample.set_defaults(
        run=_sample,
        prose="wrote {faces} faces to {out}/ (median distance to the nearest training face "
        "{nn_median:.3f}; training faces to each other {median_nn_distance_training:.3f})",
    )

    inpaint = actions.add_parser("inpaint", help="replace a masked region of a face (§6.1)")
    _library_args(inpaint)
    inpaint.add_argument("--image", required=True, help="the face to edit (aligned, same size)")
    inpaint.add_argument("--mask", required=True, help="mask image: white where to replace")
    inpaint.add_argument("--n", type=int, default=4, help="number of hypotheses (default 4)")
    inpaint.add_argument("--components", type=int, default=8, help="PCA components (default 8)")
    inpaint.add_argument("--model", help="global model file (.npz): posterior targets")
    inpaint.set_defaults(run=_inpaint, prose="wrote {hypotheses} hypotheses to {out}/")

    edit = actions.add_parser("edit", help="turn a painted edit into realistic texture (§6.2)")
    _library_args(edit)
    edit.add_argument("--image", required=True, help="the face before the edit")
    edit.add_argument("--painted", required=True, help="the same face with painted strokes")
    edit.set_defaults(run=_edit, lam=_editing.GUIDE_LAM, prose="wrote {out}/edited.png")

    restyle = actions.add_parser(
        "restyle", help="change a face's style (expression) with a bilinear model (§6.3)"
    )
    _library_args(restyle)
    restyle.add_argument("--model", required=True, help="bilinear model file (.npz)")
    restyle.add_argument("--image", required=True, help="the face in the source style")
    restyle.add_argument("--mask", help="mask image: white where to restyle (default: all)")
    restyle.add_argument("--source", type=int, default=0, help="style of the face (default 0)")
    restyle.add_argument("--target", type=int, default=1, help="style wanted (default 1)")
    restyle.set_defaults(run=_restyle, prose="wrote {out}/restyled.png")


# --- helpers ------------------------------------------------------------------------------------


def _image_files(names: list[str]) -> list[Path]:
    files: list[Path] = []
    for name in names:
        path = Path(name)
        if path.is_dir():
            files += sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        elif path.is_file():
            files.append(path)
        else:
            raise FileNotFoundError(f"no such image file or folder: {path}")
    if len(files) < 2:
        raise ValueError(f"need at least two training faces, found {len(files)}")
    return files


def read_faces(names: list[str], grey: bool) -> tuple[np.ndarray, list[Path]]:
    """Aligned training faces (image files, or folders of them) as one float32 stack.

    Raises:
        ValueError: fewer than two faces, faces of different sizes, or a constant image (no face
            in it); the message names the file.
    """
    files = _image_files(names)
    images = []
    for file in tqdm(files, desc="read", unit="face", disable=len(files) < 200):
        image = io.read_image(file, grey=grey)
        if images and image.shape != images[0].shape:
            raise ValueError(
                f"training faces must all have one size (aligned): {files[0]} is "
                f"{images[0].shape}, {file} is {image.shape}"
            )
        if np.ptp(image) == 0:
            raise ValueError(
                f"{file} is a constant image (every pixel {float(image.flat[0]):.3g}): "
                "no face to learn from"
            )
        images.append(image)
    return np.stack(images).astype(np.float32), files


def panel_inches(upscale: int | None) -> float:
    """Side of one face panel in a figure, in inches: ``upscale`` times the default."""
    return plots.PANEL_INCHES * (upscale or 1)


def _grid(args: argparse.Namespace, shape: tuple[int, int]) -> int:
    """``--grid``, or the finest grid up to the default that fits faces of ``shape``."""
    if args.grid is not None:
        return args.grid
    for grid in range(_patches.GRID, 1, -1):
        try:
            _patches.make_geometry(shape, grid, args.patch)
        except ValueError:
            continue
        if grid != _patches.GRID:
            print(f"--grid {grid}: the finest grid that fits {shape[1]}×{shape[0]} px faces")
        return grid
    raise ValueError(f"no patch grid fits {shape[1]}×{shape[0]} px faces; give --grid and --patch")


def _library(args: argparse.Namespace, images: np.ndarray) -> faces.PatchLibrary:
    if args.upscale is not None and args.upscale < 1:  # refused before the work, not after
        raise ValueError(f"--upscale must be at least 1, got {args.upscale}")
    library = faces.build_library(
        images,
        _grid(args, images.shape[1:3]),
        patch=args.patch,
        translations=args.translations,
        angles=args.angles,
    )
    print(_patches.describe_library(library))
    return library


def pca_targets(key: jax.Array, images: np.ndarray, n_components: int, n: int) -> np.ndarray:
    """``n`` global targets: mean + Σ_k z_k s_k v_k / sqrt(N), z ~ N(0, 1), clipped to [0, 1]."""
    flat = images.reshape(len(images), -1).astype(np.float64)
    mean = flat.mean(0)
    _, s, vt = np.linalg.svd(flat - mean, full_matrices=False)
    k = max(1, min(n_components, len(s)))
    z = np.asarray(jax.random.normal(key, (n, k), dtype=jnp.float32), np.float64)
    out = mean + (z * s[:k] / np.sqrt(len(flat))) @ vt[:k]
    return np.clip(out, 0, 1).reshape(n, *images.shape[1:]).astype(np.float32)


def pca_fill(image: np.ndarray, mask: np.ndarray, images: np.ndarray, n_components: int):
    """Least-squares PCA loadings from the observed pixels → the image completed by the model."""
    flat = images.reshape(len(images), -1).astype(np.float64)
    mean = flat.mean(0)
    _, s, vt = np.linalg.svd(flat - mean, full_matrices=False)
    k = max(1, min(n_components, len(s)))
    basis = vt[:k].T * s[:k] / np.sqrt(len(flat))  # (d, k)
    seen = ~np.broadcast_to(mask[..., None] if image.ndim == 3 else mask, image.shape).ravel()
    a = basis[seen]
    h = np.linalg.solve(a.T @ a + np.eye(k), a.T @ (image.ravel()[seen] - mean[seen]))
    return np.clip(mean + basis @ h, 0, 1).reshape(image.shape).astype(np.float32)


def colour_sources(sources: np.ndarray) -> np.ndarray:
    """A per-pixel source map coloured by a fixed hash of the training image id (Fig. 8)."""
    ids = np.asarray(sources, np.int64)
    hashed = (ids[..., None] * np.array([0.618034, 0.414214, 0.732051]) + 0.1) % 1.0
    return np.where(ids[..., None] >= 0, 0.15 + 0.85 * hashed, 1.0).astype(np.float32)


def _settings(args: argparse.Namespace) -> dict:
    return {
        "lam": args.lam,
        "n_best": args.n_best,
        "symmetric": not args.no_symmetry,
    }


# --- commands -------------------------------------------------------------------------------------


def _check_outputs(out: Path, names) -> None:
    """Refuse, before any work, outputs that would replace an input (a training face, say)."""
    for name in names:
        io.check_output(out / name, (".png", ".json"))


def _sample(args: argparse.Namespace) -> dict:
    return sample_faces(args)[1]


def sample_faces(args: argparse.Namespace) -> tuple[np.ndarray, dict]:
    """Synthesise ``--n`` faces, write them, and return them ``(n, H, W[, C])`` with the
    summary."""
    if args.n < 1:
        raise ValueError(f"--n must be at least 1, got {args.n}")
    faces_out = [f"face_{i:03d}.png" for i in range(args.n)]
    extra = ("faces.png", "targets.png", "quilted.png", "sources.png", "summary.json")
    _check_outputs(Path(args.out), [*faces_out, *extra])
    images, files = read_faces(args.images, args.grey)
    library = _library(args, images)
    key_target, key_quilt = jax.random.split(jax.random.key(args.seed))
    if args.model:
        return _sample_from_model(args, images, library, files)
    if args.global_model == "pca":
        targets = pca_targets(key_target, images, args.components, args.n)
    else:
        targets = np.broadcast_to(images.mean(0), (args.n, *images.shape[1:])).copy()
    keys = jax.random.split(key_quilt, args.n)
    settings = _settings(args)
    # one face at a time (one compilation, progress shown); jax.vmap batches in Python use
    made = [
        faces.quilt(k, library, t, blend=not args.no_blend, **settings)
        for k, t in tqdm(zip(keys, targets, strict=True), total=args.n, desc="quilt", unit="face")
    ]
    result = jax.tree.map(lambda *xs: jnp.stack(xs), *made)
    summary = _write_samples(args, images, library, files, result, targets, settings)
    return np.asarray(result.image), summary


def _load_model(path: str):
    if not hasattr(faces, "load_model"):
        raise ValueError("--model needs the factor models of jface.faces, not in this copy")
    return faces.load_model(path).model


def _sample_from_model(args, images, library, files) -> tuple[np.ndarray, dict]:
    model = _load_model(args.model)
    assignment = None
    if hasattr(model, "n_components"):
        assignment = faces.assign_components(model, images)
    settings = _settings(args)
    keys = jax.random.split(jax.random.key(args.seed), args.n)
    made = [
        faces.synthesize(
            k, library, model, assignment=assignment, blend=not args.no_blend, **settings
        )
        for k in tqdm(keys, desc="quilt", unit="face")
    ]
    result = jax.tree.map(lambda *xs: jnp.stack(xs), *[m[0] for m in made])
    targets = np.stack([np.asarray(m[1]) for m in made])
    summary = _write_samples(args, images, library, files, result, targets, settings)
    return np.asarray(result.image), summary


def _write_samples(args, images, library, files, result, targets, settings) -> dict:
    out = Path(args.out)
    meta = io.provenance(seed=args.seed, training=len(files), **settings)
    smaps = np.asarray(faces.source_map(result, library))
    for i in range(args.n):
        io.write_png(out / f"face_{i:03d}.png", np.asarray(result.image[i]), metadata=meta)
    for name, pictures, title in (
        ("faces.png", result.image, "Synthesised faces (quilted, Poisson-blended)"),
        ("targets.png", targets, "Global targets drawn from the factor analyser"),
        ("quilted.png", result.quilted, "Quilted faces before blending"),
        ("sources.png", colour_sources(smaps), "Source training image of each pixel (colour)"),
    ):
        figure = plots.image_grid(
            list(np.asarray(pictures)), title=title, panel_inches=panel_inches(args.upscale)
        )
        io.write_figure(out / name, figure, metadata=meta)
    nearest = [faces.nearest_training(result.image[i], images)[1] for i in range(args.n)]
    summary = {
        "out": str(out),
        "faces": args.n,
        "median_nn_distance_training": float(np.median(faces.training_nn_distances(images))),
        "nn_distance": [round(float(d), 4) for d in nearest],
        "nn_median": float(np.median(nearest)),
        "target_distance": [
            round(float(faces.target_distance(result.image[i], targets[i])), 4)
            for i in range(args.n)
        ],
        "distinct_sources": [int(np.unique(s[s >= 0]).size) for s in np.asarray(result.sources)],
    }
    io.write_json(out / "summary.json", summary)
    return summary


def _read_mask(path: str, shape: tuple[int, int]) -> np.ndarray:
    mask = io.read_image(path, grey=True) > 0.5
    if mask.shape != shape:
        raise ValueError(f"--mask must be {shape[0]}×{shape[1]} like the face, got {mask.shape}")
    return mask


def _one_face(path: str, images: np.ndarray, grey: bool, name: str) -> np.ndarray:
    face = io.read_image(path, grey=grey).astype(np.float32)
    if face.shape != images.shape[1:]:
        raise ValueError(
            f"{name} must have the training faces' shape {images.shape[1:]}, got {face.shape}"
        )
    return face


def _inpaint(args: argparse.Namespace) -> dict:
    if args.n < 1:
        raise ValueError(f"--n must be at least 1, got {args.n}")
    names = [f"inpainted_{i:03d}.png" for i in range(args.n)]
    _check_outputs(Path(args.out), [*names, "inpainting.png"])
    images, files = read_faces(args.images, args.grey)
    face = _one_face(args.image, images, args.grey, "--image")
    mask = _read_mask(args.mask, face.shape[:2])
    library = _library(args, images)
    settings = _settings(args)
    if args.model:
        result, targets = faces.inpaint_hypotheses(
            jax.random.key(args.seed),
            library,
            _load_model(args.model),
            face,
            mask,
            args.n,
            **settings,
        )
        target = np.asarray(targets[0])
    else:
        target = pca_fill(face, mask, images, args.components)
        keys = jax.random.split(jax.random.key(args.seed), args.n)
        made = [
            faces.inpaint(k, library, face, mask, target, **settings)
            for k in tqdm(keys, desc="inpaint", unit="hypothesis")
        ]
        result = jax.tree.map(lambda *xs: jnp.stack(xs), *made)
    out = Path(args.out)
    meta = io.provenance(seed=args.seed, image=Path(args.image).name, **settings)
    holed = np.where(mask if face.ndim == 2 else mask[..., None], 1.0, face)
    for i in range(args.n):
        io.write_png(out / f"inpainted_{i:03d}.png", np.asarray(result.image[i]), metadata=meta)
    figure = plots.panel_grid(
        [[face, holed, target, *np.asarray(result.image)]],
        title="Inpainting: the hole filled by quilting towards the global model's fill",
        col_labels=["input", "hole", "global fill"]
        + [f"hypothesis {i + 1}" for i in range(args.n)],
        quantities="image",
        panel_inches=panel_inches(args.upscale),
    )
    io.write_figure(out / "inpainting.png", figure, metadata=meta)
    return {"out": str(out), "hypotheses": args.n, "training": len(files)}


def _edit(args: argparse.Namespace) -> dict:
    _check_outputs(Path(args.out), ("edited.png", "edit.png"))
    images, _ = read_faces(args.images, args.grey)
    face = _one_face(args.image, images, args.grey, "--image")
    painted = _one_face(args.painted, images, args.grey, "--painted")
    library = _library(args, images)
    result = faces.guided_edit(
        jax.random.key(args.seed),
        library,
        face,
        painted,
        lam=args.lam,
        n_best=args.n_best,
        symmetric=not args.no_symmetry,
    )
    out = Path(args.out)
    meta = io.provenance(seed=args.seed, image=Path(args.image).name, lam=args.lam)
    io.write_png(out / "edited.png", np.asarray(result.image), metadata=meta)
    figure = plots.panel_grid(
        [[face, painted, np.asarray(result.image)]],
        title="Guided edit: a painted face made realistic by quilting",
        col_labels=["input", "painted", "edited"],
        quantities="image",
        panel_inches=panel_inches(args.upscale),
    )
    io.write_figure(out / "edit.png", figure, metadata=meta)
    return {"out": str(out)}


def _restyle(args: argparse.Namespace) -> dict:
    _check_outputs(Path(args.out), ("restyled.png", "restyle.png"))
    images, _ = read_faces(args.images, args.grey)
    face = _one_face(args.image, images, args.grey, "--image")
    mask = _read_mask(args.mask, face.shape[:2]) if args.mask else None
    library = _library(args, images)
    result, prediction = faces.restyle(
        jax.random.key(args.seed),
        library,
        _load_model(args.model),
        face,
        mask,
        source=args.source,
        target=args.target,
        **_settings(args),
    )
    out = Path(args.out)
    meta = io.provenance(seed=args.seed, image=Path(args.image).name, model=Path(args.model).name)
    io.write_png(out / "restyled.png", np.asarray(result.image), metadata=meta)
    figure = plots.panel_grid(
        [[face, np.asarray(prediction), np.asarray(result.image)]],
        title=f"Style change: {args.source} → {args.target}",
        col_labels=["input", "predicted by the style model", "restyled"],
        quantities="image",
        panel_inches=panel_inches(args.upscale),
    )
    io.write_figure(out / "restyle.png", figure, metadata=meta)
    return {"out": str(out)}


def demo(out: Path, seed: int) -> None:
    """Mohammed et al. Fig. 5 on built-in data: 120 renders of random ICT-FaceKit identities, a
    factor analyser as the global model, then per face the global target, local-only quilting
    (λ = 0), quilting conditioned on the target, and the Poisson-blended result."""
    from jface.cli._faces import face_renders

    images = face_renders(seed, 120)
    model = faces.fit_factor_analyser(images, 8).model
    library = faces.build_library(images, 5)
    keys = jax.random.split(jax.random.key(seed), 8)
    result, targets, _ = jax.vmap(lambda k: faces.synthesize(k, library, model))(keys)
    local = jax.vmap(lambda k, t: faces.quilt(k, library, t, lam=0.0))(keys, targets)
    rows = [list(np.asarray(x)) for x in (targets, local.image, result.quilted, result.image)]
    out = Path(out) / "quilt"
    meta = io.provenance(seed=seed, source="jface/data/ict_face_small.npz renders")
    figure = plots.panel_grid(
        rows,
        title="Face synthesis by non-stationary quilting (Mohammed et al. 2009 Fig. 5)",
        row_labels=["global target", "local only (λ = 0)", "quilted", "blended"],
        quantities="image",
        panel_inches=1.0,
    )
    io.write_figure(out / "faces.png", figure, metadata=meta)
    print(f"quilt: global targets, local-only, quilted, blended faces in {out}/faces.png")
