"""Small pieces shared by the algorithms of the package."""

import glob
import os
import re
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import numpy as np


def _new_file_mode() -> int:
    """Permissions of a file created with ``open(path, "w")``: 0o666 less the process's umask."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """
    Write a file all at once or not at all: the block writes to the yielded temporary path, in the same folder as
    ``path``; when the block succeeds the temporary file is synced to disk and renamed over ``path``
    (``os.replace``, atomic on POSIX and Windows), else it is deleted and ``path`` is left as it was.
    A full disk or an interrupted save therefore never destroys the previous file.

    :param path: The file to write (its folder is created if needed; a symbolic link is written through)
    :return: The temporary path to write to (it keeps ``path``'s suffix: ``.<name>.<random>.tmp.<suffix>``)
    """
    path = Path(path)
    if path.is_symlink():
        path = Path(os.path.realpath(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    mode = (os.stat(path).st_mode & 0o7777) if path.is_file() else _new_file_mode()
    remove_stale_temporaries(path)
    # The writer's process id in the name: remove_stale_temporaries deletes the files of writers no longer running
    descriptor, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.{os.getpid()}.", suffix=f".tmp{path.suffix}")
    os.close(descriptor)
    temporary_path = Path(temporary)
    try:
        yield temporary_path
        with open(temporary_path, "rb+") as file:
            os.fsync(file.fileno())
        os.chmod(temporary_path, mode)
        os.replace(temporary_path, path)
    except BaseException:
        with suppress(OSError):
            temporary_path.unlink()
        raise


def remove_stale_temporaries(path: str | os.PathLike) -> None:
    """
    Delete the temporary files that :func:`atomic_path` writes for ``path`` and whose writer process no longer runs
    (a save killed before it could clean up); those of running writers are kept.
    """
    path = Path(path)
    name = re.compile(rf"\.{re.escape(path.stem)}\.(\d+)\.[^.]+\.tmp{re.escape(path.suffix)}")
    for temporary in path.parent.glob(f".{glob.escape(path.stem)}.*.tmp{glob.escape(path.suffix)}"):
        match = name.fullmatch(temporary.name)
        if match and not _process_runs(int(match.group(1))):
            with suppress(OSError):
                temporary.unlink()


def _process_runs(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's process
    return True


def save_path_with_suffix(path: str | os.PathLike, suffix: str) -> Path:
    """
    The file SB3's ``save``/``save_to_pkl`` write for ``path``: ``path`` with ``.<suffix>`` appended when it has
    no suffix (``model`` -> ``model.zip``), ``<path>_2`` when that is a folder.
    """
    path = Path(path)
    if path.suffix == "":
        path = Path(f"{path}.{suffix}")
    if path.is_dir():
        path = Path(f"{path}_2")
    return path


def non_finite_entries(observation: Any, name: str = "obs", limit: int = 5) -> str | None:
    """
    Describe the NaN and infinite entries of an observation, e.g. ``obs[0, 1] = nan, obs['image'][2] = inf``.

    :param observation: An array, or a dict of arrays (Dict observation spaces); integer arrays are always finite
    :param name: What to call the observation in the description
    :param limit: At most that many entries are listed, then how many more there are
    :return: The description, or ``None`` when every entry is finite
    """
    items = observation.items() if isinstance(observation, dict) else [(None, observation)]
    listed: list[str] = []
    count = 0
    for key, value in items:
        array = np.asarray(value)
        if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.complexfloating)):
            continue
        bad = ~np.isfinite(array)
        if not bad.any():
            continue
        indices = np.argwhere(bad)
        count += len(indices)
        prefix = name if key is None else f"{name}[{key!r}]"
        for index in indices[: max(limit - len(listed), 0)]:
            entry = f"[{', '.join(str(i) for i in index)}]" if array.ndim > 0 else ""
            listed.append(f"{prefix}{entry} = {array[tuple(index)]}")
    if count == 0:
        return None
    more = f" and {count - len(listed)} more" if count > len(listed) else ""
    return ", ".join(listed) + more
