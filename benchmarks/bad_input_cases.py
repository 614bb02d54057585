"""Failure cases of bad input ("nothing lost, nothing stale, nothing silently wrong"), each run
as a user would, with the outcome as one JSON line per case.

For every case: the exit status of ``jface`` (or the exception a Python call raised), the last
line of what it printed on stderr, whether every input is byte-identical afterwards, whether
anything was left under the refused output name or as a temporary file, and ``ok``: whether the
outcome is the one the issue asks for (exit status 2 with a one-line message naming the file,
inputs unchanged, nothing left behind; or, for the cases that must work, success with correct
results). Runs on any version of jface (it uses only the command line and public functions), so
the same script measures before and after a change.

Run: ``python benchmarks/bad_input_cases.py [--only NAME]`` (about a minute on 2 CPU cores).
Measured on 2 CPU cores: 6 of the 49 cases as asked on the commit before the fix (f525ce4), 49
of 49 after.
"""

from __future__ import annotations

import argparse
import contextlib
import io as stdio
import json
import os
import signal
import subprocess
import sys
import tempfile
import traceback
import zipfile
import zlib
from pathlib import Path

import jax
import numpy as np

from jface import detail, faces, io, optim
from jface.cli import main

RNG = np.random.default_rng(0)
CASES = {}


def case(section: str):
    def register(fn):
        CASES[fn.__name__] = (section, fn)
        return fn

    return register


def noise(size: int = 128) -> np.ndarray:
    return RNG.standard_normal((size, size)).astype(np.float32)


def run_cli(argv: list[str]) -> tuple[int | str, str]:
    """``jface ARGV`` in-process: (exit status or the exception's type, last stderr line)."""
    err = stdio.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(stdio.StringIO()):
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse
            code = exc.code
        except BaseException as exc:
            tb = traceback.format_exception_only(type(exc), exc)[-1].strip()
            return f"traceback: {tb}"[:240], ""
    lines = [ln for ln in err.getvalue().splitlines() if ln.strip() and "it/s]" not in ln]
    return code, (lines[-1] if lines else "")


def snapshot(paths) -> dict[str, bytes]:
    out = {}
    for p in paths:
        p = Path(p)
        files = sorted(p.iterdir()) if p.is_dir() else [p]
        for f in files:
            if f.is_file():
                out[str(f)] = f.read_bytes()
    return out


def temporaries(root: Path) -> list[str]:
    return sorted(
        str(p.relative_to(root)) for p in root.rglob(".*") if p.is_file() and p.name != ".keep"
    )


def refusal(d: Path, argv, inputs, outputs=(), *, names=()) -> dict:
    """A command that must be refused: exit 2, one line naming a file, inputs unchanged, nothing
    new under the output names, no temporary file."""
    before = snapshot(inputs)
    existed = {str(o): Path(o).exists() for o in outputs}
    code, line = run_cli([str(a) for a in argv])
    after = snapshot(inputs)
    written = [o for o, was in existed.items() if not was and Path(o).exists()]
    named = not names or any(str(n) in line for n in names)
    result = {
        "exit": code,
        "message": line[:240],
        "inputs_unchanged": before == after,
        "written_under_output": written,
        "temporaries": temporaries(d),
    }
    result["ok"] = (
        code == 2 and named and before == after and not written and not result["temporaries"]
    )
    return result


# --- inputs overwritten ------------------------------------------------------------------------


@case("inputs overwritten")
def db_build_out_is_input(d):
    m = io.write_exr(d / "m.exr", noise())
    return refusal(d, ["db", "build", m, "--out", m, "--grid", "8", "--scales", "3"], [m])


@case("inputs overwritten")
def extract_out_is_input(d):
    m = io.write_exr(d / "in.exr", noise())
    return refusal(d, ["wrinkles", "extract", m, "--out", m, "--crop", "64"], [m])


def _population(d: Path) -> Path:
    stats = [detail.analyze(noise() * (1 + i), grid=8, n_scales=3) for i in range(4)]
    pop = detail.Population.from_faces(stats, [{"id": f"f{i}", "age": 20 * i} for i in range(4)])
    pop.save(d / "pop.npz")
    return d / "pop.npz"


@case("inputs overwritten")
def db_compare_out_is_db(d):
    pop = _population(d)
    groups = ["--group", "a:age=0..25", "--group", "b:age=30..90"]
    return refusal(d, ["db", "compare", pop, *groups, "--out", pop], [pop])


def _params(path: Path) -> Path:
    path.write_text(
        json.dumps({"kind": "WrinkleParams", "units": {"frame": "uv"}, "levels": [{"d": 0.05}]})
    )
    return path


@case("inputs overwritten")
def render_png_beside_is_base(d):
    sub = d / "D"
    sub.mkdir()
    base = io.write_png(sub / "x.png", RNG.random((64, 64)))
    params = _params(d / "p.json")
    argv = ["wrinkles", "render", "--params", params, "--base", base, "--out", sub / "x.exr",
            "--size", "64", "--steps", "2"]  # fmt: skip
    return refusal(d, argv, [base, params], [sub / "x.exr"])


@case("inputs overwritten")
def simulate_rewrites_params(d):
    sub = d / "D"
    sub.mkdir()
    params = _params(sub / "params.json")
    argv = ["wrinkles", "simulate", "--params", params, "--out", sub, "--steps", "2",
            "--size", "16", "--theta", "1.0"]  # fmt: skip
    return refusal(d, argv, [params], [sub / "wrinkles.npz"])


@case("inputs overwritten")
def synthesize_two_outputs_on_one_name(d):
    m = io.write_exr(d / "s.exr", noise())
    stats = d / "st.npz"
    detail.save_stats(stats, detail.analyze(noise(), grid=8, n_scales=3))
    argv = ["synthesize", m, "--stats", stats, "--out", d / "s.png", "--iters", "1"]
    return refusal(d, argv, [m, stats], [d / "s.png"])


@case("inputs overwritten")
def extract_two_outputs_on_one_name(d):
    m = io.write_exr(d / "in.exr", noise())
    argv = ["wrinkles", "extract", m, "--out", d / "p.json", "--pores-out", d / "p.json",
            "--crop", "64"]  # fmt: skip
    return refusal(d, argv, [m], [d / "p.json"])


@case("inputs overwritten")
def render_out_is_hard_link_of_input(d):
    m = io.write_exr(d / "m.exr", noise())
    os.link(m, d / "h.png")
    return refusal(d, ["render", m, "--out", d / "h.png"], [m, d / "h.png"])


@case("inputs overwritten")
def render_out_is_symlink_to_input(d):
    m = io.write_png(d / "m.png", RNG.random((32, 32)))
    os.symlink(m, d / "s.png")
    return refusal(d, ["render", d / "s.png", "--out", m], [m])


@case("inputs overwritten")
def faces_synth_out_is_training_folder(d):
    sub = d / "train"
    sub.mkdir()
    for i in range(6):
        io.write_png(sub / f"face_{i:03d}.png", RNG.random((24, 24)))
    argv = ["faces", "synth", sub, "--out", sub, "--n", "1", "--grid", "3", "--angles"]
    return refusal(d, argv, [sub])


def _face_folder(d: Path) -> Path:
    from jface import mesh
    from jface.cli._mesh import write_face

    scan = mesh.synthetic_scan(jax.random.key(0), n_subdivisions=1)
    remeshed = mesh.remesh(scan.scan.vertices, np.asarray(scan.scan.faces), scan.landmarks,
                           image_size=64)  # fmt: skip
    write_face(d / "face", remeshed, io.provenance(), "obj")
    return d / "face"


@case("inputs overwritten")
def add_detail_out_is_face_folder(d):
    face = _face_folder(d)
    stats = d / "st.npz"
    detail.save_stats(stats, detail.analyze(noise(64), grid=4, n_scales=2))
    argv = ["add-detail", face, "--stats", stats, "--out", face, "--iters", "1"]
    return refusal(d, argv, [face, stats])


# --- silently wrong ------------------------------------------------------------------------------


def _tetra_obj(path: Path, nan_line: bool) -> Path:
    lines = ["v 0 0 0", "v 1 0 0", "v 0 1 0", "v 0 0 1"]
    if nan_line:
        lines.insert(1, "v nan nan nan")
        faces_ = ["f 1 3 4", "f 1 3 5", "f 1 4 5", "f 3 4 5"]
    else:
        faces_ = ["f 1 2 3", "f 1 2 4", "f 1 3 4", "f 2 3 4"]
    path.write_text("\n".join(lines + faces_) + "\n")
    return path


@case("silently wrong")
def obj_with_nan_vertex(d):
    path = _tetra_obj(d / "nan.obj", True)
    try:
        mesh = io.read_mesh(path)
    except ValueError as err:
        return {"raised": str(err)[:240], "ok": "nan.obj" in str(err)}
    return {"loaded_vertices": len(mesh.vertices), "file_vertices": 5, "ok": False}


@case("silently wrong")
def faces_train_constant_images(d):
    files = []
    for i in range(6):
        files.append(io.write_png(d / f"c{i}.png", np.full((16, 16), 0.1 + 0.1 * i)))
    argv = ["faces", "train", *files, "--out", d / "m.npz", "--factors", "2", "--iters", "2"]
    return refusal(d, argv, files, [d / "m.npz"])


def _stats_of_dtype(dtype) -> detail.DetailStats:
    good = detail.analyze(noise(64), grid=4, n_scales=2)
    return detail.DetailStats(
        np.asarray(good.std * 100).astype(dtype), None, None, 2, 4, good.image_shape
    )


def _api_refusal(fn) -> dict:
    try:
        fn()
    except (TypeError, ValueError) as err:
        return {"raised": f"{type(err).__name__}: {str(err)[:200]}", "ok": True}
    except Exception as err:
        return {"raised": f"traceback: {type(err).__name__}: {str(err)[:200]}", "ok": False}
    return {"raised": None, "ok": False}


@case("silently wrong")
def integer_statistics(d):
    stats = _stats_of_dtype(np.int32)
    return _api_refusal(lambda: detail.synthesize(jax.random.key(0), noise(64), stats, n_iter=1))


@case("silently wrong")
def complex_statistics(d):
    stats = _stats_of_dtype(np.complex64)
    return _api_refusal(lambda: detail.synthesize(jax.random.key(0), noise(64), stats, n_iter=1))


@case("silently wrong")
def integer_statistics_file(d):
    arrays, meta = detail._stats.stats_to_arrays(detail.analyze(noise(), grid=8, n_scales=3))
    arrays = {"std": (np.asarray(arrays["std"]) * 1000).astype(np.int64)}
    io.save_arrays(d / "int.npz", arrays, io.provenance(**meta), kind="DetailStats")
    m = io.write_exr(d / "m.exr", noise())
    argv = ["synthesize", m, "--stats", d / "int.npz", "--out", d / "o.exr", "--iters", "1"]
    return refusal(d, argv, [m, d / "int.npz"], [d / "o.exr"], names=["int.npz"])


@case("silently wrong")
def pso_bounds_1e39(d):
    def run():
        result = optim.pso(
            jax.random.key(0), lambda x: (x**2).sum(), ([-1e39], [1e39]), n_agents=4, n_epochs=2
        )
        if not np.all(np.isfinite(np.asarray(result.params))):
            raise RuntimeError(f"best position {np.asarray(result.params)}")

    return _api_refusal(run)


@case("silently wrong")
def fit_bounds_outside_table1(d):
    from jface import wrinkles

    def run():
        wrinkles.fit_wrinkles(
            jax.random.key(0), noise(64), names=("1.cross",), bounds={"1.cross": (-5.0, 50.0)},
            n_agents=3, n_epochs=1, n_trials=1, n_steps=1, refine_steps=0, d_levels=2,
        )  # fmt: skip

    return _api_refusal(run)


# --- stale results --------------------------------------------------------------------------------


@case("stale results")
def db_build_resume_after_edit(d):
    maps = [io.write_exr(d / f"m{i}.exr", noise()) for i in range(2)]
    bad = d / "m1.exr"
    good_bytes = bad.read_bytes()
    bad.write_bytes(b"broken")  # the first run dies at the second chunk
    out = d / "db.npz"
    opts = ["--grid", "8", "--scales", "3", "--chunk", "1"]
    first = run_cli(["db", "build", *map(str, maps), "--out", str(out), *opts])
    edited = noise() * 5
    io.write_exr(maps[0], edited)  # edited between the runs
    bad.write_bytes(good_bytes)
    second = run_cli(["db", "build", *map(str, maps), "--out", str(out), *opts])
    if not out.exists():
        return {"runs": [first, second], "ok": False}
    got = np.asarray(detail.Population.load(out).stats.std[0])
    fresh = np.asarray(detail.analyze(edited, grid=8, n_scales=3).std)
    return {"runs": [first, second], "first_map_stats_current": bool(np.allclose(got, fresh)),
            "ok": bool(np.allclose(got, fresh))}  # fmt: skip


@case("stale results")
def analyze_rerun_other_grid(d):
    m = io.write_exr(d / "m.exr", noise())
    out = d / "stats"
    run_cli(["analyze", str(m), "--out", str(out), "--grid", "8", "--scales", "3"])
    second = run_cli(["analyze", str(m), "--out", str(out), "--grid", "4", "--scales", "3"])
    grid = detail.load_stats(out / "m.stats.npz").stats.grid
    return {"second_run": second, "grid_in_file": grid, "ok": grid == 4}


@case("stale results")
def analyze_rerun_after_edit(d):
    m = io.write_exr(d / "m.exr", noise())
    out = d / "stats"
    run_cli(["analyze", str(m), "--out", str(out), "--grid", "8", "--scales", "3"])
    edited = noise() * 3
    io.write_exr(m, edited)
    second = run_cli(["analyze", str(m), "--out", str(out), "--grid", "8", "--scales", "3"])
    got = np.asarray(detail.load_stats(out / "m.stats.npz").stats.std)
    ok = bool(np.allclose(got, np.asarray(detail.analyze(edited, grid=8, n_scales=3).std)))
    return {"second_run": second, "stats_current": ok, "ok": ok}


@case("stale results")
def db_build_same_name_two_folders(d):
    (d / "a").mkdir()
    (d / "b").mkdir()
    maps = [io.write_exr(d / sub / "face.exr", noise() * (1 + i)) for i, sub in enumerate("ab")]
    out = d / "db.npz"
    code, line = run_cli(["db", "build", *map(str, maps), "--out", str(out), "--grid", "8",
                          "--scales", "3"])  # fmt: skip
    if code != 0:
        return {"exit": code, "message": line, "ok": code == 2 and "face" in line}
    ids = [r["id"] for r in detail.Population.load(out).records]
    return {"exit": code, "ids": ids, "ok": len(set(ids)) == 2}


# --- valid JAX use --------------------------------------------------------------------------------


def _jax_case(fn) -> dict:
    try:
        fn()
    except Exception as err:
        return {"raised": f"{type(err).__name__}: {str(err).splitlines()[0][:200]}", "ok": False}
    return {"raised": None, "ok": True}


@case("valid JAX use raises")
def jit_synthesize_stats_closed_over(d):
    stats = detail.analyze(noise(64), grid=4, n_scales=2)
    f = jax.jit(lambda key, m: detail.synthesize(key, m, stats, n_iter=1))
    return _jax_case(lambda: f(jax.random.key(0), noise(64)))


@case("valid JAX use raises")
def jit_fit_factor_analyser(d):
    data = RNG.random((12, 6, 6)).astype(np.float32)
    f = jax.jit(lambda x: faces.fit_factor_analyser(x, 2, n_iter=2).model.mean)
    return _jax_case(lambda: f(data))


@case("valid JAX use raises")
def vmap_fit_factor_analyser(d):
    data = RNG.random((3, 12, 6, 6)).astype(np.float32)
    f = jax.vmap(lambda x: faces.fit_factor_analyser(x, 2, n_iter=2).model.mean)
    return _jax_case(lambda: f(data))


# --- tracebacks instead of messages ---------------------------------------------------------------


@case("tracebacks")
def output_permission_denied(d):
    m = io.write_exr(d / "m.exr", noise(32))
    target = "/sys/jface-out.png"  # read-only even for root
    return refusal(d, ["render", m, "--out", target], [m], [target], names=[target])


@case("tracebacks")
def output_is_a_directory(d):
    m = io.write_exr(d / "m.exr", noise(32))
    (d / "D").mkdir()
    return refusal(d, ["render", m, "--out", d / "D"], [m], names=[d / "D"])


@case("tracebacks")
def output_parent_is_a_file(d):
    m = io.write_exr(d / "m.exr", noise(32))
    (d / "f.txt").write_text("x")
    out = d / "f.txt" / "sub" / "o.png"
    return refusal(d, ["render", m, "--out", out], [m, d / "f.txt"], [out], names=["f.txt"])


def _corrupt_npz(d: Path) -> Path:
    path = d / "st.npz"
    detail.save_stats(path, detail.analyze(noise(), grid=8, n_scales=3))
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("std.npy")
    data = bytearray(path.read_bytes())
    name_len, extra_len = (int.from_bytes(data[info.header_offset + i : info.header_offset + i + 2],
                                          "little") for i in (26, 28))  # fmt: skip
    data[info.header_offset + 30 + name_len + extra_len] = 0xFF  # an invalid deflate block type
    path.write_bytes(bytes(data))
    return path


@case("tracebacks")
def corrupt_npz_deflate(d):
    stats = _corrupt_npz(d)
    m = io.write_exr(d / "m.exr", noise())
    argv = ["synthesize", m, "--stats", stats, "--out", d / "o.exr", "--iters", "1"]
    return refusal(d, argv, [m, stats], [d / "o.exr"], names=["st.npz"])


@case("tracebacks")
def corrupt_npy_header(d):
    path = d / "bad.npy"
    np.save(path, noise(32))
    data = bytearray(path.read_bytes())
    data[10:30] = b"{'descr': '<f4', 'fo"[:20].replace(b"'", b"(")
    path.write_bytes(bytes(data))
    return refusal(d, ["analyze", path, "--out", d / "o"], [path], [d / "o"], names=["bad.npy"])


@case("tracebacks")
def metadata_not_utf8(d):
    m = io.write_exr(d / "m.exr", noise())
    (d / "meta.json").write_bytes(b"\xff\xfe\x00garbage")
    argv = ["db", "build", m, "--out", d / "db.npz", "--metadata", d / "meta.json"]
    return refusal(d, argv, [m, d / "meta.json"], [d / "db.npz"], names=["meta.json"])


@case("tracebacks")
def metadata_bad_json_lines(d):
    m = io.write_exr(d / "m.exr", noise())
    (d / "meta.json").write_text('{"id": "m"}\n{"id": \n')
    argv = ["db", "build", m, "--out", d / "db.npz", "--metadata", d / "meta.json"]
    return refusal(d, argv, [m, d / "meta.json"], [d / "db.npz"], names=["meta.json"])


def _scan(d: Path) -> Path:
    return _tetra_obj(d / "scan.obj", False)


def _remesh_refusal(d: Path, landmarks: Path) -> dict:
    scan = _scan(d)
    argv = ["remesh", scan, "--landmarks", landmarks, "--out", d / "out", "--image-size", "32"]
    return refusal(d, argv, [scan, landmarks], [d / "out"], names=[landmarks.name])


@case("tracebacks")
def landmarks_json_list_of_numbers(d):
    (d / "l.json").write_text("[1, 2, 3]")
    return _remesh_refusal(d, d / "l.json")


@case("tracebacks")
def landmarks_csv_huge_number(d):
    (d / "l.csv").write_text("nose_tip,1e400\n")
    return _remesh_refusal(d, d / "l.csv")


@case("tracebacks")
def landmarks_csv_nan(d):
    (d / "l.csv").write_text("nose_tip,nan\n")
    return _remesh_refusal(d, d / "l.csv")


@case("tracebacks")
def landmarks_json_huge_id(d):
    from jface.mesh import LANDMARK_NAMES

    marks = {name: 0 for name in LANDMARK_NAMES}
    marks["chin"] = 10**30
    (d / "l.json").write_text(json.dumps(marks))
    return _remesh_refusal(d, d / "l.json")


@case("tracebacks")
def pores_json_without_positions(d):
    params = _params(d / "p.json")
    (d / "pores.json").write_text(json.dumps({"kind": "Pores"}))
    argv = ["wrinkles", "render", "--params", params, "--pores", d / "pores.json", "--out",
            d / "o.exr", "--size", "64", "--steps", "2"]  # fmt: skip
    return refusal(d, argv, [params, d / "pores.json"], [d / "o.exr"], names=["pores.json"])


@case("tracebacks")
def pores_json_wrong_shape(d):
    params = _params(d / "p.json")
    (d / "pores.json").write_text(json.dumps({"kind": "Pores", "positions": [[0.1, 0.2, 0.3]]}))
    argv = ["wrinkles", "render", "--params", params, "--pores", d / "pores.json", "--out",
            d / "o.exr", "--size", "64", "--steps", "2"]  # fmt: skip
    return refusal(d, argv, [params, d / "pores.json"], [d / "o.exr"], names=["pores.json"])


@case("tracebacks")
def params_json_1e400(d):
    (d / "p.json").write_text('{"kind": "WrinkleParams", "levels": [{"d": 0.05, "theta": 1e400}]}')
    argv = ["wrinkles", "render", "--params", d / "p.json", "--out", d / "o.exr", "--size", "64"]
    return refusal(d, argv, [d / "p.json"], [d / "o.exr"], names=["p.json"])


@case("tracebacks")
def params_json_huge_integer(d):
    (d / "p.json").write_text('{"kind": "WrinkleParams", "levels": [{"d": 1%s}]}' % ("0" * 400))
    argv = ["wrinkles", "render", "--params", d / "p.json", "--out", d / "o.exr", "--size", "64"]
    return refusal(d, argv, [d / "p.json"], [d / "o.exr"], names=["p.json"])


@case("tracebacks")
def params_json_huge_texture(d):
    (d / "p.json").write_text('{"kind": "WrinkleParams", "levels": [{"d": [[0.05, 0.05], [1]]}]}')
    argv = ["wrinkles", "render", "--params", d / "p.json", "--out", d / "o.exr", "--size", "64"]
    return refusal(d, argv, [d / "p.json"], [d / "o.exr"], names=["p.json"])


@case("tracebacks")
def cli_number_1e400(d):
    return refusal(d, ["wrinkles", "simulate", "--out", d / "o", "--samples", "1e400"], [], [])


@case("tracebacks")
def cli_float_1e400(d):
    m = io.write_exr(d / "m.exr", noise(64))
    argv = ["wrinkles", "fit", m, "--out", d / "o.json", "--d-range", "0.02", "1e400"]
    return refusal(d, argv, [m], [d / "o.json"])


@case("tracebacks")
def decompression_bomb_png(d):
    from PIL import Image

    path = d / "bomb.png"
    Image.new("L", (8, 8)).save(path)
    data = bytearray(path.read_bytes())
    data[16:24] = (30000).to_bytes(4, "big") * 2  # IHDR width and height
    data[29:33] = zlib.crc32(bytes(data[12:29])).to_bytes(4, "big")
    path.write_bytes(bytes(data))
    return refusal(d, ["analyze", path, "--out", d / "o"], [path], [d / "o"], names=["bomb.png"])


@case("tracebacks")
def npy_huge_declared_size(d):
    path = d / "huge.npy"
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (1000000, 1000000), }"
    header = header.ljust(118) + "\n"
    path.write_bytes(b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode())
    return refusal(d, ["analyze", path, "--out", d / "o"], [path], [d / "o"], names=["huge.npy"])


@case("tracebacks")
def ply_huge_declared_count(d):
    path = d / "huge.ply"
    path.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\n"
        b"property float y\nproperty float z\nelement face 1\n"
        b"property list uchar int vertex_indices\nend_header\n" + bytes(64)
    )
    m = io.write_exr(d / "m.exr", noise(32))
    argv = ["displace", path, m, "--out", d / "o.obj"]
    return refusal(d, argv, [path, m], [d / "o.obj"], names=["huge.ply"])


@case("tracebacks")
def nan_map_names_the_file(d):
    image = noise()
    image[3, 3] = np.nan
    m = io.write_exr(d / "nan.exr", image)
    return refusal(d, ["analyze", m, "--out", d / "o"], [m], [d / "o"], names=["nan.exr"])


@case("tracebacks")
def db_build_mixed_sizes(d):
    maps = [io.write_exr(d / "a.exr", noise()), io.write_exr(d / "b.exr", noise(64))]
    maps += [io.write_exr(d / f"c{i}.exr", noise()) for i in range(3)]
    argv = ["db", "build", *maps, "--out", d / "db.npz", "--chunk", "1", "--grid", "4",
            "--scales", "2"]  # fmt: skip
    result = refusal(d, argv, maps, [d / "db.npz"], names=["b.exr"])
    parts = d / "db.npz.parts"
    result["chunks_analysed_before_failing"] = len(list(parts.glob("*.npz"))) if parts.exists() \
        else 0  # fmt: skip
    result["ok"] = result["ok"] and result["chunks_analysed_before_failing"] == 0
    return result


# --- leftovers ------------------------------------------------------------------------------------

_KILLED_WRITER = """
import os, signal, sys
import numpy as np
from jface import io
with io.atomic_path(sys.argv[1]) as tmp:
    tmp.write_bytes(b"partial")
    os.kill(os.getpid(), signal.SIGKILL)
"""


@case("leftovers")
def kill_during_write(d):
    out = d / "o.exr"
    proc = subprocess.run([sys.executable, "-c", _KILLED_WRITER, str(out)], check=False)
    left = temporaries(d)
    m = io.write_exr(d / "m.exr", noise(32))
    code, _ = run_cli(["render", str(m), "--out", str(d / "o.png")])  # the next run, same folder
    after = temporaries(d)
    return {"killed": proc.returncode == -signal.SIGKILL, "left_after_kill": left,
            "left_after_next_run": after, "output_under_name": out.exists(),
            "ok": not out.exists() and not after and code == 0}  # fmt: skip


def main_(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", help="case names")
    args = parser.parse_args(argv)
    n_ok = 0
    for name, (section, fn) in CASES.items():
        if args.only and name not in args.only:
            continue
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            try:
                result = fn(d)
            except Exception as err:
                result = {"harness_error": f"{type(err).__name__}: {err}"[:240], "ok": False}
        n_ok += bool(result.get("ok"))
        print(json.dumps({"case": name, "section": section, **result}, default=str), flush=True)
    print(json.dumps({"cases": len(CASES) if not args.only else len(args.only), "ok": n_ok}))


if __name__ == "__main__":
    main_()
