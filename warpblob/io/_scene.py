"""One way to name a scene: a built-in reference model or a USD file.

The command line and the scenario runners all take ``SCENE`` arguments; this
module resolves them, so the rule (and its error message) lives in one place.
"""

from __future__ import annotations

import os

from .._errors import SceneError

__all__ = ["USD_SUFFIXES", "load_scene"]

#: suffixes of the USD layers the readers take
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")


def load_scene(scene: str):
    """A built-in scene by name, or a model from a USD file.

    Args:
        scene: a name of :data:`warpblob.scenes.ALL` (``"tumor"``) or the path
            of a USD file in the format of ``docs/usd_format.md``.

    Returns:
        The model (:class:`~warpblob.tree.Node`).

    Raises:
        SceneError: an unknown name (the message lists the built-in ones), or
            a file that cannot be read.

    Example:
        >>> from warpblob.io._scene import load_scene
        >>> load_scene("peanut").bounds()[0].shape
        (3,)
    """
    from .. import scenes

    if scene in scenes.ALL:
        return scenes.ALL[scene]()
    if scene.lower().endswith(USD_SUFFIXES) or os.path.sep in scene:
        from .usd import load_model

        return load_model(scene)
    names = ", ".join(scenes.ALL)
    raise SceneError(f"unknown scene {scene!r}; give a USD file or one of the built-in scenes: {names}")
