"""Output folders that are never mixed: one writer at a time, and outputs replaced as a whole.

**One writer.** Every command that writes into a folder holds its *writer lock*
(:func:`hold`): ``flock`` on ``OUT/.bftaichi.lock``, which records the holder (pid, command,
start time, host). A second writer fails at once with an error naming the holder. The kernel
releases a ``flock`` when its process dies, so a lock left by a killed process is broken by the
next writer (it finds the dead holder's record in the file and says so); a clean release
removes the file.

**All or nothing.** A writer stages its outputs in ``OUT/.bftaichi-partial/`` and
:meth:`Staging.commit` moves them in:

1. ``OUT/.bftaichi-commit.json`` (the *journal*: the names to replace and the names to remove)
   is written atomically. This is the commit point: from here on the new outputs win.
2. Each old output named in the journal is moved into ``OUT/.bftaichi-previous/``, then each
   staged file or folder into ``OUT`` (``rename`` within one file system).
3. The journal is removed; the previous outputs and the staging folder are deleted.

If a move fails (EPERM, EBUSY, ...), the moves are undone in reverse and the journal removed:
the folder holds the previous outputs, and the caller records the failure. If the process dies
anywhere in steps 1-3 (SIGKILL, power loss), the journal stays; whoever takes the folder next,
writer or reader, first rolls the commit forward (:func:`recover`). Each step is decided by what
is on disk (a staged file still in the staging folder means its old counterpart in ``OUT`` is
the previous one), so rolling forward is correct from any state, including a half-done undo.

**Readers** (``bftaichi view``, ``nbv``, ``evalviews``, :meth:`bftaichi.Posterior.load`) read
inside :func:`reading`: a shared ``flock`` on the folder itself, which a commit takes
exclusively for steps 1-3. A reader therefore sees the previous outputs or the new ones, never
a mix, and a reader never blocks a run for longer than a commit (a few renames).

Locks are advisory (other programs can still write into ``OUT``) and need a local file system
with ``flock`` (on NFS, Linux emulates it with POSIX locks; both work). SIGINT, SIGTERM and
SIGHUP are held back during steps 1-3 and delivered after them.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import json
import os
import shutil
import signal
import socket
import sys
import threading
import time
import warnings
from pathlib import Path

from ..errors import BftaichiError, BftaichiWarning, DataError

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no locking (documented in the README)
    fcntl = None

__all__ = ["hold", "reading", "recover", "Staging", "LOCK", "STAGING", "PREVIOUS", "JOURNAL"]

LOCK = ".bftaichi.lock"
STAGING = ".bftaichi-partial"
PREVIOUS = ".bftaichi-previous"
JOURNAL = ".bftaichi-commit.json"
#: Entries of a folder that belong to this mechanism, not to a run (hidden; readers skip them).
INTERNAL = (LOCK, STAGING, PREVIOUS, JOURNAL)

#: flock errors of a file system without locks (some network file systems): go on without.
_NO_LOCKS = (errno.ENOLCK, errno.EOPNOTSUPP, errno.EINVAL, errno.EBADF)

#: What the holder record says the command is; the CLI sets it to the command line.
command_line = " ".join([Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python",
                         *sys.argv[1:]])

#: How many times (50 ms apart) a refused writer rereads a lock whose record is still empty.
_RECORD_WAITS = 20
_held: dict[tuple, list] = {}  # (resolved folder, thread) -> [fd, depth]: re-entrant per thread
_held_guard = threading.Lock()


def _holder_record() -> dict:
    return {"pid": os.getpid(), "command": command_line, "host": socket.gethostname(),
            "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds")}


def _read_record(fd: int) -> dict | None:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        text = os.read(fd, 65536).decode("utf-8", "replace")
        return json.loads(text) if text.strip() else None
    except (OSError, ValueError):
        return {}


def _describe(record: dict | None) -> str:
    if not record:
        return "another process (its record is unreadable)"
    return (f"pid {record.get('pid', '?')} on {record.get('host', '?')} "
            f"(`{record.get('command', '?')}`, started {record.get('started', '?')})")


def _alive(record: dict) -> bool | None:
    """Whether the recorded holder still runs (None: another host, or unknown)."""
    if record.get("host") != socket.gethostname() or not isinstance(record.get("pid"), int):
        return None
    try:
        os.kill(record["pid"], 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


@contextlib.contextmanager
def hold(out: str | os.PathLike):
    """The writer lock of folder ``out`` (which must exist), for the ``with`` block.

    Raises BftaichiError naming the holder if another process (or another open of the lock in
    this process) holds it. Re-entrant within a thread of one process: a command that runs
    another (``evalviews`` runs ``run``) holds it once. On taking the lock, an interrupted
    commit is completed (:func:`recover`) and the leftovers of a killed writer are removed.
    """
    out = Path(out)
    key = (str(out.resolve()), threading.get_ident())
    with _held_guard:
        entry = _held.get(key)
        if entry is not None:
            entry[1] += 1
    if entry is not None:
        try:
            yield
        finally:
            with _held_guard:
                entry[1] -= 1
        return
    fd = _acquire(out)
    with _held_guard:
        _held[key] = [fd, 1]
    try:
        recover(out, locked=True)
        yield
    finally:
        with _held_guard:
            del _held[key]
        _release(out, fd)


def _acquire(out: Path) -> int | None:
    if fcntl is None:  # pragma: no cover
        return None
    path = out / LOCK
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            raise DataError(f"cannot write into output folder {out}: cannot create its lock "
                            f"file {LOCK} ({e.strerror or e})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            holder = _read_record(fd)
            for _ in range(_RECORD_WAITS):  # the holder writes its record just after locking
                if holder or e.errno in _NO_LOCKS:
                    break
                time.sleep(0.05)
                holder = _read_record(fd)
            os.close(fd)
            if e.errno in _NO_LOCKS:
                warnings.warn(f"{out}: the file system does not support locks ({e.strerror}); "
                              "writing without one: do not run two commands into this folder "
                              "at once", BftaichiWarning, stacklevel=4)
                return None
            if e.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise DataError(f"cannot lock output folder {out}: {e.strerror or e}") from None
            raise BftaichiError(
                f"output folder {out} is in use by {_describe(holder)}; wait for it to finish "
                "or choose another output folder") from None
        try:  # the file we locked must still be the lock: a releaser may have unlinked it
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
            continue
        stale = _read_record(fd)
        if stale is not None:  # a holder that never released it: killed
            state = {False: "no longer runs", None: "is gone"}.get(_alive(stale) if stale else None,
                                                                  "is gone")
            warnings.warn(f"{out}: broke the stale lock of {_describe(stale)}, which {state}",
                          BftaichiWarning, stacklevel=4)
        data = json.dumps(_holder_record()).encode()
        os.ftruncate(fd, 0)
        os.pwrite(fd, data, 0)
        return fd


def _release(out: Path, fd: int | None) -> None:
    if fd is None:  # pragma: no cover
        return
    try:
        os.unlink(out / LOCK)  # while still locked: the next writer creates a fresh file
    except OSError:
        os.ftruncate(fd, 0)  # cannot unlink (folder became read-only): mark it released
    finally:
        os.close(fd)


@contextlib.contextmanager
def _folder_lock(out: Path, exclusive: bool):
    """``flock`` on the folder itself: shared for readers, exclusive for a commit."""
    if fcntl is None:  # pragma: no cover
        yield
        return
    try:
        fd = os.open(out, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:  # cannot open it: nothing to read either; the reader reports the files
        yield
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        except OSError as e:
            if e.errno not in _NO_LOCKS:
                raise DataError(f"cannot lock output folder {out}: {e.strerror or e}") from None
        yield
    finally:
        os.close(fd)


@contextlib.contextmanager
def reading(out: str | os.PathLike, timeout_s: float = 30.0):
    """Read the outputs in folder ``out`` inside this block: no commit happens meanwhile.

    An interrupted commit found there is completed first (which needs write access to the
    folder; otherwise DataError says so)."""
    out = Path(out)
    if not out.is_dir():
        yield
        return
    deadline = time.monotonic() + timeout_s
    while True:
        with _folder_lock(out, exclusive=False):
            if not (out / JOURNAL).exists():
                yield
                return
        # the commit's writer died after its commit point: complete it, then read
        try:
            with hold(out):
                pass  # taking the writer lock recovers
        except BftaichiError:
            if time.monotonic() > deadline:  # a live writer holds it: it recovers itself
                raise DataError(f"{out} holds an interrupted commit ({JOURNAL}) that the writer "
                                f"holding the folder has not completed in {timeout_s:.0f} s")
            time.sleep(0.2)


def recover(out: str | os.PathLike, *, locked: bool = False) -> bool:
    """Complete an interrupted commit in ``out`` and remove a killed writer's leftovers.
    Needs the writer lock (``locked=True`` says the caller holds it). True if a commit was
    completed."""
    out = Path(out)
    if not locked:
        with hold(out):
            return False  # hold() recovered
    journal = _read_journal(out)
    if journal is not None:
        try:
            with _folder_lock(out, exclusive=True):
                _roll_forward(out, journal)
                _remove(out / JOURNAL)
        except OSError as e:
            raise DataError(f"{out} holds an interrupted commit ({JOURNAL}) that cannot be "
                            f"completed: {e.strerror or e}") from None
    _remove_leftovers(out)
    return journal is not None


def _remove_leftovers(out: Path) -> None:
    """Delete what a writer staged and the previous outputs a commit moved aside."""
    for name in (STAGING, PREVIOUS):
        shutil.rmtree(out / name, ignore_errors=True)


def _read_journal(out: Path) -> dict | None:
    path = out / JOURNAL
    try:
        journal = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as e:
        raise DataError(f"{path}: the record of an interrupted commit is unreadable ({e}); "
                        f"move the folder's outputs aside and delete {JOURNAL}") from None
    ok = (isinstance(journal, dict) and isinstance(journal.get("replace"), list)
          and isinstance(journal.get("remove"), list)
          and all(isinstance(n, str) and n and "/" not in n and n not in (".", "..")
                  for n in journal["replace"] + journal["remove"]))
    if not ok:
        raise DataError(f"{path}: not a commit record of bftaichi; move the folder's outputs "
                        f"aside and delete {JOURNAL}")
    return journal


def _move(src: Path, dst: Path) -> None:
    """One step of a commit (a rename; the kill-at-every-move test replaces it)."""
    os.rename(src, dst)


def _roll_forward(out: Path, journal: dict) -> None:
    staging, previous = out / STAGING, out / PREVIOUS
    previous.mkdir(exist_ok=True)
    for name in journal["replace"] + journal["remove"]:
        old = out / name
        new_staged = name in journal["replace"] and os.path.lexists(staging / name)
        # what is in OUT is the previous output while the new one is still staged, or when the
        # name is only removed
        if (new_staged or name in journal["remove"]) and os.path.lexists(old) \
                and not os.path.lexists(previous / name):
            _move(old, previous / name)
        if new_staged:
            _move(staging / name, old)
    _fsync_dir(out)


def _roll_back(out: Path, journal: dict) -> None:
    staging, previous = out / STAGING, out / PREVIOUS
    for name in reversed(journal["replace"]):
        if not os.path.lexists(staging / name) and os.path.lexists(out / name):
            _move(out / name, staging / name)  # a new output already moved in: back out
    for name in reversed(journal["replace"] + journal["remove"]):
        if os.path.lexists(previous / name) and not os.path.lexists(out / name):
            _move(previous / name, out / name)
    _fsync_dir(out)


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif os.path.lexists(path):
        path.unlink()


@contextlib.contextmanager
def _signals_held():
    """Hold SIGINT, SIGTERM and SIGHUP back for the block (delivered when it ends)."""
    sigs = {signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", signal.SIGTERM)}
    if threading.current_thread() is not threading.main_thread() or \
            not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


class Staging:
    """``OUT/.bftaichi-partial/``: where a writer holding :func:`hold` puts its outputs until
    :meth:`commit` moves them into ``OUT`` all at once (or :meth:`discard` drops them)."""

    def __init__(self, out: str | os.PathLike):
        self.out = Path(out)
        self.dir = self.out / STAGING
        if os.path.lexists(self.dir):  # left by a writer killed before its commit point
            _remove(self.dir)
        try:
            self.dir.mkdir()
        except OSError as e:
            raise DataError(f"cannot write into output folder {self.out}: "
                            f"{e.strerror or e}") from None

    def commit(self, remove: tuple[str, ...] = ()) -> None:
        """Replace the outputs of ``OUT`` by the staged ones, and delete the ``remove`` names
        this commit does not produce, as one step. On failure the previous outputs stay and
        DataError says what could not be replaced."""
        from ..io import write_json

        replace = sorted(p.name for p in self.dir.iterdir())
        journal = {"replace": replace, "remove": sorted(set(remove) - set(replace))}
        _fsync_dir(self.dir)
        with _signals_held(), _folder_lock(self.out, exclusive=True):
            write_json(self.out / JOURNAL, journal)  # the commit point
            _fsync_dir(self.out)
            try:
                _roll_forward(self.out, journal)
            except OSError as e:
                failed = e
                try:
                    _roll_back(self.out, journal)
                    _remove(self.out / JOURNAL)
                except OSError:  # cannot undo either: the next writer or reader completes it
                    pass
                raise DataError(f"cannot replace the outputs in {self.out}: "
                                f"{failed.filename or ''}: {failed.strerror or failed}; the "
                                "previous outputs are kept") from None
            _remove(self.out / JOURNAL)
        _fsync_dir(self.out)
        self.discard()

    def discard(self) -> None:
        """Delete what is staged, and the previous outputs a commit moved aside."""
        _remove_leftovers(self.out)


@contextlib.contextmanager
def staged(out: str | os.PathLike, remove: tuple[str, ...] = ()):
    """Hold the writer lock of ``out`` and yield a staging folder whose content replaces the
    same names in ``out`` (plus ``remove``) when the block ends without an exception; an
    exception leaves ``out`` as it was."""
    with hold(out):
        staging = Staging(out)
        try:
            yield staging.dir
            staging.commit(remove)
        except BaseException:
            staging.discard()
            raise
