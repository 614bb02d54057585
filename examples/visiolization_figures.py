"""Mohammed, Prince & Kautz 2009 (*Visio-lization*): Fig. 3–5, 8, 10 and 11 on real faces.

Faces: the 100 aligned faces of scikit-image's LFW subset, upsampled to 50 × 50 (the paper's
XM2VTS faces are not public). The global model is a principal-component sample here (8
components, Gaussian loadings, no noise); pass ``--model`` with a factor analyser or mixture
file (``jface.faces.save_model``) to use the paper's global models instead. Writes:

* ``fig5.png`` rows: global targets (Fig. 4), local model only (λ = 0, Fig. 3C), quilted
  patches (Fig. 5B), Poisson-blended faces (Fig. 5C);
* ``fig8.png`` rows: faces, source maps (Fig. 8D–F), the nearest training face (Fig. 8G–I);
* ``fig10.png``: original, top removed, global target, three inpainting hypotheses;
* ``fig11.png``: a face, a painted mustache, the synthesised mustache;
* numbers (novelty, distance to target, distinct sources) as JSON on stdout.

Run: ``python examples/visiolization_figures.py --out visiolization`` (needs scikit-image).
"""

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from skimage import data, transform

from jface import faces, io
from jface.cli._quilt import colour_sources, montage, pca_fill, pca_targets


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="visiolization")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", type=int, default=50)
    parser.add_argument("--model", help="factor analyser / mixture file for the global targets")
    args = parser.parse_args()
    out = Path(args.out)
    images = np.stack(
        [transform.resize(f, (args.size, args.size), order=1) for f in data.lfw_subset()[:100]]
    ).astype(np.float32)
    library = faces.build_library(images, 9)
    key_t, key_q, key_i, key_e = jax.random.split(jax.random.key(args.seed), 4)
    n = 8
    keys = jax.random.split(key_q, n)
    if args.model:
        model, _ = faces.load_model(args.model)
        assignment = faces.assign_components(model, images) if hasattr(model, "weights") else None
        made = [faces.synthesize(k, library, model, assignment=assignment) for k in keys]
        targets = np.stack([np.asarray(m[1]) for m in made])
    else:
        targets = pca_targets(key_t, images, 8, n)
    targets_j = jnp.asarray(targets)
    combined = jax.vmap(lambda k, t: faces.quilt(k, library, t))(keys, targets_j)
    local = jax.vmap(lambda k, t: faces.quilt(k, library, t, lam=0.0))(keys, targets_j)
    rows = [targets, np.asarray(local.image), np.asarray(combined.quilted), combined.image]
    io.write_png(out / "fig5.png", montage(np.concatenate([np.asarray(r) for r in rows]), n))

    nearest = [faces.nearest_training(im, images) for im in combined.image]
    smaps = colour_sources(np.asarray(faces.source_map(combined, library)))
    closest = images[[int(i) for i, _ in nearest]]
    grey3 = np.repeat(np.asarray(combined.image)[..., None], 3, -1)
    fig8 = np.concatenate([grey3, smaps, np.repeat(closest[..., None], 3, -1)])
    io.write_png(out / "fig8.png", montage(fig8, n))

    face = images[17]
    mask = np.zeros(face.shape, bool)
    mask[: args.size * 2 // 5] = True  # the top of the head (Fig. 10B)
    target = pca_fill(face, mask, images, 8)
    hyp = jax.vmap(lambda k: faces.inpaint(k, library, face, mask, target))(
        jax.random.split(key_i, 3)
    )
    holed = np.where(mask, 1.0, face)
    io.write_png(
        out / "fig10.png",
        montage(np.concatenate([np.stack([face, holed, target]), np.asarray(hyp.image)]), 6),
    )

    painted = face.copy()
    s = args.size
    painted[int(0.68 * s) : int(0.72 * s), int(0.33 * s) : int(0.67 * s)] = 0.08  # a mustache
    edited = faces.guided_edit(key_e, library, face, painted)
    io.write_png(out / "fig11.png", montage(np.stack([face, painted, edited.image]), 3))

    nn = np.asarray(faces.training_nn_distances(images))
    print(
        json.dumps(
            {
                "out": str(out),
                "training_nn_distance_median": round(float(np.median(nn)), 4),
                "training_nn_distance_min": round(float(nn.min()), 4),
                "face_nn_distance": [round(float(d), 4) for _, d in nearest],
                "face_target_distance": [
                    round(float(faces.target_distance(im, t)), 4)
                    for im, t in zip(combined.image, targets, strict=True)
                ],
                "local_only_target_distance": [
                    round(float(faces.target_distance(im, t)), 4)
                    for im, t in zip(local.image, targets, strict=True)
                ],
                "distinct_sources": [
                    int(np.unique(s[s >= 0]).size) for s in np.asarray(combined.sources)
                ],
            }
        )
    )


if __name__ == "__main__":
    main()
