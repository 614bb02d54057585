"""``jface faces``: train global face models on images and draw samples from them; align faces
to a template (and un-warp synthesised ones, ``synth --unwarp``)."""

from __future__ import annotations

import argparse
import time
from importlib import resources
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from jface import faces, plots, raster
from jface.cli import _quilt as quilting
from jface.cli import deprecated_alias, refuse_shared_names
from jface.io import (
    check_output,
    load_arrays,
    provenance,
    read_image,
    read_json,
    write_figure,
    write_json,
    write_png,
)


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "faces", help="global face models: factor analysers and their mixtures (Visio-lization)"
    )
    sub = parser.add_subparsers(dest="faces_command", required=True, metavar="ACTION")

    train = sub.add_parser(
        "train",
        help="fit a factor analyser (or a mixture, or the bilinear style model) to face images",
    )
    train.add_argument(
        "images",
        nargs="+",
        help="aligned face images of one size (PNG/JPEG) or folders of them; with --bilinear, "
        "one folder per style holding the same people under the same file names",
    )
    train.add_argument("--out", required=True, help="model file to write (.npz)")
    train.add_argument("--factors", type=int, default=8, help="number of factors (default 8)")
    train.add_argument(
        "--components", type=int, default=1, help="mixture components (default 1: one FA)"
    )
    train.add_argument(
        "--bilinear",
        action="store_true",
        help="fit the asymmetric bilinear style model (§6.3) that `jface faces restyle` uses",
    )
    train.add_argument("--iters", type=int, default=40, help="EM iterations (default 40)")
    train.add_argument("--seed", type=int, default=0, help="seed of the mixture initialisation")
    train.set_defaults(
        run=_train,
        prose="fitted {model} to {images} images of {width}×{height} in {seconds:.1f} s: "
        "log-likelihood {first_log_likelihood:.1f} → {log_likelihood:.1f} nats/image; "
        "wrote {out}",
    )

    sample = sub.add_parser("sample", help="draw images from a trained model")
    sample.add_argument("model", help="model file written by `jface faces train`")
    sample.add_argument("--n", type=int, default=16, help="number of images (default 16)")
    sample.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sample.add_argument("--noise", action="store_true", help="add the per-pixel noise term")
    sample.add_argument("--out", required=True, help="output folder (PNGs and grid.png)")
    sample.add_argument(
        "--upscale",
        type=int,
        default=None,
        help="draw the faces of grid.png N times larger (default: 1; the sample PNGs keep "
        "their size)",
    )
    sample.set_defaults(run=_sample, prose="wrote {n} samples and {grid}")

    align = sub.add_parser(
        "align", help="register face images to a template by an affine map (§2.2)"
    )
    align.add_argument("images", nargs="+", help="face images (PNG/JPEG) or folders of them")
    align.add_argument(
        "--template",
        help="template image: the frame to align to (default: the mean of the images, which "
        "must then share one size)",
    )
    align.add_argument(
        "--landmarks",
        help='JSON {"template": [[x, y], ...], "images": {"file name": [[x, y], ...]}}: align '
        "from these landmarks (closed form) instead of by intensity; use them for faces of "
        "different people (by intensity, a face is only reliably aligned to a close template)",
    )
    align.add_argument("--grey", action="store_true", help="read the faces as greyscale")
    align.add_argument("--levels", type=int, default=3, help="pyramid levels (default 3)")
    align.add_argument(
        "--iters", type=int, default=100, help="registration solver steps per level (default 100)"
    )
    deprecated_alias(align, "--max-steps", "--iters")
    align.add_argument(
        "--out", required=True, help="output folder: the aligned faces and transforms.json"
    )
    align.set_defaults(
        run=_align,
        prose="aligned {faces} faces to a {width}×{height} template by {method} (rms to the "
        "template: median {rms_median:.3f}, max {rms_max:.3f}); wrote {out}/",
    )

    quilting.add_actions(sub, sample_name="synth")
    synth = sub.choices["synth"]
    synth.add_argument(
        "--unwarp",
        metavar="TRANSFORMS",
        help="transforms.json of `jface faces align`: also write each face un-warped by the "
        "inverse of a randomly chosen training transformation (§4)",
    )
    synth.set_defaults(run=_synth)


def _fit(data: np.ndarray, factors: int, components: int, iters: int, seed: int):
    if components == 1:
        return faces.fit_factor_analyser(data, factors, n_iter=iters)
    return faces.fit_mixture(jax.random.key(seed), data, components, factors, n_iter=iters)


def _styles(folders: list[str]) -> np.ndarray:
    """``(n, S, H, W)`` faces of the style folders, paired by file name."""
    if len(folders) < 2 or not all(Path(f).is_dir() for f in folders):
        raise ValueError(
            f"--bilinear needs two or more style folders (one per style), got {folders}"
        )
    stacks = [quilting.read_faces([folder], grey=True) for folder in folders]
    names = [[f.name for f in files] for _, files in stacks]
    for folder, these in zip(folders[1:], names[1:], strict=True):
        if these != names[0]:
            odd = sorted(set(these) ^ set(names[0]))
            raise ValueError(
                f"style folders must hold the same file names (one face per person): "
                f"{folders[0]} and {folder} differ in {odd[:3]}"
            )
    return np.stack([images for images, _ in stacks], axis=1)


def _train(args: argparse.Namespace) -> dict:
    check_output(args.out, (".npz",))
    if args.bilinear and args.components != 1:
        raise ValueError("--bilinear fits one bilinear model: leave --components at 1")
    data = _styles(args.images) if args.bilinear else quilting.read_faces(args.images, grey=True)[0]
    start = time.perf_counter()
    if args.bilinear:
        result = faces.fit_bilinear(data, args.factors, n_iter=args.iters)
    else:
        result = _fit(data, args.factors, args.components, args.iters, args.seed)
    ll = np.asarray(result.log_likelihood)
    meta = provenance(
        seed=args.seed,
        n_images=int(data.shape[0]),
        bilinear=bool(args.bilinear),
        n_factors=args.factors,
        n_components=args.components,
        n_iter=int(result.n_iter),
        log_likelihood=float(ll[-1]),
    )
    faces.save_model(args.out, result.model, meta)
    return {
        "out": args.out,
        "model": type(result.model).__name__,
        "images": int(data.shape[0]),
        "height": int(data.shape[-2]),
        "width": int(data.shape[-1]),
        "seconds": time.perf_counter() - start,
        "first_log_likelihood": float(ll[0]),
        "log_likelihood": float(ll[-1]),
    }


def _write_samples(out: Path, images: np.ndarray, meta: dict, *, upscale: int | None) -> Path:
    images = np.clip(images, 0.0, 1.0)
    for i, img in enumerate(images):
        write_png(out / f"sample_{i:03d}.png", img, metadata=meta)
    figure = plots.image_grid(
        list(images),
        title=f"{len(images)} faces sampled from the factor analyser (seed {meta.get('seed')})",
        labels=[f"sample {i}" for i in range(len(images))],
        panel_inches=quilting.panel_inches(upscale),
    )
    return write_figure(out / "grid.png", figure, metadata=meta)


def _sample(args: argparse.Namespace) -> dict:
    if args.upscale is not None and args.upscale < 1:
        raise ValueError(f"--upscale must be at least 1, got {args.upscale}")
    model = faces.load_model(args.model).model
    if isinstance(model, faces.BilinearModel):
        model = faces.style(model, 0)
    if len(model.shape) != 2:
        raise ValueError(f"{args.model} describes vectors of shape {model.shape}, not images")
    images = np.asarray(faces.sample(jax.random.key(args.seed), model, args.n, noise=args.noise))
    meta = provenance(seed=args.seed, model=str(args.model), n=args.n, noise=bool(args.noise))
    path = _write_samples(Path(args.out), images, meta, upscale=args.upscale)
    return {"out": args.out, "n": args.n, "grid": str(path)}


# --- demo ------------------------------------------------------------------------------------


def face_renders(key_seed: int, n: int, size: int = 32, *, smile: float = 0.0) -> np.ndarray:
    """``n`` frontal renders of random identities of the built-in ICT-FaceKit face model;
    ``smile`` adds the model's smile expression with that weight (the same seed gives the same
    identities, poses and noise, so two calls make neutral/smiling pairs)."""
    source = resources.files("jface") / "data" / "ict_face_small.npz"
    with resources.as_file(source) as path:
        mesh, _ = load_arrays(path, kind="FaceMeshModel")
    verts = mesh["vertices"].astype(np.float64) + smile * mesh["smile_delta"].astype(np.float64)
    modes = mesh["identity_deltas"].astype(np.float64).reshape(len(mesh["identity_deltas"]), -1)
    rng = np.random.default_rng(key_seed)
    center, extent = np.array([0.0, -1.0, 5.0]), 16.0
    out = np.empty((n, size, size), np.float32)
    for i in range(n):
        person = verts + (rng.standard_normal(modes.shape[0]) @ modes).reshape(-1, 3)
        out[i] = raster.render(
            person, mesh["faces"], size, yaw=rng.uniform(-8, 8), center=center, extent=extent
        )
    return out + rng.normal(0.0, 0.01, out.shape).astype(np.float32)


def demo(out_dir: Path, seed: int) -> None:
    """Render 120 random faces, fit an 8-factor analyser, write 16 samples and a grid."""
    out = Path(out_dir) / "faces"
    data = face_renders(seed, 120)
    result = faces.fit_factor_analyser(data, 8)
    meta = provenance(seed=seed, step="faces demo", n_images=120, n_factors=8)
    faces.save_model(out / "face_model.npz", result.model, meta)
    figure = plots.image_grid(
        list(np.clip(data[:16], 0, 1)), title="Training faces: renders of random ICT identities"
    )
    write_figure(out / "training_grid.png", figure, metadata=meta)
    images = np.asarray(faces.sample(jax.random.key(seed), result.model, 16))
    grid_path = _write_samples(out / "samples", images, meta, upscale=None)
    ll = np.asarray(result.log_likelihood)
    print(
        f"faces: 8-factor analyser fitted to 120 renders (log-likelihood {ll[0]:.0f} → "
        f"{ll[-1]:.0f} nats/image); 16 samples in {grid_path}"
    )
    quilting.demo(out_dir, seed)


# --- alignment and un-warping -----------------------------------------------------------------


def _landmark_table(path: str, files: list[Path]) -> tuple[np.ndarray, list[np.ndarray]]:
    """The template's landmarks and each file's, from a JSON keyed by file name."""
    table = read_json(path)
    if (
        not isinstance(table, dict)
        or not {"template", "images"} <= table.keys()
        or not isinstance(table["images"], dict)
    ):
        raise ValueError(f'{path} must hold {{"template": [...], "images": {{...}}}}')
    missing = [f.name for f in files if f.name not in table["images"]]
    if missing:
        raise ValueError(f"{path} has no landmarks for {', '.join(missing[:5])}")
    try:
        template = np.asarray(table["template"], np.float64)
        return template, [np.asarray(table["images"][f.name], np.float64) for f in files]
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: landmarks must be lists of [x, y] numbers ({err})") from err


def _align(args: argparse.Namespace) -> dict:
    files = quilting._image_files(args.images)
    out = Path(args.out)
    names = [f"{f.stem}.png" for f in files]
    refuse_shared_names(files, names)
    for name in [*names, "transforms.json"]:
        check_output(out / name, (".png", ".json"))
    images = [read_image(f, grey=args.grey).astype(np.float32) for f in files]
    if args.template:
        template = read_image(args.template, grey=args.grey).astype(np.float32)
    elif len({im.shape for im in images}) == 1:
        template = np.mean(images, axis=0)
    else:
        raise ValueError("the images differ in size: give --template (the frame to align to)")
    marks = _landmark_table(args.landmarks, files) if args.landmarks else None
    records, aligned = [], []
    pairs = list(zip(files, images, strict=True))
    for i, (file, image) in enumerate(
        tqdm(pairs, desc="align", unit="face", disable=len(pairs) < 200)
    ):
        extra = {} if marks is None else {"landmarks": marks[1][i], "template_landmarks": marks[0]}
        try:
            result = faces.align(image, template, levels=args.levels, max_steps=args.iters, **extra)
        except ValueError as err:
            raise ValueError(f"{file}: {err}") from err
        aligned.append(np.clip(np.asarray(result.image), 0, 1))
        records.append(
            {
                "file": file.name,
                "shape": list(image.shape[:2]),
                "transform": np.asarray(result.transform, np.float64).round(6).tolist(),
                "rms": round(float(result.rms), 5),
                "coverage": round(float(result.coverage), 4),
            }
        )
    method = "landmarks" if marks else "intensity"
    meta = provenance(method=method, template=args.template or "mean of the images")
    for name, image in zip(names, aligned, strict=True):
        write_png(out / name, image, metadata=meta)
    document = {**meta, "template_shape": list(template.shape[:2]), "faces": records}
    write_json(out / "transforms.json", document)
    rms = [r["rms"] for r in records]
    return {
        "out": str(out),
        "faces": len(files),
        "width": int(template.shape[1]),
        "height": int(template.shape[0]),
        "method": method,
        "rms_median": float(np.median(rms)),
        "rms_max": float(max(rms)),
    }


def read_transforms(path: str) -> tuple[np.ndarray, list[tuple[int, int]], list[str], tuple]:
    """Training transforms written by ``jface faces align``: ``(n, 2, 3)``, each face's
    ``(h, w)``, its file name, and the template's ``(H, W)``."""
    document = read_json(path)
    try:
        records = document["faces"]
        transforms = np.asarray([r["transform"] for r in records], np.float64)
        shapes = [tuple(int(v) for v in r["shape"]) for r in records]
        names = [str(r["file"]) for r in records]
        template_shape = tuple(int(v) for v in document["template_shape"])
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(
            f"{path} is not a transforms file of `jface faces align` ({err!r})"
        ) from err
    if transforms.ndim != 3 or transforms.shape[1:] != (2, 3) or not len(records):
        raise ValueError(f"{path} must hold (2, 3) transforms, got shape {transforms.shape}")
    return transforms, shapes, names, template_shape


def _synth(args: argparse.Namespace) -> dict:
    if args.unwarp is None:
        return quilting.sample_faces(args)[1]
    transforms, shapes, names, template_shape = read_transforms(args.unwarp)
    out = Path(args.out)
    for i in range(max(args.n, 0)):
        check_output(out / f"unwarped_{i:03d}.png", (".png",))
    made, summary = quilting.sample_faces(args)
    if made.shape[1:3] != template_shape:
        raise ValueError(
            f"--unwarp: {args.unwarp} holds transforms of faces aligned to a "
            f"{template_shape[1]}×{template_shape[0]} template, the faces are "
            f"{made.shape[2]}×{made.shape[1]}"
        )
    # keys apart from the synthesis's (which splits the seed's key itself)
    keys = jax.random.split(jax.random.fold_in(jax.random.key(args.seed), 1), len(made))
    frames = []
    for i, (key, face) in enumerate(zip(keys, made, strict=True)):
        try:
            unwarped, index = faces.unwarp(key, face, transforms)
            index = int(index)
            if shapes[index] != face.shape[:2]:  # the same key chooses the same face again
                unwarped, _ = faces.unwarp(key, face, transforms, shape=shapes[index])
        except ValueError as err:
            raise ValueError(f"--unwarp {args.unwarp}: {err}") from err
        meta = provenance(seed=args.seed, face=i, frame_of=names[index])
        write_png(out / f"unwarped_{i:03d}.png", np.clip(np.asarray(unwarped), 0, 1), metadata=meta)
        frames.append(names[index])
    return {**summary, "unwarped": len(made), "frames_of": frames}
