"""Cutting ("VolCut", SPEC section 6): sweep surfaces, the cut, generated subdivision tables.

Follows the thesis' non-progressive cutter (Shirazian 2014, VolCut) and
extends it with progressive (partial) cuts after Bielser et al. 2003 and
Mor & Kanade 2000.
"""

from .._errors import CutError
from ._cut import STAGES, CutResult, cut
from ._picture import render_cut
from ._sim import warm_up
from ._sweep import SweepSurface
from ._tables import CutTables, cut_tables, rank_index

__all__ = ["STAGES", "CutError", "CutResult", "CutTables", "SweepSurface", "cut", "cut_tables", "rank_index", "render_cut", "warm_up"]
