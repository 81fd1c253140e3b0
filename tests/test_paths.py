"""paths.cache_dir and its temporary fallback: an unusable cache folder never stops a run, and the fallback is
never a folder another user could have planted."""

from __future__ import annotations

import errno
import os
import stat
import tempfile
import warnings
from pathlib import Path

import pytest

from aerial_loc_env import paths
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.paths import CacheLocationWarning, cache_dir, temporary_cache_dir


def _own_root(tmp: Path) -> Path:
    return tmp / f"aerial_loc_env-cache-{os.getuid()}"


def test_a_usable_cache_folder_is_used_silently(cache_homes):
    cache, _ = cache_homes
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert cache_dir("maps") == cache / "aerial_loc_env" / "maps"
        assert cache_dir("maps") == cache / "aerial_loc_env" / "maps"
    assert (cache / "aerial_loc_env" / "maps").is_dir()
    assert list((cache / "aerial_loc_env" / "maps").iterdir()) == []     # the write probe leaves nothing


def _make_file(cache: Path) -> str:
    cache.write_text("x")
    return f"{cache} is not a folder"


def _make_dangling(cache: Path) -> str:
    (cache / "aerial_loc_env").parent.mkdir(parents=True)
    (cache / "aerial_loc_env").symlink_to(cache / "gone")
    return f"{cache / 'aerial_loc_env'} is a dangling link"


def _make_unwritable(cache: Path, monkeypatch) -> str:
    folder = cache / "aerial_loc_env" / "maps"
    folder.mkdir(parents=True)
    folder.chmod(0o555)
    real_open = os.open

    def fake_open(target, flags, *args, **kwargs):     # root ignores modes: deny as the kernel would a user
        if flags & os.O_CREAT and Path(target).parent == folder:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(target))
        return real_open(target, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", fake_open)
    return "cannot write in it: Permission denied"


@pytest.mark.parametrize("damage", ["file", "dangling", "unwritable"])
def test_an_unusable_cache_folder_falls_back_to_a_temporary_one_with_one_warning(cache_homes, monkeypatch, damage):
    cache, tmp = cache_homes
    problem = {"file": lambda: _make_file(cache), "dangling": lambda: _make_dangling(cache),
               "unwritable": lambda: _make_unwritable(cache, monkeypatch)}[damage]()
    with pytest.warns(CacheLocationWarning) as record:
        got = cache_dir("maps")
        again = cache_dir("maps")
    assert [str(w.message) for w in record] == [
        f"cache folder {cache / 'aerial_loc_env' / 'maps'} is unusable ({problem}); caching in the temporary "
        f"folder {_own_root(tmp) / 'maps'} instead, which the system may clear; set XDG_CACHE_HOME to a writable "
        "folder to keep the cache"]
    assert got == again == _own_root(tmp) / "maps" and got.is_dir()
    assert stat.S_IMODE(_own_root(tmp).stat().st_mode) == 0o700
    if damage == "unwritable":
        (cache / "aerial_loc_env" / "maps").chmod(0o755)


@pytest.mark.parametrize("planted", ["open_to_all", "a_link"])
def test_a_temporary_root_that_others_could_write_is_never_used(cache_homes, planted):
    _, tmp = cache_homes
    root = _own_root(tmp)
    if planted == "open_to_all":
        root.mkdir()
        root.chmod(0o777)
    else:
        (tmp / "theirs").mkdir()
        root.symlink_to(tmp / "theirs")
    got = temporary_cache_dir("maps")
    assert got.parent != root and got.parent.parent == tmp and got.name == "maps"
    assert got.parent.name.startswith("aerial_loc_env-cache-") and stat.S_IMODE(got.parent.stat().st_mode) == 0o700
    assert temporary_cache_dir("maps") == got          # the same private folder for the rest of the process
    assert list((tmp / "theirs").iterdir() if planted == "a_link" else root.iterdir()) == []


def test_no_usable_folder_at_all_is_a_config_error(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("x")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "file"))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "file"))
    monkeypatch.setattr(paths, "_PRIVATE_ROOTS", {})
    with pytest.raises(ConfigError, match=r"no usable cache folder: the temporary folder .*file is not writable "
                                          r"\(.*\); set XDG_CACHE_HOME \(or TMPDIR\) to a writable folder"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", CacheLocationWarning)
            cache_dir("maps")
