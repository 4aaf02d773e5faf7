"""The FMU cache (sep_plant.plants.fmu.archive.cache_dir) holds shared libraries that sep loads:
it must be private. 0.8.0 used a predictable <tmp>/sep-fmu-<user>, created with exist_ok and
never checked, so another local user could pre-create it (or make it writable) and plant a
library. Pure Python: no FMU, compiler or ROS needed."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

from sep_plant.plants.fmu import archive


def test_the_default_cache_is_per_user_and_not_in_the_shared_tmp(monkeypatch, tmp_path):
    monkeypatch.delenv(archive.CACHE_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    root = archive.cache_dir()
    assert root == tmp_path / "xdg" / "sep" / "fmu"
    assert not str(root).startswith(tempfile.gettempdir() + "/sep-fmu")
    assert oct(os.stat(root).st_mode & 0o777) == oct(0o700)


def test_a_cache_writable_by_others_is_refused(monkeypatch, tmp_path):
    shared = tmp_path / "shared"
    shared.mkdir()
    os.chmod(shared, 0o777)                     # what another user could have pre-created
    monkeypatch.setenv(archive.CACHE_ENV, str(shared))
    with pytest.raises(PermissionError, match="writable by group or others"):
        archive.cache_dir()
    with pytest.raises(PermissionError):
        archive.cached_copy(b"not loaded")
    assert not any(shared.iterdir())            # nothing written there


def test_a_cache_that_is_a_symlink_is_refused(monkeypatch, tmp_path):
    (tmp_path / "real").mkdir(mode=0o700)
    (tmp_path / "link").symlink_to(tmp_path / "real")
    monkeypatch.setenv(archive.CACHE_ENV, str(tmp_path / "link"))
    with pytest.raises(PermissionError, match="symbolic link"):
        archive.cache_dir()


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="chown to another user needs root")
def test_a_cache_owned_by_another_user_is_refused(monkeypatch, tmp_path):
    other = tmp_path / "other"
    other.mkdir(mode=0o700)
    os.chown(other, 4242, 4242)
    monkeypatch.setenv(archive.CACHE_ENV, str(other))
    with pytest.raises(PermissionError, match="owned by uid 4242"):
        archive.cache_dir()


def test_a_private_cache_is_used(monkeypatch, tmp_path):
    monkeypatch.setenv(archive.CACHE_ENV, str(tmp_path / "mine"))
    path = archive.cached_copy(b"bytes")
    assert path.parent == tmp_path / "mine" and path.read_bytes() == b"bytes"
    assert Path(archive.cache_dir()) == tmp_path / "mine"
