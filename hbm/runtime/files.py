"""Files hbm writes: atomic writes, output checks and locks.

Every file hbm writes goes through :func:`atomic_path`: a temporary file next to the target,
renamed onto it when complete, with the permissions a plain ``open()`` would give
(``0o666 & ~umask``).  :func:`prepare_output_dir` / :func:`prepare_output_file` test an output
location (create, write, replace) before any computation; :func:`output_lock` keeps two runs
out of one folder and :func:`file_lock` two writers off one file (the one writer
rule).  Memory checks are in :mod:`hbm.runtime.memory`.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import tempfile
from pathlib import Path
from typing import Iterator

from ..errors import OutputError, OutputLockedError
from .memory import format_bytes

__all__ = ["atomic_path", "atomic_write_text", "current_umask", "file_mode", "remove_stale_temps", "retire_checkpoint",
           "prepare_output_dir", "prepare_output_file", "output_lock", "file_lock", "file_lock_path", "LOCK_NAME",
           "write_error"]

#: name of the lock file :func:`output_lock` holds inside an output folder
LOCK_NAME = ".hbm.lock"
#: temporary files of :func:`atomic_path`: ``.<target name>.<8 random characters>.tmp``
_TEMP_RE = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp$")
_TEMP_SUFFIX = ".tmp"


def current_umask() -> int:
    """The process umask, read without changing it where the OS allows (Linux >= 4.7)."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)  # elsewhere: set and restore (a brief race with other threads' creations)
    os.umask(mask)
    return mask


def file_mode() -> int:
    """Permissions of a new regular file: ``0o666 & ~umask`` (what ``open(path, "w")`` gives)."""
    return 0o666 & ~current_umask()


def write_error(path: str | os.PathLike, exc: BaseException) -> OutputError:
    """An :class:`OutputError` naming ``path`` for an OS/netCDF error raised while writing it.

    A full disk or quota is named as such, also when the library only says "HDF error".
    """
    path = Path(path)
    code = getattr(exc, "errno", None)
    reason = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
    if code in (errno.ENOSPC, errno.EDQUOT):
        reason = "no space left on the device" if code == errno.ENOSPC else "disk quota exceeded"
    elif not isinstance(exc, OSError) or code is None:
        free = _free_bytes(path.parent)
        if free is not None and free < 64 << 20:  # a library error on a full disk (netCDF: "HDF error")
            reason = f"{reason} (the disk is full? {format_bytes(free)} free)"
    return OutputError(f"cannot write {path}: {reason}")


def _free_bytes(folder: Path) -> int | None:
    try:
        st = os.statvfs(folder)
    except (OSError, AttributeError):
        return None
    return st.f_bavail * st.f_frsize


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success rename it onto ``path``.

    A crash or exception leaves any previous file at ``path`` untouched and no half-written
    file behind (the temporary file is removed on every exception, including Ctrl-C).  The
    result has mode ``0o666 & ~umask`` (``mkstemp`` creates 0600).  An OS error while creating,
    writing or renaming (permission, missing folder, full disk) is raised as
    :class:`hbm.errors.OutputError` naming ``path``.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix="." + path.name + ".", suffix=_TEMP_SUFFIX, dir=path.parent)
        os.close(fd)
    except OSError as exc:
        raise write_error(path, exc) from exc
    tmp_path = Path(tmp)
    try:
        try:
            yield tmp_path
            os.chmod(tmp_path, file_mode())
            os.replace(tmp_path, path)
        except OSError as exc:
            if isinstance(exc, OutputError):
                raise
            raise write_error(path, exc) from exc
    finally:
        with contextlib.suppress(OSError):
            tmp_path.unlink()


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (temp file + rename)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def retire_checkpoint(path: str | os.PathLike | None) -> None:
    """Remove a fit's checkpoint file once its result is written (the result supersedes it), and its keyed
    folder when that is then empty."""
    if path is None or not Path(path).exists():
        return
    Path(path).unlink()
    try:
        Path(path).parent.rmdir()  # only if empty
    except OSError:
        pass


def remove_stale_temps(folder: str | os.PathLike, *, recursive: bool = True, target: str | None = None) -> list[Path]:
    """Remove temporary files of :func:`atomic_path` left in ``folder`` by a killed process.

    Only names of the form ``.<name>.<8 characters>.tmp`` are touched (``target``: only those of
    that file name).  Call it while holding the folder's :func:`output_lock` or the file's
    :func:`file_lock`; temporary files of a target whose :func:`file_lock` another process holds
    are never touched.

    Returns
    -------
    list of Path
        The files removed.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return []
    pattern = f".{target}.*{_TEMP_SUFFIX}" if target else f".*{_TEMP_SUFFIX}"
    found = folder.rglob(pattern) if recursive else folder.glob(pattern)
    removed = []
    for p in found:
        if _TEMP_RE.match(p.name) and p.is_file() and not p.is_symlink():
            target = p.parent / p.name[1:-len(".abcdefgh.tmp")]
            if _locked_elsewhere(file_lock_path(target)) or (
                    recursive and _locked_elsewhere(p.parent / LOCK_NAME) and p.parent != folder):
                continue  # a live writer's file: only the lock holder sweeps it
            with contextlib.suppress(OSError):
                p.unlink()
                removed.append(p)
    return removed


def _probe(folder: Path, what: str) -> None:
    """Create, write and rename a temporary file in ``folder`` (what writing results needs)."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=".hbm-probe.", suffix=_TEMP_SUFFIX, dir=folder)
    except OSError as exc:
        raise OutputError(f"{what}: cannot create files in {folder}: {_reason(exc)}") from None
    moved = os.path.join(folder, ".hbm-probe-renamed." + os.path.basename(tmp).split(".")[2] + _TEMP_SUFFIX)
    try:
        os.write(fd, b"hbm")
        os.fsync(fd)
        os.close(fd)
        fd = -1
        os.replace(tmp, moved)
    except OSError as exc:
        raise OutputError(f"{what}: cannot write files in {folder}: {_reason(exc)}") from None
    finally:
        if fd >= 0:
            os.close(fd)
        for p in (tmp, moved):
            with contextlib.suppress(OSError):
                os.unlink(p)


def _reason(exc: OSError) -> str:
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return "no space left on the device" if exc.errno == errno.ENOSPC else "disk quota exceeded"
    return (exc.strerror or str(exc)).lower()


def _make_dir(folder: Path, what: str) -> None:
    for parent in [folder, *folder.parents]:  # the first existing ancestor must be a folder
        if parent.exists() or parent.is_symlink():
            if not parent.is_dir():
                if parent == folder:
                    raise OutputError(f"{what} {folder}: is a file, expected a folder")
                raise OutputError(f"{what} {folder}: cannot create the folder, {parent} is a file")
            break
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{what} {folder}: cannot create the folder: {_reason(exc)}") from None


def prepare_output_dir(folder: str | os.PathLike, what: str = "output folder", *,
                       files: tuple[str, ...] = (), subdirs: tuple[str, ...] = ()) -> Path:
    """Create ``folder`` (with parents) and check that hbm can create, write and replace files there.

    Parameters
    ----------
    folder : path
    what : str
        How the message names it, e.g. ``"--out"``.
    files : names
        Files that will be replaced inside ``folder``: each must not be a folder.
    subdirs : names
        Sub-folders that will be written: each must be a folder (or absent) and writable.

    Returns
    -------
    Path
        The absolute folder.

    Raises
    ------
    OutputError
        With a one-line message naming the folder and the reason.
    """
    folder = Path(folder).expanduser().absolute()
    _make_dir(folder, what)
    _probe(folder, f"{what} {folder}")
    for name in files:
        if (folder / name).is_dir():
            raise OutputError(f"{what} {folder}: {folder / name} is a folder, expected a file (or nothing)")
    for name in subdirs:
        sub = folder / name
        if sub.exists() or sub.is_symlink():
            if not sub.is_dir():
                raise OutputError(f"{what} {folder}: {sub} is a file, expected a folder (or nothing)")
            _probe(sub, f"{what} {folder}")
    return folder


def prepare_output_file(path: str | os.PathLike, what: str = "output file") -> Path:
    """Check that ``path`` can be written atomically: its folder is created and writable, and
    ``path`` itself is not a folder.  Returns the absolute path; raises :class:`OutputError`."""
    path = Path(path).expanduser().absolute()
    if path.is_dir():
        raise OutputError(f"{what} {path}: is a folder, expected a file name")
    _make_dir(path.parent, what)
    _probe(path.parent, f"{what} {path}")
    return path


def _lock_holder(lock: Path) -> str:
    try:
        pid = lock.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError):
        pid = ""
    return f"pid {pid}" if pid.isdigit() else "pid unknown"


#: lock files this process holds now (a second flock from the same process would fail, so the
#: temp sweep asks here first)
_HELD: set[Path] = set()


def file_lock_path(path: str | os.PathLike) -> Path:
    """The lock file of one output file: ``<folder>/.<name>.lock`` (``.hbm.lock`` for a folder)."""
    path = Path(path).expanduser().absolute()
    return path / LOCK_NAME if path.is_dir() else path.parent / f".{path.name}.lock"


@contextlib.contextmanager
def _flock(lock: Path, busy: str) -> Iterator[Path]:
    """Hold ``fcntl.flock`` on ``lock`` (created if absent); ``busy``: message if another holds it."""
    import fcntl  # POSIX only; imported here so that Windows can still import hbm.runtime.files

    lock = lock.absolute()
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as exc:
        raise OutputError(f"cannot create the lock file {lock}: {_reason(exc)}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise OutputError(f"cannot lock {lock}: {_reason(exc)}") from None
            raise OutputLockedError(f"{busy} ({_lock_holder(lock)})") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        _HELD.add(lock)
        try:
            yield lock
        finally:
            _HELD.discard(lock)
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)  # before the unlock: a waiting run must not read a stale pid
    finally:
        os.close(fd)  # releases the flock


def _locked_elsewhere(lock: Path) -> bool:
    """True if another process holds ``lock`` now (probed without waiting, released at once)."""
    import fcntl

    if lock.absolute() in _HELD or not lock.is_file():
        return False
    try:
        fd = os.open(lock, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)  # releases a probe lock
    return False


@contextlib.contextmanager
def output_lock(folder: str | os.PathLike) -> Iterator[Path]:
    """Hold an exclusive lock on ``folder`` (``fcntl.flock`` on ``<folder>/.hbm.lock``).

    A second process asking for the same folder gets :class:`OutputLockedError`
    ("``<folder>`` is in use by another hbm run (pid N)") at once instead of duplicating or
    interleaving the work.  The lock goes with the process (also on kill -9); the lock file stays.
    """
    folder = Path(folder)
    with _flock(folder / LOCK_NAME, f"{folder} is in use by another hbm run") as lock:
        yield lock


@contextlib.contextmanager
def file_lock(path: str | os.PathLike, what: str = "output file") -> Iterator[Path]:
    """Hold the writer's lock of one output file (:func:`file_lock_path`) while it is produced.

    The one writer rule: a process writes ``path`` (and sweeps its temporary files) only while
    it holds this lock; a second writer gets :class:`OutputLockedError` naming ``what`` and the
    holder at once.  Lock files stay (removing them would race with a waiting writer).
    """
    path = Path(path).expanduser().absolute()
    with _flock(file_lock_path(path), f"{what} {path} is being written by another hbm process; wait for it to "
                                      "finish or choose another output") as lock:
        yield lock
