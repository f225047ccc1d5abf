"""Write ``usd_scenes/<name>.usda`` for every reference model of ``warpblob.scenes``.

Run ``python usd_scenes/make_scenes.py`` after changing a model or the USD
format, and commit the files; ``tests/test_usd.py`` fails while they are out
of date. The output is deterministic. ``three_slabs`` is written as
``3slabs.usda``, the thesis' name for it.
"""

from __future__ import annotations

import pathlib
import sys

import warpblob
import warpblob.usd

#: model name -> file stem, where they differ
FILE_STEMS = {"three_slabs": "3slabs"}


def scene_files(directory=None) -> dict[str, pathlib.Path]:
    """Model name -> the ``.usda`` path it is written to."""
    directory = pathlib.Path(__file__).resolve().parent if directory is None else pathlib.Path(directory)
    return {name: directory / f"{FILE_STEMS.get(name, name)}.usda" for name in warpblob.scenes.ALL}


def main(directory=None) -> list[pathlib.Path]:
    """Write every reference scene into ``directory`` (default: this script's folder)."""
    written = []
    for name, path in scene_files(directory).items():
        doc = f"warpblob reference model '{name}' (warpblob.scenes.{name}); format: docs/usd_format.md"
        written.append(warpblob.usd.save_model(warpblob.scenes.ALL[name](), path, doc=doc))
    return written


if __name__ == "__main__":
    for p in main(sys.argv[1] if len(sys.argv) > 1 else None):
        print(f"{p}  {p.stat().st_size / 1e6:.3f} MB")
