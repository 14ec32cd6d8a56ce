"""Crash-safe writing: every file and directory the package writes appears whole or not at all.

A file is written to a temporary sibling, flushed to disk and renamed over the target
(:func:`atomic_write`). A directory (a dataset) is built in a temporary sibling directory and then
swapped with the target in one step (:func:`atomic_directory`), so a kill at any moment leaves
either the old directory or the new one, never a mix.

Temporary names carry the writer's process id (``.NAME.<pid>.<random>.tmp``); a leftover of a
writer that no longer runs is removed the next time the same target is written
(:func:`remove_leftovers`), while a live writer's temporary is left alone.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import re
import secrets
import shutil
from pathlib import Path

from ttsim_jax.errors import UserError

_RENAME_EXCHANGE = 2  # linux/fs.h
#: Why a write fails that the user must act on (a full disk or quota, a read-only or forbidden
#: place, a file beyond the filesystem's size): one ``error:`` line, not a traceback.
_REFUSED = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG}


class WriteError(UserError, OSError):
    """A write that failed for want of room or permission; the message names the path and the
    reason, and nothing half-written is left behind (any previous output is whole)."""

    def __str__(self) -> str:
        return self.args[0] if self.args else "a write failed"


def write_error(e: OSError, path, what: str = "", atomic: bool = True) -> WriteError | None:
    """``e`` as a :class:`WriteError` naming ``path`` (and ``what`` was being written), or None
    when it is not a refused write (:data:`_REFUSED`; pyarrow's errors carry no errno, only the
    system's message). ``atomic``: the write went through this module's writers, so nothing of
    it is left behind (the message says so)."""
    if isinstance(e, WriteError):
        return e
    reason = e.strerror or str(e)
    if e.errno not in _REFUSED and not any(os.strerror(n) in str(e) for n in _REFUSED):
        return None
    for n in _REFUSED:
        if os.strerror(n) in str(e):
            reason = os.strerror(n)
    text = f"cannot write {path}{f' ({what})' if what else ''}: {reason}"
    if atomic:
        text += "; nothing was left half-written" + (", any previous version is kept" if Path(path).exists() else "")
    return WriteError(text)
_AT_FDCWD = -100


def _temp_name(target: Path) -> Path:
    return target.with_name(f".{target.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")


def _is_stale(name: str, target_name: str) -> bool:
    """Whether ``name`` is a temporary of ``target_name`` whose writer no longer runs."""
    m = re.fullmatch(rf"\.{re.escape(target_name)}\.(\d+)\.[0-9a-f]{{8}}\.tmp", name)
    if m is None:
        # the temporaries of earlier releases (tempfile.mkstemp) carry no pid: nobody owns them
        return re.fullmatch(rf"\.{re.escape(target_name)}\.[a-z0-9_]{{8}}\.tmp", name) is not None
    pid = int(m.group(1))
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # exists but belongs to another user
        return False
    return False


def remove_leftovers(target) -> list[Path]:
    """Removes temporaries of ``target`` left by writers that were killed.

    Arguments:
        target: the file or directory whose temporaries (``.NAME.<pid>.<random>.tmp`` beside it)
            are looked for.

    Returns:
        The removed paths.
    """
    target = Path(os.path.abspath(target))
    removed = []
    try:
        names = os.listdir(target.parent)
    except FileNotFoundError:
        return removed
    for name in names:
        if _is_stale(name, target.name):
            p = target.parent / name
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                with contextlib.suppress(FileNotFoundError):
                    p.unlink()
            removed.append(p)
    return removed


def fsync_directory(directory) -> None:
    """Makes renames inside ``directory`` durable (not possible on every platform)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass


def probe_writable(directory) -> str | None:
    """Whether files can be created in ``directory``: a probe file is created and removed.

    Permission bits say too little (root passes every ``os.access`` test, and pseudo-filesystems
    such as ``/proc`` or ``/sys`` refuse new files whatever their modes), so an output that a job
    writes only at its end is tried before the work starts.

    Arguments:
        directory: an existing directory.

    Returns:
        None if a file could be created there, else the reason (the operating system's message).
    """
    probe = Path(directory) / f".ttsim-probe.{os.getpid()}.{secrets.token_hex(4)}.tmp"
    try:
        fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
    except OSError as e:
        if e.errno == errno.ENOENT:  # what /proc answers for a directory that exists
            return "its filesystem does not accept new files"
        return e.strerror or str(e)
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)
    return None


def atomic_write(path, data: bytes, what: str = "") -> None:
    """Writes ``data`` to ``path`` atomically: a temporary file in the same directory, fsync,
    then os.replace, so a crash leaves either the old file or the new one, never a partial one.

    Arguments:
        path: destination file.
        data: the bytes.
        what: what the file holds, for the message of a failed write.

    Raises:
        WriteError: a full disk, a read-only or forbidden place (the temporary is removed).
    """
    path = Path(os.path.abspath(path))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_leftovers(path)
    except OSError as e:
        raise (write_error(e, path, what) or e) from None
    tmp = _temp_name(path)
    try:
        with open(tmp, "xb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(e, OSError) and (refused := write_error(e, path, what)) is not None:
            raise refused from None
        raise
    fsync_directory(path.parent)


def _exchange(a: Path, b: Path) -> bool:
    """Swaps two existing paths in one step (Linux renameat2); False where that is unsupported."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (22, 38, 95):  # EINVAL, ENOSYS, EOPNOTSUPP: this file system or kernel cannot
        return False
    raise OSError(err, os.strerror(err), str(a), None, str(b))


def _sync_tree(root: Path) -> None:
    for dirpath, _, files in os.walk(root):
        for name in files:
            fd = os.open(os.path.join(dirpath, name), os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        fsync_directory(dirpath)


@contextlib.contextmanager
def atomic_directory(target, keep=()):
    """Builds a directory in a temporary sibling and swaps it in for ``target`` on success.

    Usage::

        with atomic_directory(out) as tmp:
            write files into tmp
        # now out holds exactly what was written into tmp (plus the kept entries)

    If the body raises, ``target`` is left untouched and the temporary is removed. A replaced
    old directory is deleted after the swap. Where the system cannot swap two directories in one
    step, the old one is first renamed aside, leaving a short window without ``target``.

    Arguments:
        target: the directory to create or replace (a symlink is followed: its target is replaced).
        keep: names of entries of an existing ``target`` to carry over into the new directory
            (hard-linked, or copied where links are impossible).

    Yields:
        The temporary directory (a :class:`~pathlib.Path`) to write into.
    """
    target = Path(os.path.realpath(target))
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        remove_leftovers(target)
        tmp = _temp_name(target)
        tmp.mkdir()
    except OSError as e:
        raise (write_error(e, target) or e) from None
    try:
        try:
            yield tmp
        except OSError as e:  # a writer of the body (pyarrow, numpy) on a full disk
            raise (write_error(e, target) or e) from None
        try:
            for name in keep:
                src = target / name
                if src.is_dir() and not src.is_symlink():
                    shutil.copytree(src, tmp / name, symlinks=True, copy_function=_link_or_copy)
                elif src.exists() or src.is_symlink():
                    _link_or_copy(src, tmp / name)
            _sync_tree(tmp)
        except OSError as e:
            raise (write_error(e, target) or e) from None
        if target.exists():
            if not _exchange(tmp, target):
                aside = _temp_name(target)
                os.rename(target, aside)
                os.rename(tmp, target)
                tmp = aside
        else:
            os.rename(tmp, target)
        fsync_directory(target.parent)
    finally:
        if tmp.exists():  # the failed new directory, or the replaced old one
            shutil.rmtree(tmp, ignore_errors=True)


def _link_or_copy(src, dst) -> None:
    if os.path.islink(src):
        os.symlink(os.readlink(src), dst)
        return
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)
