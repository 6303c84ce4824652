"""Marching-cubes case table, generated from first principles (no copied table).

A lattice cell is a unit cube with corners ``c = x + 2*y + 4*z`` at offsets ``(x, y, z)`` in ``{0, 1}^3``.
Its 12 edges are numbered by axis, ``edge = 4 * axis + j``; edge ``j`` of an axis starts at the corner
whose other two offsets are ``(j & 1, j >> 1)`` in cyclic axis order (see :data:`EDGE_ORIGIN`).

The table is built per *case*: which corners are negative (inside, SDF < 0; zero counts as positive)
plus, for each of the 6 cube faces, how an ambiguous face (diagonal corners of equal sign) is resolved.
For every face we draw the iso-line segments that cross it, oriented so that, looking at the face from
outside the cube, the positive (free-space) side is on the left. Each crossed edge then starts exactly one
segment and ends exactly one, so the segments chain into closed loops; triangulating each loop (in its
own direction) gives triangles whose right-hand normals point towards positive SDF.

Because a face's segments depend only on that face's four corners (and its ambiguity bit, which the
extractor derives from those same four values), two cells sharing a face draw the same segments in
opposite directions: the surface has no cracks and a consistent winding across cells. Every mesh edge is
then shared by exactly two triangles, provided no two cells draw the same chord: only the four points of an
ambiguous face can be reached from both of its cells, so only the cell above such a face may join them;
a loop that cannot be triangulated under that rule (rare, strongly ambiguous cases) is fanned around a
vertex of its own, placed at the mean of the loop's vertices.
"""

from __future__ import annotations

import functools

import numpy as np

__all__ = [
    "CORNER_OFFSETS",
    "EDGE_ORIGIN",
    "EDGE_AXIS",
    "EDGE_CORNERS",
    "FACE_CORNERS",
    "CENTRE_CODE",
    "triangle_table",
]

CORNER_OFFSETS = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=np.int64)
"""``[8, 3]`` int64: offset of each cube corner from the cell's lower corner, in lattice steps."""


def _edges() -> tuple[np.ndarray, np.ndarray]:
    origin = np.zeros((12, 3), dtype=np.int64)
    axis = np.zeros(12, dtype=np.int64)
    for a in range(3):
        for j in range(4):
            e = 4 * a + j
            origin[e, (a + 1) % 3] = j & 1
            origin[e, (a + 2) % 3] = j >> 1
            axis[e] = a
    return origin, axis


EDGE_ORIGIN, EDGE_AXIS = _edges()
"""``[12, 3]`` int64 lower-end offset and ``[12]`` int64 axis (0 x, 1 y, 2 z) of each cube edge."""


def _corner_index(offset: np.ndarray) -> int:
    return int(offset[0] + 2 * offset[1] + 4 * offset[2])


EDGE_CORNERS = np.array(
    [[_corner_index(EDGE_ORIGIN[e]), _corner_index(EDGE_ORIGIN[e] + np.eye(3, dtype=np.int64)[EDGE_AXIS[e]])]
     for e in range(12)],
    dtype=np.int64,
)
"""``[12, 2]`` int64: (lower corner, upper corner) of each edge."""


def _faces() -> np.ndarray:
    """Corners of each face, counter-clockwise seen from outside the cube."""
    faces = []
    for axis in range(3):
        for side in (0, 1):
            u, w = np.eye(3)[(axis + 1) % 3], np.eye(3)[(axis + 2) % 3]
            if side == 0:  # outward normal is -axis: swap the in-plane basis to keep u x w = normal
                u, w = w, u
            corners = [c for c in range(8) if CORNER_OFFSETS[c, axis] == side]
            rel = CORNER_OFFSETS[corners] - 0.5
            angle = np.arctan2(rel @ w, rel @ u)
            faces.append([corners[i] for i in np.argsort(angle)])
    return np.array(faces, dtype=np.int64)


FACE_CORNERS = _faces()
"""``[6, 4]`` int64: corners of faces (-x, +x, -y, +y, -z, +z), counter-clockwise seen from outside."""

_EDGE_OF_CORNERS = {frozenset(map(int, EDGE_CORNERS[e])): e for e in range(12)}


def _face_segments(negative: list[bool], face: int, positive_joined: bool) -> list[tuple[int, int]]:
    """Oriented iso-line segments ``(start edge, end edge)`` on one face (positive side on the left)."""
    q = FACE_CORNERS[face]
    crossings = []  # (edge, starts a negative run) in counter-clockwise order
    for i in range(4):
        a, b = int(q[i]), int(q[(i + 1) % 4])
        if negative[a] != negative[b]:
            crossings.append((_EDGE_OF_CORNERS[frozenset((a, b))], not negative[a]))
    n = len(crossings)
    segments = []
    for k, (edge, pos_to_neg) in enumerate(crossings):
        if not pos_to_neg:
            continue
        # Two crossings: the only partner. Four: cut off the negative run (positive corners joined
        # through the face centre) or the positive run before it (negative corners joined).
        partner = crossings[(k + 1) % n] if (n == 2 or positive_joined) else crossings[(k - 1) % n]
        segments.append((edge, partner[0]))
    return segments


def _triangles(case: int, face_bits: int) -> tuple[list[tuple[int, int, int]], list[list[int]]]:
    """Triangles of one table row and the loops that needed a centre vertex (see :func:`triangle_table`)."""
    negative = [bool((case >> c) & 1) for c in range(8)]
    successor: dict[int, int] = {}
    forbidden: set[frozenset[int]] = set()
    for face in range(6):
        segments = _face_segments(negative, face, bool((face_bits >> face) & 1))
        successor.update(segments)
        if len(segments) == 2 and face % 2 == 1:  # ambiguous upper face: see _triangulate
            points = [e for seg in segments for e in seg]
            forbidden |= {frozenset((a, b)) for a in points for b in points if a != b}
            forbidden -= {frozenset(seg) for seg in segments}
    triangles: list[tuple[int, int, int]] = []
    centred: list[list[int]] = []
    while successor:
        first = min(successor)
        loop = [first]
        nxt = successor.pop(first)
        while nxt != first:
            loop.append(nxt)
            nxt = successor.pop(nxt)
        found = _triangulate(loop, frozenset(forbidden))
        if found is None:  # fan around a vertex private to this cell and loop
            centre = CENTRE_CODE + len(centred)
            centred.append(loop)
            found = [(centre, loop[i], loop[(i + 1) % len(loop)]) for i in range(len(loop))]
        triangles += found
    return triangles, centred


def _triangulate(loop: list[int], forbidden: frozenset[frozenset[int]]) -> list[tuple[int, int, int]] | None:
    """Triangles (in loop winding) spanning a closed loop with no chord in ``forbidden``, or None.

    A chord joins two loop points that are not neighbours in the loop. The cells on both sides of an
    ambiguous face could both join two of its four points that no segment joins, giving an edge with four
    triangles; so only the cell above a face (for which it is the lower face) may draw such chords. A fan
    is tried from each apex first, then any admissible triangulation.
    """
    k = len(loop)
    for start in range(k):
        ring = loop[start:] + loop[:start]
        if all(frozenset((ring[0], ring[i])) not in forbidden for i in range(2, k - 1)):
            return [(ring[0], ring[i], ring[i + 1]) for i in range(1, k - 1)]
    return _interval_triangulation(loop, forbidden)


def _interval_triangulation(loop: list[int], forbidden: frozenset[frozenset[int]]) -> list | None:
    """Any triangulation of the polygon ``loop`` avoiding ``forbidden`` chords (O(k^3) interval search)."""
    k = len(loop)

    def allowed(i: int, j: int) -> bool:
        return j - i == 1 or (i, j) == (0, k - 1) or frozenset((loop[i], loop[j])) not in forbidden

    apex: dict[tuple[int, int], int | None] = {}  # sub-polygon i..j closed by side (i, j) -> apex or None
    for span in range(1, k):
        for i in range(k - span):
            j = i + span
            if span == 1:
                apex[i, j] = -1  # a side, nothing to fill
                continue
            apex[i, j] = next((m for m in range(i + 1, j) if allowed(i, m) and allowed(m, j)
                               and apex[i, m] is not None and apex[m, j] is not None), None)
    if apex[0, k - 1] is None:
        return None
    triangles, todo = [], [(0, k - 1)]
    while todo:
        i, j = todo.pop()
        m = apex[i, j]
        if m != -1:
            triangles.append((loop[i], loop[m], loop[j]))
            todo += [(i, m), (m, j)]
    return triangles


CENTRE_CODE = 12
"""Table entries ``>= CENTRE_CODE`` name the centre vertex of the cell's loop ``entry - CENTRE_CODE``."""


@functools.lru_cache(maxsize=1)
def triangle_table() -> tuple[np.ndarray, np.ndarray]:
    """The marching-cubes table, built once per process (about half a second).

    Row ``case * 64 + face_bits``: ``case`` bit ``c`` set when corner ``c`` is negative; ``face_bits`` bit
    ``f`` set when ambiguous face ``f`` (of :data:`FACE_CORNERS`) joins its positive corners. Bits of
    unambiguous faces are ignored (rows repeat).

    Returns:
        triangles: ``[256 * 64, T_max, 3]`` int8, -1 padded; entries 0..11 are cube edges (the vertex on
            that edge), entries ``CENTRE_CODE + j`` the centre vertex of loop ``j``.
        centres: ``[256 * 64, 4]`` int16 bit masks of the cube edges whose vertices' mean is the centre
            vertex ``j`` (0 when unused). Centre vertices appear only where an ambiguous face leaves a loop
            no admissible triangulation without one.
    """
    rows: dict[int, tuple[list[tuple[int, int, int]], list[list[int]]]] = {}
    for case in range(256):
        negative = [(case >> c) & 1 for c in range(8)]
        ambiguous = 0
        for face in range(6):
            s = [negative[c] for c in FACE_CORNERS[face]]
            if s[0] == s[2] and s[1] == s[3] and s[0] != s[1]:
                ambiguous |= 1 << face
        cache: dict[int, tuple[list[tuple[int, int, int]], list[list[int]]]] = {}
        for bits in range(64):
            if bits & ambiguous not in cache:
                cache[bits & ambiguous] = _triangles(case, bits & ambiguous)
            rows[case * 64 + bits] = cache[bits & ambiguous]
    t_max = max(len(tris) for tris, _ in rows.values())
    triangles = np.full((256 * 64, t_max, 3), -1, dtype=np.int8)
    centres = np.zeros((256 * 64, 4), dtype=np.int16)
    for row, (tris, loops) in rows.items():
        if tris:
            triangles[row, : len(tris)] = tris
        for j, loop in enumerate(loops):
            centres[row, j] = sum(1 << e for e in loop)
    return triangles, centres
