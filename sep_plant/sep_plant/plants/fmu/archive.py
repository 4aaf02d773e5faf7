"""FMU files: identity (SHA-256), sanity of the zip archive, and unpacked copies keyed by content.

An FMU is a zip archive (modelDescription.xml, binaries/<platform>/<id>.so|.dll|.dylib, ...).
sep identifies an FMU by the SHA-256 of its bytes, never by its path: two scenarios that name
the same file from different folders mean the same plant, and a design refuses another FMU
under the same name. The archive is unpacked once per content into a cache folder
(``$SEP_FMU_CACHE``, default ``$XDG_CACHE_HOME/sep/fmu``, i.e. ``~/.cache/sep/fmu``),
``<cache>/<sha256>/``, so that every plant object, process and worker of a user shares one copy
and a changed file never reuses a stale one. Shared libraries are loaded from that folder, so it
must be private: it is created with mode 0700, and a folder that is a symbolic link, is owned by
another user or is writable by group or others is refused (`CacheNotPrivate`), never used. A
worker whose disk lacks the FMU gets its bytes (`cached_copy`) and writes them to
``<cache>/<sha256>.fmu``. Pure Python: no ROS import.
"""
from __future__ import annotations

import hashlib
import os
import stat
import tempfile
import zipfile
from pathlib import Path

#: environment variable naming the cache folder of unpacked FMUs
CACHE_ENV = "SEP_FMU_CACHE"


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes (read in 1 MB pieces)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


class CacheNotPrivate(PermissionError):
    """The FMU cache folder could be changed by another user (it holds shared libraries sep loads)."""


def default_cache_root() -> Path:
    """``$XDG_CACHE_HOME/sep/fmu``, else ``~/.cache/sep/fmu``: a per-user folder, never a
    predictable name in the shared temporary folder."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "sep" / "fmu"


def check_private(root: Path) -> None:
    """Raise CacheNotPrivate unless `root` is a real folder (no symbolic link) owned by this user
    and not writable by group or others."""
    st = os.lstat(root)
    hint = f"set {CACHE_ENV} to a folder only you can write"
    if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode):
        raise CacheNotPrivate(f"FMU cache {root} is not a folder (a symbolic link or a file): {hint}")
    if hasattr(os, "getuid") and st.st_uid != os.getuid():
        raise CacheNotPrivate(f"FMU cache {root} is owned by uid {st.st_uid}, not by you (uid {os.getuid()}): "
                              f"sep loads shared libraries from it; {hint}")
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise CacheNotPrivate(f"FMU cache {root} is writable by group or others (mode "
                              f"{stat.S_IMODE(st.st_mode):o}): sep loads shared libraries from it; "
                              f"chmod 700 it or {hint}")


def cache_dir() -> Path:
    """The folder of unpacked FMUs ($SEP_FMU_CACHE, else `default_cache_root()`), created with
    mode 0700 and checked to be private (`check_private`)."""
    env = os.environ.get(CACHE_ENV)
    root = Path(env).expanduser() if env else default_cache_root()
    root.mkdir(mode=0o700, parents=True, exist_ok=True)
    check_private(root)
    return root


def archive_problems(path: Path) -> list[str]:
    """What makes `path` unusable as an FMU archive (empty list when it is a readable zip
    with a modelDescription.xml)."""
    if not path.is_file():
        return [f"file not found: {path}"]
    try:
        with zipfile.ZipFile(path) as zf:
            names = set(zf.namelist())
            bad = zf.testzip()
    except zipfile.BadZipFile as exc:
        return [f"not a zip archive ({exc}): an FMU is a zip file with a modelDescription.xml"]
    except (OSError, RuntimeError, NotImplementedError) as exc:   # unsupported compression, ...
        return [f"cannot read the zip archive: {exc}"]
    except Exception as exc:  # noqa: BLE001 - zlib.error on a damaged member
        return [f"corrupt zip archive: {type(exc).__name__}: {exc}"]
    out = []
    if bad is not None:
        out.append(f"corrupt zip archive: member {bad} fails its CRC check")
    if "modelDescription.xml" not in names:
        out.append("not an FMU: the archive has no modelDescription.xml")
    for name in names:
        if name.startswith("/") or ".." in Path(name).parts or "\\" in name or ":" in name:
            out.append(f"unsafe member name {name!r} in the archive (absolute, '..', '\\' or ':')")
            break
    return out


def unpacked(path: Path, sha256: str, required: tuple[str, ...] = ()) -> Path:
    """The folder holding the unpacked FMU of content `sha256` (unpacked on first use; the
    unpacking goes to a temporary folder renamed into place, so concurrent processes never
    see half an FMU). A copy that lacks a `required` member (e.g. the binary) is unpacked anew."""
    import shutil

    root = cache_dir()
    target = root / sha256
    members = ("modelDescription.xml",) + tuple(required)
    if all((target / m).is_file() for m in members):
        return target
    if target.exists():
        shutil.rmtree(target, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{sha256[:12]}-", dir=root))
    try:
        with zipfile.ZipFile(path) as zf:
            zf.extractall(tmp)
        for dirpath, _, files in os.walk(tmp / "binaries"):
            for f in files:                                   # shared libraries must be readable
                os.chmod(os.path.join(dirpath, f), 0o755)
        try:
            os.replace(tmp, target)
        except OSError:                     # another process was first (target not empty)
            pass
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    if not all((target / m).is_file() for m in members):
        raise OSError(f"could not unpack {path} into {target}")
    return target


def cached_copy(data: bytes, sha256: str | None = None) -> Path:
    """The FMU file of these bytes in the cache, ``<cache>/<sha256>.fmu`` (written when absent):
    how a worker without the user's file gets one."""
    digest = sha256_bytes(data)
    if sha256 is not None and sha256 != digest:
        raise ValueError(f"the FMU bytes have SHA-256 {digest}, expected {sha256}")
    path = cache_dir() / f"{digest}.fmu"
    if not path.is_file() or sha256_file(path) != digest:
        fd, tmp = tempfile.mkstemp(prefix=".fmu-", dir=path.parent)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    return path


__all__ = ["CACHE_ENV", "CacheNotPrivate", "archive_problems", "cache_dir", "cached_copy", "check_private",
           "default_cache_root", "sha256_bytes", "sha256_file", "unpacked"]
