"""Cutting ("VolCut", SPEC section 6): so far the generated subdivision tables.

Follows the thesis' non-progressive cutter (Shirazian 2014, VolCut) and
extends it with progressive (partial) cuts after Bielser et al. 2003 and
Mor & Kanade 2000.
"""

from .._errors import CutError
from ._tables import CutTables, cut_tables, rank_index

__all__ = ["CutError", "CutTables", "cut_tables", "rank_index"]
