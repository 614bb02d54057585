"""Registration and un-warping for Visio-lization (Mohammed et al. 2009, §2.2 and §4's last step).

The 100 faces of scikit-image's LFW subset (already aligned crops), upsampled to 64 × 64, are the
ground truth. Each is warped by a random affine map (rotation ≤ 8°, scale ≤ 8 %, shear ≤ 0.05,
shift ≤ 4 px): these are the unaligned training faces. Then:

1. landmarks (eye centres, nose tip, mouth corners of the mean crop, carried through each warp,
   plus Gaussian hand-marking noise) align every face back to the template, in closed form;
2. an 8-factor analyser and the 9 × 9 patch libraries are fitted to the aligned faces, and new
   faces are synthesised (§4);
3. every new face is un-warped by the inverse of a randomly chosen training transformation.

The intensity alignment is measured too: each warped face aligned to its own unwarped crop
(recovery of a known map), and to the mean face (a template of other people).

Writes ``OUT/alignment.png`` (rows: crops, warped with landmarks, aligned, synthesised,
un-warped), ``OUT/alignment_errors.png`` (corner errors of each way of aligning) and prints the
numbers as one JSON line. Run: ``python examples/faces_alignment.py --out docs/faces``.
"""

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from skimage import data

from jface import faces, io, plots

SIZE = 64
# eye centres, nose tip, mouth corners of the mean LFW crop at 64 × 64, (x, y) pixels
TEMPLATE_LANDMARKS = np.array(
    [[18.0, 21.0], [45.0, 21.0], [31.5, 36.0], [21.0, 46.0], [42.0, 46.0]], np.float32
)
CORNERS = np.array([[0, 0], [SIZE - 1, 0], [0, SIZE - 1], [SIZE - 1, SIZE - 1]], np.float64)


def random_affine(rng: np.random.Generator) -> np.ndarray:
    angle = np.deg2rad(rng.uniform(-8, 8))
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    shear = np.array([[1, rng.uniform(-0.05, 0.05)], [0, 1]])
    linear = (1 + rng.uniform(-0.08, 0.08)) * rotation @ shear
    centre = np.full(2, (SIZE - 1) / 2)
    shift = centre - linear @ centre + rng.uniform(-4, 4, 2)
    return np.concatenate([linear, shift[:, None]], axis=1).astype(np.float32)


def apply(transform, points) -> np.ndarray:
    a = np.asarray(transform, np.float64)
    return np.asarray(points, np.float64) @ a[:, :2].T + a[:, 2]


def corner_errors(found, truth) -> np.ndarray:
    """Per face, the largest distance between where two transforms send the frame's corners."""
    return np.array(
        [
            np.linalg.norm(apply(f, CORNERS) - apply(t, CORNERS), axis=1).max()
            for f, t in zip(found, truth, strict=True)
        ]
    )


def landmark_errors(found, truth) -> np.ndarray:
    """Per face, the largest distance of a true landmark, aligned, from the template's."""
    out = []
    for f, t in zip(found, truth, strict=True):
        back = apply(faces.invert_affine(f), apply(t, TEMPLATE_LANDMARKS))
        out.append(np.linalg.norm(back - TEMPLATE_LANDMARKS, axis=1).max())
    return np.array(out)


def summary(errors: np.ndarray) -> dict:
    return {"median": round(float(np.median(errors)), 3), "max": round(float(errors.max()), 3)}


def main(out: Path, seed: int) -> None:
    crops = jnp.asarray(data.lfw_subset()[:100], jnp.float32)
    originals = np.clip(np.asarray(jax.image.resize(crops, (100, SIZE, SIZE), "cubic")), 0, 1)
    rng = np.random.default_rng(seed)
    maps = [random_affine(rng) for _ in originals]
    warped = np.stack([np.asarray(faces.warp(f, b)) for f, b in zip(originals, maps, strict=True)])
    truth = np.stack([np.asarray(faces.invert_affine(b)) for b in maps])
    mean = originals.mean(axis=0)
    numbers: dict = {"faces": len(originals), "size": SIZE}

    # 1. landmarks, with 0, 0.25 and 0.5 px of hand-marking noise
    errors = {}
    for noise in (0.0, 0.25, 0.5):
        marked = np.stack([apply(t, TEMPLATE_LANDMARKS) for t in truth])
        marked += rng.normal(0, noise, marked.shape)
        result = jax.vmap(
            lambda im, lm: faces.align(
                im, mean, landmarks=lm, template_landmarks=TEMPLATE_LANDMARKS
            )
        )(jnp.asarray(warped), jnp.asarray(marked, jnp.float32))
        errors[f"landmarks σ={noise}"] = corner_errors(result.transform, truth)
        numbers[f"landmarks_noise_{noise}"] = {
            "landmark_error_px": summary(landmark_errors(result.transform, truth)),
            "corner_error_px": summary(errors[f"landmarks σ={noise}"]),
        }
        if noise == 0.25:
            used, used_marks = result, marked

    # intensity: to each face's own crop (known answer), and to the mean face of other people
    results = [faces.align(w, o) for w, o in zip(warped, originals, strict=True)]
    own = jax.tree.map(lambda *xs: jnp.stack(xs), *results)
    errors["intensity, own crop"] = corner_errors(own.transform, truth)
    numbers["intensity_own_crop"] = {
        "corner_error_px": summary(errors["intensity, own crop"]),
        "converged": int(np.sum(own.converged)),
        "rms_to_crop": summary(np.asarray(own.rms)),
    }
    # to the mean, only the inner face counts; consistency: the warped face must land where
    # its unwarped crop lands (the mean's own frame is not a unique answer for another person)
    yy, xx = np.mgrid[:SIZE, :SIZE]
    face_region = (((xx - 31.5) / 24) ** 2 + ((yy - 31.5) / 27.6) ** 2 <= 1).astype(np.float32)
    to_mean = jax.jit(jax.vmap(lambda im: faces.align(im, mean, weights=face_region, throw=False)))
    from_warped, from_crop = to_mean(jnp.asarray(warped)), to_mean(jnp.asarray(originals))
    expected = [
        (np.vstack([t, [0, 0, 1]]) @ np.vstack([c, [0, 0, 1]]))[:2]
        for t, c in zip(truth, np.asarray(from_crop.transform), strict=True)
    ]
    consistency = corner_errors(from_warped.transform, expected)
    errors["intensity, mean face\n(consistency)"] = consistency
    numbers["intensity_mean_face_consistency"] = {
        "corner_error_px": summary(consistency),
        "share_within_1px": round(float(np.mean(consistency <= 1)), 2),
        "converged": int(np.sum(from_warped.converged)),
        "crop_to_mean_corner_shift_px": summary(
            corner_errors(from_crop.transform, [np.eye(2, 3)] * len(originals))
        ),
    }

    # 2. synthesis in the template frame, 3. un-warping
    aligned = np.asarray(used.image)
    model = faces.fit_factor_analyser(aligned, 8).model
    library = faces.build_library(aligned, 9)
    keys = jax.random.split(jax.random.key(seed), 6)
    made, _, _ = jax.vmap(lambda k: faces.synthesize(k, library, model, symmetric=False))(keys)
    unwarp_keys = jax.random.split(jax.random.fold_in(jax.random.key(seed), 1), 6)
    unwarped, chosen = jax.vmap(lambda k, im: faces.unwarp(k, im, used.transform))(
        unwarp_keys, made.image
    )
    numbers["unwarped_into_frames_of"] = np.asarray(chosen).tolist()

    meta = io.provenance(seed=seed, source="skimage.data.lfw_subset, 64 × 64")
    figure_grid(originals, warped, used_marks, aligned, made.image, unwarped, chosen, out, meta)
    figure_errors(errors, out, meta)
    print(json.dumps(numbers))


def figure_grid(originals, warped, marks, aligned, made, unwarped, chosen, out, meta) -> None:
    show = 6
    rows = {
        "LFW crops\n(ground truth)": originals[:show],
        "warped: the\ntraining faces": warped[:show],
        "aligned from\nlandmarks": aligned[:show],
        "synthesised\n(template frame)": np.asarray(made),
        "un-warped": np.asarray(unwarped),
        "training face\nlending its frame": warped[np.asarray(chosen)],
    }
    figure = plots.panel_grid(
        [list(np.clip(images[:show], 0, 1)) for images in rows.values()],
        title="Visio-lization registration (Mohammed et al. 2009 §2.2, §4): random affine warps "
        "of real faces,\naligned from landmarks (red: marked with 0.25 px noise; cyan: "
        "template), synthesised, un-warped",
        col_labels=[f"face {c}" for c in range(show)],
        row_labels=list(rows),
        quantities="image",
        panel_inches=1.5,
    )
    axes = np.array(figure.axes).reshape(len(rows), show)
    for c in range(show):
        axes[1, c].plot(marks[c, :, 0], marks[c, :, 1], "+", color="tab:red", ms=6)
        axes[2, c].plot(*TEMPLATE_LANDMARKS.T, "+", color="tab:cyan", ms=6)
        axes[5, c].set_title(f"face {int(chosen[c])}", fontsize=8)
    io.write_figure(out / "alignment.png", figure, metadata=meta)


def figure_errors(errors: dict, out: Path, meta: dict) -> None:
    figure, ((ax,),) = plots.axes_grid(
        title="Recovery of 100 random affine warps of LFW faces (whiskers: min–max)",
        size=(7, 3.8),
    )
    names = list(errors)
    ax.boxplot([np.maximum(errors[n], 1e-6) for n in names], whis=(0, 100))
    ax.set_xticks(range(1, len(names) + 1), names, fontsize=8)
    ax.set_yscale("log")
    ax.axhline(1.0, color="tab:red", lw=1, ls="--", label="1 px")
    ax.set_xlabel("how the faces were aligned")
    ax.set_ylabel("corner error (px, 64 × 64 frame)")
    ax.legend(loc="upper left", fontsize=8)
    io.write_figure(out / "alignment_errors.png", figure, metadata=meta)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="alignment", help="output folder")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    main(Path(args.out), args.seed)
