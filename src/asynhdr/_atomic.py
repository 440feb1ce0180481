"""Atomic file output: write to a temporary file in the target folder, then rename.

Temporary files live in the folder's own name space (``.asynhdr-tmp-PID-...``, hidden,
carrying the writing process's id). A process killed while writing (SIGKILL, a power
cut) cannot remove its temporary file; the next write into the same folder does
(:func:`sweep`), once no process with that id runs.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ["TEMP_PREFIX", "atomic_path", "check_output", "sweep"]

logger = logging.getLogger(__name__)

TEMP_PREFIX = ".asynhdr-tmp-"
"""Name prefix of every temporary file or folder asynhdr writes."""


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    except OSError:
        return True
    return True


def sweep(folder: str | os.PathLike[str]) -> int:
    """Remove the temporary files and folders that processes which no longer run left in
    ``folder``; returns how many were removed (each is logged)."""
    removed = 0
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return 0
    for e in entries:
        if not e.name.startswith(TEMP_PREFIX):
            continue
        pid_text = e.name[len(TEMP_PREFIX):].split("-", 1)[0]
        if not pid_text.isdigit() or _alive(int(pid_text)):
            continue
        try:
            if e.is_dir(follow_symlinks=False):
                shutil.rmtree(e.path)
            else:
                os.unlink(e.path)
        except FileNotFoundError:  # another process swept it first
            continue
        except OSError as exc:
            logger.warning("%s: left by process %s, which no longer runs; cannot remove it: %s",
                           e.path, pid_text, exc)
            continue
        removed += 1
        logger.info("%s: removed, left by process %s, which no longer runs", e.path, pid_text)
    return removed


def check_output(path: str | os.PathLike[str], *, overwrite: bool) -> Path:
    """Check, before any work, that ``path`` can be written: its folder exists or can be
    made (no file stands where a folder is needed), it is not a folder, and it does not
    exist unless ``overwrite`` (even then a read-only file is not replaced).

    Raises ``FileExistsError`` (exists, ``overwrite`` False) or ``ValueError`` (a
    read-only file, a folder that cannot be written, a folder where a file is wanted, or
    a file in the way of a folder), each naming the path."""
    target = Path(path)
    for parent in reversed(target.parents):
        if parent.exists() and not parent.is_dir():
            raise ValueError(f"{target}: cannot create the folder {parent}: a file has "
                             "that name")
    if target.is_dir():
        raise ValueError(f"{target}: is a folder; expected a file name")
    if target.exists() or target.is_symlink():
        if not overwrite:
            raise FileExistsError(f"{target}: exists; not replaced (overwrite it explicitly)")
        if not os.stat(target).st_mode & 0o222 or not os.access(target, os.W_OK):
            raise ValueError(f"{target}: exists and is read-only; not replaced")
    folder = next((p for p in [target.parent, *target.parent.parents] if p.exists()), None)
    if folder is not None and not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"{target}: the folder {folder} cannot be written")
    return target


@contextlib.contextmanager
def atomic_path(
    path: str | os.PathLike[str], *, suffix: str | None = None, overwrite: bool = True
) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    On any exception the temporary file is removed and ``path`` is left as it was,
    so no half-written file is ever visible under the final name; the folders made for
    ``path`` are removed again where they are empty. ``suffix``
    defaults to the target's own (some writers pick the format from it).
    ``overwrite`` False refuses an existing ``path`` (see :func:`check_output`).
    Temporary files that killed processes left in the folder are swept first.
    """
    target = check_output(path, overwrite=overwrite)
    made = [p for p in [target.parent, *target.parent.parents] if not p.exists()]
    target.parent.mkdir(parents=True, exist_ok=True)
    sweep(target.parent)
    sfx = "" if suffix is None else suffix
    fd, tmp_name = tempfile.mkstemp(prefix=f"{TEMP_PREFIX}{os.getpid()}-",
                                    suffix=f"-{target.name}{sfx}", dir=target.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the usual file mode
    try:
        yield tmp
        if not overwrite and target.exists():
            raise FileExistsError(f"{target}: appeared while it was being written; not "
                                  "replaced")
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        for folder in made:  # the folders made for it, deepest first, where still empty
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
