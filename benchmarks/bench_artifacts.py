"""Artifact check of ``usdface personalize``: is the personalized avatar locally rougher than both the generic
avatar and the person (truth) anywhere - a crease, a spike at one vertex, a Mouth that tears from the jaw -
where the RMSE ratios and the seam figure of ``bench_personalize.py`` would not show it?

Run:  USDFACE_SHARED=/work/shared python benchmarks/bench_artifacts.py [--cases sample,dev1,dev2,artist:1]

The cases are ``bench_personalize.py``'s (a bench case, ``sample``, ``artist:SEED`` / ``generic:SEED`` /
``noisy:SEED``), read by its :func:`bench_personalize._case`, personalized in-process with the defaults
(``personalize_avatar``) and compared, mesh by mesh and shape by shape, on three offset sets of the same
topology: personalized ``out``, ``generic`` (the avatar's own) and ``truth`` (``truth/avatar_truth.npz``).

Measures (pure numpy on ``offsets[K,n,3]``, metres):

- edge strain ``|d_i - d_j| / |x_i - x_j|`` over every edge of the mesh (dimensionless: offset change per
  length of rest edge), reported as the jump ``|d_i - d_j|`` in mm;
- spike: the umbrella Laplacian ``|d_i - mean_{j in N(i)} d_j|`` over the mean rest length of i's edges
  (dimensionless), reported in mm;
- Mouth rigidity: per shape, the residual (mm) of the best rigid motion (Kabsch) of the Mouth's moving body
  (the vertices the generic shape moves by more than 10 % of its peak: lower teeth, gums and tongue under
  the jaw shapes) and of each connected piece that is not in it (an upper tooth must not be dragged), for
  out, generic and truth; and (``affine``) the residual of the best affine map from the generic pose in
  the same pieces (a uniform change of the jaw's motion - it opens 4 % less: what a linear rig does at a
  weight below 1, and what dev3's truth does - is not a tear; what is left is).

A value is FLAGGED (:func:`flag`) when, for that shape, the personalized value exceeds ``FACTOR`` (2) times
the larger of the generic's and the truth's at the same edge/vertex (the output is twice as rough as both
references there), AND exceeds the 99.9th percentile over the mesh of the references' values for that
shape (``max(generic, truth)`` per element: as rough as the roughest 0.1 % of what the artist or the person
has anywhere in that shape), AND the jump (spike, residual) is above ``FLOOR_MM`` (0.05 mm: less does not
show on a face; the float32 rounding of the files is 1e-5 mm). A flagged element is an artifact of the
method: neither the artist nor the person has it. :func:`score` puts the three tests in one number, flagged
when > 1; the table gives per mesh and kind the count of flagged elements (all shapes) and the element of
largest score (the one nearest to, or furthest past, the bar) with who has that feature there:
``person`` when the truth's value there is at least half the output's, ``generic`` when the generic's is,
else ``new``. Every case the bench knows has a truth; :func:`check_mesh` without one compares with the generic
alone, which flags the person's own features too (the sample: 637 Head edges instead of 1, and every Mouth
vertex the personalization moves non-affinely), so its flags then mean "changed", not "artifact".

Where: ``mask`` = the vertices the capture covers (bench: Head 0-6705; generated: ``covered_vertices``),
``band`` = within two edge rings of the mask's border (the seam figure's edges), ``face`` = the rest of the
face region (bench: Head 0-9408), ``head`` = beyond it; and the shape whose generic motion is largest at that
vertex (a name for the part of the face: ``eyeBlinkLeft`` = the left upper lid).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from usdface.mesh import edges as mesh_edges
from usdface.mesh import uniform_laplacian
from usdface.transfer.scoring import border_band_edges

#: flagged: the output's value is this many times the larger reference value at the same element
FACTOR = 2.0
#: ... and above this percentile (over the mesh, per shape) of the references' values
PERCENTILE = 99.9
#: ... and the jump / spike / residual is above this (mm): below it nothing shows
FLOOR_MM = 0.05
#: a Mouth vertex is in the shape's moving body when its generic motion exceeds this fraction of the peak
BODY = 0.1


def edge_strain(points, offsets, edges) -> tuple[np.ndarray, np.ndarray]:
    """``(strain[K,e], jump[K,e])`` of ``offsets[K,n,3]`` on rest ``points[n,3]`` across ``edges[e,2]``:
    ``jump = |d_i - d_j|`` (units of the offsets) and ``strain = jump / |x_i - x_j|`` (dimensionless)."""
    x = np.asarray(points, dtype=np.float64)
    d = np.asarray(offsets, dtype=np.float64)
    length = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=-1)
    jump = np.linalg.norm(d[:, edges[:, 0]] - d[:, edges[:, 1]], axis=-1)
    return jump / np.maximum(length, 1e-12), jump


def umbrella_spike(points, offsets, triangles) -> tuple[np.ndarray, np.ndarray]:
    """``(spike[K,n], size[K,n])``: ``size = |d_i - mean_{j in N(i)} d_j|`` of ``offsets[K,n,3]`` (units of
    the offsets; the umbrella Laplacian, :func:`usdface.mesh.uniform_laplacian`) and ``spike = size /`` the
    mean rest length of i's edges (dimensionless)."""
    x = np.asarray(points, dtype=np.float64)
    d = np.asarray(offsets, dtype=np.float64)
    n = len(x)
    L = uniform_laplacian(triangles, n)
    e = mesh_edges(triangles)
    length = np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=-1)
    total = np.bincount(e.ravel(), weights=np.repeat(length, 2), minlength=n)
    count = np.bincount(e.ravel(), minlength=n)
    mean_length = total / np.maximum(count, 1)
    K = d.shape[0]
    lap = (L @ d.transpose(1, 0, 2).reshape(n, 3 * K)).reshape(n, K, 3).transpose(1, 0, 2)   # [K,n,3]
    size = np.linalg.norm(lap, axis=-1)
    return size / np.maximum(mean_length, 1e-12), size


def flag(out, generic, truth=None, size=None, *, factor: float = FACTOR, percentile: float = PERCENTILE,
         floor: float = FLOOR_MM * 1e-3) -> np.ndarray:
    """``[K,e]`` bool: the elements (edges or vertices) where the personalized value ``out[K,e]`` exceeds
    ``factor`` times the larger reference (``generic``, ``truth``: ``[K,e]``, truth optional) at the same
    element, exceeds the ``percentile`` over the elements of the references' values in that shape, and
    ``size[K,e]`` (the jump or spike in the offsets' units; default ``out``) is above ``floor``."""
    return score(out, generic, truth, size, factor=factor, percentile=percentile, floor=floor) > 1.0


def score(out, generic, truth=None, size=None, *, factor: float = FACTOR, percentile: float = PERCENTILE,
          floor: float = FLOOR_MM * 1e-3) -> np.ndarray:
    """``[K,e]`` how far each element is from the bar of :func:`flag` (flagged when > 1):
    ``min(out / max(factor x reference, percentile of the references), size / floor)``."""
    ref = np.asarray(generic, dtype=np.float64)
    if truth is not None:
        ref = np.maximum(ref, np.asarray(truth, dtype=np.float64))
    out = np.asarray(out, dtype=np.float64)
    size = out if size is None else np.asarray(size, dtype=np.float64)
    level = np.percentile(ref, percentile, axis=1, keepdims=True) if ref.shape[1] else ref[:, :0]
    bar = np.maximum(factor * ref, level)
    with np.errstate(divide="ignore", invalid="ignore"):
        over = np.where(bar > 0, out / np.where(bar > 0, bar, 1.0), np.where(out > 0, np.inf, 0.0))
    return np.minimum(over, size / floor)


def _grouping(groups):
    """``(keep[n] bool, gi[m] group index of each kept vertex, S[G,m] 0/1 sparse sum over each group)`` for
    ``groups[n]`` int labels (negative: not scored); ``S`` None when no vertex is scored."""
    g = np.asarray(groups)
    keep = g >= 0
    if not keep.any():
        return keep, None, None
    _, gi = np.unique(g[keep], return_inverse=True)
    G, m = int(gi.max()) + 1, int(keep.sum())
    return keep, gi, sp.csr_matrix((np.ones(m), (gi, np.arange(m))), shape=(G, m))


def rigid_residual(points, offsets, groups) -> np.ndarray:
    """``[n]`` distance of each vertex's moved position ``points + offsets`` (``[n,3]``, ``[n,3]``) from the
    best rigid motion (rotation + translation, least squares: Kabsch) of its group, ``groups[n]`` int
    labels (negative: not scored, 0). One small SVD per group, vectorized."""
    p = np.asarray(points, dtype=np.float64)
    q = p + np.asarray(offsets, dtype=np.float64)
    out = np.zeros(len(p))
    keep, gi, S = _grouping(groups)
    if S is None:
        return out
    G, m = S.shape
    count = np.asarray(S.sum(axis=1))
    pk, qk = p[keep], q[keep]
    cp, cq = (S @ pk) / count, (S @ qk) / count                                        # [G,3]
    a, b = pk - cp[gi], qk - cq[gi]
    H = (S @ np.einsum("ni,nj->nij", a, b).reshape(m, 9)).reshape(G, 3, 3)            # sum a b^T
    U, _, Vt = np.linalg.svd(H)
    det = np.sign(np.linalg.det(np.einsum("gij,gjk->gik", U, Vt)))
    D = np.broadcast_to(np.eye(3), (G, 3, 3)).copy()
    D[:, 2, 2] = det
    R = np.einsum("gji,gjk,glk->gil", Vt, D, U)                                       # V D U^T
    fit = np.einsum("nij,nj->ni", R[gi], a)
    out[keep] = np.linalg.norm(fit - b, axis=-1)
    return out


def affine_residual(source, target, groups) -> np.ndarray:
    """``[n]`` distance of each ``target[n,3]`` point from the best affine map (least squares) of its
    group's ``source[n,3]`` points, ``groups[n]`` int labels (negative: not scored, 0). With the generic
    pose as the source: what is left of a Mouth shape once any uniform change of the generic motion (a jaw
    that opens 4 % less, as a linear rig's weight below 1 does) is taken out - a tear or a crease."""
    p = np.asarray(source, dtype=np.float64)
    q = np.asarray(target, dtype=np.float64)
    out = np.zeros(len(p))
    keep, gi, S = _grouping(groups)
    if S is None:
        return out
    G, m = S.shape
    a = np.column_stack([p[keep], np.ones(m)])                                         # [m,4]
    M = (S @ np.einsum("ni,nj->nij", a, a).reshape(m, 16)).reshape(G, 4, 4)
    B = (S @ np.einsum("ni,nj->nij", a, q[keep]).reshape(m, 12)).reshape(G, 4, 3)
    coef = np.einsum("gij,gjk->gik", np.linalg.pinv(M), B)                           # [G,4,3]
    out[keep] = np.linalg.norm(np.einsum("ni,nij->nj", a, coef[gi]) - q[keep], axis=-1)
    return out


def mouth_groups(generic, triangles) -> np.ndarray:
    """``[K,n]`` int: per shape of ``generic[K,n,3]`` the rigid pieces of the Mouth: 0 = the moving body
    (generic motion above :data:`BODY` of the shape's peak: the jaw's teeth, gums and tongue move as one),
    1 + c = the rest of connected piece c (each piece on its own: a still tooth must stay rigid too)."""
    d = np.asarray(generic, dtype=np.float64)
    n = d.shape[1]
    e = mesh_edges(triangles)
    _, piece = connected_components(sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)),
                                    directed=False)
    mag = np.linalg.norm(d, axis=-1)
    body = mag > BODY * np.maximum(mag.max(axis=1, keepdims=True), 1e-300)
    return np.where(body, 0, 1 + piece[None, :])


def mouth_rigidity(points, triangles, generic, sets: dict) -> tuple[dict, dict]:
    """``({label: [K,n]}, {label: [K,n]})``: per offset set ``sets[label][K,n,3]`` the non-rigid residual
    (same units as the offsets) in the Mouth's rigid pieces (:func:`mouth_groups` of ``generic``), and the
    residual of the best affine map from the generic pose ``points + generic`` in the same pieces
    (:func:`affine_residual`; 0 for the generic itself)."""
    groups = mouth_groups(generic, triangles)
    x = np.asarray(points, dtype=np.float64)
    g = np.asarray(generic, dtype=np.float64)
    rigid = {label: np.stack([rigid_residual(x, d[k], groups[k]) for k in range(len(d))])
             for label, d in sets.items()}
    affine = {label: np.stack([affine_residual(x + g[k], x + d[k], groups[k]) for k in range(len(d))])
              for label, d in sets.items()}
    return rigid, affine


@dataclass
class Finding:
    """One of the roughest elements of a kind (``edge`` / ``vertex`` / ``rigid`` / ``affine``) on one mesh of
    one case (figures in mm)."""

    mesh: str
    kind: str
    shape: str
    index: str          # vertex index, "i-j" for an edge
    out_mm: float
    generic_mm: float
    truth_mm: float
    score: float        # :func:`score` of that element: > 1 flagged
    where: str
    owner: str          # person / generic / new
    flagged: int        # how many elements of this kind are flagged on this mesh (all shapes)


def _owner(o, g, t) -> str:
    if t is not None and t >= 0.5 * o:
        return "person"
    return "generic" if g >= 0.5 * o else "new"


def _regions(n, triangles, face, covered) -> np.ndarray:
    """``[n]`` labels mask / band / face / head of the Head's vertices (see the module docstring)."""
    where = np.full(n, "head", dtype=object)
    where[np.asarray(face, dtype=bool)] = "face"
    where[np.asarray(covered, dtype=bool)] = "mask"
    band = border_band_edges(triangles, covered, 2)
    where[np.unique(band)] = "band"
    return where


def _worst(kind, mesh, names, out, gen, tru, size_out, size_gen, size_tru, where, index,
           top: int = 1) -> list[Finding]:
    """The ``top`` elements (shape, element) nearest to being flagged or furthest past it: the largest
    :func:`score` (of equal scores, the largest jump). ``out``/``gen``/``tru`` ``[K,e]`` the scored values,
    ``size_*`` ``[K,e]`` the jumps (m); ``where(e)`` and ``index(e)`` name an element."""
    sc = score(out, gen, tru, size_out)
    flagged = int((sc > 1.0).sum())
    order = np.lexsort((size_out.ravel(), sc.ravel()))[::-1][:top]          # ties: the larger jump first
    found = []
    for k, e in zip(*np.unravel_index(order, sc.shape), strict=True):
        o, g = size_out[k, e] * 1e3, size_gen[k, e] * 1e3
        t = size_tru[k, e] * 1e3 if size_tru is not None else float("nan")
        owner = _owner(out[k, e], gen[k, e], tru[k, e] if tru is not None else None)
        found.append(Finding(mesh, kind, names[k], index(e), o, g, t, float(sc[k, e]), where(e), owner,
                             flagged))
    return found


def check_mesh(name, names, points, triangles, out, generic, truth, where=None, *,
               top: int = 1) -> list[Finding]:
    """The ``top`` findings of each kind (edge, vertex; rigid and affine for the Mouth) of one mesh:
    ``out``, ``generic``, ``truth`` ``[K,n,3]`` (m, truth may be None), ``where[n]`` region labels (default:
    the mesh's name)."""
    e = mesh_edges(triangles)
    gen_motion = np.linalg.norm(np.asarray(generic, dtype=np.float64), axis=-1)             # [K,n]
    feature = np.asarray(names, dtype=object)[np.argmax(gen_motion, axis=0)]
    label = where if where is not None else np.full(len(points), name, dtype=object)

    def at_vertex(i):
        return f"{label[i]} {feature[i]}"

    sets = {"out": out, "gen": generic} | ({"tru": truth} if truth is not None else {})
    strain = {k: edge_strain(points, v, e) for k, v in sets.items()}
    spike = {k: umbrella_spike(points, v, triangles) for k, v in sets.items()}
    found = []
    for kind, vals, index, where_e in (
            ("edge", strain, lambda i: f"{e[i, 0]}-{e[i, 1]}", lambda i: at_vertex(e[i, 0])),
            ("vertex", spike, str, at_vertex)):
        tv = vals.get("tru", (None, None))
        found += _worst(kind, name, names, vals["out"][0], vals["gen"][0], tv[0], vals["out"][1],
                        vals["gen"][1], tv[1], where_e, index, top)
    if name == "Mouth":
        rigid, affine = mouth_rigidity(points, triangles, generic, sets)
        for kind, res in (("rigid", rigid), ("affine", affine)):
            tr = res.get("tru")
            found += _worst(kind, name, names, res["out"], res["gen"], tr, res["out"], res["gen"], tr,
                            at_vertex, str, top)
    return found


def check_case(case: str, top: int = 1) -> list[Finding]:
    """Personalize ``case`` (defaults) and check every mesh with shapes (:func:`check_mesh`)."""
    from bench_personalize import _case

    from usdface.transfer import personalize_avatar

    avatar, capture, face, covered, truth = _case(case)
    res = personalize_avatar(avatar, capture, None)
    found = []
    for m in avatar.meshes:
        key = m.source.prim
        if key not in res.offsets or not len(m.names):
            continue
        where = _regions(m.n_vertices, m.triangles, face, covered) if m.name == "Head" else None
        found += check_mesh(m.name, list(m.names), m.neutral, m.triangles, res.offsets[key], m.deltas,
                            truth.get(key), where, top=top)
    return found


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="sample,dev1,dev2,dev3")
    ap.add_argument("--top", type=int, default=1, help="the N elements of largest score per mesh and kind")
    args = ap.parse_args(argv)
    from bench_personalize import _known

    cases = [c for c in args.cases.split(",") if _known(c)]
    print(f"flagged: out > {FACTOR:g} x max(generic, truth) at the element, > the shape's {PERCENTILE:g}th "
          f"percentile of max(generic, truth), jump > {FLOOR_MM:g} mm; "
          f"worst: the largest score = min(out / max({FACTOR:g} x reference there, that percentile), "
          f"jump / {FLOOR_MM:g} mm): > 1 flagged")
    print(f"{'case':9} {'mesh':6} {'kind':6} {'flagged':>7} {'worst shape':>20} {'index':>11} "
          f"{'out mm':>7} {'gen mm':>7} {'truth mm':>8} {'score':>9} {'owner':>7}  where")
    for case in cases:
        for f in check_case(case, args.top):
            print(f"{case:9} {f.mesh:6} {f.kind:6} {f.flagged:7d} {f.shape:>20} {f.index:>11} "
                  f"{f.out_mm:7.3f} {f.generic_mm:7.3f} {f.truth_mm:8.3f} {f.score:9.2f} {f.owner:>7}  "
                  f"{f.where}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
