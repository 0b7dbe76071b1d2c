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


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """
    Write a file all at once or not at all: the block writes to the yielded temporary path (``.<name>.<pid>.<random>
    .tmp.<suffix>`` in ``path``'s folder, which is created if needed); when it succeeds the file is synced to disk and
    renamed over ``path`` (a symbolic link is written through), else it is deleted and ``path`` is left as it was.
    """
    path = Path(os.path.realpath(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.is_file():
        mode = os.stat(path).st_mode & 0o7777
    else:  # as open(path, "w") would create it
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o666 & ~umask
    remove_stale_temporaries(path)
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
    """Delete the temporary files of :func:`atomic_path` for ``path`` whose writer process no longer runs (a killed save)."""
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
    except PermissionError:  # another user's process
        pass
    return True


def save_path_with_suffix(path: str | os.PathLike, suffix: str) -> Path:
    """The file SB3's ``save``/``save_to_pkl`` write for ``path``: with ``.<suffix>`` if it has none, ``<path>_2`` if a folder."""
    path = Path(path)
    if path.suffix == "":
        path = Path(f"{path}.{suffix}")
    if path.is_dir():
        path = Path(f"{path}_2")
    return path


def non_finite_entries(observation: Any, limit: int = 5) -> str | None:
    """
    The NaN and infinite entries of an observation, an array or a dict of arrays, e.g. ``obs[0, 1] = nan,
    obs['image'][2] = inf`` (at most ``limit``, then how many more), or ``None`` when every entry is finite.
    """
    listed: list[str] = []
    count = 0
    for key, value in observation.items() if isinstance(observation, dict) else [(None, observation)]:
        array = np.asarray(value)
        if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.complexfloating)):
            continue  # integers are always finite
        indices = np.argwhere(~np.isfinite(array))
        count += len(indices)
        prefix = "obs" if key is None else f"obs[{key!r}]"
        for index in indices[: max(limit - len(listed), 0)]:
            entry = f"[{', '.join(str(i) for i in index)}]" if array.ndim > 0 else ""
            listed.append(f"{prefix}{entry} = {array[tuple(index)]}")
    if count == 0:
        return None
    return ", ".join(listed) + (f" and {count - len(listed)} more" if count > len(listed) else "")
