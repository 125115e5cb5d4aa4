"""Atomic file output: everything is written to a temporary file beside its target and
renamed into place, so a failing run never leaves half-written files or clobbers results."""

import json
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from calib3r_graph.errors import OutputError

_UMASK = os.umask(0)
os.umask(_UMASK)


@contextmanager
def atomic_path(path, suffix=""):
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix, dir=path.parent)
        os.close(fd)
    except OSError as e:
        raise OutputError(f"{path}: cannot write ({e.strerror})") from None
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp creates 0600; give the file normal permissions
        os.replace(tmp, path)
    except OSError as e:
        raise OutputError(f"{path}: cannot write ({e.strerror})") from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write_text(path, text: str):
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_json(path, obj):
    atomic_write_text(path, json.dumps(obj, indent=2) + "\n")


def atomic_savez(path, **arrays):
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, **arrays)


@contextmanager
def staged_directory(final_dir):
    """Build a directory's content in a hidden sibling and move it into place only on success.

    Files already in ``final_dir`` survive a failing run; on success each staged file
    replaces its namesake (others are kept).
    """
    final_dir = Path(final_dir)
    try:
        final_dir.parent.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{final_dir.name}.staging.", dir=final_dir.parent))
    except OSError as e:
        raise OutputError(f"{final_dir}: cannot write ({e.strerror})") from None
    try:
        yield stage
        final_dir.mkdir(parents=True, exist_ok=True)
        for src in sorted(stage.rglob("*")):
            dst = final_dir / src.relative_to(stage)
            if src.is_dir():
                dst.mkdir(parents=True, exist_ok=True)
            else:
                os.replace(src, dst)
    except OSError as e:
        raise OutputError(f"{final_dir}: cannot write ({e.strerror})") from None
    finally:
        shutil.rmtree(stage, ignore_errors=True)
