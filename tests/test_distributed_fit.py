"""Distributed wrinkle fitting: the swarm's agents sharded over devices give the bits of the
unsharded swarm, ``jface wrinkles fit`` on several patches over processes gives the fits of one
patch at a time, reruns keep finished patches and refit changed ones, and bad set-ups fail with
messages that name what is wrong. Tiny settings (64² patches, few agents and epochs): most of
the time is compiling, shared through the persistent compilation cache of the command line."""

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from conftest import TINY_FIT, free_port, run_jface, run_with_process_counts

from jface import _distributed, io
from jface._distributed import deterministic_cpu_flags
from jface.cli import main
from jface.cli._processes import spread
from jface.wrinkles import fit_wrinkles

#: A fit small enough to compile and run in well under a minute on two cores.
FIT = [*TINY_FIT, "--iters", "2"]
#: Every process of these tests runs XLA's CPU code the one deterministic way (as the command's
#: own processes do), so that the persistent compilation cache serves all of them.
FLAGS = deterministic_cpu_flags(os.environ.get("XLA_FLAGS", ""))

# One process with 4 virtual CPU devices fits a patch with its 6 agents on one device and
# sharded over 4 (padded to 8 with copies of agent 0), and prints both results and how often
# the swarm's loss and the refinement were compiled.
SHARDED = """
import json, logging, sys
import jax, numpy as np
from jface.wrinkles import fit_wrinkles
from jface.wrinkles._fit import SHARD_FROM, _agent_mesh
patch = np.load(sys.argv[1])
assert len(jax.local_devices()) == 4
# by default: one device for a small swarm, one per agent at most for a large one
assert _agent_mesh(None, 50, SHARD_FROM - 1) is None
assert _agent_mesh(None, 50, SHARD_FROM).size == 4 and _agent_mesh(None, 3, SHARD_FROM).size == 3
compiled = []
class Compiles(logging.Handler):
    def emit(self, record):
        compiled.append(record.getMessage().split(" with ")[0])
logging.getLogger("jax").addHandler(Compiles())
jax.config.update("jax_log_compiles", True)
kwargs = dict(n_agents=6, n_epochs=2, n_trials=1, n_steps=5, d_levels=2, refine_steps=2,
              d_range=(0.04, 0.05))
out = {}
for name, devices in (("one", jax.local_devices()[:1]), ("four", jax.local_devices())):
    fit = fit_wrinkles(jax.random.key(3), patch, devices=devices, **kwargs)
    out[name] = {"params": np.asarray(fit.swarm.params).tobytes().hex(),
                 "history": np.asarray(fit.swarm.history).tobytes().hex(),
                 "loss": float(fit.swarm_loss), "refined": float(fit.loss),
                 "heldout": np.asarray(fit.heldout_losses).tobytes().hex()}
out["compiles"] = {name: compiled.count(f"Compiling jit({name})")
                   for name in ("swarm_evaluate", "_refined")}
print(json.dumps(out))
"""


def crops(gravel, n):
    """``n`` different 64² crops of the real gravel texture."""
    return [gravel[64 * i : 64 * i + 64, 32 : 32 + 64].astype(np.float32) for i in range(n)]


@pytest.fixture(scope="module")
def patches(gravel, tmp_path_factory):
    folder = tmp_path_factory.mktemp("patches")
    return [str(io.write_exr(folder / f"p{i}.exr", c)) for i, c in enumerate(crops(gravel, 3))]


def jface(*argv, timeout=400):
    """``jface ARGV`` in a process of its own with the deterministic CPU flags."""
    return run_jface(*argv, env={"XLA_FLAGS": FLAGS}, timeout=timeout)


def without_provenance(path):
    document = json.loads(Path(path).read_text())
    document.pop("provenance")
    return document


def test_sharded_swarm_equals_the_unsharded_one(gravel, tmp_path):
    np.save(tmp_path / "patch.npy", crops(gravel, 1)[0])
    env = dict(os.environ, XLA_FLAGS=f"{FLAGS} --xla_force_host_platform_device_count=4")
    done = subprocess.run(
        [sys.executable, "-c", SHARDED, str(tmp_path / "patch.npy")],
        env=env, capture_output=True, text=True, timeout=400,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    runs = json.loads(done.stdout.strip().splitlines()[-1])
    # the same bits: best parameters, loss history, refined and held-out losses
    assert runs["one"] == runs["four"]
    assert np.isfinite(runs["one"]["loss"])
    # one swarm loss per mesh, whatever placement the sharded epochs leave the positions in
    # (held-out keys included), and one refinement for both (the bests come from the host)
    assert runs["compiles"] == {"swarm_evaluate": 2, "_refined": 1}


def test_a_command_run_alone_gets_a_cpu_device_per_core(monkeypatch):
    alone = argparse.Namespace(processes=1, coordinator=None, process_id=None,
                               num_processes=None, cluster=False, timeout=1.0)  # fmt: skip
    cores = len(os.sched_getaffinity(0))
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")
    assert spread(alone, []) is False  # this process does the work
    assert os.environ["XLA_FLAGS"].split() == [
        "--xla_backend_optimization_level=0",
        "--xla_cpu_multi_thread_eigen=false",
        f"--xla_force_host_platform_device_count={cores}",
    ]
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=3")  # the user's
    spread(alone, [])
    assert os.environ["XLA_FLAGS"].count("device_count") == 1
    assert "device_count=3" in os.environ["XLA_FLAGS"]
    # a process of a jax.distributed run gets the deterministic threads alone
    monkeypatch.setattr(_distributed, "join_processes", lambda *args, **kwargs: None)
    monkeypatch.setenv("XLA_FLAGS", "")
    joined = argparse.Namespace(**{**vars(alone), "coordinator": "localhost:1", "process_id": 0,
                                   "num_processes": 2})  # fmt: skip
    assert spread(joined, []) is False
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_multi_thread_eigen=false"


# Single-patch commands one after the other in one process (which compiles the fit once).
SEQUENTIAL = """
import json, sys
from jface.cli import main
fit, patches, outs = json.loads(sys.argv[1])
for patch, out in zip(patches, outs):
    if main(["wrinkles", "fit", patch, "--out", out, *fit]) != 0:
        sys.exit(1)
"""


@pytest.fixture(scope="module")
def sequential(patches, tmp_path_factory):
    """The three patches fitted one at a time, each by a single-patch command."""
    folder = tmp_path_factory.mktemp("sequential")
    outs = [folder / f"{Path(patch).stem}.json" for patch in patches]
    done = subprocess.run(
        [sys.executable, "-c", SEQUENTIAL, json.dumps([FIT, patches, [str(o) for o in outs]])],
        env=dict(os.environ, XLA_FLAGS=FLAGS), capture_output=True, text=True, timeout=400,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return outs


def test_two_processes_fit_three_patches_like_three_single_fits(patches, sequential, tmp_path):
    out = tmp_path / "fits"
    done = jface("wrinkles", "fit", *patches, "--out", str(out), *FIT, "--processes", "2",
                 "--json")  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout)  # one JSON object, from process 0 alone
    assert (summary["fitted"], summary["kept"]) == (3, 0)
    assert [Path(p["out"]).name for p in summary["patches"]] == ["p0.json", "p1.json", "p2.json"]
    for one in sequential:
        ours = out / one.name
        assert without_provenance(ours) == without_provenance(one)
        for suffix in ("_convergence.png", "_target_fit.png"):
            assert (out / f"{one.stem}{suffix}").is_file()
    page = (out / "index.html").read_text()
    assert all(f"p{i}_target_fit.png" in page for i in range(3))  # one page lists every patch


def test_rerun_keeps_finished_patches_and_refits_a_changed_one(patches, sequential, tmp_path):
    out = tmp_path / "fits"
    out.mkdir()
    for one in sequential:  # finished fits of an earlier run, with their figures
        for suffix in (".json", "_convergence.png", "_target_fit.png"):
            name = f"{one.stem}{suffix}"
            (out / name).write_bytes((one.parent / name).read_bytes())
    changed = tmp_path / "p1.exr"  # the same name, new content
    io.write_exr(changed, np.asarray(io.read_map(patches[1])).T.copy())
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    done = jface("wrinkles", "fit", patches[0], str(changed), patches[2], "--out", str(out),
                 *FIT, "--json")  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout)
    assert [p["kept"] for p in summary["patches"]] == [True, False, True]
    assert (summary["fitted"], summary["kept"]) == (1, 2)
    assert (out / "p0.json").stat().st_mtime_ns == before["p0.json"]
    assert (out / "p2.json").stat().st_mtime_ns == before["p2.json"]
    refit = json.loads((out / "p1.json").read_text())
    assert refit["fit"]["key"] != json.loads(sequential[1].read_text())["fit"]["key"]
    again = jface("wrinkles", "fit", patches[0], str(changed), patches[2], "--out", str(out),
                  *FIT, "--json")  # fmt: skip
    assert json.loads(again.stdout)["kept"] == 3


def test_bad_devices_name_the_argument(unchecked):
    patch = np.eye(64, dtype=np.float32)
    with pytest.raises(ValueError, match=r"devices must be a non-empty sequence .* got \[\]"):
        fit_wrinkles(jax.random.key(0), patch, devices=[])
    with pytest.raises(ValueError, match=r"devices must be .*'cpu:0' among them"):
        fit_wrinkles(jax.random.key(0), patch, devices=["cpu:0"])
    with pytest.raises(TypeError, match=r"devices must be .* got \w*Device"):
        fit_wrinkles(jax.random.key(0), patch, devices=jax.devices()[0])
    twice = [jax.devices()[0]] * 2
    with pytest.raises(ValueError, match="devices must be a non-empty sequence of distinct"):
        fit_wrinkles(jax.random.key(0), patch, devices=twice)


def test_out_clashing_with_an_input_is_refused(patches, tmp_path, capsys):
    folder = tmp_path / "in"
    folder.mkdir()
    a, b = folder / "a.npy", folder / "a_convergence.png"
    np.save(a, np.eye(64, dtype=np.float32))
    io.write_png(b, np.eye(64, dtype=np.float32))
    assert main(["wrinkles", "fit", str(a), str(b), "--out", str(folder), *FIT]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jface wrinkles fit: error: refusing to overwrite the input file")
    assert "a_convergence.png" in err
    assert main(["wrinkles", "fit", patches[0], "--out", patches[0], *FIT]) == 2
    assert f"--out {patches[0]} is the input patch" in capsys.readouterr().err
    assert main(["wrinkles", "fit", *patches[:2], "--out", str(tmp_path / "x.json")]) == 2
    assert "--out must be a folder when fitting 2 patches" in capsys.readouterr().err
    assert sorted(p.name for p in folder.iterdir()) == ["a.npy", "a_convergence.png"]


def test_unreachable_coordinator_fails_fast(patches, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    argv = ["wrinkles", "fit", *patches, "--out", str(tmp_path / "fits"), *FIT]
    argv += ["--coordinator", f"127.0.0.1:{free_port()}", "--process-id", "1"]
    start = time.monotonic()
    assert main([*argv, "--num-processes", "2", "--timeout", "2"]) == 2
    assert time.monotonic() - start < 20
    err = capsys.readouterr().err
    assert "jface wrinkles fit: error: cannot reach the coordinator 127.0.0.1" in err
    assert not (tmp_path / "fits").exists()


def test_bad_process_options_are_refused(patches, tmp_path, capsys):
    argv = ["wrinkles", "fit", *patches, "--out", str(tmp_path / "fits"), *FIT]
    assert main([*argv, "--processes", "2", "--process-id", "0"]) == 2
    assert "--processes must be at least 1 and goes without --coordinator" in (
        capsys.readouterr().err
    )
    assert main([*argv, "--processes", "0"]) == 2
    assert "got --processes 0" in capsys.readouterr().err


def test_mismatched_process_counts_are_refused(patches, tmp_path):
    argv = ["wrinkles", "fit", *patches, "--out", str(tmp_path / "fits"), *FIT]
    argv += ["--coordinator", f"127.0.0.1:{free_port()}", "--timeout", "10"]
    for status, err in run_with_process_counts(argv, ("2", "3")):
        assert status == 2
        assert "jface wrinkles fit: error: the processes were given different process counts" in err
    assert not (tmp_path / "fits").exists()
