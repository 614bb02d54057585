"""The command line's one vocabulary: help with defaults, deprecated spellings, --json, and face
folders of ``jface remesh`` accepted where maps are."""

import argparse
import json

import numpy as np
import pytest

from jface import detail, io
from jface.cli import _leaves, build_parser, main
from jface.cli._apps import _target
from jface.cli._detail import parse_group


def _options(parser):
    for action in parser._actions:
        if action.option_strings and not isinstance(action, argparse._HelpAction):
            yield action


def test_every_option_has_help_showing_its_default_or_that_it_is_required():
    leaves = list(_leaves(build_parser()))
    assert len(leaves) == 24  # every command, sub-commands and the hidden `fit` included
    missing = [
        f"{leaf.prog} {action.option_strings[0]}"
        for leaf in leaves
        for action in _options(leaf)
        if action.help != argparse.SUPPRESS
        and not ("default" in (action.help or "") or (action.help or "").endswith("(required)"))
    ]
    assert missing == []
    for leaf in leaves:  # the help renders (a stray % in a help text would raise here)
        assert "--json" in leaf.format_help()
    remesh = next(leaf for leaf in leaves if leaf.prog == "jface remesh")
    assert [a.help for a in remesh._actions if "--out" in a.option_strings] == [
        "output folder (required)"
    ]


@pytest.mark.parametrize(
    ("argv", "dest", "value", "old", "new"),
    [
        (["synthesize", "m.exr", "--stats", "s.npz", "--out", "o.exr", "--n-iter", "3"],
         "iters", 3, "--n-iter", "--iters"),
        (["add-detail", "f", "--stats", "s.npz", "--out", "o", "--n-iter", "3"],
         "iters", 3, "--n-iter", "--iters"),
        (["remesh", "scan.obj", "--out-dir", "d"], "out", "d", "--out-dir", "--out"),
        (["wrinkles", "fit", "p.exr", "--out", "p.json", "--epochs", "7"],
         "epochs", 7, "--epochs", "--iters"),
        (["faces", "align", "a.png", "--out", "d", "--max-steps", "9"],
         "iters", 9, "--max-steps", "--iters"),
        (["db", "compare", "db.npz", "--group", "a:x=1", "--out", "c.png", "--scale", "2"],
         "show_scale", 2, "--scale", "--show-scale"),
        (["wrinkles", "extract", "c.exr", "--out", "p.json", "--pores-out", "q.json"],
         "pores_out", "q.json", "--pores-out", "--out"),
    ],
)  # fmt: skip
def test_deprecated_spellings_store_like_the_new_one_with_one_notice(
    argv, dest, value, old, new, capsys
):
    args = build_parser().parse_args(argv)
    assert getattr(args, dest) == value
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"jface: {old} is deprecated; use {new}")
    if old != "--pores-out":  # the new spelling parses to the same value, silently
        renamed = build_parser().parse_args([new if a == old else a for a in argv])
        assert getattr(renamed, dest) == value and capsys.readouterr().err == ""


def test_old_spellings_are_hidden_and_new_ones_shown():
    parser = build_parser()
    helps = {leaf.prog: leaf.format_help() for leaf in _leaves(parser)}
    assert "--iters" in helps["jface synthesize"] and "--n-iter" not in helps["jface synthesize"]
    assert "--out-dir" not in helps["jface remesh"]
    assert "--pores-out" not in helps["jface wrinkles extract"]
    assert "--epochs" not in helps["jface wrinkles fit"]
    assert " fit " not in parser.format_help()  # jface fit: a hidden deprecated command
    wrinkles = parser._subparsers._group_actions[0].choices["wrinkles"]
    assert "fit" in wrinkles.format_help()


def test_jface_fit_is_a_deprecated_alias_of_wrinkles_fit(capsys):
    old = build_parser().parse_args(["fit", "p.exr", "--out", "p.json", "--iters", "2"])
    new = build_parser().parse_args(["wrinkles", "fit", "p.exr", "--out", "p.json", "--iters", "2"])
    assert old.run is new.run and old.epochs == new.epochs == 2
    assert main(["fit", "missing.exr", "--out", "p.json"]) == 2  # runs the fit: refuses the input
    err = capsys.readouterr().err.splitlines()
    assert err[0] == "jface: fit is deprecated; use wrinkles fit"
    assert "missing.exr" in err[1]


def test_json_prints_one_object_prose_otherwise(tmp_path, capsys):
    m = io.write_exr(tmp_path / "m.exr", np.random.default_rng(0).random((32, 32), np.float32))
    out = tmp_path / "stats"
    argv = ["analyze", str(m), "--out", str(out), "--grid", "4", "--scales", "2"]
    assert main([*argv, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary == {"out": str(out), "analyzed": 1, "kept": 0}
    assert main(argv) == 0
    assert capsys.readouterr().out.startswith("analyzed 0 map(s), kept 1 already done")


def test_remesh_folders_are_maps_named_by_folder(tmp_path, capsys):
    rng = np.random.default_rng(1)
    folders = []
    for name in ("alice", "bob"):
        (tmp_path / "faces" / name).mkdir(parents=True)
        io.write_exr(tmp_path / "faces" / name / "displacement.exr", rng.random((32, 32), "f4"))
        folders.append(str(tmp_path / "faces" / name))
    small = ["--grid", "4", "--scales", "2"]
    assert main(["analyze", *folders, "--out", str(tmp_path / "stats"), *small]) == 0
    for name, folder in zip(("alice", "bob"), folders, strict=True):
        saved = detail.load_stats(tmp_path / "stats" / f"{name}.stats.npz")
        stats, meta = saved.stats, saved.metadata
        expected = detail.analyze(io.read_map(f"{folder}/displacement.exr"), grid=4, n_scales=2)
        np.testing.assert_allclose(stats.std, expected.std, rtol=1e-6)
        assert meta["source"] == f"{name}/displacement.exr"
    # the maps themselves share one name: refused before any work, naming both
    maps = [f"{f}/displacement.exr" for f in folders]
    assert main(["analyze", *maps, "--out", str(tmp_path / "s2"), *small]) == 2
    err = capsys.readouterr().err
    assert f"{maps[0]} and {maps[1]} would both write the output" in err
    assert not (tmp_path / "s2").exists()
    db = tmp_path / "db.npz"
    assert main(["db", "build", *folders, "--out", str(db), *small, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["faces"] == 2
    assert [r["id"] for r in detail.Population.load(db).records] == ["alice", "bob"]
    assert main(["analyze", str(tmp_path / "faces"), "--out", str(tmp_path / "s3")]) == 2
    assert "without displacement.exr" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("spec", "name", "criteria"),
    [
        ("old:age=50..60", "old", {"age": (50.0, 60.0)}),
        ("age=50..60", "age=50..60", {"age": (50.0, 60.0)}),  # named by its criteria
        ("f:sex=f,age=30", "f", {"sex": "f", "age": 30}),
        ("id=a:b", "id=a:b", {"id": "a:b"}),  # a colon after '=' is part of the value
    ],
)
def test_group_spellings(spec, name, criteria):
    assert parse_group(spec) == (name, criteria)


@pytest.mark.parametrize(
    ("spec", "why"),
    [
        ("old", "'old' is not FIELD=VALUE"),
        ("old:", "got 'old:'"),
        (":age=1", "got ':age=1'"),
        ("old:age=x..y", "'x..y' is not a range LOW..HIGH"),
    ],
)
def test_bad_group_names_the_option_and_the_expected_form(spec, why):
    with pytest.raises(ValueError, match=r"--group must look like \[NAME:\]FIELD=VALUE") as err:
        parse_group(spec)
    assert why in str(err.value) and "e.g. 'old:age=50..60'" in str(err.value)


def test_one_group_syntax_in_db_compare_add_detail_and_age(tmp_path, gravel, capsys):
    maps = [io.write_exr(tmp_path / f"f{i}.exr", gravel[:64, :64] * (1 + i)) for i in range(4)]
    io.write_json(tmp_path / "meta.json", [{"id": f"f{i}", "age": 20 + 15 * i} for i in range(4)])
    db = tmp_path / "db.npz"
    build = ["db", "build", *map(str, maps), "--metadata", str(tmp_path / "meta.json")]
    assert main([*build, "--out", str(db), "--grid", "4", "--scales", "2"]) == 0
    capsys.readouterr()
    # db compare: a named group beside one named by its criteria
    png = tmp_path / "c.png"
    groups = ["--group", "young:age=20..40", "--group", "age=41..80"]
    assert main(["db", "compare", str(db), *groups, "--out", str(png), "--show-scale", "0"]) == 0
    table = io.read_json(png.with_suffix(".json"))
    assert table["reference"] == "young" and table["age=41..80"]["faces"] == 2
    same = ["--group", "age=20..40", "--group", "age=20..40"]
    assert main(["db", "compare", str(db), *same, "--out", str(tmp_path / "d.png")]) == 2
    assert "two --group options name the group 'age=20..40'" in capsys.readouterr().err

    # add-detail and age: the target group with or without a name, the same statistics
    def target(spec):
        return _target(argparse.Namespace(db=str(db), group=spec, stats=None, target=None), None)

    np.testing.assert_array_equal(target("age=41..80")[0].std, target("old:age=41..80")[0].std)
    with pytest.raises(ValueError, match=r"--group must look like \[NAME:\]FIELD=VALUE"):
        target("age")


def test_time_estimate_once_from_the_second_unit_and_only_for_long_runs(monkeypatch, capsys):
    from jface import _progress

    clock = iter([0.0, 20.0, 0.0, 1.0])  # the clock at each update that reads it
    monkeypatch.setattr(_progress.time, "perf_counter", lambda: next(clock))
    slow = _progress.Estimate(12, "map")
    slow.skip(2)  # kept from an earlier run
    for _ in range(5):  # the first pays compilation; the second's 20 s per map is the cost
        slow.update(1)
    assert capsys.readouterr().err == "about 3 min for the remaining 8 maps\n"
    quick = _progress.Estimate(10, "row")
    quick.update(1)
    quick.update(1)  # 1 s per row, 8 rows left: not worth a line
    assert capsys.readouterr().err == ""
