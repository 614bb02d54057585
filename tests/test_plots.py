"""Figures (jface.plots, jface.io.write_figure) and the run page (index.html)."""

import html.parser
import json
import sys
import types
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from conftest import titled, value_images_have_colour_bars, write_aged_maps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from PIL import Image

from jface import detail, faces, io, plots
from jface.cli import _report, main


@pytest.fixture(scope="module")
def stats(gravel):
    return detail.analyze(np.asarray(gravel[:64, :64]), grid=4, n_scales=2)


def _figures(gravel, stats):
    patch = np.asarray(gravel[:32, :32])
    errors = [np.linspace(0, 1, 16).reshape(4, 4)] * 3
    history = np.minimum.accumulate(np.linspace(1.0, 0.01, 30)[None] * [[1.0], [2.0]], axis=1)
    return {
        "method_comparison": plots.method_comparison(
            [patch] * 3, errors, ["young", "old", "aged"], title="Methods"
        ),
        "band_statistics": plots.band_statistics(stats.std, stats.n_orientations, title="Bands"),
        "convergence": plots.convergence(history, title="Convergence"),
        "heatmap": plots.heatmap(
            np.eye(2) + 0.5, title="Ratios", row_labels=["a", "b"], col_labels=["0°", "90°"]
        ),
        "image": plots.image(patch, title="Displacement", units="mm"),
        "lines": plots.lines([1.0, 2.0], {"x": [1.0, 2.0]}, title="t", xlabel="x", ylabel="y"),
        "axes_grid": plots.axes_grid(1, 2, title="Drawn")[0],
    }


def test_every_figure_has_a_title_and_colour_bars_where_colour_encodes_a_value(gravel, stats):
    for name, figure in _figures(gravel, stats).items():
        assert titled(figure), name
        assert value_images_have_colour_bars(figure), name


def test_the_checker_sees_a_missing_colour_bar():
    figure = plots.panel_grid([[np.eye(4)]], title="t", quantities="error")
    assert value_images_have_colour_bars(figure)
    bare = matplotlib.figure.Figure()
    bare.subplots().imshow(np.eye(4), cmap="magma")
    assert not value_images_have_colour_bars(bare)


def test_panel_grid_labels_rows_columns_and_units():
    figure = plots.panel_grid(
        [[np.eye(4), np.eye(4)], [np.ones((4, 4, 3)), None]],
        title="Grid",
        col_labels=["left", "right"],
        row_labels=["values", "colour"],
        quantities=["displacement", "relief"],
        units=["mm", None],
    )
    titles = [ax.get_title() for ax in figure.axes]
    assert "left" in titles and "right" in titles
    assert {ax.get_ylabel() for ax in figure.axes} >= {"values", "colour"}
    bars = [im.colorbar for ax in figure.axes for im in ax.images if im.colorbar is not None]
    assert len(bars) == 1 and bars[0].ax.get_ylabel() == "mm"
    # Signed displacement is centred on zero: the colour scale is symmetric.
    norm = bars[0].mappable.norm
    assert norm.vmin == -norm.vmax == -1.0


def test_panel_grid_lines_up_rows_with_and_without_a_colour_bar():
    # a fit's figure: shaded relief (no bar) above displacement (a bar)
    values = np.linspace(-1.0, 1.0, 64).reshape(8, 8)
    figure = plots.panel_grid(
        [[np.full((8, 8, 3), 0.5)] * 2, [values, values]],
        title="t",
        quantities=["relief", "displacement"],
    )
    figure.canvas.draw()
    panels = [ax for ax in figure.axes if ax.images]  # a colour bar's axes hold no image
    top, bottom = panels[:2], panels[2:]
    for a, b in zip(top, bottom, strict=True):
        pa, pb = a.get_position(), b.get_position()
        assert pa.x0 == pytest.approx(pb.x0, abs=1e-6) and pa.width == pytest.approx(pb.width)


def test_convergence_draws_one_labelled_line_per_trial_on_a_log_axis():
    history = np.array([[1.0, 0.5, 0.1], [2.0, 0.2, 0.05], [1.5, 1.0, np.inf]])
    figure = plots.convergence(history, title="Fit")
    ax = figure.axes[0]
    assert [line.get_label() for line in ax.get_lines()] == ["trial 1", "trial 2", "trial 3"]
    assert ax.get_yscale() == "log" and ax.get_xlabel() == "epoch" and ax.get_ylabel()
    np.testing.assert_array_equal(ax.get_lines()[1].get_ydata(), history[1])
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["trial 1", "trial 2", "trial 3"]


def test_convergence_marks_an_answer_refined_after_the_search():
    history = np.array([[1.0, 0.5, 0.4]])
    figure = plots.convergence(history, title="Fit", answer=("refined", 0.05))
    ax = figure.axes[0]
    star = ax.get_lines()[-1]
    assert star.get_label() == "refined" and star.get_marker() == "*"
    assert list(star.get_xdata()) == [2.0] and list(star.get_ydata()) == [0.05]
    assert ax.get_ylim()[0] <= 0.05  # on the axis
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["trial 1", "refined"]
    bare = plots.convergence(history, title="Fit", answer=("refined", np.inf)).axes[0]
    assert [line.get_label() for line in bare.get_lines()] == ["trial 1"]


def test_a_log_axis_within_a_decade_reads_plain_numbers():
    """A short fit's losses span less than a decade: its tick labels are plain numbers, not
    ``1.716×10⁰``, also between 1 and 2 (where a log axis has no ticks of its own); a history
    over decades keeps the powers of ten."""

    def labels(history, answer=None):
        figure = plots.convergence(np.asarray(history), title="Fit", answer=answer)
        FigureCanvasAgg(figure).draw()
        ax = figure.axes[0]
        low, high = ax.get_ylim()
        ticks = ax.yaxis.get_majorticklabels() + ax.yaxis.get_minorticklabels()
        return [t.get_text() for t in ticks if t.get_text() and low <= t.get_position()[1] <= high]

    narrow = labels([[1.716, 1.716, 1.705]])
    assert narrow and not any("10^" in t or "times" in t for t in narrow)
    assert all(1.6 < float(t) < 1.8 for t in narrow)
    exploratory = [float(t) for t in labels([[1.716] * 5 + [1.483]], ("refined", 0.5156))]
    assert len(exploratory) >= 4 and sum(1.0 < t < 1.8 for t in exploratory) >= 2, exploratory
    wide = labels([[10.0, 1.0, 0.01]])
    assert any("10^" in t for t in wide)


def test_axes_grid_gives_a_titled_figure_of_empty_axes_to_draw_on():
    figure, axes = plots.axes_grid(2, 3, title="Custom", size=(6, 4), width_ratios=(1, 2, 1))
    assert axes.shape == (2, 3) and figure.get_suptitle() == "Custom"
    assert list(figure.get_size_inches()) == [6, 4]
    assert not any(ax.lines or ax.images for ax in axes.ravel())


def test_building_figures_leaves_no_global_state(gravel, stats):
    import matplotlib.pyplot as plt

    before = dict(matplotlib.rcParams)
    _figures(gravel, stats)
    assert plt.get_fignums() == []
    assert dict(matplotlib.rcParams) == before


@pytest.mark.parametrize("suffix", [".png", ".pdf", ".svg"])
def test_write_figure_same_data_same_bytes_with_provenance(tmp_path, suffix):
    meta = io.provenance(seed=3, experiment="test")

    def make():
        return plots.image(np.outer(np.arange(8.0), np.ones(8)) - 3, title="Ramp", units="mm")

    a = io.write_figure(tmp_path / f"a{suffix}", make(), metadata=meta)
    b = io.write_figure(tmp_path / f"b{suffix}", make(), metadata=meta)
    assert a.read_bytes() == b.read_bytes()
    if suffix == ".png":
        with Image.open(a) as img:
            assert json.loads(img.text["jface"]) == meta
    else:
        assert b"jface_version" in a.read_bytes()
        assert b"CreationDate" not in a.read_bytes()


def test_bad_figure_input_names_the_argument(tmp_path):
    with pytest.raises(ValueError, match="quantities"):
        plots.panel_grid([[np.eye(3)]], title="t", quantities="temperature")
    with pytest.raises(ValueError, match="col_labels must have 2 entries"):
        plots.panel_grid([[np.eye(3), np.eye(3)]], title="t", col_labels=["one"])
    with pytest.raises(ValueError, match=r"rows\[0\]\[0\] must be finite"):
        plots.panel_grid([[np.full((3, 3), np.nan)]], title="t")
    with pytest.raises(TypeError, match=r"rows\[0\]\[0\] must be an image array"):
        plots.panel_grid([["picture.png"]], title="t")
    with pytest.raises(ValueError, match="series 'a' must have 2 values"):
        plots.lines([1.0, 2.0], {"a": [1.0]}, title="t", xlabel="x", ylabel="y")
    with pytest.raises(ValueError, match="title must be a non-empty text"):
        plots.axes_grid(title=" ")
    with pytest.raises(TypeError, match="matplotlib Figure"):
        io.write_figure(tmp_path / "x.png", np.eye(3))
    with pytest.raises(ValueError, match=r"must end in \.png or \.pdf or \.svg"):
        io.write_figure(tmp_path / "x.jpg", plots.image(np.eye(3), title="t"))


class _Links(html.parser.HTMLParser):
    def __init__(self):
        super().__init__()
        self.images, self.links, self.text = [], [], []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "img":
            self.images.append(attrs["src"])
        if tag == "a":
            self.links.append(attrs["href"])

    def handle_data(self, data):
        self.text.append(data)


def _parse(page: Path) -> _Links:
    parser = _Links()
    parser.feed(page.read_text(encoding="utf-8"))
    return parser


def test_index_names_only_existing_files_and_says_what_is_missing(tmp_path):
    io.write_figure(tmp_path / "a" / "good.png", plots.image(np.eye(4), title="t"))
    (tmp_path / "a" / "cut.png").write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00")  # truncated
    io.write_png(tmp_path / "s" / "sample_000.png", np.eye(4))
    (tmp_path / "empty.json").write_bytes(b"")
    page = _report.write_index(
        tmp_path,
        title="run",
        provenance={"jface_version": "x", "seed": 0},
        steps=[{"name": "one", "seconds": 1.5, "console": ["error 12.5%"]}],
        expected=["a/good.png", "b/never.png"],
    )
    parsed = _parse(page)
    assert parsed.images == ["a/good.png", "s/sample_000.png"]  # the figure, then the series
    for name in parsed.images + parsed.links:
        assert (tmp_path / name).is_file(), name
    text = "".join(parsed.text)
    assert "b/never.png" in text and "not written" in text
    assert "a/cut.png" in text and "not a readable PNG" in text
    assert "empty.json" in text and "empty file" in text
    assert "error 12.5%" in text and "1.5" in text


def test_demo_page_shows_steps_done_and_the_failed_one(tmp_path, monkeypatch, capsys):
    def good(out, seed):
        io.write_figure(Path(out) / "good" / "fig.png", plots.image(np.eye(4) * seed, title="t"))
        print("good: error 3.0%")

    def bad(out, seed):
        io.write_json(Path(out) / "bad" / "partial.json", {})
        raise ValueError("broken input")

    modules = [
        types.SimpleNamespace(
            __name__=f"jface.cli._{f.__name__}", demo=f, register=lambda sub: None
        )
        for f in (good, bad)
    ]
    monkeypatch.setattr(sys.modules["jface.cli"], "_modules", lambda: modules)
    assert main(["demo", "--out", str(tmp_path), "--seed", "2"]) == 2
    page = tmp_path / "index.html"
    parsed = _parse(page)
    assert parsed.images == ["good/fig.png"]
    assert not (tmp_path / "bad" / "partial.json").exists()  # the failed step's outputs go
    for name in parsed.images + parsed.links:
        assert (tmp_path / name).is_file(), name
    text = "".join(parsed.text)
    assert "good: error 3.0%" in text and "failed: ValueError: broken input" in text
    assert "jface demo" in text


def test_figures_of_analyze_and_db_compare(tmp_path, gravel, written_figures):
    written = written_figures
    maps = write_aged_maps(tmp_path, gravel, (20, 50, 80), 64)
    assert main(["analyze", maps[0], "--out", str(tmp_path / "stats"), "--grid", "4"]) == 0
    db = tmp_path / "db.npz"
    build = ["db", "build", *maps, "--out", str(db), "--metadata", str(tmp_path / "meta.json")]
    assert main([*build, "--grid", "4", "--scales", "2"]) == 0
    groups = ["--group", "young:age=20..40", "--group", "old:age=41..80"]
    assert main(["db", "compare", str(db), *groups, "--out", str(tmp_path / "cmp.png")]) == 0
    assert set(written) == {"f0.stats.png", "cmp.png"}
    for name, figure in written.items():
        assert titled(figure) and value_images_have_colour_bars(figure), name
    labels = {ax.get_ylabel() for ax in written["cmp.png"].axes}
    assert {"young", "old"} <= labels


def _checked_page(run_dir: Path) -> tuple[_Links, str]:
    """The parsed page of a run folder, after checking that every figure and file it names
    exists; and its text."""
    parsed = _parse(run_dir / "index.html")
    for name in parsed.images + parsed.links:
        assert (run_dir / name).is_file(), name
    return parsed, "".join(parsed.text)


def _maps(folder: Path, gravel, n: int) -> list[str]:
    return [
        str(io.write_exr(folder / f"m{i}.exr", gravel[64 * i : 64 * i + 64, :64].astype("f4")))
        for i in range(n)
    ]


def test_commands_that_write_a_folder_write_its_page(tmp_path, gravel, capsys):
    maps = _maps(tmp_path, gravel, 2)
    stats = tmp_path / "stats"
    argv = ["analyze", *maps, "--out", str(stats), "--grid", "4", "--scales", "2"]
    assert main(argv) == 0
    parsed, text = _checked_page(stats)
    assert parsed.images == ["m0.stats.png", "m1.stats.png"]
    assert parsed.links == ["m0.stats.npz", "m0.stats.png", "m1.stats.npz", "m1.stats.png"]
    assert "analyzed 2 map(s), kept 0" in text and "--grid 4 --scales 2" in text
    assert "Missing" not in text
    assert main(argv) == 0  # a rerun keeps the maps done and refreshes the page
    assert "analyzed 0 map(s), kept 2" in _checked_page(stats)[1]
    # an image series (thumbnails) and its figure, the seed and the summary's numbers
    train = np.random.default_rng(0).random((6, 6, 6)).astype(np.float32)
    model = faces.save_model(tmp_path / "fa.npz", faces.fit_factor_analyser(train, 2).model)
    samples = tmp_path / "samples"
    argv = ["faces", "sample", str(model), "--n", "2", "--seed", "7", "--out", str(samples)]
    assert main(argv) == 0
    parsed, text = _checked_page(samples)
    assert parsed.images == ["grid.png", "sample_000.png", "sample_001.png"]
    assert "jface faces sample" in text and "seed7" in text.replace(" ", "")
    # a command that writes one file writes no page beside it
    assert main(["render", maps[0], "--out", str(tmp_path / "r.png")]) == 0
    assert not (tmp_path / "index.html").exists()


def test_a_batch_that_stopped_part_way_gets_a_page_that_says_what_is_missing(
    tmp_path, gravel, capsys, monkeypatch
):
    good, other = _maps(tmp_path, gravel, 2)
    cut = tmp_path / "cut.exr"
    cut.write_bytes(Path(good).read_bytes()[:300])
    out = tmp_path / "stats"
    argv = ["analyze", good, str(cut), "--out", str(out), "--grid", "4", "--scales", "2"]
    assert main(argv) == 2
    assert "cut.exr is not a readable OpenEXR file" in capsys.readouterr().err
    parsed, text = _checked_page(out)
    assert parsed.images == ["m0.stats.png"]  # the map done before the failure stays
    assert "cut.stats.npz" in text and "cut.stats.png" in text and "not written" in text
    assert "failed: ValueError" in text
    # a command refused before it wrote anything leaves no page, and no folder
    assert main(["analyze", str(cut), "--out", str(tmp_path / "none")]) == 2
    assert not (tmp_path / "none").exists()
    # interrupted after the first map
    real, done = detail.analyze, []

    def analyze_once(*args, **kwargs):
        if done:
            raise KeyboardInterrupt
        done.append(True)
        return real(*args, **kwargs)

    monkeypatch.setattr(detail, "analyze", analyze_once)
    out = tmp_path / "interrupted"
    assert main(["analyze", good, other, "--out", str(out), "--grid", "4", "--scales", "2"]) == 130
    parsed, text = _checked_page(out)
    assert parsed.images == ["m0.stats.png"] and "interrupted" in text and "m1.stats.npz" in text


def test_the_page_never_replaces_an_input(tmp_path, gravel, capsys):
    # a face folder of `jface remesh` (with its page) analysed into itself: the page is an input
    face = tmp_path / "face"
    io.write_exr(face / "displacement.exr", gravel[:64, :64].astype("f4"))
    (face / "index.html").write_text("the remesh run's page")
    assert main(["analyze", str(face), "--out", str(face), "--grid", "4", "--scales", "2"]) == 0
    assert "warning: no index.html written: refusing to overwrite the input" in (
        capsys.readouterr().err
    )
    assert (face / "index.html").read_text() == "the remesh run's page"
    assert (face / "face.stats.png").is_file()


def test_examples_draw_through_jface_plots():
    """No example draws with pyplot or Pillow or saves a figure itself: figures come from
    jface.plots and are written by io.write_figure (title, colour bars, provenance)."""
    for path in sorted((Path(__file__).parents[1] / "examples").glob("*.py")):
        text = path.read_text(encoding="utf-8")
        for banned in ("pyplot", "from PIL", "import PIL", ".savefig(", "render.colormap("):
            assert banned not in text, f"{path.name} uses {banned}"
