"""The output folder of a reconstruction: what a run writes there, and the rules that keep the
user's files and the folder's state safe.

* **Inputs are never deleted or replaced.** Every path a run deletes or replaces (the names in
  :data:`OUTPUTS`, its temporaries; under ``overwrite`` these are all it deletes) is checked
  against every input before anything is written: the images folder, each image file, the pairs
  file, the camera file and any other file the caller read (weights), symbolic links resolved.
  An input that is, or lies inside, such a path is an error (:func:`check_inputs_kept`).
* **One run at a time.** A run holds an exclusive lock (``fcntl.flock``) on ``OUT/.lock`` from
  before its first write to its end (:func:`output_lock`); another run on the folder is refused.
* **The summary describes the folder.** ``summary.json`` and ``reconstruction.png`` are removed
  before any step changes the files they describe (:func:`begin_writing`), and written last.
* **Temporaries.** Files are written under names unique to the run (:func:`localscale.core.outputs.temporary_name`)
  and renamed; ``sparse/`` is built beside it and swapped in (:func:`localscale.core.outputs.replace_dir`).
  The temporaries a killed run left are removed by the next run that writes the folder.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator

from ..core.errors import LocalScaleError
from ..core.outputs import make_dir, resolved_path, stale_temporaries

#: the files and folders a run writes into its output folder
OUTPUTS = (
    "run.json",
    "features.h5",
    "pairs.txt",
    "matches.h5",
    "keypoints.h5",
    "geometries.h5",
    "database.db",
    "sparse",
    "summary.json",
    "reconstruction.png",
)
#: the files that describe a finished run: removed first, written last
SUMMARY_FILES = ("summary.json", "reconstruction.png")
#: the lock file a run holds (:func:`output_lock`)
LOCK_NAME = ".lock"
#: the prefixes of the temporary folders of ``sparse/`` (:func:`~.mapping.run_mapping`, :func:`~localscale.core.outputs.replace_dir`)
SPARSE_TEMPORARIES = (".sparse.tmp", ".sparse.new", ".sparse.old")


class OutputFolderError(LocalScaleError):
    """The output folder holds something a run must not overwrite or resume."""


def temporaries(out: Path) -> list:
    """The temporary files and folders of ours that a killed run left in ``out``."""
    if not out.is_dir():
        return []
    found = [t for name in OUTPUTS for t in stale_temporaries(out / name)]
    found += [p for p in out.iterdir() if p.name.startswith(SPARSE_TEMPORARIES)]
    return sorted(set(found))


def run_entries(out: Path) -> list:
    """What ``out`` holds, less the lock file and the temporaries a killed run left."""
    if not out.is_dir():
        return []
    leftovers = set(temporaries(out)) | {out / LOCK_NAME}
    return [p for p in out.iterdir() if p not in leftovers]


def _forms(path) -> set:
    """``path`` as written (absolute) and with its symbolic links resolved."""
    return {Path(os.path.abspath(path)), resolved_path(path)}


def check_inputs_kept(out: Path, inputs: Iterable) -> None:
    """Raise :class:`OutputFolderError` when an input (``(what, path)`` pairs; None paths are
    skipped) is, or lies inside, a path that a run in ``out`` deletes or replaces."""
    replaced = [out / name for name in OUTPUTS] + temporaries(out)
    targets = [(p, f) for p in replaced for f in _forms(p)]
    for what, path in inputs:
        if path is None:
            continue
        for form in _forms(path):
            for p, target in targets:
                if form == target:
                    raise OutputFolderError(
                        f"{p} is the {what} ({path}), and a run in {out} deletes or replaces it: "
                        "give another output folder (-o)"
                    )
                if target in form.parents:
                    raise OutputFolderError(
                        f"the {what} {path} lies inside {p}, which a run in {out} deletes or replaces: "
                        "give another output folder (-o)"
                    )


def _busy(out: Path) -> OutputFolderError:
    return OutputFolderError(
        f"another run is writing to {out} (it holds {out / LOCK_NAME}): wait for it to end, or give another folder"
    )


def check_not_held(out: Path) -> None:
    """Raise :class:`OutputFolderError` when another run holds ``out`` (:func:`output_lock`);
    writes nothing."""
    try:
        import fcntl
    except ImportError:  # no flock: runs are not locked
        return
    try:
        fd = os.open(out / LOCK_NAME, os.O_RDONLY)
    except OSError:
        return  # no lock file: no run has written the folder yet
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        raise _busy(out) from None
    except OSError:
        pass  # a file system without locks
    finally:
        os.close(fd)


@contextmanager
def output_lock(out: Path) -> Iterator[None]:
    """Create ``out`` and hold the exclusive lock on ``out/.lock`` within the block; raises
    :class:`OutputFolderError` when another run holds it. Where the file system has no locks the
    block runs unlocked."""
    make_dir(out)
    try:
        fd = os.open(out / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:
        raise OutputFolderError(f"cannot write {out / LOCK_NAME}: {e.strerror or e}") from None
    try:
        try:
            import fcntl

            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise _busy(out) from None
        except (ImportError, OSError):
            pass
        yield
    finally:
        os.close(fd)  # releases the lock


def begin_writing(out: Path, overwrite: bool) -> None:
    """Before the first step changes ``out``: remove the summary files (they describe the run
    before), then with ``overwrite`` every name of :data:`OUTPUTS` (``run.json`` first), and the
    temporaries a killed run left. Call it holding :func:`output_lock`."""
    names = SUMMARY_FILES + tuple(n for n in OUTPUTS if n not in SUMMARY_FILES) if overwrite else SUMMARY_FILES
    for p in [out / n for n in names] + temporaries(out):
        _remove(p)


def _remove(p: Path) -> None:
    import shutil

    try:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()
    except OSError as e:
        raise OutputFolderError(f"cannot remove {p}: {e.strerror or e}") from None
