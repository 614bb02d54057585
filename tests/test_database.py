"""Statistics database: batch analysis sharded over devices, resumable builds."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jface import detail, io


@pytest.fixture(scope="module")
def maps(gravel, brick):
    crops = [
        gravel[:128, :128],
        gravel[128:256, :128],
        brick[:128, :128],
        brick[:128, 128:256],
        gravel[256:384, 256:384],
    ]
    return np.stack(crops).astype(np.float32)


def test_batch_equals_loop(maps):
    batch = detail.analyze_batch(maps, grid=8, n_scales=3)
    for i, image in enumerate(maps):
        np.testing.assert_allclose(
            batch.std[i], detail.analyze(image, grid=8, n_scales=3).std, rtol=1e-5
        )


def test_sharded_equals_unsharded(maps, tmp_path):
    """Four host devices (a separate process: XLA reads the flag at start-up)."""
    np.save(tmp_path / "maps.npy", maps)
    script = textwrap.dedent(
        f"""
        import jax, numpy as np
        from jface import detail
        maps = np.load({str(tmp_path / "maps.npy")!r})
        assert len(jax.devices()) == 4, jax.devices()
        stats = detail.analyze_batch(maps, grid=8, n_scales=3)
        np.save({str(tmp_path / "sharded.npy")!r}, np.asarray(stats.std))
        """
    )
    flags = f"{os.environ['XLA_FLAGS']} --xla_force_host_platform_device_count=4"
    env = dict(os.environ, XLA_FLAGS=flags)
    subprocess.run([sys.executable, "-c", script], check=True, env=env, cwd=Path.cwd())
    unsharded = detail.analyze_batch(maps, grid=8, n_scales=3, devices=jax.devices()[:1])
    np.testing.assert_allclose(np.load(tmp_path / "sharded.npy"), unsharded.std, rtol=1e-5)


def test_build_database_resumes(maps, tmp_path, monkeypatch):
    paths = []
    for i, image in enumerate(maps):
        paths.append(io.write_exr(tmp_path / f"face{i}.exr", image))
    records = [{"id": f"face{i}", "age": 20 + 10 * i, "sex": "fm"[i % 2]} for i in range(5)]
    out = tmp_path / "db.npz"

    calls = []
    original = detail._database.analyze_batch

    def dies_on_third_chunk(images, **kwargs):
        calls.append(len(images))
        if len(calls) == 3:
            raise RuntimeError("simulated crash")
        return original(images, **kwargs)

    monkeypatch.setattr(detail._database, "analyze_batch", dies_on_third_chunk)
    with pytest.raises(RuntimeError, match="simulated crash"):
        detail.build_database(
            paths, out, records=records, grid=8, n_scales=3, chunk=2, progress=False
        )
    assert len(list((tmp_path / "db.npz.parts").glob("*.npz"))) == 2  # 4 faces kept
    calls.clear()
    population = detail.build_database(
        paths, out, records=records, grid=8, n_scales=3, chunk=2, progress=False
    )
    assert calls == [1]  # only the unfinished chunk ran again
    assert not (tmp_path / "db.npz.parts").exists()
    loaded = detail.Population.load(out)
    assert [r["id"] for r in loaded.records] == [f"face{i}" for i in range(5)]
    np.testing.assert_allclose(loaded.stats.std, population.stats.std)
    expected = detail.analyze_batch(maps, grid=8, n_scales=3)
    np.testing.assert_allclose(loaded.stats.std, expected.std, rtol=1e-6)
    assert len(loaded.select(sex="f")) == 3


def test_bad_input(unchecked, maps, tmp_path):
    with pytest.raises(ValueError, match="images must have 3 axes"):
        detail.analyze_batch(maps[0])
    with pytest.raises(ValueError, match="at least one map"):
        detail.build_database([], tmp_path / "x.npz")
    with pytest.raises(FileNotFoundError, match="not found"):
        detail.build_database([tmp_path / "missing.exr"], tmp_path / "x.npz")
    path = io.write_exr(tmp_path / "a.exr", maps[0])
    with pytest.raises(ValueError, match="one record per map"):
        detail.build_database([path], tmp_path / "x.npz", records=[], grid=8, n_scales=3)
    with pytest.raises(ValueError, match="grid=16 must split"):
        detail.analyze_batch(jnp.zeros((2, 100, 100)))
