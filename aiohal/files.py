"""Files named in a config or on the command line: read without hanging or filling memory,
written without destroying anything but the file named.

A FIFO blocks ``open()`` until a writer comes, a device such as ``/dev/zero`` never ends, and
either would stop aiohal before anything checks it. :func:`read_regular` opens without waiting
(``O_NONBLOCK``), looks at what it opened (``fstat``, so the answer is about that very file) and
reads only a regular file, up to a size cap. An output (:func:`check_output_path`,
:func:`write_atomically`) replaces only a regular file, never through a symbolic link, never the
config or a file it names, and is written whole or not at all.
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from pathlib import Path
from typing import BinaryIO

from .errors import AiohalError

#: the default cap on what one file may hold (the largest shipped data file is about 100 KiB)
MAX_FILE_BYTES = 16 << 20

_KINDS = (
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISDIR, "a directory"),
)


def _size(n: int) -> str:
    for unit, shift in (("GiB", 30), ("MiB", 20), ("KiB", 10)):
        if n >= 1 << shift and n % (1 << shift) == 0:
            return f"{n >> shift} {unit}"
    return f"{n} bytes"


class FileRefused(AiohalError, ValueError):
    """A named file that is not a regular file, too large, or unreadable; says which key named it."""


def _refused(key: str, problem: str, path: str | Path) -> FileRefused:
    return FileRefused(f"{key}: {problem}: {path}" if key else f"{problem}: {path}")


def _open_regular(path: str | Path, key: str, limit: int) -> tuple[int, int]:
    """An fd open on ``path`` and its size, if it is a regular file within ``limit`` bytes."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except FileNotFoundError:
        raise _refused(key, "file not found", path) from None
    except OSError as exc:
        raise _refused(key, f"cannot open ({exc.strerror or exc})", path) from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = next((name for test, name in _KINDS if test(st.st_mode)), "not a file")
            raise _refused(key, f"not a regular file ({kind})", path)
        if st.st_size > limit:
            raise _refused(key, f"larger than {_size(limit)}", path)
    except BaseException:
        os.close(fd)
        raise
    return fd, st.st_size


def check_regular(path: str | Path, key: str = "", limit: int = MAX_FILE_BYTES) -> None:
    """Raise :class:`FileRefused` unless ``path`` is a regular file of at most ``limit`` bytes
    (for a file another library reads by its path)."""
    fd, _ = _open_regular(path, key, limit)
    os.close(fd)


def open_regular(path: str | Path, key: str = "", limit: int = MAX_FILE_BYTES) -> BinaryIO:
    """``path`` open for reading in binary, if it is a regular file of at most ``limit`` bytes
    (for a reader that streams the file itself)."""
    fd, _ = _open_regular(path, key, limit)
    return os.fdopen(fd, "rb")


def read_regular(path: str | Path, key: str = "", limit: int = MAX_FILE_BYTES) -> bytes:
    """The bytes of ``path`` if it is a regular file of at most ``limit`` bytes; otherwise
    :class:`FileRefused` naming ``key`` and the file. Never blocks on a FIFO, never reads more
    than ``limit + 1`` bytes (a file that grows while read is refused too)."""
    fd, _ = _open_regular(path, key, limit)
    chunks, total = [], 0
    try:
        while total <= limit:  # bounded: each read returns at least one byte or ends it
            chunk = os.read(fd, min(1 << 20, limit + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
    except OSError as exc:
        raise _refused(key, f"cannot read ({exc.strerror or exc})", path) from None
    finally:
        os.close(fd)
    if total > limit:
        raise _refused(key, f"larger than {_size(limit)}", path)
    return b"".join(chunks)


def read_regular_text(path: str | Path, key: str = "", limit: int = MAX_FILE_BYTES) -> str:
    """:func:`read_regular`, decoded as UTF-8 (an undecodable file is refused the same way)."""
    data = read_regular(path, key, limit)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise _refused(key, f"not UTF-8 text ({exc.reason} at byte {exc.start})", path) from None


def check_output_path(path: str | Path, *, protect: tuple[Path, ...] = ()) -> Path:
    """Where an output (a report, a recording, a figure) may go, checked before anything
    starts; ValueError says why not.

    An output only ever replaces a regular file: a device, FIFO, symlink or directory at
    ``path`` is left alone, and so is any file in ``protect`` (the config it came from and the
    files the config names).
    """
    path = Path(path)
    if path.name in ("", ".", ".."):
        raise ValueError(f"{path} is a directory, not a file name")
    try:
        st = path.lstat()
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise ValueError(f"cannot use {path}: {exc.strerror}") from None
    if st is not None:
        if stat.S_ISLNK(st.st_mode):
            raise ValueError(f"{path} is a symbolic link; give the file it points to, or a new name")
        if stat.S_ISDIR(st.st_mode):
            raise ValueError(f"{path} is a directory, not a file name")
        if not stat.S_ISREG(st.st_mode):
            raise ValueError(f"{path} exists and is not a regular file (a device, FIFO or socket)")
        for other in protect:
            try:
                if os.path.samefile(path, other):
                    raise ValueError(f"{path} is {other} (the config or a file it names); it would be replaced")
            except OSError:
                continue
    parent = path.parent
    if not parent.is_dir():
        raise ValueError(f"the directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"the directory {parent} is not writable")
    return path


def write_atomically(path: str | Path, data: bytes, *, protect: tuple[Path, ...] = ()) -> None:
    """Write ``data`` to ``path`` through a temporary file in its own directory, renamed over it
    (the rename replaces a name, never the file a link points to) after ``path`` is checked
    again (:func:`check_output_path`): nothing else took the name meanwhile."""
    path = check_output_path(path, protect=protect)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 is for the temporary file, not the output
        check_output_path(path, protect=protect)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
