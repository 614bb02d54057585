"""Mohammed, Prince & Kautz 2009 (*Visio-lization*): Fig. 3–5, 8, 10, 11 and 12 on real faces.

Two datasets (the paper's XM2VTS faces are not public):

* ``lfw``: the 100 aligned faces of scikit-image's LFW subset, upsampled to 50 × 50 (symmetry
  off: these crops are not frontal);
* ``ict``: 50 × 50 renders of random identities of the built-in ICT-FaceKit face model
  (``jface.cli._faces.face_renders``, the demo's renders), neutral and smiling.

For each, an 8-factor analyser fitted to the training faces is the global model (the last ten
faces are held out for the edits), and the patch library is the paper's 9 × 9 grid. Writes, per
dataset, into ``OUT/<dataset>/``:

* ``fig5.png`` rows: global samples (blurry, Fig. 4), local model only (λ = 0, "Frankenstein",
  Fig. 3C), quilted patches (Fig. 5B), Poisson-blended faces (Fig. 5C);
* ``fig8.png`` rows: faces, source maps (one colour per training image, Fig. 8D–F), the nearest
  training face (Fig. 8G–I);
* ``fig10.png``: a held-out face, its top removed, the factor posterior's target, three
  inpainting hypotheses from posterior samples (Fig. 10);
* ``fig11.png``: a face, a painted mustache, the synthesised mustache (Fig. 11);
* ``fig12.png`` (ICT only: LFW has no expression pairs): held-out neutral faces, the bilinear
  model's smiling prediction, the restyled face quilted from smiling patches, the true smiling
  render (Fig. 12);
* numbers (novelty, distance to target, distinct sources) as one JSON line per dataset.

Run: ``python examples/visiolization_figures.py --out visiolization`` (needs scikit-image).
"""

import argparse
import json
from pathlib import Path

import jax
import numpy as np
from skimage import data, transform

from jface import faces, io, plots
from jface.cli._faces import face_renders
from jface.cli._quilt import colour_sources

HELD_OUT = 10


def lfw_faces(size: int) -> np.ndarray:
    return np.stack(
        [transform.resize(f, (size, size), order=1) for f in data.lfw_subset()[:100]]
    ).astype(np.float32)


def figures(
    name: str, images: np.ndarray, out: Path, key, smiling=None, symmetric=True, n: int = 8
) -> dict:
    """Write the figures for one dataset; ``smiling`` (the same identities smiling) adds
    Fig. 12; ``symmetric``: the paper's same-individual symmetry. Returns the numbers."""
    out = out / name
    size = images.shape[1]
    train, held = images[:-HELD_OUT], images[-HELD_OUT:]
    model = faces.fit_factor_analyser(train, 8).model
    library = faces.build_library(train, 9)
    key_q, key_i, key_e, key_s = jax.random.split(key, 4)
    keys = jax.random.split(key_q, n)
    combined, targets, _ = jax.vmap(
        lambda k: faces.synthesize(k, library, model, symmetric=symmetric)
    )(keys)
    local = jax.vmap(lambda k, t: faces.quilt(k, library, t, lam=0.0, symmetric=symmetric))(
        keys, targets
    )
    rows = [list(np.asarray(r)) for r in (targets, local.image, combined.quilted, combined.image)]
    figure = plots.panel_grid(
        rows,
        title=f"{name.upper()}: synthesis by non-stationary quilting (Mohammed et al. 2009 Fig. 5)",
        row_labels=["global target", "local only (λ = 0)", "quilted", "blended"],
        quantities="image",
        panel_inches=1.0,
    )
    io.write_figure(out / "fig5.png", figure)

    nearest = [faces.nearest_training(im, train) for im in combined.image]
    smaps = colour_sources(np.asarray(faces.source_map(combined, library)))
    closest = train[[int(i) for i, _ in nearest]]
    figure = plots.panel_grid(
        [list(np.clip(np.asarray(combined.image), 0, 1)), list(smaps), list(closest)],
        title=f"{name.upper()}: faces, their patch sources, nearest training faces (MPK09 Fig. 8)",
        row_labels=["synthesised", "patch sources", "nearest"],
        quantities="image",
        panel_inches=1.0,
    )
    io.write_figure(out / "fig8.png", figure)

    face = held[0]
    mask = np.zeros(face.shape, bool)
    mask[: size * 2 // 5] = True  # the top of the head (Fig. 10B)
    hyp, hyp_targets = faces.inpaint_hypotheses(
        key_i, library, model, face, mask, 3, symmetric=symmetric
    )
    holed = np.where(mask, 1.0, face)
    figure = plots.panel_grid(
        [[face, holed, np.asarray(hyp_targets[0]), *np.asarray(hyp.image)]],
        title=f"{name.upper()}: inpainting the top of the head (Mohammed et al. 2009 Fig. 10)",
        col_labels=["input", "hole", "global fill", "hypothesis 1", "hypothesis 2", "hypothesis 3"],
        quantities="image",
        panel_inches=1.3,
    )
    io.write_figure(out / "fig10.png", figure)

    painted = face.copy()
    painted[int(0.68 * size) : int(0.72 * size), int(0.33 * size) : int(0.67 * size)] = 0.08
    edited = faces.guided_edit(key_e, library, face, painted)
    figure = plots.panel_grid(
        [[face, painted, np.asarray(edited.image)]],
        title=f"{name.upper()}: guided edit (Mohammed et al. 2009 Fig. 11)",
        col_labels=["input", "painted", "edited"],
        quantities="image",
        panel_inches=1.5,
    )
    io.write_figure(out / "fig11.png", figure)

    if smiling is not None:
        pairs = np.stack([train, smiling[:-HELD_OUT]], axis=1)
        bilinear = faces.fit_bilinear(pairs, 8).model
        smile_library = faces.build_library(smiling[:-HELD_OUT], 9)
        shown = range(4)
        made = [
            faces.restyle(k, smile_library, bilinear, held[i])
            for k, i in zip(jax.random.split(key_s, len(shown)), shown, strict=True)
        ]
        # one column per face: neutral, prediction, restyled, true smile
        rows = [
            [held[i] for i in shown],
            [np.asarray(p) for _, p in made],
            [np.asarray(r.image) for r, _ in made],
            [smiling[-HELD_OUT + i] for i in shown],
        ]
        figure = plots.panel_grid(
            rows,
            title=f"{name.upper()}: neutral to smiling (Mohammed et al. 2009 Fig. 12)",
            row_labels=["neutral", "style model", "restyled", "true smile"],
            quantities="image",
            panel_inches=1.2,
        )
        io.write_figure(out / "fig12.png", figure)

    nn = np.asarray(faces.training_nn_distances(train))
    return {
        "dataset": name,
        "out": str(out),
        "training_nn_distance_median": round(float(np.median(nn)), 4),
        "training_nn_distance_min": round(float(nn.min()), 4),
        "face_nn_distance": [round(float(d), 4) for _, d in nearest],
        "target_nn_distance": [
            round(float(faces.nearest_training(t, train)[1]), 4) for t in targets
        ],
        "face_target_distance": [
            round(float(faces.target_distance(im, t)), 4)
            for im, t in zip(combined.image, targets, strict=True)
        ],
        "local_only_target_distance": [
            round(float(faces.target_distance(im, t)), 4)
            for im, t in zip(local.image, targets, strict=True)
        ],
        "distinct_sources": [int(np.unique(s[s >= 0]).size) for s in np.asarray(combined.sources)],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="visiolization")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", type=int, default=50)
    parser.add_argument("--dataset", choices=["lfw", "ict", "both"], default="both")
    args = parser.parse_args()
    out = Path(args.out)
    key_lfw, key_ict = jax.random.split(jax.random.key(args.seed))
    if args.dataset in ("lfw", "both"):
        # LFW crops are not frontal and their backgrounds differ left and right: the paper's
        # symmetry (for frontal XM2VTS faces) leaves the right half badly matched (seam errors
        # up to 40× those without it), so it is off here
        lfw = figures("lfw", lfw_faces(args.size), out, key_lfw, symmetric=False)
        print(json.dumps(lfw))
    if args.dataset in ("ict", "both"):
        neutral = face_renders(args.seed, 110, args.size)
        smiling = face_renders(args.seed, 110, args.size, smile=1.0)
        print(json.dumps(figures("ict", neutral, out, key_ict, smiling)))


if __name__ == "__main__":
    main()
