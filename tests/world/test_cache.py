"""The map cache (``world/maps/cache.py``) against what users' machines do to it: a dangling link, a folder that
cannot be written, XDG_CACHE_HOME a file, a full disk, a layer changed at the same size, entries written before
checksums. Each case ends with the right map (bit for bit a fresh build) and a warning naming the problem."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest

from aerial_loc_env.paths import CacheLocationWarning, CacheRebuiltWarning
from aerial_loc_env.world.city import city_cache_path, default_city, generate_city, small_city_config
from aerial_loc_env.world.maps import orthomap


@pytest.fixture(scope="module")
def fresh():
    """The small city built without the cache: what every case must give."""
    return _digest(generate_city(small_city_config(0)))


def _digest(om) -> str:
    h = hashlib.sha256()
    for name in ("rgb", "dsm_m", "classes", "nodata"):
        a = getattr(om, name)
        h.update(name.encode() + (b"-" if a is None else np.ascontiguousarray(a).tobytes()))
    return h.hexdigest()


def _only(record, category) -> str:
    messages = [str(w.message) for w in record if issubclass(w.category, category)]
    assert len(messages) == 1, messages
    return messages[0]


def _quietly():
    """A block that fails on any warning: the cache is expected to be silent there."""
    ctx = warnings.catch_warnings()
    ctx.__enter__()
    warnings.simplefilter("error")
    return ctx


def test_an_entry_that_is_a_dangling_link_is_replaced_with_a_warning(cache_homes, fresh):
    cfg = small_city_config(0)
    path = city_cache_path(cfg)
    gone = path.parent / "elsewhere" / "gone.alm"
    path.symlink_to(gone)
    with pytest.warns(CacheRebuiltWarning) as record:
        om = default_city(cfg)
    assert _only(record, CacheRebuiltWarning) == (f"cached map {path} is unusable (it is a link to {gone}, which "
                                                  "does not exist); rebuilding it")
    assert _digest(om) == fresh and om.bundle_path == path
    assert path.is_dir() and not path.is_symlink() and not gone.parent.exists()     # the link went, nothing made
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]


@pytest.fixture()
def read_only(monkeypatch):
    """Make a folder read-only as the kernel does for a user without write permission: mode 0555, and, since root
    ignores modes, creating a file or folder in it fails with EACCES whoever runs the test."""
    folders: list[Path] = []
    real_open, real_mkdir = os.open, os.mkdir

    def denied(target) -> bool:
        parent = Path(os.path.abspath(target)).parent
        return any(parent == f for f in folders)

    def fake_open(target, flags, *args, **kwargs):
        if flags & os.O_CREAT and denied(target):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(target))
        return real_open(target, flags, *args, **kwargs)

    def fake_mkdir(target, *args, **kwargs):
        if denied(target):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(target))
        return real_mkdir(target, *args, **kwargs)

    monkeypatch.setattr(os, "open", fake_open)
    monkeypatch.setattr(os, "mkdir", fake_mkdir)

    def make(folder: Path) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        folder.chmod(0o555)
        folders.append(folder.resolve())

    yield make
    for f in folders:
        f.chmod(0o755)


def test_a_cache_folder_that_cannot_be_written_falls_back_to_a_temporary_one(cache_homes, read_only, fresh):
    cache, tmp = cache_homes
    maps = cache / "aerial_loc_env" / "maps"
    read_only(maps)
    with pytest.warns(CacheLocationWarning) as record:
        om = default_city(small_city_config(0))
    fallback = tmp / f"aerial_loc_env-cache-{os.getuid()}" / "maps"
    assert _only(record, CacheLocationWarning) == (
        f"cache folder {maps} is unusable (cannot write in it: Permission denied); caching in the temporary "
        f"folder {fallback} instead, which the system may clear; set XDG_CACHE_HOME to a writable folder to keep "
        "the cache")
    assert _digest(om) == fresh and om.bundle_path == fallback / city_cache_path(small_city_config(0)).name
    assert list(maps.iterdir()) == []
    ctx = _quietly()        # warned once per process; the temporary entry serves from then on
    try:
        again = default_city(small_city_config(0))
    finally:
        ctx.__exit__(None, None, None)
    assert again.bundle_path == om.bundle_path and isinstance(again.rgb, np.memmap)


def test_xdg_cache_home_a_file_falls_back_to_a_temporary_one(cache_homes, fresh):
    cache, tmp = cache_homes
    cache.write_text("not a folder")
    with pytest.warns(CacheLocationWarning) as record:
        om = default_city(small_city_config(0))
    fallback = tmp / f"aerial_loc_env-cache-{os.getuid()}" / "maps"
    assert _only(record, CacheLocationWarning) == (
        f"cache folder {cache / 'aerial_loc_env' / 'maps'} is unusable ({cache} is not a folder); caching in the "
        f"temporary folder {fallback} instead, which the system may clear; set XDG_CACHE_HOME to a writable folder "
        "to keep the cache")
    assert _digest(om) == fresh and om.bundle_path.parent == fallback
    assert cache.read_text() == "not a folder"


@pytest.mark.slow
@pytest.mark.parametrize("full", ["cache", "cache_and_tmp"])
def test_a_full_disk_while_writing_leaves_no_half_entry(cache_homes, fresh, monkeypatch, full):
    """np.save writes part of a layer, then the disk is full: no entry is left that a later call could use, the
    map is right anyway (from the temporary folder, else from memory), and once there is room it is cached."""
    cache, tmp = cache_homes
    cfg = small_city_config(0)
    path = city_cache_path(cfg)
    real_save = np.save

    def save_on_a_full_disk(file, arr, **kwargs):
        if full == "cache_and_tmp" or str(file).startswith(str(cache)):
            with open(file, "wb") as fh:
                fh.write(b"\x93NUMPY" + bytes(100))
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(file))
        return real_save(file, arr, **kwargs)

    monkeypatch.setattr(np, "save", save_on_a_full_disk)
    with pytest.warns(CacheLocationWarning) as record:
        om = default_city(cfg)
    message = _only(record, CacheLocationWarning)
    twin = tmp / f"aerial_loc_env-cache-{os.getuid()}" / "maps" / path.name
    if full == "cache":
        assert message == (f"cannot write the cached map {path.name} in {path.parent}: No space left on device; "
                           f"saved it in the temporary folder {twin.parent} instead, which the system may clear; "
                           f"free space in {path.parent} or set XDG_CACHE_HOME to a writable folder")
        assert om.bundle_path == twin
    else:
        assert message == (f"cannot write the cached map {path.name} ({path.parent}: No space left on device; "
                           f"{twin.parent}: No space left on device); using it from memory in this process, which "
                           f"builds it again next time; free space in {path.parent} or set XDG_CACHE_HOME to a "
                           "writable folder")
        assert om.bundle_path is None and not twin.exists()
    assert _digest(om) == fresh
    assert sorted(p.name for p in path.parent.iterdir()) == []          # no half-written entry, no temp folder
    assert sorted(p.name for p in twin.parent.iterdir()) == ([twin.name] if full == "cache" else [])
    monkeypatch.undo()
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    ctx = _quietly()        # room again: the next call caches it where it belongs, silently
    try:
        again = default_city(cfg)
    finally:
        ctx.__exit__(None, None, None)
    assert again.bundle_path == path and _digest(again) == fresh


@pytest.mark.slow
@pytest.mark.parametrize("how", ["in_place", "new_file"])
@pytest.mark.parametrize("layer", ["rgb", "dsm_m", "classes"])
def test_a_layer_changed_at_the_same_size_is_rebuilt_with_a_warning(cache_homes, fresh, layer, how):
    cfg = small_city_config(0)
    path = city_cache_path(cfg)
    default_city(cfg)
    f = path / f"{layer}.npy"
    size = f.stat().st_size
    data = bytearray(f.read_bytes())
    data[size // 2: size // 2 + 64] = bytes(64) if any(data[size // 2: size // 2 + 64]) else b"\x07" * 64
    if how == "in_place":
        with open(f, "r+b") as fh:
            fh.write(data)
    else:            # another program's safe save: a new file renamed over the old one
        (path / "swap").write_bytes(data)
        os.replace(path / "swap", f)
    assert f.stat().st_size == size
    with pytest.warns(CacheRebuiltWarning) as record:
        om = default_city(cfg)
    assert _only(record, CacheRebuiltWarning) == (
        f"cached map {path} is unusable ({layer}.npy: layer {layer!r} does not match the SHA-256 in meta.json (the "
        "file changed after the bundle was written); the bundle is corrupt, rebuild it); rebuilding it")
    assert _digest(om) == fresh and om.bundle_path == path
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]


def test_an_entry_written_before_checksums_gains_them_and_is_checked_from_then_on(cache_homes, fresh):
    cfg = small_city_config(0)
    path = city_cache_path(cfg)
    default_city(cfg)
    meta = json.loads((path / "meta.json").read_text())
    for info in meta["layers"].values():        # as the version before checksums wrote it
        del info["sha256"]
    (path / "meta.json").write_text(json.dumps(meta))
    (path / orthomap.STAMP_FILE).unlink()
    ctx = _quietly()
    try:
        om = default_city(cfg)           # taken as it is, without a rebuild or a warning
    finally:
        ctx.__exit__(None, None, None)
    assert _digest(om) == fresh and om.bundle_path == path
    gained = json.loads((path / "meta.json").read_text())
    assert gained["bundle_id"] == meta["bundle_id"]
    assert {n: len(info["sha256"]) for n, info in gained["layers"].items()} == {n: 64 for n in meta["layers"]}
    with open(path / "dsm_m.npy", "r+b") as fh:      # now a same-size change is caught
        fh.seek(-8, os.SEEK_END)
        fh.write(b"\x00\x00\x80\x7f" * 2)
    with pytest.warns(CacheRebuiltWarning, match="layer 'dsm_m' does not match the SHA-256"):
        om = default_city(cfg)
    assert _digest(om) == fresh
