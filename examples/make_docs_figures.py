"""Regenerate the figures the README shows, from the demo: ``python examples/make_docs_figures.py``.

Runs ``jface demo`` with one seed into a scratch folder (default: ``jface-docs-run``), copies the
README's figures from it into ``docs/figures/`` and, when headless Chromium is installed
(``apt-get install chromium``), takes a screenshot of the run's ``index.html`` into
``docs/figures/demo_index.png``. The same seed gives byte-identical figures (the screenshot
depends on the browser's fonts and version, so it is left out of that promise).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import tempfile
from pathlib import Path

from jface import io
from jface.cli import main as jface

#: Demo outputs shown in the README → their name in docs/figures.
FIGURES = {
    "age/comparison.png": "age_comparison.png",
    "detail/fig5_original_smoothed_synthesized.png": "detail_resynthesis.png",
    "detail/statistics.png": "detail_statistics.png",
    "mesh/known_vs_recovered.png": "mesh_known_vs_recovered.png",
    "quilt/faces.png": "quilt_faces.png",
    "wrinkles/wrinkles.png": "wrinkles_graph.png",
}


def screenshot(page: Path, out: Path) -> bool:
    """Headless Chromium's picture of ``page`` (1200 × 2000 pixels); False without Chromium."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        return False
    with tempfile.TemporaryDirectory() as profile, io.atomic_path(out) as tmp:
        subprocess.run(
            [browser, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={profile}", f"--screenshot={tmp}", "--window-size=1200,2000",
             "--hide-scrollbars", page.resolve().as_uri()],
            check=True, capture_output=True, timeout=120,
        )  # fmt: skip
    return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seed", type=int, default=0, help="demo seed (default: 0)")
    parser.add_argument("--run", default="jface-docs-run", help="scratch folder for the demo run")
    parser.add_argument("--out", default="docs/figures", help="docs figure folder")
    args = parser.parse_args()
    run, out = Path(args.run), Path(args.out)
    if jface(["demo", "--out", str(run), "--seed", str(args.seed)]) != 0:
        raise SystemExit("jface demo failed; no docs figures written")
    for source, name in FIGURES.items():
        with io.atomic_path(out / name) as tmp:
            tmp.write_bytes((run / source).read_bytes())
    shot = screenshot(run / "index.html", out / "demo_index.png")
    print(
        f"wrote {len(FIGURES)} figures to {out}/"
        + ("" if shot else "; no Chromium, so no screenshot of index.html")
    )


if __name__ == "__main__":
    main()
