"""Linearization: a BlobTree becomes flat, kernel-ready arrays.

Following the thesis' section on linearized BlobTrees (SPEC 1.5) the tree is

1. **reduced**: transform nodes are composed and pushed into the leaves (and
   into warps, whose output starts a new frame), so that operators carry no
   matrix; every primitive and warp keeps the inverse 3x4 matrix from its
   parent frame to its local frame, and every node its box in its parent frame;
2. **merged**: nested blends, unions and intersections of the same kind
   become one operator (``Union(a, Union(b, c)) = Union(a, b, c)``), so a
   chain of unions (a tower of floors) is one wide union that the grid below
   indexes; max and min are exactly associative, a sum up to float rounding;
3. **ordered for a bounded register file**: the operands of each operator
   are sorted so that the operand needing the most registers is evaluated
   first (Sethi & Ullman 1970, generalized to n-ary nodes). With the first
   operand's result becoming the operator's accumulator, a chain of any depth
   needs one register and a balanced tree of n leaves log2(n); the kernels
   use a fixed file of :data:`SLOTS` registers per thread and no recursion;
4. **flattened** in pre-order into a structure of arrays with integer links:
   ``skip`` (one past the node's subtree, the next sibling), ``parent`` and
   ``ref`` (row in the primitive/warp table, or grid of a wide operator);
5. **indexed**: a blend, union or smooth blend with many operands
   (:data:`WIDE` or more) gets a uniform grid over its box whose cells list,
   in ascending order, the operands whose boxes meet the cell, so that a point
   visits O(1) operands instead of all of them (medusa has 2,920 primitives
   under 11 operators). The order is the same as a full traversal's, so
   pruned and full evaluation agree bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ._errors import ModelError
from .tree import _kinds
from .tree._node import Node, Transform, box_intersection, box_is_empty, box_transform, box_union
from .tree._operators import Operator, Warp
from .tree._primitives import Primitive

__all__ = ["LinearModel", "linearize", "SLOTS", "WARP_NESTING", "WIDE"]

#: registers per thread in the kernels (values, gradients, colours of open operators)
SLOTS = 16
#: warps nested inside warps along one path, at most
WARP_NESTING = 8
#: operand count from which a sparse operator gets a grid
WIDE = 8
_GRID_MAX_CELLS = 1 << 20
_GRID_CELL_FRACTION = 0.25
_GRID_MAX_ITEMS = 1 << 22
#: operators whose nested copies merge into one (max and min exactly; the sum up to rounding)
_ASSOCIATIVE = (_kinds.BLEND, _kinds.UNION, _kinds.INTERSECTION)


class _ENode:
    __slots__ = ("code", "children", "inv", "box", "params", "data", "color", "radius", "need", "source")

    def __init__(self, code, source, box, params=None):
        self.code = code
        self.source = source
        self.box = box
        self.children = []
        self.inv = None
        self.params = np.zeros(4) if params is None else params
        self.data = np.zeros(0)
        self.color = np.zeros(3)
        self.radius = 0.0
        self.need = 0


def _reduce(root: Node) -> _ENode:
    """Build the evaluation tree: transforms pushed into leaves and warps (iterative)."""
    out = [None]
    # (node, matrix to the current frame, parent enode or None, position)
    stack = [(root, np.eye(4), None, 0)]
    while stack:
        node, mat, parent, pos = stack.pop()
        while isinstance(node, Transform):
            mat = mat @ node.matrix
            node = node.child
        if isinstance(node, Primitive):
            local = mat @ node.frame
            en = _ENode(node.code, node, box_transform(mat, node.bounds()), node.params())
            en.inv = np.linalg.inv(local)[:3]
            en.data = node.data()
            en.color = node.color
            en.radius = node.radius
        elif isinstance(node, Warp):
            en = _ENode(node.code, node, box_transform(mat, node.bounds()), node.params())
            en.inv = np.linalg.inv(mat)[:3]
            en.data = node.data() if hasattr(node, "data") else np.zeros(0)
            stack.append((node.child, np.eye(4), en, 0))
        elif isinstance(node, Operator):
            en = _ENode(node.code, node, None, node.params())
            for k, child in enumerate(node.children):
                stack.append((child, mat, en, k))
            en.children = [None] * len(node.children)
        else:
            raise ModelError(f"linearize: unknown node {node!r}")
        if parent is None:
            out[0] = en
        elif parent.code in _kinds.WARP_KINDS:
            parent.children = [en]
        else:
            parent.children[pos] = en
    return out[0]


def _postorder(root: _ENode):
    order, stack = [], [root]
    while stack:
        n = stack.pop()
        order.append(n)
        stack.extend(n.children)
    return reversed(order)


def _unwrap(n: _ENode) -> _ENode:
    """A union or intersection of one operand is that operand (exactly: both
    return it unchanged); a blend of one is kept (its colour is divided by
    its own value, which rounds)."""
    while n.code in (_kinds.UNION, _kinds.INTERSECTION) and len(n.children) == 1:
        n = n.children[0]
    return n


def _finish(root: _ENode):
    """Operator boxes (from the reduced children), operand order, register need."""
    for n in _postorder(root):
        n.children = [_unwrap(c) for c in n.children]
        if n.code < _kinds.PRIMITIVE_KIND_END or n.code in _kinds.WARP_KINDS:
            n.need = n.children[0].need if n.children else 0
            continue
        if n.code in _ASSOCIATIVE:
            # Union(a, Union(b, c)) == Union(a, b, c): chains become one wide operator
            flat = []
            for c in n.children:
                flat.extend(c.children if c.code == n.code else [c])
            n.children = flat
        boxes = [c.box for c in n.children]
        if n.code == _kinds.INTERSECTION:
            n.box = box_intersection(boxes)
        elif n.code == _kinds.DIFFERENCE:
            n.box = boxes[0]
        else:
            n.box = box_union(boxes)
        needs = [c.need for c in n.children]
        if n.code == _kinds.DIFFERENCE:
            if needs[1] > needs[0]:
                n.children.reverse()
                n.params = np.array([1.0, 0.0, 0.0, 0.0])  # operands stored as (b, a)
        else:
            n.children.sort(key=lambda c: -c.need)  # stable: equal needs keep the user's order
        needs = [c.need for c in n.children]
        n.need = max(needs[0], 1 + max(needs[1:], default=0))
        if n.code in _kinds.SPARSE_KINDS and len(n.children) >= WIDE:
            n.need = max(n.need, 1 + max(needs))  # a wide operator opens its register first


def _warp_nesting(root: _ENode) -> int:
    best, stack = 0, [(root, 0)]
    while stack:
        n, w = stack.pop()
        w += n.code in _kinds.WARP_KINDS
        best = max(best, w)
        stack.extend((c, w) for c in n.children)
    return best


def _evaluation_depth(root: _ENode) -> int:
    best, stack = 0, [(root, 1)]
    while stack:
        n, d = stack.pop()
        best = max(best, d)
        stack.extend((c, d + 1) for c in n.children)
    return best


@dataclass(eq=False)
class LinearModel:
    """The flat, kernel-ready form of a model (see :func:`linearize`).

    Node arrays (pre-order, length ``node_count``): ``kind`` (int32), ``skip``
    (int32, one past the subtree), ``parent`` (int32, -1 at the root), ``ref``
    (int32: row in the placed table for primitives and warps, grid index for
    wide operators, else -1), ``lower``/``upper`` (float32 (n, 3), box in the
    parent frame), ``params`` (float32 (n, 4); a wide operator keeps its
    operand count in ``params[:, 1]``; an operator whose operands are all
    primitives has ``params[:, 2]`` 1, a "flat" operator).

    Placed table (primitives and warps, length ``placed_count``): ``inverse``
    (float32 (m, 3, 4), parent frame to local), ``stretch`` (float32, the
    spectral norm of the inverse's linear part), ``radius``, ``color`` (m, 3),
    ``data_start`` (int32) into the float32 ``data`` buffer.

    Grids of wide operators: ``grid_lower`` (g, 3), ``grid_inv_cell`` (g, 3),
    ``grid_dims`` (int32 (g, 3)), ``grid_base`` (int32, offset of the grid's
    cells in ``cell_offsets``), ``cell_offsets`` (int32, CSR), ``cell_items``
    (int32 node indices, ascending within a cell).

    Counts describe the authored tree: ``primitive_count``, ``operator_count``
    (operators, warps and transform nodes), ``depth`` (nodes on the longest
    root-to-leaf path; transform nodes add no level). ``evaluation_depth`` is
    the depth after merging, ``registers`` the register slots a thread needs,
    ``warp_nesting`` the deepest nesting of warps.
    """

    kind: np.ndarray
    skip: np.ndarray
    parent: np.ndarray
    ref: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    params: np.ndarray
    inverse: np.ndarray
    stretch: np.ndarray
    radius: np.ndarray
    color: np.ndarray
    data_start: np.ndarray
    data: np.ndarray
    grid_lower: np.ndarray
    grid_inv_cell: np.ndarray
    grid_dims: np.ndarray
    grid_base: np.ndarray
    cell_offsets: np.ndarray
    cell_items: np.ndarray
    primitive_count: int
    operator_count: int
    depth: int
    evaluation_depth: int
    registers: int
    warp_nesting: int
    _device_cache: dict = field(default_factory=dict, repr=False)

    @property
    def node_count(self) -> int:
        """Nodes of the evaluation tree (primitives, operators and warps)."""
        return int(self.kind.shape[0])

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lower, upper)`` of the whole model, float64 (3,)."""
        return self.lower[0].astype(np.float64), self.upper[0].astype(np.float64)

    def _arrays(self):
        return {k: v for k, v in self.__dict__.items() if isinstance(v, np.ndarray)}

    @property
    def nbytes(self) -> int:
        """Bytes of all arrays of the linearized form."""
        return int(sum(a.nbytes for a in self._arrays().values()))

    def nbytes_by_part(self) -> dict:
        """Bytes per primitive, per operator and of the acceleration grids."""
        node_row = sum(getattr(self, k).itemsize * int(np.prod(getattr(self, k).shape[1:])) for k in ("kind", "skip", "parent", "ref", "lower", "upper", "params"))
        placed_row = sum(getattr(self, k).itemsize * int(np.prod(getattr(self, k).shape[1:])) for k in ("inverse", "stretch", "radius", "color", "data_start"))
        grids = sum(getattr(self, k).nbytes for k in ("grid_lower", "grid_inv_cell", "grid_dims", "grid_base", "cell_offsets", "cell_items"))
        return {
            "per_primitive": node_row + placed_row,
            "per_operator": node_row,
            "data": int(self.data.nbytes),
            "grids": int(grids),
        }


def _grid_items(child_boxes, lo, inv_cell, dims) -> int:
    c0 = np.clip(np.floor((child_boxes[:, 0] - lo) * inv_cell), 0, dims - 1)
    c1 = np.clip(np.floor((child_boxes[:, 1] - lo) * inv_cell), 0, dims - 1)
    return int(np.prod(c1 - c0 + 1, axis=1).sum())


def _build_grid(op_box, child_boxes, child_index):
    """Uniform grid over ``op_box`` listing, per cell, the children whose boxes meet it."""
    lo, hi = op_box
    extent = np.maximum(hi - lo, 1e-9)
    sizes = child_boxes[:, 1] - child_boxes[:, 0]
    # cells of a quarter of the typical operand size, per axis: a point then
    # visits about twice the operands whose boxes really hold it, for ~8x the items
    cell = np.maximum(_GRID_CELL_FRACTION * np.median(sizes, axis=0), 1e-9)
    dims = np.clip(np.ceil(extent / cell), 1, 256).astype(np.int64)
    while np.prod(dims) > _GRID_MAX_CELLS or _grid_items(child_boxes, lo, dims / extent, dims) > _GRID_MAX_ITEMS:
        dims = np.maximum(dims // 2, 1)
    inv_cell = dims / extent
    c0 = np.clip(np.floor((child_boxes[:, 0] - lo) * inv_cell), 0, dims - 1).astype(np.int64)
    c1 = np.clip(np.floor((child_boxes[:, 1] - lo) * inv_cell), 0, dims - 1).astype(np.int64)
    span = c1 - c0 + 1
    counts = np.prod(span, axis=1)
    owner = np.repeat(np.arange(len(child_boxes)), counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    sx, sy = span[owner, 0], span[owner, 1]
    ix = c0[owner, 0] + local % sx
    iy = c0[owner, 1] + (local // sx) % sy
    iz = c0[owner, 2] + local // (sx * sy)
    flat = (iz * dims[1] + iy) * dims[0] + ix
    order = np.lexsort((child_index[owner], flat))
    items = child_index[owner][order]
    offsets = np.zeros(int(np.prod(dims)) + 1, dtype=np.int64)
    np.add.at(offsets, flat + 1, 1)
    return dims, inv_cell, np.cumsum(offsets), items


def linearize(model: Node) -> LinearModel:
    """Flatten ``model`` into the kernel-ready :class:`LinearModel` (cached per model).

    Raises:
        ModelError: when the model needs more than :data:`SLOTS` registers
            (a balanced tree of over 65,536 primitives) or nests more than
            :data:`WARP_NESTING` warps.

    Example:
        >>> import warpblob as wb
        >>> lm = wb.linearize(wb.scenes.tumor())
        >>> lm.primitive_count, lm.operator_count, lm.depth
        (10, 1, 2)
    """
    if isinstance(model, LinearModel):
        return model
    if not isinstance(model, Node):
        raise ModelError(f"linearize: expected a warpblob model (Node), got {type(model).__name__}")
    cached = getattr(model, "_linear", None)
    if cached is not None:
        return cached
    root = _reduce(model)
    _finish(root)
    root = _unwrap(root)
    if root.need > SLOTS:
        raise ModelError(f"linearize: the model needs {root.need} registers, more than the {SLOTS} the kernels have")
    nesting = _warp_nesting(root)
    if nesting > WARP_NESTING:
        raise ModelError(f"linearize: warps are nested {nesting} deep, at most {WARP_NESTING} are supported")

    # pre-order flattening
    nodes, parents = [], []
    stack = [(root, -1)]
    while stack:
        n, par = stack.pop()
        nodes.append(n)
        parents.append(par)
        me = len(nodes) - 1
        stack.extend((c, me) for c in reversed(n.children))
    count = len(nodes)
    index = {id(n): k for k, n in enumerate(nodes)}
    skip = np.zeros(count, dtype=np.int32)
    for k in range(count - 1, -1, -1):
        n = nodes[k]
        skip[k] = skip[index[id(n.children[-1])]] if n.children else k + 1

    kind = np.array([n.code for n in nodes], dtype=np.int32)
    empty = np.array([box_is_empty(n.box) for n in nodes])
    lower = np.array([n.box[0] for n in nodes], dtype=np.float64)
    upper = np.array([n.box[1] for n in nodes], dtype=np.float64)
    lower[empty], upper[empty] = 1.0, -1.0  # finite and empty
    params = np.array([n.params for n in nodes], dtype=np.float32)
    for k, n in enumerate(nodes):
        # an operator of primitives only: point evaluation folds them in one tight loop
        if n.children and n.code not in _kinds.WARP_KINDS and all(c.code < _kinds.PRIMITIVE_KIND_END for c in n.children):
            params[k, 2] = 1.0
    ref = np.full(count, -1, dtype=np.int32)

    placed = [k for k, n in enumerate(nodes) if n.inv is not None]
    ref[placed] = np.arange(len(placed), dtype=np.int32)
    inverse = np.array([nodes[k].inv for k in placed], dtype=np.float32).reshape(-1, 3, 4)
    # largest stretch of each inverse map (spectral norm), padded against rounding
    stretch = (np.linalg.norm(inverse[:, :, :3].astype(np.float64), ord=2, axis=(1, 2)) * (1.0 + 1e-5)).astype(np.float32) if len(placed) else np.zeros(0, np.float32)
    radius = np.array([nodes[k].radius for k in placed], dtype=np.float32)
    color = np.array([nodes[k].color for k in placed], dtype=np.float32).reshape(-1, 3)
    blocks = [nodes[k].data for k in placed]
    sizes = np.array([len(b) for b in blocks], dtype=np.int64)
    data_start = (np.cumsum(sizes) - sizes).astype(np.int32)
    data = np.concatenate(blocks + [np.zeros(1)]).astype(np.float32)

    g_lower, g_inv, g_dims, g_base, offsets, items = [], [], [], [], [], []
    base = 0
    item_count = 0  # items of the grids so far: the next grid's cell offsets start there
    for k, n in enumerate(nodes):
        if n.code in _kinds.SPARSE_KINDS and len(n.children) >= WIDE and not empty[k]:
            kids = [index[id(c)] for c in n.children]
            params[k, 1] = len(kids)  # operand count: interval queries compare it with the cells a ball spans
            kid_boxes = np.stack([lower[kids], upper[kids]], axis=1)
            dims, inv_cell, offs, its = _build_grid((lower[k], upper[k]), kid_boxes, np.array(kids))
            ref[k] = len(g_lower)
            g_lower.append(lower[k])
            g_inv.append(inv_cell)
            g_dims.append(dims)
            g_base.append(base)
            offsets.append(offs + item_count)
            items.append(its)
            item_count += len(its)
            base += len(offs)

    def arr(x, dtype, shape):
        return np.array(x, dtype=dtype).reshape(shape) if len(x) else np.zeros(shape, dtype=dtype)

    lm = LinearModel(
        kind=kind,
        skip=skip,
        parent=np.array(parents, dtype=np.int32),
        ref=ref,
        lower=lower.astype(np.float32),
        upper=upper.astype(np.float32),
        params=params,
        inverse=inverse,
        stretch=stretch,
        radius=radius,
        color=color,
        data_start=data_start,
        data=data,
        grid_lower=arr(g_lower, np.float32, (-1, 3)) if g_lower else np.zeros((0, 3), np.float32),
        grid_inv_cell=arr(g_inv, np.float32, (-1, 3)) if g_inv else np.zeros((0, 3), np.float32),
        grid_dims=arr(g_dims, np.int32, (-1, 3)) if g_dims else np.zeros((0, 3), np.int32),
        grid_base=np.array(g_base, dtype=np.int32),
        cell_offsets=np.concatenate(offsets).astype(np.int32) if offsets else np.zeros(1, np.int32),
        cell_items=np.concatenate(items).astype(np.int32) if items else np.zeros(1, np.int32),
        primitive_count=model.primitive_count(),
        operator_count=model.operator_count(),
        depth=model.depth(),
        evaluation_depth=_evaluation_depth(root),
        registers=int(root.need),
        warp_nesting=nesting,
    )
    model._linear = lm
    return lm
