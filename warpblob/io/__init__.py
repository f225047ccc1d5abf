"""Readers and writers of other tools' formats.

Each submodule loads its heavy dependency (``pxr`` for :mod:`warpblob.io.usd`)
when it is imported; ``import warpblob`` imports none of them. The public
entry points are re-exported elsewhere (``warpblob.usd.save_model``).
"""

__all__: list[str] = []
