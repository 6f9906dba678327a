"""Input paths as GDAL takes them: a local file, a file inside an archive (``/vsizip/``,
``/vsitar/``, ``/vsigzip/``), or a remote object (``/vsicurl/``, ``/vsis3/``, ``/vsigs/``,
``/vsiaz/``, ``http(s)://``…), made the same from any process and described for a build's
provenance without reading them."""

from __future__ import annotations

import os
from typing import Any

__all__ = ["ARCHIVES", "absolute", "is_remote", "local_file", "provenance"]

#: GDAL's prefixes for a file inside a local (or remote) archive: the path after them is the
#: archive's, then the member's.
ARCHIVES = ("/vsizip/", "/vsitar/", "/vsigzip/", "/vsi7z/", "/vsirar/")
_REMOTE = ("/vsicurl", "/vsis3", "/vsigs", "/vsiaz", "/vsiadls", "/vsioss", "/vsiswift", "/vsihdfs")
_URL = ("http://", "https://", "ftp://", "s3://", "gs://", "az://")


def _archive_split(path: str) -> tuple[str, str] | None:
    """(prefix, the rest) of a path inside an archive, or None."""
    for prefix in ARCHIVES:
        if path.startswith(prefix):
            return prefix, path[len(prefix) :]
    return None


def is_remote(path: str) -> bool:
    """Whether GDAL reads ``path`` over the network (an archive on a remote object included)."""
    split = _archive_split(path)
    if split is not None:
        return is_remote(split[1])
    return path.startswith(_REMOTE) or path.startswith(_URL)


def absolute(path: str | os.PathLike[str]) -> str:
    """``path`` as every process reads it alike: a local file (inside an archive too) made
    absolute; a remote one, or another of GDAL's virtual paths, as given."""
    text = os.fspath(path)
    split = _archive_split(text)
    if split is not None:
        prefix, rest = split
        if rest.startswith("/") or is_remote(rest):
            return text
        return prefix + os.path.abspath(rest)  # GDAL's form: /vsizip//abs/path.zip/member
    if text.startswith("/vsi") or text.startswith(_URL):
        return text
    return os.path.abspath(text)


def local_file(path: str) -> str | None:
    """The local file GDAL reads ``path`` from: itself, or the archive it is in (found by
    walking the archive path up to an existing file); None for a remote input."""
    if is_remote(path):
        return None
    split = _archive_split(path)
    if split is None:
        return None if path.startswith("/vsi") else path
    inner = split[1]
    if inner.startswith("/vsi"):
        return local_file(inner)
    parts = inner.split("/")
    for n in range(len(parts), 0, -1):
        candidate = "/".join(parts[:n])
        if candidate and os.path.isfile(candidate):
            return candidate
    return None


def provenance(path: str) -> dict[str, Any]:
    """What a build records of an input: its path as every process reads it, and the size and
    modification time of the local file that holds it (an archive's for a member); for a
    remote input, None for both (GDAL's own stat of a URL is a request; the manifest says it
    is remote instead)."""
    local = local_file(path)
    out: dict[str, Any] = {"path": absolute(path), "bytes": None, "mtime_ns": None}
    if local is None:
        out["remote"] = True
        return out
    st = os.stat(local)
    out.update(bytes=st.st_size, mtime_ns=st.st_mtime_ns)
    if local != path:
        out["file"] = os.path.abspath(local)
    return out
