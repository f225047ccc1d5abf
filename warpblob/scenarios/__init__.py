"""The source thesis' experiments as runnable set-ups (Shirazian 2014, chapter 6).

Each function returns a ready :class:`~warpblob.Simulation`: the reference
model meshed, its surface bound, its tool on a path. ``warpblob scenario
NAME --out DIR`` runs one and writes a time-sampled USD stage and pictures.
Tool contact: :func:`probe_tumor`, :func:`push_three_slabs`,
:func:`press_cake`; cutting: :func:`cut_tumor`; drilling: :func:`drill_eggshell`, :func:`craniotomy` (their cut statistics per
step: :func:`drill_steps`).

Example:
    >>> from warpblob import scenarios
    >>> sorted(scenarios.ALL)
    ['craniotomy', 'cut_tumor', 'drill_eggshell', 'press_cake', 'probe_tumor', 'push_three_slabs']
"""

from ._cutting import cut_tumor
from ._drilling import craniotomy, drill_eggshell, drill_steps, total_steps
from ._scenarios import CONTACT, press_cake, probe_tumor, push_three_slabs

#: the scenarios by name, as the command line knows them
ALL = {**CONTACT, "cut_tumor": cut_tumor, "drill_eggshell": drill_eggshell, "craniotomy": craniotomy}

__all__ = ["probe_tumor", "push_three_slabs", "press_cake", "cut_tumor", "drill_eggshell", "craniotomy", "drill_steps", "total_steps", "ALL"]
