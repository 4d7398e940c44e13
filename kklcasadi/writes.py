"""Writes that cannot be half done and cannot collide: one file, or a directory of files as one.

:func:`write_file` writes a temporary file beside the target, flushes it to disk and then either
links it into place (a new file: :func:`os.link` fails where the target exists, so of two writers
exactly one wins) or replaces the target (``overwrite``: :func:`os.replace`).

:func:`write_dir` writes every file of an artefact (a model's weights and card, the C files of an
observer) into a temporary directory beside the target and then publishes it with one rename: a
new target is renamed into place, an existing one is swapped with it in one step (Linux
``renameat2(RENAME_EXCHANGE)``) after the files of the target that are not the writer's have been
hard-linked into the new directory. A writer killed at any point leaves the old directory or the
new one whole, and at most a hidden ``.NAME.tmp-*`` directory beside it. The check of what the
target holds and the publishing rename run under a lock of the parent directory (``flock``), so
of two writers of one new target without ``overwrite`` exactly one wins and the other gets a
:class:`FileExistsError`.

Where one rename cannot do it (a system without ``RENAME_EXCHANGE``, a target that holds a
directory that is not the writer's, or the current directory), the files are replaced one by one
in the order given, each atomically: a writer killed in between can leave a mixed set. A model's
card then refuses the other weights on load (its ``weights_sha256``); C files have no such check.

:func:`staged` gives code that writes files itself (a plot's ``savefig``, a report's table) a
temporary directory whose files are then published with :func:`write_dir`: the report commands'
files (``evaluate``, ``compare``, ``generalise``, ``robustness``, ``bench scaling``) appear as one.
"""

from __future__ import annotations

import ctypes
import errno
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Mapping, Union

from .validation import error

__all__ = ["write_file", "write_dir", "write_files", "staged", "locked", "claim", "refuse_existing", "place",
           "Data"]

Data = Union[bytes, str]

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def _bytes(data: Data) -> bytes:
    return data.encode("utf-8") if isinstance(data, str) else bytes(data)


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _temp_file(directory: Path, name: str, data: Data) -> Path:
    handle, temp = tempfile.mkstemp(dir=directory, prefix=f".{name}.tmp-")
    try:
        with os.fdopen(handle, "wb") as stream:
            stream.write(_bytes(data))
            stream.flush()
            os.fsync(stream.fileno())
    except BaseException:
        os.unlink(temp)
        raise
    return Path(temp)


@contextmanager
def locked(directory: Path) -> Iterator[None]:
    """Hold an exclusive ``flock`` of ``directory`` (an existing directory) while the block runs.

    Every writer of this module takes the lock of the target's parent for its check and its rename;
    where the system has no ``flock`` the block runs unlocked.
    """
    try:
        import fcntl
    except ImportError:                  # not POSIX: the renames alone decide
        yield
        return
    fd = os.open(directory, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)                     # closing the descriptor releases the lock


@contextmanager
def claim(directory: Path, argument: str) -> Iterator[Path]:
    """Create ``directory`` if needed and hold it for this process while the block runs (a non-blocking
    ``flock``): a second process that claims it gets a one-line error naming ``argument`` at once.

    Raises
    ------
    FileExistsError
        Another process holds it.
    """
    directory.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:
        yield directory
        return
    fd = os.open(directory, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise FileExistsError(f"{argument}: another process is writing {directory} now; wait for it to "
                                  "finish, or choose another path.") from None
        yield directory
    finally:
        os.close(fd)


def refuse_existing(targets: Mapping[Union[str, os.PathLike], str]) -> None:
    """Refuse, before any work, a run that would write where something already is: a command without
    ``--overwrite`` checks its outputs first (and writes them exclusively at the end), so a long run is not lost
    on a path it may not write.

    Parameters
    ----------
    targets : Mapping[path-like, str]
        Each output path and the argument (the CLI flag) that names it, in the order checked.

    Raises
    ------
    FileExistsError
        A target exists (a file, a directory or a link); the one line names its argument.
    """
    for path, argument in targets.items():
        if os.path.lexists(path):
            raise FileExistsError(f"{argument}: {path} exists and this command does not overwrite; move it away, "
                                  f"or choose another {argument}.")


def write_file(path: Union[str, os.PathLike], data: Data, *, overwrite: bool = False,
               argument: str = "path") -> Path:
    """Write one file atomically: the old file or the new one is whole at every moment.

    Parameters
    ----------
    path : str or path-like
        The file; its directory is created if needed.
    data : bytes or str
        The content (a str is written as UTF-8).
    overwrite : bool
        Replace an existing file. Without it the write is an exclusive create: where ``path``
        exists (or another writer creates it first) nothing is written.
    argument : str
        Named in the errors.

    Raises
    ------
    FileExistsError
        ``path`` exists and ``overwrite`` is False.
    ValueError
        ``path`` is a directory.
    """
    path = Path(path)
    if path.is_dir():
        raise error(argument, "a file path", str(path), "It is a directory; name a file inside it.")
    path.parent.mkdir(parents=True, exist_ok=True)
    place(_temp_file(path.parent, path.name, data), path, overwrite=overwrite, argument=argument)
    return path


def place(temp: Path, path: Path, *, overwrite: bool = False, argument: str = "path") -> None:
    """Put a finished temporary file (written and synced in the folder of ``path``) at ``path`` in one step:
    linked (an exclusive create) or, with ``overwrite``, renamed over it; the temporary file is gone afterwards
    whatever happens, and the folder is synced.

    Raises
    ------
    FileExistsError
        ``path`` exists and ``overwrite`` is False (``path`` is left as it was).
    """
    try:
        if overwrite:
            os.replace(temp, path)
        else:
            try:
                os.link(temp, path)
            except FileExistsError:
                raise FileExistsError(f"{argument}: {path} exists; pass overwrite (CLI: --overwrite) to replace "
                                      "it, or choose another path.") from None
    finally:
        if temp.exists():
            temp.unlink()
    _fsync_dir(path.parent)


def _exchange(a: Path, b: Path) -> bool:
    """Swap two directories in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where the system cannot."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(code, os.strerror(code), str(b))


def _inside_cwd(target: Path) -> bool:
    try:
        cwd = Path.cwd().resolve()
    except FileNotFoundError:
        return False
    return cwd == target or target in cwd.parents


def write_dir(directory: Union[str, os.PathLike], files: Mapping[str, Data], *, overwrite: bool = False,
              owned: tuple = (), argument: str = "directory") -> Path:
    """Write the files of one artefact into ``directory`` as one step (see the module's docstring).

    Parameters
    ----------
    directory : str or path-like
        The target directory; its parent is created if needed.
    files : Mapping[str, bytes or str]
        File names (no path separators) and contents, in the order a one-by-one write uses.
    overwrite : bool
        Replace these files where the target holds them. Without it the write is an exclusive
        create: where the target holds one of them (or another writer publishes first) nothing is
        written.
    owned : tuple of str
        Other names in the target that are the writer's (e.g. a previous model's history, the
        training checkpoints): dropped, not carried into the new directory.
    argument : str
        Named in the errors.

    Returns
    -------
    Path
        ``directory``.

    Raises
    ------
    FileExistsError
        The target holds one of ``files`` and ``overwrite`` is False.
    ValueError
        ``directory`` is a file, or a file name has a path separator.
    """
    target = Path(directory).resolve()
    for name in files:
        if not name or Path(name).name != name or name in (".", ".."):
            raise error("files", "plain file names", name)
    if target.exists() and not target.is_dir():
        raise error(argument, "a directory", str(directory), "It is a file; choose a directory path.")
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}.tmp-"))
    try:
        for name, data in files.items():
            with open(staging / name, "wb") as stream:
                stream.write(_bytes(data))
                stream.flush()
                os.fsync(stream.fileno())
        _fsync_dir(staging)
        with locked(target.parent):
            _publish(staging, target, files, overwrite, owned, argument)
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    _fsync_dir(target.parent)
    return target


def write_files(files: Mapping[Union[str, os.PathLike], Data], *, argument: str = "files") -> list[Path]:
    """Write the files of one result that lie in several directories (a record and its plot beside it, the page
    in ``docs/``) exclusively: one :func:`write_dir` per directory, in the order the directories first appear.

    Every file's content is given, so nothing is computed between the writes; a writer killed between two
    directories leaves the first directory's files whole and the second's absent.

    Parameters
    ----------
    files : Mapping[path-like, bytes or str]
        Each file's path and content.
    argument : str
        Named in the errors.

    Returns
    -------
    list of Path
        The paths written, in the order given.

    Raises
    ------
    FileExistsError
        One of them exists (nothing of its directory is written; the directories before it are).
    """
    groups: dict[Path, dict[str, Data]] = {}
    for path, data in files.items():
        groups.setdefault(Path(path).resolve().parent, {})[Path(path).name] = data
    for directory, group in groups.items():
        write_dir(directory, group, argument=argument)
    return [Path(path) for path in files]


@contextmanager
def staged(directory: Union[str, os.PathLike], *, overwrite: bool = False,
           argument: str = "directory") -> Iterator[Path]:
    """A temporary directory for the files of one artefact, written by any code (a report's table, its JSON, its
    plots), published into ``directory`` as one (:func:`write_dir`) when the block ends; nothing is published where
    the block raises.

    Parameters
    ----------
    directory : str or path-like
        The target directory.
    overwrite : bool
        Replace the files ``directory`` holds under the same names (see :func:`write_dir`).
    argument : str
        Named in the errors.

    Yields
    ------
    Path
        The temporary directory (outside ``directory``); only the plain files in it are published.
    """
    with tempfile.TemporaryDirectory(prefix="kklcasadi-stage-") as temp:
        stage = Path(temp)
        yield stage
        files = {path.name: path.read_bytes() for path in sorted(stage.iterdir()) if path.is_file()}
        write_dir(directory, files, overwrite=overwrite, argument=argument)


def _publish(staging: Path, target: Path, files: Mapping[str, Data], overwrite: bool, owned: tuple,
             argument: str) -> None:
    if not target.exists():
        try:
            os.rename(staging, target)
        except OSError as exc:           # created since, by a writer that does not take the lock
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
            raise FileExistsError(f"{argument}: {target} was created by another writer just now; choose another "
                                  "path, or pass overwrite (CLI: --overwrite) to replace it.") from None
        return
    entries = {entry.name: entry for entry in os.scandir(target)}
    taken = [name for name in files if name in entries]
    if taken and not overwrite:
        raise FileExistsError(f"{argument}: {target / taken[0]} exists; pass overwrite (CLI: --overwrite) to replace "
                              "it, or choose another path.")
    carried = {name: entry for name, entry in entries.items() if name not in files and name not in owned}
    foreign_dirs = [name for name, entry in carried.items() if entry.is_dir(follow_symlinks=False)]
    if foreign_dirs or _inside_cwd(target) or not _carry(carried, staging) or not _exchange(staging, target):
        _one_by_one(staging, target, files, owned)


def _carry(entries: Mapping[str, os.DirEntry], staging: Path) -> bool:
    """Hard-link the target's other files (and copy its symbolic links) into the new directory."""
    for name, entry in entries.items():
        if entry.is_symlink():
            os.symlink(os.readlink(entry.path), staging / name)
        elif entry.is_file(follow_symlinks=False):
            try:
                os.link(entry.path, staging / name)
            except OSError:
                return False
        else:
            return False
    return True


def _one_by_one(staging: Path, target: Path, files: Mapping[str, Data], owned: tuple) -> None:
    """The files replaced one at a time, each atomically; the writer's other old files removed last."""
    for name in files:
        os.replace(staging / name, target / name)
    for name in owned:
        old = target / name
        if name not in files and old.is_dir() and not old.is_symlink():
            shutil.rmtree(old)
        elif name not in files and (old.is_file() or old.is_symlink()):
            old.unlink()

