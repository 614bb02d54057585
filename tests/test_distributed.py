"""Database builds over several jax.distributed processes: the same bytes as one process,
resumable after a killed process, and clear errors for bad set-ups."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import free_port, run_with_process_counts
from conftest import run_jface as jface

from jface import detail, io
from jface.cli import main

LAYOUT = ["--grid", "4", "--scales", "2", "--chunk", "2"]

# A process of `jface db build` whose chunk analysis can be slowed down and logged, so a test
# can stop it midway and see which chunks a rerun analyses again.
WORKER = """
import os, sys, time
from jface.detail import _database
real = _database.analyze_batch
def logged(images, **kwargs):
    time.sleep(float(os.environ.get("JFACE_TEST_DELAY", "0")))
    with open(os.environ["JFACE_TEST_LOG"], "a") as log:
        log.write(f"{float(images[0, 0, 0])!r}\\n")
    return real(images, **kwargs)
_database.analyze_batch = logged
from jface.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.fixture(scope="module")
def maps(tmp_path_factory, gravel, brick):
    """16 small real maps (gravel and brick crops)."""
    folder = tmp_path_factory.mktemp("maps")
    paths = []
    for i in range(16):
        source = gravel if i % 2 else brick
        y, x = divmod(i, 4)
        crop = source[y * 64 : y * 64 + 64, x * 64 : x * 64 + 64].astype(np.float32)
        paths.append(str(io.write_exr(folder / f"m{i:02d}.exr", crop)))
    return paths


@pytest.fixture(scope="module")
def one_process(maps, tmp_path_factory):
    out = tmp_path_factory.mktemp("one") / "db.npz"
    done = jface("db", "build", *maps, "--out", str(out), *LAYOUT)
    assert done.returncode == 0, done.stderr
    return out


def test_builds_are_byte_identical(maps, one_process, tmp_path):
    again = tmp_path / "again.npz"
    other_chunks = tmp_path / "chunk5.npz"
    assert jface("db", "build", *maps, "--out", str(again), *LAYOUT).returncode == 0
    chunk5 = jface("db", "build", *maps, "--out", str(other_chunks), *LAYOUT[:4], "--chunk", "5")
    assert chunk5.returncode == 0, chunk5.stderr
    assert again.read_bytes() == one_process.read_bytes()
    assert other_chunks.read_bytes() == one_process.read_bytes()


def test_two_processes_equal_one(maps, one_process, tmp_path):
    out = tmp_path / "db.npz"
    done = jface("db", "build", *maps, "--out", str(out), *LAYOUT, "--processes", "2")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"16 faces in {out}"  # process 0 alone reports
    assert out.read_bytes() == one_process.read_bytes()
    ours, reference = detail.Population.load(out), detail.Population.load(one_process)
    assert ours.records == reference.records
    np.testing.assert_array_equal(ours.stats.std, reference.stats.std)
    assert not out.with_name("db.npz.parts").exists()


def test_killed_process_resumes(maps, one_process, tmp_path):
    out = tmp_path / "db.npz"
    port = free_port()
    logs = [tmp_path / f"log{i}" for i in range(2)]
    workers = []
    for i in range(2):
        env = dict(
            os.environ,
            JFACE_TEST_LOG=str(logs[i]),
            JFACE_TEST_DELAY="0" if i == 0 else "1.5",
        )
        argv = ["db", "build", *maps, "--out", str(out), *LAYOUT, "--timeout", "5"]
        argv += ["--coordinator", f"127.0.0.1:{port}", "--process-id", str(i)]
        argv += ["--num-processes", "2"]
        workers.append(
            subprocess.Popen(
                [sys.executable, "-c", WORKER, *argv], env=env, stderr=subprocess.DEVNULL
            )
        )
    parts = tmp_path / "db.npz.parts"
    deadline = time.monotonic() + 25
    # process 1 has chunks 1, 3, 5, 7 (maps 2-3, 6-7, ...): stop it after its first
    while not list(parts.glob("00000002-*.npz")) and time.monotonic() < deadline:
        time.sleep(0.05)
    workers[1].send_signal(signal.SIGKILL)
    for worker in workers:  # process 0 finds its peer gone within the heartbeat timeout
        worker.wait(timeout=30)
    assert workers[0].returncode != 0 and not out.exists()
    kept = sorted(p.name[:8] for p in parts.glob("*.npz"))
    assert "00000002" in kept and len(kept) < 8

    for log in logs:
        log.unlink(missing_ok=True)
    port = free_port()
    for i in range(2):
        env = dict(os.environ, JFACE_TEST_LOG=str(logs[i]))
        argv = ["db", "build", *maps, "--out", str(out), *LAYOUT, "--timeout", "10"]
        argv += ["--coordinator", f"127.0.0.1:{port}", "--process-id", str(i)]
        workers[i] = subprocess.Popen(
            [sys.executable, "-c", WORKER, *argv, "--num-processes", "2"], env=env
        )
    for worker in workers:
        assert worker.wait(timeout=30) == 0
    analysed = sum(len(log.read_text().split()) for log in logs if log.exists())
    assert analysed == 8 - len(kept)  # only the chunks not finished before the kill
    assert out.read_bytes() == one_process.read_bytes()


def test_unreachable_coordinator_fails_fast(maps, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    argv = ["db", "build", *maps[:2], "--out", str(tmp_path / "db.npz"), *LAYOUT]
    argv += ["--coordinator", f"127.0.0.1:{free_port()}", "--process-id", "1"]
    start = time.monotonic()
    assert main([*argv, "--num-processes", "2", "--timeout", "2"]) == 2
    assert time.monotonic() - start < 20  # the 2 s timeout, not the 300 s of JAX's default
    assert "cannot reach the coordinator 127.0.0.1" in capsys.readouterr().err


def test_mismatched_process_counts_are_refused(maps, tmp_path):
    port = free_port()
    argv = ["db", "build", *maps[:4], "--out", str(tmp_path / "db.npz"), *LAYOUT]
    argv += ["--coordinator", f"127.0.0.1:{port}", "--timeout", "10"]
    for status, err in run_with_process_counts(argv, ("2", "3")):
        assert status == 2
        assert "different process counts: ['2', '3']" in err
    assert not (tmp_path / "db.npz").exists()


def test_bad_flags(maps, tmp_path):
    with pytest.raises(ValueError, match=r"process_id must be in \[0, 1\], got 2"):
        detail.join_processes("127.0.0.1:1234", 2, 2)
    with pytest.raises(ValueError, match="go together"):
        detail.join_processes("127.0.0.1:1234", None, 2)
    with pytest.raises(ValueError, match="HOST:PORT"):
        detail.join_processes("localhost", 0, 2)
    with pytest.raises(ValueError, match="processes must be in"):
        detail.run_local_processes(["db"], 0)


def test_database_of_another_layout_or_version_is_kept(maps, one_process, tmp_path, monkeypatch):
    out = tmp_path / "db.npz"
    out.write_bytes(one_process.read_bytes())
    with pytest.raises(ValueError, match=r"another version or layout: grid 4 \(now 2\)"):
        detail.build_database(maps, out, grid=2, n_scales=2, progress=False)
    monkeypatch.setattr("jface.__version__", "9.9")
    with pytest.raises(ValueError, match=r"jface_version '0\.1\.0' \(now '9\.9'\)"):
        detail.build_database(maps, out, grid=4, n_scales=2, progress=False)
    assert out.read_bytes() == one_process.read_bytes()


def test_a_failing_process_stops_the_others(maps, tmp_path):
    port = free_port()
    entry = "import sys; from jface.cli import main; sys.exit(main())"
    workers = []
    for i, last in ((0, maps[2]), (1, str(tmp_path / "missing.exr"))):
        argv = ["db", "build", *maps[:2], last, "--out", str(tmp_path / "db.npz"), *LAYOUT]
        argv += ["--coordinator", f"127.0.0.1:{port}", "--process-id", str(i)]
        argv += ["--num-processes", "2", "--timeout", "10"]
        workers.append(
            subprocess.Popen(
                [sys.executable, "-c", entry, *argv], stderr=subprocess.PIPE, text=True
            )
        )
    errors = [worker.communicate(timeout=30)[1] for worker in workers]
    assert [worker.returncode for worker in workers] == [2, 2]
    assert "process 1 failed: 1 source map(s) not found" in errors[0]
    assert "missing.exr" in errors[1]


def test_cluster_outside_a_cluster_job_is_refused(maps, tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SLURM_", "OMPI_", "PMI"))}
    entry = "import sys; from jface.cli import main; sys.exit(main())"
    argv = ["db", "build", *maps[:2], "--out", str(tmp_path / "db.npz"), *LAYOUT, "--cluster"]
    done = subprocess.run(
        [sys.executable, "-c", entry, *argv], env=env, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 2
    assert "found no cluster job to join" in done.stderr


def test_a_map_changed_during_the_build_is_refused(maps, tmp_path, monkeypatch):
    paths = [tmp_path / f"m{i}.exr" for i in range(4)]
    for path, source in zip(paths, maps, strict=False):
        path.write_bytes(Path(source).read_bytes())
    real = io.read_map

    def read_then_edit(path, *args, **kwargs):  # another program rewrites m2 as it is read
        image = real(path, *args, **kwargs)
        if str(path).endswith("m2.exr"):
            Path(path).write_bytes(Path(path).read_bytes() + b"edit")
        return image

    monkeypatch.setattr(io, "read_map", read_then_edit)
    with pytest.raises(ValueError, match=r"m2\.exr, .*m3\.exr changed while the build ran"):
        detail.build_database(paths, tmp_path / "db.npz", grid=4, n_scales=2, chunk=2)
    assert len(list((tmp_path / "db.npz.parts").glob("*.npz"))) == 1  # the first chunk stays
