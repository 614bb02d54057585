"""``jface faces``: train global face models on images and draw samples from them."""

from __future__ import annotations

import argparse
import math
import time
from importlib import resources
from pathlib import Path

import jax
import numpy as np

from jface import faces, raster
from jface.cli import _quilt as quilting
from jface.io import check_output, load_arrays, provenance, write_png


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "faces", help="global face models: factor analysers and their mixtures (Visio-lization)"
    )
    sub = parser.add_subparsers(dest="faces_command", required=True, metavar="ACTION")

    train = sub.add_parser("train", help="fit a factor analyser (or a mixture) to face images")
    train.add_argument("images", nargs="+", help="aligned face images of one size (PNG/JPEG)")
    train.add_argument("--out", required=True, help="model file to write (.npz)")
    train.add_argument("--factors", type=int, default=8, help="number of factors (default 8)")
    train.add_argument(
        "--components", type=int, default=1, help="mixture components (default 1: one FA)"
    )
    train.add_argument("--iters", type=int, default=40, help="EM iterations (default 40)")
    train.add_argument("--seed", type=int, default=0, help="seed of the mixture initialisation")
    train.set_defaults(run=_train)

    sample = sub.add_parser("sample", help="draw images from a trained model")
    sample.add_argument("model", help="model file written by `jface faces train`")
    sample.add_argument("--n", type=int, default=16, help="number of images (default 16)")
    sample.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sample.add_argument("--noise", action="store_true", help="add the per-pixel noise term")
    sample.add_argument("--out", required=True, help="output folder (PNGs and grid.png)")
    sample.set_defaults(run=_sample)
    quilting.add_actions(sub, sample_name="synth")


def _fit(data: np.ndarray, factors: int, components: int, iters: int, seed: int):
    if components == 1:
        return faces.fit_factor_analyser(data, factors, n_iter=iters)
    return faces.fit_mixture(jax.random.key(seed), data, components, factors, n_iter=iters)


def _train(args: argparse.Namespace) -> None:
    check_output(args.out, (".npz",))
    data, _ = quilting.read_faces(args.images, grey=True)
    start = time.perf_counter()
    result = _fit(data, args.factors, args.components, args.iters, args.seed)
    ll = np.asarray(result.log_likelihood)
    meta = provenance(
        seed=args.seed,
        n_images=len(args.images),
        n_factors=args.factors,
        n_components=args.components,
        n_iter=int(result.n_iter),
        log_likelihood=float(ll[-1]),
    )
    faces.save_model(args.out, result.model, meta)
    print(
        f"fitted {type(result.model).__name__} to {data.shape[0]} images of "
        f"{data.shape[1]}×{data.shape[2]} in {time.perf_counter() - start:.1f} s: "
        f"log-likelihood {ll[0]:.1f} → {ll[-1]:.1f} nats/image; wrote {args.out}"
    )


def grid(images: np.ndarray, pad: int = 1) -> np.ndarray:
    """Tile ``(n, H, W)`` images into a near-square grid with ``pad`` pixels of white between."""
    n, h, w = images.shape
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    out = np.ones((rows * (h + pad) + pad, cols * (w + pad) + pad), np.float32)
    for i, img in enumerate(images):
        r, c = divmod(i, cols)
        out[
            pad + r * (h + pad) : (r + 1) * (h + pad), pad + c * (w + pad) : (c + 1) * (w + pad)
        ] = img
    return out


def _write_samples(out: Path, images: np.ndarray, meta: dict, *, scale: int = 1) -> Path:
    images = np.clip(images, 0.0, 1.0)
    for i, img in enumerate(images):
        write_png(out / f"sample_{i:03d}.png", img, metadata=meta)
    big = np.kron(grid(images), np.ones((scale, scale), np.float32))
    return write_png(out / "grid.png", big, metadata=meta)


def _sample(args: argparse.Namespace) -> None:
    model, _ = faces.load_model(args.model)
    if isinstance(model, faces.BilinearModel):
        model = faces.style(model, 0)
    if len(model.shape) != 2:
        raise ValueError(f"{args.model} describes vectors of shape {model.shape}, not images")
    images = np.asarray(faces.sample(jax.random.key(args.seed), model, args.n, noise=args.noise))
    meta = provenance(seed=args.seed, model=str(args.model), n=args.n, noise=bool(args.noise))
    path = _write_samples(Path(args.out), images, meta)
    print(f"wrote {args.n} samples and {path}")


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
    write_png(out / "training_grid.png", np.kron(grid(np.clip(data[:16], 0, 1)), np.ones((4, 4))))
    images = np.asarray(faces.sample(jax.random.key(seed), result.model, 16))
    grid_path = _write_samples(out / "samples", images, meta, scale=4)
    ll = np.asarray(result.log_likelihood)
    print(
        f"faces: 8-factor analyser fitted to 120 renders (log-likelihood {ll[0]:.0f} → "
        f"{ll[-1]:.0f} nats/image); 16 samples in {grid_path}"
    )
    quilting.demo(out_dir, seed)
