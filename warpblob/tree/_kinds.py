"""The one table of node kinds shared by the tree, the linearizer and the kernels."""

# primitives (leaves)
POINT = 0
SEGMENT = 1
DISC = 2
RING = 3
CONE = 4  # solid truncated cone; a cylinder is a cone with equal radii
POLYGON = 5  # filled planar polygon; a triangle is a polygon of three vertices
BOX = 6
INFLATE = 7
REVOLVE = 8
SWEEP = 9
PRIMITIVE_KIND_END = 10

# operators
BLEND = 10
UNION = 11
INTERSECTION = 12
DIFFERENCE = 13
SMOOTH_BLEND = 14

# warps (one operand, evaluated at a warped point)
TWIST = 20
TAPER = 21
BEND = 22

WARP_KINDS = (TWIST, TAPER, BEND)
#: operators whose operands may be visited in any subset (a zero operand is a no-op)
SPARSE_KINDS = (BLEND, UNION, SMOOTH_BLEND)
