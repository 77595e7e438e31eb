"""Eyelid-eyeball repair (Menzel et al. 2022, sec. 3.3, last paragraph): the capture mask has no eyeballs,
so a personalized eyelid shape can push eyelid vertices into the eye; those vertices are moved back onto the
eyeball surface.

Eyeballs are found by name (``eye``/``eyeball`` in the mesh name, not lashes/brows/lids) or by geometry (a
closed, nearly spherical mesh of eyeball size), and modelled by their least-squares sphere.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from ..mesh import vector_lengths
from ..natives import open3d
from .correspond import ramp_down, ramp_up

__all__ = ["Eyeball", "fit_sphere", "find_eyeballs", "eye_surfaces", "repair_eyelids", "NAMED_RADIUS"]

_EYE_NAME = re.compile(r"eye", re.IGNORECASE)
_NOT_EYE = re.compile(r"lash|brow|lid|socket|shadow|occlusion|tear", re.IGNORECASE)
#: Meshes named for the mouth's parts are never eyeballs, however round (a teeth-and-tongue block can fit a
#: sphere within the geometric test's tolerance).
_MOUTH_PART = re.compile(r"mouth|teeth|tooth|tongue|gum|jaw", re.IGNORECASE)


@dataclass
class Eyeball:
    """A sphere ``center[3]``, ``radius`` (metres) fitted to mesh ``name``; ``rms`` the fit residual (m)."""

    name: str
    center: np.ndarray
    radius: float
    rms: float


def fit_sphere(points) -> tuple[np.ndarray, float, float]:
    """Linear least-squares sphere through ``points[n,3]``: ``(center[3], radius, rms_residual)``."""
    p = np.asarray(points, dtype=np.float64)
    a = np.column_stack([2.0 * p, np.ones(len(p))])
    b = np.einsum("ij,ij->i", p, p)
    sol = np.linalg.lstsq(a, b, rcond=None)[0]
    c = sol[:3]
    r = float(np.sqrt(max(sol[3] + c @ c, 0.0)))
    rms = float(np.sqrt(np.mean((np.linalg.norm(p - c, axis=1) - r) ** 2)))
    return c, r, rms


#: The radius (m) a mesh named for an eye may have: from a child's eye to a stylized character's (a human
#: eyeball is 11-13 mm); a mesh found by geometry alone must look like a human eye (``min_radius`` to
#: ``max_radius`` of :func:`find_eyeballs`).
NAMED_RADIUS = (0.003, 0.05)


def find_eyeballs(meshes: dict, *, min_radius: float = 0.007, max_radius: float = 0.02,
                  max_rel_rms: float = 0.12, face=None, named_radius=NAMED_RADIUS,
                  rejected: list | None = None) -> list[Eyeball]:
    """Eyeballs among ``meshes`` = ``{name: points[n,3]}`` (internal metres).

    A mesh qualifies by name (contains "eye" but not lash/brow/lid/...) with a sphere fit of a radius in
    ``named_radius`` (:data:`NAMED_RADIUS`), or, unnamed (and not named for a part of the mouth), by geometry
    alone (sphere fit residual below ``max_rel_rms`` x radius, radius in [``min_radius``, ``max_radius``]).
    ``rejected``: a list that receives, for each mesh named for an eye that did not qualify, a sentence
    saying why (for the caller's warning). With ``face`` (``points[m,3]``,
    the face mesh's vertices) only the eyes of that face: spheres whose centre is within two radii of a face
    vertex (under its lids), not those of another character in the same stage. At most the two best-fitting
    spheres are returned.
    """
    tree = None
    if face is not None and len(face):
        from scipy.spatial import cKDTree

        tree = cKDTree(np.asarray(face, dtype=np.float64))
    found = []
    for name, pts in meshes.items():
        pts = np.asarray(pts, dtype=np.float64)
        if len(pts) < 20:
            continue
        c, r, rms = fit_sphere(pts)
        leaf = str(name).rsplit("/", 1)[-1]
        named = bool(_EYE_NAME.search(leaf)) and not _NOT_EYE.search(leaf)
        lo, hi = named_radius if named else (min_radius, max_radius)
        why = None
        if not (lo <= r <= hi):
            why = f"its sphere's radius {r * 1e3:.1f} mm is outside {lo * 1e3:g}-{hi * 1e3:g} mm"
        elif not named and _MOUTH_PART.search(leaf):
            continue
        elif tree is not None and tree.query(c)[0] > 2.0 * r:
            why = "its centre is not under this face's lids"   # another character's eye, or a prop
        elif not (named and rms < 2 * max_rel_rms * r or rms < max_rel_rms * r):
            why = f"it is not round (sphere fit residual {rms / r:.0%} of its radius)"
        if why is None:
            found.append(Eyeball(str(name), c, r, rms))
        elif named and rejected is not None:
            rejected.append(f"{name}: {why}")
    found.sort(key=lambda e: e.rms / e.radius)
    return found[:2]


#: Rays whose majority vote tells inside from outside (Open3D's ``nsamples``; its default is one): one ray's
#: parity is wrong where it passes within ~0.3 um of an edge of the eye mesh (the crossing counted twice or
#: not at all), and which point's ray does depends on the last bit of its float32 position. Dev1's Blender
#: round trip (float32 storage) had a lid vertex 0.21 mm outside its eyeball measured 0.21 mm *inside* after
#: its step out of the eye, sent 0.42 mm further out and spread over its lid (0.22 mm in
#: ``eyeLookDownRight``); three rays in fixed directions agree (the same answer in every run), at ~15 % more
#: CPU a query.
SIGN_RAYS = 3


class _EyeSurface:
    """One Open3D raycasting scene of a closed eye mesh (built once, queried several times)."""

    def __init__(self, points, triangles):
        o3d = open3d()

        self._o3d = o3d
        p = np.asarray(points, dtype=np.float64)
        self.origin = p.mean(axis=0)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor((p - self.origin).astype(np.float32)),
                                 o3d.core.Tensor(np.asarray(triangles, dtype=np.uint32)))

    def _tensor(self, queries):
        q = np.asarray(queries, dtype=np.float64).reshape(-1, 3) - self.origin
        return self._o3d.core.Tensor(q.astype(np.float32))

    def signed_distance(self, queries) -> np.ndarray:
        """Signed distance (m, negative inside) from ``queries[q,3]``; signed by :data:`SIGN_RAYS` rays."""
        return self.scene.compute_signed_distance(self._tensor(queries),
                                                  nsamples=SIGN_RAYS).numpy().astype(np.float64)

    def inside(self, queries) -> np.ndarray:
        """``[q]`` bool: inside the mesh (the same ray-parity vote that signs :meth:`signed_distance`)."""
        return self.scene.compute_occupancy(self._tensor(queries), nsamples=SIGN_RAYS).numpy() > 0.5

    def closest_points(self, queries) -> np.ndarray:
        """Closest surface points ``[q,3]``."""
        c = self.scene.compute_closest_points(self._tensor(queries))["points"].numpy()
        return c.astype(np.float64) + self.origin


def eye_surfaces(points, triangles) -> list:
    """``[(points[p,3], triangles[s,3]), ...]``: the surfaces of an eye mesh ``points[n,3]`` /
    ``triangles[t,3]`` that bound the lids one at a time: each closed piece that encloses another (most of
    that piece's vertices inside it), from the outer to the inner, then the eyeball (the pieces that enclose
    no other: the eyeball, a cornea lens in front of it) last, so the repair that keeps a lid off the eyeball
    is the one no later step undoes (it moves the lid outwards: out of the shells' depth too); the mesh
    itself when it is one piece or no piece encloses another.

    An eye modelled as an eyeball inside a closed shell (a cornea, tear-film or occlusion layer all round it:
    the bench avatars' eyes, a shell 2 mm out that the avatar's own lids sit inside) has no inside by ray
    parity as one mesh: a point between the two sheets is inside, at its distance from the *nearer* sheet,
    and a point inside the eyeball is inside both, so outside. Bounded by the whole mesh, the repair let a lid
    the generic shape keeps between the sheets go into the eyeball (dev1's `eyeBlinkLeft`: 23 lid vertices
    up to 0.70 mm closer to it than allowed) and sent lid vertices near the eyeball towards it as "out"
    (neighbours repaired in opposite directions: lid-margin steps). Each surface on its own has an inside,
    and every repair moves a lid out of it: away from the eyeball."""
    from scipy.sparse.csgraph import connected_components

    from ..mesh import boundary_edges, vertex_adjacency

    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles)
    count, label = connected_components(vertex_adjacency(t, len(p)), directed=False)
    if count < 2:
        return [(p, t)]
    piece = label[t[:, 0]]                                        # [t] each triangle's piece
    present = np.unique(piece).tolist()                           # the pieces with triangles
    encloses = {}
    for c in present:
        if len(boundary_edges(t[piece == c])):
            continue                                              # (an open piece has no inside)
        shell = _EyeSurface(p, t[piece == c])
        inner = [o for o in present if o != c and shell.inside(p[label == o]).mean() > 0.5]
        if inner:
            encloses[c] = len(inner)
    if not encloses:
        return [(p, t)]

    def part(cs):
        keep = np.isin(piece, cs)
        used = np.unique(t[keep])
        local = np.full(len(p), -1)
        local[used] = np.arange(used.size)
        return p[used], local[t[keep]]

    shells = sorted(encloses, key=encloses.get, reverse=True)
    return [part([c]) for c in shells] + [part([c for c in present if c not in encloses])]


def _share(surf, generic, personalized, bound, steps: int = 12) -> np.ndarray:
    """``[q]``: the largest ``t`` in [0, 1] for which ``generic + t (personalized - generic)`` (``[q,3]``)
    lies at least ``bound[q]`` from the eye (:class:`_EyeSurface`; signed distance): 1 where
    ``personalized`` meets it, else the crossing bracketed by ``steps`` bisections (to ``2^-steps``) and
    placed in its bracket by the line through the distances at its ends (one secant step). The secant makes
    ``t`` a continuous function of the points: where a bisection's midpoint lies on the bound, either
    branch ends on that midpoint (the bracket below ends at it with its distance equal to the bound, the one
    above starts there), where the bisection alone ended ``2^-steps`` of the segment apart. ``t = 0``, the
    generic shape's position, meets the bound by definition (0 where it does not)."""
    lo, hi = np.zeros(len(generic)), np.ones(len(generic))
    step = personalized - generic
    d_lo = surf.signed_distance(generic)
    d_end = d_hi = surf.signed_distance(personalized)
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        d_mid = surf.signed_distance(generic + mid[:, None] * step)
        ok = d_mid >= bound
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
        d_lo, d_hi = np.where(ok, d_mid, d_lo), np.where(ok, d_hi, d_mid)
    # the bound's crossing on the line through (lo, d_lo) and (hi, d_hi): d_lo >= bound > d_hi, but at
    # the ends of the segment (hi = 1 met, lo = 0 not)
    gap = d_lo - d_hi
    frac = np.clip((d_lo - bound) / np.where(gap > 0, gap, 1.0), 0.0, 1.0)
    t = lo + (hi - lo) * np.where(gap > 0, frac, 0.0)
    t = np.where(d_lo >= bound, t, 0.0)
    return np.where(d_end >= bound, 1.0, t)


def _largest_share(surf, generic, end, bound, steps: int = 12):
    """``[q,3]``: the point ``generic + t (end - generic)`` with the largest ``t`` of :func:`_share`: where
    neither step of :func:`_onto_bound` reaches the bound (a grazing corner of a non-star-shaped eye
    mesh), as much of the way to ``end[q,3]`` (the moved or the personalized position) as keeps the lid off
    the eye, not all or nothing; ``end`` itself where it meets the bound (``t = 1``)."""
    return generic + _share(surf, generic, end, bound, steps)[:, None] * (end - generic)


#: The correction that moves a lid vertex off the eye is spread over this many eyeball radii around it
#: (:func:`_spread_corrections`): the lid keeps one smooth margin, at the scale of the eye's own curvature,
#: whatever the mesh's resolution.
SPREAD_RADIUS = 0.5
#: Rounds of spreading (:func:`repair_eyelids`): what one round leaves short of its bound is spread again,
#: then moved onto its bound alone.
SPREAD_ROUNDS = 3
#: Corrections spread at a time (:func:`_spread_corrections`): their pairs within 1.25 :data:`SPREAD_RADIUS`
#: (~2,000 a correction on a twice-subdivided head's lid) are the repair's largest arrays.
SPREAD_CHUNK = 256


def _amount(excess, tolerance: float) -> np.ndarray:
    """How far (m) a vertex ``excess[p]`` m short of its bound is moved towards it: 0 for ``excess <= 0``,
    ``excess`` (onto the bound) from ``tolerance`` on, ``excess x smoothstep(excess / tolerance)`` between:
    a vertex that barely violates its bound is barely moved, so the repair is a continuous function of the
    positions (Lipschitz constant 1.69 in the excess), with at most 0.26 ``tolerance`` left short."""
    e = np.maximum(np.asarray(excess, dtype=np.float64), 0.0)
    return e if tolerance <= 0 else e * ramp_up(e, 0.0, tolerance)


def _spread_corrections(out, x0, near, js, ks, correction, radius: float, tree):
    """The smooth part of :func:`repair_eyelids`, in place: in shape ``js[p]`` the lid around the vertex
    ``near[ks[p]]`` that cuts into the eye (``near[k]``: indices into ``x0[n,3]``, the neutral, metres),
    whose move towards its bound is ``correction[p,3]`` (length ``m_p``), moves with it. A near vertex ``i``
    moves by the mean correction ``sum_p a_ip c_p / sum_p a_ip`` with ``a_ip = w(d_ip) m_p``, ``w = 1 -
    smoothstep(distance / radius)``, times the fade ``max_p a_ip / max_p w'(d_ip) m_p`` (``w'`` is 1 up to
    ``radius`` and falls to 0 at 1.25 ``radius``): a vertex among others that cut in takes their mean
    correction, one alone its own, and the lid around fades from the largest corrections near it to nothing
    over ``radius`` whatever the mesh's resolution (a normalisation by ``max(1, sum w)`` made the result
    depend on how many vertices lie within ``radius``). Every weight is in proportion to its correction, so a
    vertex that barely cuts in barely counts: the output is a continuous function of the corrections (before,
    a vertex's membership in the corrected set switched the mean and the fade's nearest corrected vertex).
    A vertex's shift is at most as long as the shape's offset there (the projection onto that ball: the
    repair adds no motion where the artist's shape has none, and little where it has little, continuously;
    a vertex it leaves short of its bound is moved alone). One smooth margin instead of vertices each moved
    its own way (a notched lid margin in a blink, seen in Blender on dev1, where neighbouring margin vertices
    reached their bounds along different lines). The corrections point out of the eye; a vertex the mean
    leaves short of its bound is corrected again (:func:`repair_eyelids`). ``tree``: a ``cKDTree`` of
    ``x0[near]`` (one for every round). Cost: the pairs within 1.25 ``radius`` of the corrected vertices
    only. Returns the (shape, near vertex) pairs it moved by :data:`UNMOVED` or more, ``(js[m], ks[m])``."""
    from scipy.sparse import coo_matrix
    from scipy.spatial import cKDTree

    moved_js, moved_ks = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    size = vector_lengths(correction)
    reach = 1.25 * radius
    for j in np.unique(js):                                          # the few shapes that cut into the eye
        mine = np.flatnonzero(js == j)
        m_own = size[mine]
        # [P,4]: 1 and the correction, so one product gives the weights' sum and the weighted corrections
        own = np.column_stack([np.ones(mine.size), correction[mine]])
        # only to the vertices the shape moves, each by at most as much as the shape does
        mag = vector_lengths(out[j, near])
        still = None if mag.min() > 0 else ~(mag > 0)             # (most shapes: none still)
        total = np.zeros(near.size)
        shift = np.zeros((3, near.size))
        top = np.zeros(near.size)                                 # the largest weighted correction ...
        scale = np.zeros(near.size)                               # ... against the largest near it
        for lo in range(0, mine.size, SPREAD_CHUNK):              # (pairs of a few hundred sources at a time)
            part = slice(lo, lo + SPREAD_CHUNK)
            pairs = cKDTree(x0[near[ks[mine[part]]]]).sparse_distance_matrix(tree, reach,
                                                                             output_type="ndarray")
            # the record fields as contiguous arrays, read once (each strided read of the millions of pairs
            # of a subdivided head's lid cost as much as the arithmetic on it)
            fr, to, dist = (np.ascontiguousarray(pairs[k]) for k in ("i", "j", "v"))
            del pairs
            if still is not None:
                keep = ~still[to]
                fr, to, dist = fr[keep], to[keep], dist[keep]
            fr += lo
            m = m_own[fr]
            # beyond ``radius`` a pair's weight is 0 (to the bit) and its fade's w'(d) m; within it w(d) m and
            # m (w' = 1): the sums and the largest weight over the pairs within ``radius`` only
            inner = dist <= radius
            outer = ~inner
            fade = ramp_down(dist[outer], radius, reach, overwrite=True)     # (in the compressed copy)
            fade *= m[outer]
            np.maximum.at(scale, to[outer], fade)
            fr, to, m = fr[inner], to[inner], m[inner]
            a = ramp_down(dist[inner], 0.0, radius, overwrite=True)
            a *= m
            del dist, inner, outer, fade
            np.maximum.at(scale, to, m)
            np.maximum.at(top, to, a)
            # sum_p a_ip [1, c_p] in one pass over the pairs, in their order (scipy's COO product adds
            # a_ip x own[p] to row i pair by pair: the same bits as a bincount of each column)
            sums = coo_matrix((a, (to, fr)), shape=(near.size, mine.size)) @ own
            total += sums[:, 0]
            shift += sums[:, 1:].T
        v = np.flatnonzero(total > 0)
        step = shift[:, v].T * (top[v] / (scale[v] * total[v]))[:, None]
        size_v = vector_lengths(step)
        cap = np.minimum(1.0, mag[v] / np.maximum(size_v, 1e-300))
        out[j, near[v]] += step * cap[:, None]
        v = v[size_v * cap >= UNMOVED]
        moved_js.append(np.full(v.size, j))
        moved_ks.append(v)
    return np.concatenate(moved_js), np.concatenate(moved_ks)


#: The step (m) of the differences that give the direction out of the eye (:func:`_outward`, central: this
#: much each way): the eye mesh's normal averaged over this much either side, the repair's tolerance, so
#: the direction turns within 0.05 mm of a facet's edge instead of jumping there (half of it each way turned
#: twice as fast: the coarse eye's test 10x its noise, against 5.4x; forward differences over it 4.9-5.8x).
#: Forward differences over 0.1 mm sent the lids in the bench eyes' 0.5 mm shell back more often by the side
#: the resolution chose (the subdivided heads' same answer 1.99 / 1.76 % against 1.49 / 1.69); over 0.02 mm
#: the direction turned nearly as fast as it jumped before.
GRADIENT_STEP = 5e-5


def _outward(surf, q, radial) -> np.ndarray:
    """``[p,3]`` unit directions out of the eye at ``q[p,3]``: the signed distance's gradient by central
    differences (``q +- GRADIENT_STEP`` along each axis, :data:`GRADIENT_STEP`): the shortest way to more
    distance from the eye mesh, whatever its shape (the bench avatars' eyes have a shell 0.5 mm thick
    about 2 mm outside the eyeball: a lid vertex inside the shell goes back into the gap, not out through
    the shell; radially it did, and dev3's face ratio went 0.292 -> 0.305). The line to the closest point
    on the mesh, used before, is the same direction but jumps where the closest facet changes inside the
    mesh: a brow vertex 3.3 mm into the sample's eye (its facets 16 degrees apart) went back 0.44 mm
    elsewhere when its float32 position changed by 40 um. Where the differences cancel (midway between two
    sheets of the mesh, its medial axis, or on a crease of the distance between two parts of the eye) the
    direction turns smoothly to ``radial[p,3]``, the unit line from the eyeball's centre. Forward
    differences (``q`` and ``q + GRADIENT_STEP``, three queries fewer; before stop 52) cancel between two
    parallel sheets but not on a crease: in the wedge between two parts of an eye nearly touching, a
    vertex up to a step on one side of the crease was sent towards the *other* part, as one on that side
    (the repair of a mirror-symmetric eye and lid 30-110 um from mirror-symmetric,
    tests/test_eyelids_continuity.py); centred, the two sides' steps mirror each other and one on the
    crease goes out along it."""
    h = GRADIENT_STEP
    steps = np.concatenate([np.eye(3), -np.eye(3)])                     # [6,3]: +x +y +z -x -y -z
    s = surf.signed_distance((q[:, None, :] + h * steps[None]).reshape(-1, 3)).reshape(-1, 2, 3)
    grad = (s[:, 0] - s[:, 1]) / (2.0 * h)
    out = grad + 0.7 * ramp_down(vector_lengths(grad), 0.3, 0.7)[:, None] * radial
    return out / np.maximum(vector_lengths(out)[:, None], 1e-300)


def _onto_bound(surf, eye, q, d, required, generic, tolerance: float) -> np.ndarray:
    """``[p,3]``: the positions ``q[p,3]`` (signed distances ``d[p]``) moved towards their bounds
    ``required[p]`` by :func:`_amount` of their excess (onto the bound when it exceeds ``tolerance``): along
    the direction out of the eye (:func:`_outward`, continuous in the position), then - since a step off one
    part of a non-convex eye (the cornea's bulge) can come closer to another - radially from the eyeball's
    centre, along which the distance to a star-shaped eye grows; with the ``generic[p,3]`` positions, where
    that still falls short of the bound by more than ``tolerance`` (a grazing corner of a non-star-shaped
    eye mesh, the bench eyes' shell), the largest share of the way from the generic position that keeps it
    less ``tolerance`` (:func:`_largest_share`): the way to the moved position where the steps missed that
    by nothing, to the personalized position (the person's data, not the steps' failed direction) where
    they missed it by ``tolerance`` or more, between them by ``smoothstep`` of the miss. Every step is
    continuous: the share is 1 at a moved position on the bound less ``tolerance``, so a vertex on either
    side of it ends (nearly) at the same place (before, a vertex jumped from its moved position to the
    share of the way to its personalized position there)."""
    start = q
    target = d + _amount(required - d, tolerance)
    radial = q - eye.center
    radial /= np.maximum(vector_lengths(radial)[:, None], 1e-300)
    q = q + _outward(surf, q, radial) * (target - d)[:, None]
    d, active = np.empty(len(q)), np.arange(len(q))
    for _ in range(8):                              # (only the points still short are measured again)
        d[active] = surf.signed_distance(q[active])
        short = np.maximum(target[active] - d[active], 0.0)
        q[active] += radial[active] * short[:, None]   # (a continuous step: 0 where the bound is met)
        d[active] += short
        active = active[short > 1e-7]
        if active.size == 0:
            break
    if generic is not None:
        d[active] = surf.signed_distance(q[active])
        short = np.flatnonzero(d < required - tolerance)
        if short.size:
            # the way's end: the moved position where the steps barely failed, the personalized one (the
            # person's own data, not the steps' failed direction) where they failed by a tolerance more
            missed = required[short] - tolerance - d[short]
            w = ramp_up(missed, 0.0, tolerance) if tolerance > 0 else np.ones(short.size)
            end = q[short] + w[:, None] * (start[short] - q[short])
            q[short] = _largest_share(surf, generic[short], end, required[short] - tolerance)
    return q


def _signed_distance(points, triangles, queries):
    """Signed distance (m, negative inside) and closest points from ``queries[q,3]`` to a closed mesh."""
    surf = _EyeSurface(points, triangles)
    return surf.signed_distance(queries), surf.closest_points(queries)


#: A correction shorter than this (m) is not made (:func:`_violations`): a vertex short of its bound by less
#: than ~2 um (:func:`_amount`), most often one the personalization leaves about where the generic shape has
#: it, costs the repair's queries and moves nothing.
NEGLIGIBLE = 1e-8


#: The margin (m) by which the Lipschitz bound of :func:`_violations` must clear a pair's largest possible
#: bound for the pair to go unmeasured: well above the float32 rounding of Open3D's queries (~1e-9 m at an
#: eye's size), so a skipped pair is one the measurement would have passed.
LIPSCHITZ_SLACK = 1e-7


#: A vertex the spread moves by less than this (m) is not measured again (:func:`_spread_corrections`): it
#: can have come at most that much closer to the eye, and a vertex short of its bound by ~3 um is moved
#: ~30 nm (:func:`_amount`).
UNMOVED = 1e-6


def _violations(surf, x0, out, near, js, ks, reference, clearance: float, tolerance: float, known,
                last=None):
    """The (shape ``js``, near vertex ``ks``) pairs of :func:`repair_eyelids` whose personalized position
    violates its bound, by any amount that calls for a correction (:data:`NEGLIGIBLE`): ``(js, ks,
    position[p,3], signed distance[p], bound[p], generic position[p,3] or None without a reference)``, or
    None. ``known``: ``(d0[k], d_ref[J,k])``, the signed distances of the neutral and of the generic shapes'
    near vertices, NaN until measured (they do not change from one round to the next). ``last``: ``(key[p],
    position[p,3], signed distance[p])`` of pairs measured before (``key = js x near.size + ks``, ascending):
    a pair at the very same position keeps its distance (a vertex short of its bound by less than the
    tolerance and beyond the spread's reach is checked every round)."""
    vertex = near[ks]
    offset = out[js, vertex]                      # (each [J,n,3] array read once at the pairs)
    if reference is not None:
        generic = reference[js, vertex]
        # a vertex the personalization leaves where the generic shape has it is fine by definition, and one
        # it moves by ``delta`` is short of its bound by at most ``delta`` (the bound is at most the generic
        # position's signed distance, and the signed distance is 1-Lipschitz): where even that calls for no
        # correction (:func:`_amount` below :data:`NEGLIGIBLE`: ``delta`` below ~2 um), the pair is not
        # measured (on the twice-subdivided bench head a quarter of the first measurement's pairs: the shapes
        # that barely touch the lids)
        delta = vector_lengths(offset - generic)
        moved = (delta > 1e-9) & (_amount(delta + LIPSCHITZ_SLACK, tolerance) >= NEGLIGIBLE)
        js, ks, vertex, offset, generic = js[moved], ks[moved], vertex[moved], offset[moved], generic[moved]
    if js.size == 0:
        return None
    # the signed distance is 1-Lipschitz: a pair whose neutral lies ``d0`` from the eye and whose offset is
    # shorter than ``d0`` less the most any bound asks (the clearance with a reference, 0 without) is at
    # least that far from the eye, fine whatever its bound: not measured (the neutral's distance is one query
    # a vertex, the pairs' one a vertex and shape; on the twice-subdivided bench head a tenth of the first
    # measurement's pairs: most lie inside the bench eye's shell, which no bound clears)
    d0 = known[0]
    new = np.unique(ks[np.isnan(d0[ks])])
    if new.size:
        d0[new] = surf.signed_distance(x0[near[new]])
    ceiling = max(clearance, 0.0) if reference is not None else 0.0
    doubtful = d0[ks] - vector_lengths(offset) < ceiling + LIPSCHITZ_SLACK
    js, ks, vertex, offset = js[doubtful], ks[doubtful], vertex[doubtful], offset[doubtful]
    if reference is not None:
        generic = generic[doubtful]
    if js.size == 0:
        return None
    q = x0[vertex] + offset
    d = np.full(len(q), np.nan)
    if last is not None and last[0].size:
        at = np.minimum(np.searchsorted(last[0], js * near.size + ks), last[0].size - 1)
        same = (last[0][at] == js * near.size + ks) & (last[1][at] == q).all(axis=1)
        d[same] = last[2][at[same]]
    measure = np.isnan(d)
    d[measure] = surf.signed_distance(q[measure])
    # a pair's bound is at most the clearance (with a reference; 0 without): one at least that far outside
    # the eye is fine whatever its bound, and its neutral's and generic shape's distances are not needed
    # (most of the lid vertices near the eye, in most shapes)
    doubt = d < ceiling
    js, ks, q, d, vertex = js[doubt], ks[doubt], q[doubt], d[doubt], vertex[doubt]
    if js.size == 0:
        return None
    d_ref = known[1]
    required = np.minimum(d0[ks], 0.0)
    if reference is None:
        generic = None
    else:
        generic = x0[vertex] + generic[doubt]
        new = np.flatnonzero(np.isnan(d_ref[js, ks]))
        if new.size:
            d_ref[js[new], ks[new]] = surf.signed_distance(generic[new])
        dr = d_ref[js, ks]
        required = np.where(dr > 0, np.minimum(dr, clearance), np.minimum(required, dr))
    bad = _amount(required - d, tolerance) >= NEGLIGIBLE
    if not bad.any():
        return None
    return js[bad], ks[bad], q[bad], d[bad], required[bad], None if generic is None else generic[bad]


def repair_eyelids(neutral, shapes, eyeballs, *, reference=None, tolerance: float = 5e-5,
                   clearance: float = 3e-4, overwrite: bool = False, smooth: bool = True):
    """Keep eyelid vertices off the eyeballs: a personalized shape may not bring a vertex closer to (or deeper
    into) an eyeball than the avatar's own generic shape does.

    Parameters
    ----------
    neutral : ``[n,3]`` face-mesh neutral (metres).
    shapes : ``[J,n,3]`` personalized offsets.
    eyeballs : list of ``(Eyeball, points[m,3], triangles[t,3])``, closed eye meshes (an eyeball inside a
        closed shell bounds the lids surface by surface: :func:`eye_surfaces`).
    reference : ``[J,n,3]`` the avatar's generic offsets (optional).
    clearance : metres. Where the generic shape keeps a vertex outside the eyeball, the personalized one keeps
        at least ``min(generic clearance, clearance)`` (0.3 mm: a closed lid shows no eyeball through it).
        Where the generic shape (or the neutral) tucks a vertex inside on purpose (eye sockets, lids modelled
        behind the eyeball), it may go as deep as the deeper of the two, no deeper. Without ``reference``
        only penetration deeper than the neutral's is repaired.
    tolerance : metres. A vertex short of its bound by more than this moves onto it; one short by less, by
        a share that rises smoothly from 0 (:func:`_amount`: at most 0.26 ``tolerance`` left short), so that
        the output is a continuous function of the input positions.
    overwrite : repair ``shapes`` in place (a float64 array the caller does not need unrepaired) instead of
        a copy: one ``[J,n,3]`` array fewer.

    A vertex that violates its bound moves towards it out of the eye (the signed distance's gradient, then
    radially from the eyeball's centre; with ``reference``, where that does not reach the bound, the largest
    share of its personalization that does: :func:`_onto_bound`). With ``smooth`` (default) those
    corrections are spread over the lid within :data:`SPREAD_RADIUS` eyeball radii first
    (:func:`_spread_corrections`: the margin stays one smooth curve, each correction weighted by its size;
    the share spread rises smoothly from 0 for a vertex ``tolerance`` short to all of it at twice that), for
    up to :data:`SPREAD_ROUNDS` rounds, and only what they leave short of its bound is moved alone. Every
    step is continuous in the positions (tests/test_eyelids_continuity.py; the fallback to the largest share
    too, where the way from the generic position crosses the bound once) but for jumps below
    :data:`NEGLIGIBLE` / :data:`UNMOVED`.
    Returns ``(repaired shapes[J,n,3], number of vertex-shape pairs that violated their bound by more than
    tolerance)``.

    Distance queries are limited to (shape, vertex) pairs within the eye's bounding sphere plus ``clearance``;
    one raycasting scene per eye.
    """
    x0 = np.asarray(neutral, dtype=np.float64)
    out = np.array(shapes, dtype=np.float64, copy=not overwrite)
    ref_all = None if reference is None else np.asarray(reference, dtype=np.float64)
    margin = clearance if ref_all is not None else 0.0
    count = 0
    # each closed surface of an eye on its own, the eyeball last (eye_surfaces: nested shells have no inside
    # as one mesh)
    for eye, pts, tris in [(e, *surface) for e, p, t in eyeballs for surface in eye_surfaces(p, t)]:
        r0 = vector_lengths(x0 - eye.center)
        near = np.flatnonzero(r0 < 1.5 * eye.radius)
        if near.size == 0:
            continue
        center = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
        bound = float(np.linalg.norm(pts - center, axis=1).max()) * (1.0 + 1e-6) + 1e-6 + margin
        pos = x0[near][None] + out[:, near]                                  # [J,k,3]
        js, ks = np.nonzero(np.sum((pos - center) ** 2, axis=-1) <= bound ** 2)
        if js.size == 0:
            continue
        surf = _EyeSurface(pts, tris)
        if margin <= 0:
            inside = surf.inside(pos[js, ks])
            js, ks = js[inside], ks[inside]
            if js.size == 0:
                continue
        known = (np.full(near.size, np.nan), np.full((out.shape[0], near.size), np.nan))
        found = _violations(surf, x0, out, near, js, ks, ref_all, clearance, tolerance, known)
        if found is None:
            continue
        js, ks, q, d, required, generic = found
        count += int(np.count_nonzero(d < required - tolerance))
        if smooth:
            from scipy.spatial import cKDTree

            tree = cKDTree(x0[near])
            for _ in range(SPREAD_ROUNDS):
                # the corrections spread smoothly over the lid around the vertices that cut in; what that
                # leaves short of its bound is spread again, and after the last round moved alone; spread,
                # the corrections of the vertices more than the tolerance short, in full from twice it (a
                # smooth share: the few that matter, not the many a few um short that cost the spread's
                # pairs: a twice-subdivided head's lid 22 s against 5 s)
                share = (ramp_up(required - d, tolerance, 2.0 * tolerance) if tolerance > 0
                         else (required > d).astype(np.float64))
                src = np.flatnonzero(share > 0)
                if src.size == 0:
                    break
                fixed = _onto_bound(surf, eye, q[src], d[src], required[src],
                                    None if generic is None else generic[src], tolerance)
                last = (js * near.size + ks, q, d)          # (js, ks ascending: as measured)
                mj, mk = _spread_corrections(out, x0, near, js[src], ks[src],
                                             (fixed - q[src]) * share[src, None], SPREAD_RADIUS * eye.radius,
                                             tree)
                # measured again: the pairs the spread moved and those that violated their bound (every
                # other pair keeps the distance it met its bound with)
                pair = np.unique(np.concatenate([js * near.size + ks, mj * near.size + mk]))
                js, ks = pair // near.size, pair % near.size
                inside = np.sum((x0[near[ks]] + out[js, near[ks]] - center) ** 2, axis=-1) <= bound ** 2
                found = _violations(surf, x0, out, near, js[inside], ks[inside], ref_all, clearance,
                                    tolerance, known, last)
                if found is None:              # (as above: beyond the bounding sphere all is fine)
                    break
                js, ks, q, d, required, generic = found
        if found is not None:
            out[js, near[ks]] = _onto_bound(surf, eye, q, d, required, generic, tolerance) - x0[near[ks]]
    return out, count
