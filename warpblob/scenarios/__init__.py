"""The source thesis' tool-contact experiments as runnable set-ups (Shirazian 2014, chapter 6).

Each function returns a ready :class:`~warpblob.Simulation`: the reference
model meshed, its surface bound, its tool on a path. ``warpblob scenario
NAME --out DIR`` runs one and writes a time-sampled USD stage and pictures.

Example:
    >>> from warpblob import scenarios
    >>> sorted(scenarios.ALL)
    ['press_cake', 'probe_tumor', 'push_three_slabs']
"""

from ._scenarios import ALL, press_cake, probe_tumor, push_three_slabs

__all__ = ["probe_tumor", "push_three_slabs", "press_cake", "ALL"]
