"""Output files that are either complete or absent: :func:`atomic_output`."""
from __future__ import annotations

import glob
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class OutputError(OSError):
    """An output file could not be written; the message names the file and the reason."""


def _file_mode(path: Path) -> int:
    """The mode the file at ``path`` has, or a new file gets (0666 less the umask)."""
    if path.exists():
        return path.stat().st_mode & 0o777
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def _resolved(path: Path) -> Path:
    """The file ``path`` names once symlinks are followed (a dangling link: the file it would create);
    OutputError for a symlink loop."""
    try:
        return Path(os.path.realpath(path, strict=True))
    except FileNotFoundError:
        return Path(os.path.realpath(path))
    except OSError as error:
        raise OutputError(f"{path}: cannot write there ({error.strerror or error})") from None


@contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """Yields a temporary path beside ``path`` (same folder and suffix) to write to. When the block
    ends without error the file is flushed to disk and renamed over ``path``; otherwise it is
    removed, so ``path`` holds either the new complete file or what it held before. A symlink is
    followed (the file it points to is replaced, the link kept). Where ``path`` is not a regular
    file (``/dev/null``, ``/dev/stdout``, a FIFO) the block writes into it directly: it is never
    replaced. An ``OSError`` (full disk, file size limit, unwritable folder) becomes
    :class:`OutputError` naming ``path``."""
    path = Path(path)
    target = _resolved(path)
    if target.is_dir():
        raise OutputError(f"{path} is a folder; give a file name")
    if target.exists() and not target.is_file():
        try:
            yield target
        except OSError as error:
            raise OutputError(f"{path}: could not write it ({error.strerror or error})") from None
        return
    try:
        fd, temporary = tempfile.mkstemp(prefix=f".{target.name}.", suffix=target.suffix, dir=target.parent)
        os.close(fd)
    except OSError as error:
        raise OutputError(f"{path}: cannot write there ({error.strerror or error})") from None
    temporary = Path(temporary)
    try:
        yield temporary
        with open(temporary, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(temporary, _file_mode(target))  # mkstemp's files are private (0600); an output is not
        os.replace(temporary, target)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        raise OutputError(f"{path}: could not write it ({error.strerror or error}); nothing was written") from None
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def remove_leftovers(path: str | os.PathLike) -> list[Path]:
    """Removes the temporary files that :func:`atomic_output` writers of ``path`` killed mid-write
    left beside it (``.NAME.<random>SUFFIX``) -> the files removed. Call it only where no other
    process is writing ``path``."""
    target = _resolved(Path(path))
    removed = []
    for leftover in target.parent.glob(f".{glob.escape(target.name)}.*{glob.escape(target.suffix)}"):
        if leftover.is_file():
            leftover.unlink(missing_ok=True)
            removed.append(leftover)
    return removed


def read_json_lines(path: str | os.PathLike) -> list[dict]:
    """The records of a JSON Lines file written a record at a time, up to the first line a killed
    writer left unfinished ([] when the file does not exist)."""
    import json

    records = []
    path = Path(path)
    for line in path.read_text().splitlines() if path.exists() else []:
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            break
    return records


def write_json_lines(path: str | os.PathLike, records: list[dict]) -> None:
    """``records`` as JSON Lines at ``path``, through :func:`atomic_output`."""
    import json

    write_text_atomically(path, "".join(json.dumps(record) + "\n" for record in records))


def save_atomically(obj: object, path: str | os.PathLike) -> None:
    """``torch.save(obj, path)`` through :func:`atomic_output`. The object is serialised in memory
    first, so a full disk surfaces as the OS's reason ("No space left on device"), not as a
    serialiser error."""
    import io

    import torch

    buffer = io.BytesIO()
    torch.save(obj, buffer)
    with atomic_output(path) as temporary:
        temporary.write_bytes(buffer.getbuffer())


def write_text_atomically(path: str | os.PathLike, text: str) -> None:
    """``Path(path).write_text(text)`` through :func:`atomic_output`."""
    with atomic_output(path) as temporary:
        temporary.write_text(text)
