"""The decimated bunny is remembered on disk (``<cache root>/meshes``): what is read back is the
decimation bit for bit, a damaged file is decimated again, and a cache that cannot be written
costs nothing but the time."""
import os
import time

import numpy as np
import pytest

from psdr_cli.scene import meshes


@pytest.fixture
def cache_home(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    meshes.decimated_bunny.cache_clear()
    yield tmp_path / "cache"
    meshes.decimated_bunny.cache_clear()


def test_a_cached_bunny_is_the_decimation_and_is_not_decimated_again(cache_home, monkeypatch):
    V, F = meshes.decimated_bunny(300)
    fresh = meshes.decimate_bunny(300)
    assert np.array_equal(V, fresh[0]) and np.array_equal(F, fresh[1]) and V.dtype == np.float64 and F.dtype == np.int64
    assert meshes.cached_bunny_path(300).is_relative_to(cache_home / "psdr" / "meshes")
    meshes.decimated_bunny.cache_clear()  # as a new process

    def decimate(faces):
        raise AssertionError("decimated again although the cache holds the mesh")

    monkeypatch.setattr(meshes, "decimate_bunny", decimate)
    V2, F2 = meshes.decimated_bunny(300)
    assert np.array_equal(V, V2) and np.array_equal(F, F2) and not V2.flags.writeable


DAMAGES = ["truncated", "garbage", "bad-index", "npy-not-npz", "bad-compressed-data", "non-finite"]


@pytest.mark.parametrize("damage", DAMAGES)
def test_a_damaged_cached_bunny_is_decimated_again(cache_home, damage):
    V, F = meshes.decimated_bunny(300)
    path = meshes.cached_bunny_path(300)
    if damage == "truncated":
        path.write_bytes(path.read_bytes()[:200])
    elif damage == "garbage":
        path.write_bytes(b"not a mesh")
    elif damage == "bad-index":
        np.savez(path, V=np.array(V), F=np.array(F) + len(V))
    elif damage == "npy-not-npz":
        with open(path, "wb") as fh:
            np.save(fh, np.array(V))
    elif damage == "bad-compressed-data":
        with open(path, "wb") as fh:
            np.savez_compressed(fh, V=np.array(V), F=np.array(F))
        data = bytearray(path.read_bytes())
        data[len(data) // 3: len(data) // 3 + 64] = bytes(64)
        path.write_bytes(bytes(data))
    else:
        bad = np.array(V)
        bad[3, 1] = np.nan
        np.savez(path, V=bad, F=np.array(F))
    meshes.decimated_bunny.cache_clear()
    V2, F2 = meshes.decimated_bunny(300)
    assert np.array_equal(V, V2) and np.array_equal(F, F2)
    assert meshes.read_cached_bunny(path) is not None  # written again


def test_the_cache_key_follows_the_decimation_settings(cache_home, monkeypatch):
    """A change of how the bunny is decimated gives another file: no stale mesh is served."""
    before = meshes.cached_bunny_path(300)
    monkeypatch.setitem(meshes.BUNNY_DECIMATION, "qualitythr", 0.3)
    assert meshes.cached_bunny_path(300) != before
    assert meshes.cached_bunny_path(400) != meshes.cached_bunny_path(300)


def test_no_cache_without_pymeshlabs_version(cache_home, monkeypatch):
    def unknown(name):
        raise meshes.PackageNotFoundError(name)

    monkeypatch.setattr(meshes, "version", unknown)
    V, F = meshes.decimated_bunny(300)
    assert len(F) > 0 and not (cache_home / "psdr" / "meshes").exists()


def test_a_killed_writers_old_temporary_is_removed_a_fresh_one_kept(cache_home):
    """A writer killed mid-write leaves ``.bunny-….tmp.npz``; the next write removes it once it is
    older than a write could take, and leaves another process's fresh one alone."""
    folder = cache_home / "psdr" / "meshes"
    folder.mkdir(parents=True)
    stale, fresh = folder / ".bunny-300-x.abc.tmp.npz", folder / ".bunny-300-x.def.tmp.npz"
    stale.write_bytes(b"half")
    fresh.write_bytes(b"half")
    old = time.time() - meshes.STALE_TEMPORARY_SECONDS - 5
    os.utime(stale, (old, old))
    meshes.decimated_bunny(300)
    assert not stale.exists() and fresh.exists()


def test_an_unwritable_cache_still_gives_the_bunny(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("a file, not a folder")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "file"))
    meshes.decimated_bunny.cache_clear()
    try:
        V, F = meshes.decimated_bunny(300)
    finally:
        meshes.decimated_bunny.cache_clear()
    assert len(F) > 0 and F.max() < len(V)
