"""Writing results: everything goes into a temporary folder beside the destination, which is
moved into place only when complete, so a failure or a kill leaves nothing half-written."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from ._errors import DifffogError


def check_out_dir(out: str | os.PathLike, flag: str = "--out") -> Path:
    """``out`` as a Path, or a one-line error if it exists and is not a folder."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DifffogError(f"{flag} {out}: exists and is not a folder; choose a folder path")
    return out


@contextlib.contextmanager
def atomic_folder(out: str | os.PathLike):
    """``with atomic_folder(out) as tmp:`` write files into ``tmp``; on a clean exit they are
    moved into ``out`` (created if needed, files of the same name replaced); on an exception
    ``tmp`` is removed and ``out`` is untouched."""
    out = check_out_dir(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}-", dir=out.parent))
    try:
        yield tmp
        out.mkdir(parents=True, exist_ok=True)
        for f in tmp.iterdir():
            os.replace(f, out / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def save_image(folder: Path, name: str, image) -> None:
    """``name.npy`` (linear float32 radiance, row 0 at the top) and ``name.png`` (tone-mapped
    with :func:`difffog.plot.tonemap`'s map) in ``folder``."""
    from skimage import io as skio

    from ._image import tonemap

    img = np.asarray(image, np.float32)
    np.save(folder / f"{name}.npy", img)
    skio.imsave(folder / f"{name}.png", tonemap(img)[0], check_contrast=False)
