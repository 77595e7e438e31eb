"""The moving part of a mesh (usdface.submesh): crop / scatter, the sparse reader and writer, and a head
merged with a large static part into one mesh giving the head alone's answer."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_meshes import grid_triangles

from usdface.model import FaceRig
from usdface.submesh import SparseOffsets, crop, crop_rig, moving_part, peak_of_shapes, scatter


def _grid(nx, ny, z=0.0, spacing=0.01):
    x, y = np.meshgrid(np.arange(nx) * spacing, np.arange(ny) * spacing)
    return np.column_stack([x.ravel(), y.ravel(), np.full(nx * ny, z)]), grid_triangles(nx, ny)


def test_crop_then_scatter_is_the_identity_on_the_kept_vertices():
    points, tri = _grid(9, 7)
    rng = np.random.default_rng(3)
    keep = rng.random(len(points)) < 0.6
    sub = crop(tri, keep, points)
    np.testing.assert_array_equal(sub.vertices, np.flatnonzero(keep))
    # the triangles among the kept vertices, in the full mesh's order, re-indexed
    inside = tri[keep[tri].all(axis=1)]
    np.testing.assert_array_equal(sub.vertices[sub.triangles], inside)
    values = rng.normal(size=(4, len(points), 3))
    back = scatter(values[:, sub.vertices], sub, base=values)
    np.testing.assert_array_equal(back, values)                                  # exact: indexing only
    zeros = scatter(values[:, sub.vertices], sub)
    np.testing.assert_array_equal(zeros[:, ~keep], 0.0)
    np.testing.assert_array_equal(zeros[:, keep], values[:, keep])
    # index form = mask form
    np.testing.assert_array_equal(crop(tri, np.flatnonzero(keep), points).triangles, sub.triangles)


def test_sparse_offsets_densify_onto_their_base_and_check_shapes():
    base = np.arange(2 * 5 * 3, dtype=float).reshape(2, 5, 3)
    values = -np.ones((2, 2, 3))
    off = SparseOffsets([1, 3], values, 5, base=base)
    dense = np.asarray(off)
    assert off.shape == (2, 5, 3) and dense.shape == (2, 5, 3)
    np.testing.assert_array_equal(dense[:, [1, 3]], values)
    np.testing.assert_array_equal(dense[:, [0, 2, 4]], base[:, [0, 2, 4]])
    np.testing.assert_array_equal(off[1], dense[1])
    np.testing.assert_array_equal(np.asarray(SparseOffsets([1, 3], values, 5))[:, [0, 2, 4]], 0.0)
    with pytest.raises(ValueError):
        SparseOffsets([1, 2, 3], values, 5)


def test_one_shape_of_sparse_offsets_is_its_row_without_the_dense_array(monkeypatch):
    """``offsets[k]`` (the shape-by-shape loops: ``personalize --inspect``'s heat map, ``shape_changes``)
    forms shape k's [n,3] row only: densifying all K shapes for each one cost K x [K,n,3] copies, 24 CPU-s on
    the 314k-vertex head + body mesh. The same values as the dense array's row, base, copies and zeros."""
    from usdface.motion import shape_changes

    rng = np.random.default_rng(0)
    base = rng.normal(size=(4, 7, 3))
    values = rng.normal(size=(4, 3, 3))
    copies = (np.array([6]), np.array([0]))                 # vertex 6 a welded copy of vertices[0] = 1
    with_base = SparseOffsets([1, 3, 4], values, 7, base=base, copies=copies)
    zero_based = SparseOffsets([1, 3, 4], values, 7)
    dense = {id(o): o.dense() for o in (with_base, zero_based)}

    def refused(self):
        raise AssertionError("one shape densified the whole [K,n,3] array")

    monkeypatch.setattr(SparseOffsets, "dense", refused)
    for off in (with_base, zero_based):
        for k in (0, 3, -1):
            assert off[k].tobytes() == dense[id(off)][k].tobytes()
        with pytest.raises(IndexError):
            off[4]
    rms, largest = shape_changes(with_base, base)
    monkeypatch.undo()
    ref_rms, ref_largest = shape_changes(np.asarray(with_base), base)
    assert rms.tobytes() == ref_rms.tobytes() and largest.tobytes() == ref_largest.tobytes()
    assert rms[[0, 2, 5]].max() == 0.0 and rms[6] > 0


def test_peak_of_sparse_shapes_and_the_part_kept():
    points, tri = _grid(30, 30)
    # one shape moving a 3x3 patch, one dense shape moving a single vertex; float noise elsewhere
    patch = np.flatnonzero((points[:, 0] < 0.025) & (points[:, 1] < 0.025))
    dense = np.full((len(points), 3), 1e-12)
    dense[500] = [0.0, 0.0, 0.002]
    peak = peak_of_shapes(len(points), [(patch, np.full((patch.size, 3), 0.001)), (None, dense)])
    assert peak[500] == pytest.approx(0.002) and peak[patch] == pytest.approx(np.sqrt(3) * 0.001)
    keep = moving_part(peak, points)
    assert keep is not None and keep[patch].all() and keep[500]
    assert keep.sum() < 0.5 * len(points)                          # the noise is not motion
    # a mesh that moves almost everywhere is kept whole
    assert moving_part(np.ones(len(points)), points) is None


def test_a_rigs_peak_motion_is_kept_per_offsets_array_and_follows_its_crops():
    from usdface.motion import peak_motion
    from usdface.submesh import weld_rig

    points, tri = _grid(12, 10)
    rng = np.random.default_rng(5)
    deltas = rng.normal(size=(4, len(points), 3)) * 1e-3
    deltas[:, 40:] = 0.0                                         # the rest still
    rig = FaceRig(points, tri, ["a", "b", "c", "d"], deltas)
    peak = rig.peak_motion()
    np.testing.assert_array_equal(peak, peak_motion(rig.deltas))
    assert rig.peak_motion() is peak                             # computed once
    with pytest.raises(ValueError):
        peak[0] = 1.0                                            # shared: read-only
    # a crop (and a weld) carries it to its vertices: the same values as measured anew
    keep = np.zeros(len(points), dtype=bool)
    keep[:60] = True
    part, _ = crop_rig(rig, keep)
    kept = part.__dict__["_peak"][1]
    np.testing.assert_array_equal(kept, peak_motion(part.deltas))
    assert part.peak_motion() is kept
    welded_points = points.copy()
    welded_points[1] = welded_points[0]                          # vertex 1 a copy of vertex 0 ...
    copied = deltas.copy()
    copied[:, 1] = copied[:, 0]                                  # ... moving alike
    twin = FaceRig(welded_points, tri, rig.names, copied)
    twin.peak_motion()
    welded, _ = weld_rig(twin)
    assert welded.n_vertices == len(points) - 1
    np.testing.assert_array_equal(welded.peak_motion(), peak_motion(welded.deltas))
    # new offsets are measured anew, not answered from the old ones
    rig.deltas = 2.0 * rig.deltas
    np.testing.assert_array_equal(rig.peak_motion(), 2.0 * peak)


def test_the_readers_peak_motion_is_the_placed_offsets(samples):
    from usdface.io.usd_rig import read_avatar
    from usdface.motion import peak_motion

    for moving_only in (True, False):
        for rig in read_avatar(samples / "avatar.usda", moving_only=moving_only).meshes:
            np.testing.assert_array_equal(rig.peak_motion(), peak_motion(rig.deltas))


def test_crop_rig_of_a_part_keeps_full_mesh_indices_and_the_noise_outside():
    from usdface.model import MeshSource

    points, tri = _grid(12, 10)
    n = len(points)
    deltas = np.zeros((2, n, 3))
    deltas[0, :30, 2] = 0.001
    deltas[1, 100] = [1e-9, 0.0, 0.0]                                          # noise
    src = MeshSource(file="x.usda", prim="/Avatar/Head", point_indices=[None, np.array([100])],
                     normal_offsets=[None, None])
    rig = FaceRig(points, tri, ["jawOpen", "eyeBlinkLeft"], deltas, source=src, name="Head")
    keep = np.zeros(n, dtype=bool)
    keep[:40] = True
    part, sub = crop_rig(rig, keep)
    assert part.source.region is sub and sub.n == n
    np.testing.assert_array_equal(part.deltas, deltas[:, :40])
    idx, off, _ = part.source.residue[1]
    np.testing.assert_array_equal(idx, [100])
    np.testing.assert_array_equal(off, deltas[1, [100]])
    # cropped again: still indices into the whole mesh, residue carried
    again = np.zeros(40, dtype=bool)
    again[:30] = True
    part2, sub2 = crop_rig(part, again, sub)
    np.testing.assert_array_equal(sub2.vertices, np.arange(30))
    assert sub2.n == n and part2.source.residue[1][0].tolist() == [100]


def _merged_avatar(samples, tmp_path):
    """The sample avatar with its Head merged with a large static sheet and a separate moving strip below
    (a body whose neck the jaw moves) into one mesh, head vertices first; returns (path, n_head, strip)."""
    from usdface.io.avatar_writer import write_rig_usd
    from usdface.io.usd_rig import read_avatar

    avatar = read_avatar(samples / "avatar.usda")
    head = avatar.mesh("Head")
    n = head.n_vertices
    low = float(head.neutral[:, 1].min())
    sheet, sheet_tri = _grid(120, 80, z=0.0, spacing=0.005)          # 9.6k vertices, 0.6 x 0.4 m
    sheet = sheet[:, [0, 2, 1]] + [-0.3, low - 0.5, -0.2]              # horizontal, half a metre below
    strip, strip_tri = _grid(40, 5, z=0.0, spacing=0.005)
    strip = strip + [-0.1, low - 0.25, 0.0]                            # 25 cm below the head
    jaw = head.index("jawOpen")
    extra = np.zeros((head.n_shapes, len(sheet) + len(strip), 3))
    extra[jaw, len(sheet):] = [0.0, -0.002, 0.0]
    merged = FaceRig(np.concatenate([head.neutral, sheet, strip]),
                     np.concatenate([head.triangles, sheet_tri + n, strip_tri + n + len(sheet)]),
                     head.names, np.concatenate([head.deltas, extra], axis=1), name="Head")
    others = [FaceRig(m.neutral, m.triangles, m.names, m.deltas, name=m.name) for m in avatar.meshes
              if m.name != "Head"]
    others += [FaceRig(p, t, [], np.zeros((0, len(p), 3)), name=k.rsplit("/", 1)[-1])
               for k, (p, t) in avatar.metadata["static_meshes"].items()]
    path = write_rig_usd([merged] + others, tmp_path / "merged.usda", meters_per_unit=avatar.meters_per_unit)
    return path, n, np.arange(n + len(sheet), n + len(sheet) + len(strip))


def test_head_merged_with_a_large_static_part_gives_the_head_alones_offsets(samples, tmp_path):
    from usdface.io.usd_rig import read_avatar
    from usdface.transfer import personalize_avatar

    path, n, strip = _merged_avatar(samples, tmp_path)
    capture = samples / "capture.usda"
    alone = personalize_avatar(samples / "avatar.usda", capture, None)
    merged = personalize_avatar(path, capture, tmp_path / "out.usda")
    a = np.asarray(alone.offsets["/Avatar/Head"])
    m = np.asarray(merged.offsets["/Avatar/Head"])
    assert m.shape[1] == n + 9600 + strip.size
    # the head alone's answer to 1 um: the part worked on holds the head but not all of its far, still
    # skin, and the non-rigid registration's solve amplifies the rounding of sums over fewer vertices to
    # ~2e-8 m from the template's neutral, up to 2e-7 m at a few vertices from the person's scan (which lies
    # on the avatar's surface) (with the moving strip in the registration the bench's merged head was 0.15 mm
    # off)
    np.testing.assert_allclose(m[:, :n], a, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(merged.offsets["/Avatar/Mouth"]),
                               np.asarray(alone.offsets["/Avatar/Mouth"]), rtol=0, atol=1e-6)
    generic = read_avatar(path).mesh("Head").deltas
    np.testing.assert_array_equal(m[:, n:strip[0]], 0.0)                        # the static sheet stays
    assert np.abs(m[:, strip] - generic[:, strip]).max() < 1e-3                  # the strip follows the field
    # the layer holds only moved vertices, and reads back as the result
    from pxr import Usd, UsdSkel

    stage = Usd.Stage.Open(str(tmp_path / "out.usda"))
    for prim in stage.GetPrimAtPath("/Avatar/Head").GetChildren():
        if prim.IsA(UsdSkel.BlendShape) and prim.GetAttribute("pointIndices").HasAuthoredValue():
            idx = np.array(prim.GetAttribute("pointIndices").Get())
            assert idx.size and (idx < n).sum() + np.isin(idx, strip).sum() == idx.size, prim.GetPath()
    back = read_avatar(tmp_path / "out.usda").mesh("Head").deltas
    np.testing.assert_allclose(back, m, rtol=0, atol=2e-7)                       # float32 in the file


def test_retarget_map_of_a_head_merged_with_a_body_is_the_head_alones(samples, tmp_path):
    """``usdface retarget`` of a head and body as one mesh, a piece beyond the capture's reach (the bench's
    merged avatar): the map stopped with numpy's shape mismatch, the face region (on the reached part) put on
    the worked-on crop (reached + beyond) without joining the piece beyond back first."""
    from usdface.api import write_retarget_map

    path, n, strip = _merged_avatar(samples, tmp_path)
    capture = samples / "capture.usda"
    alone = write_retarget_map(samples / "avatar.usda", capture, tmp_path / "alone.json")
    merged = write_retarget_map(path, capture, tmp_path / "merged.json")
    assert merged.avatar_names == alone.avatar_names and merged.names == alone.names
    np.testing.assert_allclose(merged.weights, alone.weights, rtol=0, atol=1e-6)
    assert merged.face.shape == (n + 9600 + strip.size,)
    np.testing.assert_array_equal(merged.face[:n], alone.face)
    assert not merged.face[n:].any()


def test_read_moving_only_is_the_dense_read_on_its_part(samples, tmp_path):
    from usdface.io.usd_rig import read_avatar

    path, n, strip = _merged_avatar(samples, tmp_path)
    dense = read_avatar(path).mesh("Head")
    part = read_avatar(path, moving_only=True).mesh("Head")
    region = part.source.region
    assert region is not None and region.n == dense.n_vertices and region.size < 0.5 * region.n
    moving = np.flatnonzero(np.abs(dense.deltas).max(axis=(0, 2)) > 0)
    assert set(moving.tolist()) <= set(region.vertices.tolist()) and set(strip.tolist()) <= set(moving)
    np.testing.assert_array_equal(part.deltas, dense.deltas[:, region.vertices])
    np.testing.assert_array_equal(part.neutral, dense.neutral[region.vertices])
    np.testing.assert_array_equal(region.points, dense.neutral)
    inside = dense.triangles[np.isin(dense.triangles, region.vertices).all(axis=1)]
    np.testing.assert_array_equal(region.vertices[part.triangles], inside)
    # outside the part nothing moves (no residue of noise here)
    assert all(r[0].size == 0 for r in part.source.residue)


def test_sparse_write_of_a_part_keeps_noise_and_inbetweens_consistent(tmp_path):
    from usdface.io.avatar_writer import write_rig_usd
    from usdface.io.layers import write_avatar_layer
    from usdface.io.usd_rig import read_avatar
    from usdface.model import Inbetween

    points, tri = _grid(40, 40)
    points = points + [0.0, 1.5, 0.0]
    n = len(points)
    deltas = np.zeros((2, n, 3))
    deltas[0, :21] = [0.0, 0.0, 0.004]
    deltas[0, 1500] = [1e-8, 0.0, 0.0]                       # float noise far away: not motion, kept as is
    deltas[1, 3] = [0.0, -0.01, 0.0]
    half = Inbetween("half", 0.5, deltas[1] * 0.7)
    rig = FaceRig(points, tri, ["jawOpen", "eyeBlinkLeft"], deltas, {"eyeBlinkLeft": [half]}, name="Head")
    src = write_rig_usd([rig], tmp_path / "a.usda")
    part = read_avatar(src, moving_only=True)
    head = part.mesh("Head")
    region = head.source.region
    assert region is not None and 1500 not in set(region.vertices.tolist())
    new = head.deltas.copy()
    at3 = int(np.flatnonzero(region.vertices == 3)[0])
    new[1, at3] = [0.0, -0.012, 0.001]
    out = write_avatar_layer(part, tmp_path / "out.usda",
                             {"/Avatar/Head": SparseOffsets(region.vertices, new, n)})
    back = read_avatar(out).mesh("Head")
    before = read_avatar(src).mesh("Head")
    np.testing.assert_array_equal(back.deltas[0], before.deltas[0])               # noise and all, untouched
    np.testing.assert_allclose(back.deltas[1, 3], [0.0, -0.012, 0.001], atol=1e-8)
    np.testing.assert_array_equal(np.delete(back.deltas[1], 3, axis=0), 0.0)
    ib = back.inbetweens["eyeBlinkLeft"][0].offsets
    expect = before.inbetweens["eyeBlinkLeft"][0].offsets[3] + 0.5 * (back.deltas[1, 3] - before.deltas[1, 3])
    np.testing.assert_allclose(ib[3], expect, atol=1e-8)
    assert back.source.point_indices[1].tolist() == [3]                            # only the moved vertex


def test_merged_mesh_in_the_papers_mode_also_gives_the_head_alones_offsets(samples, tmp_path):
    """The older transfer (eq. 4 approximations beyond the face): the piece beyond the capture's reach is
    approximated like another mesh and joined back; the head keeps the head alone's answer."""
    from usdface.transfer import personalize_avatar

    path, n, strip = _merged_avatar(samples, tmp_path)
    capture = samples / "capture.usda"
    opts = {"face_transfer": "offset", "approximation": "retarget"}
    alone = personalize_avatar(samples / "avatar.usda", capture, None, **opts)
    merged = personalize_avatar(path, capture, None, **opts)
    # to 1 um, as the default mode above (the registration's rounding)
    np.testing.assert_allclose(np.asarray(merged.offsets["/Avatar/Head"])[:, :n],
                               np.asarray(alone.offsets["/Avatar/Head"]), rtol=0, atol=1e-6)
    approx = np.asarray(merged.approximation["/Avatar/Head"])
    assert approx.shape == (len(merged.names), n + 9600 + strip.size, 3)
    np.testing.assert_allclose(approx[:, :n], np.asarray(alone.approximation["/Avatar/Head"]), rtol=0,
                               atol=1e-6)
    assert merged.face.shape == (n + 9600 + strip.size,) and not merged.face[n:].any()


@pytest.mark.parametrize("merged", [False, True], ids=["head", "head-merged-with-a-body"])
def test_packed_generic_offsets_give_the_same_offsets(samples, tmp_path, monkeypatch, merged):
    """From ``PACK_BYTES`` on the face's generic offsets are held packed (float32 + the reader's conversion)
    through the field and restored after it - on the face mesh, and on the whole face mesh when a body merged
    into it was split off (reached + beyond). Forcing the packing on every size gives the same offsets to the
    last bit, and leaves the avatar's generic offsets as read."""
    from usdface.io.usd_rig import read_avatar
    from usdface.transfer import personalize_avatar, pipeline

    path = _merged_avatar(samples, tmp_path)[0] if merged else samples / "avatar.usda"
    capture = samples / "capture.usda"
    plain = personalize_avatar(path, capture, None)
    calls = []
    real = pipeline._packed_generic

    def packing(rig, names):
        packed = real(rig, names)
        calls.append(packed is not None)
        return packed

    monkeypatch.setattr(pipeline, "PACK_BYTES", 0)
    monkeypatch.setattr(pipeline, "_packed_generic", packing)
    avatar = read_avatar(path, moving_only=True)
    generic = {m.key: m.deltas.copy() for m in avatar.meshes}
    packed = personalize_avatar(avatar, capture, None)
    assert calls.count(True) == (2 if merged else 1)       # the face (and the whole face mesh when split)
    for key in plain.offsets:
        np.testing.assert_array_equal(np.asarray(packed.offsets[key]), np.asarray(plain.offsets[key]))
    for m in avatar.meshes:                                # the caller's avatar is given back as read
        np.testing.assert_array_equal(m.deltas, generic[m.key])


def test_a_still_piece_of_the_head_mesh_beyond_the_capture_is_no_empty_mesh(samples, tmp_path):
    """A small separate piece in the Head mesh that no shape moves and the capture does not reach (a helper
    card an artist added behind the head) left an empty 'beyond the capture' mesh once its still vertices
    were cropped away: personalize died with numpy's 'zero-size array to reduction operation maximum'.
    Now the piece is left out like any still vertex and the head's answer is the head alone's."""
    from usdface.io.avatar_writer import write_rig_usd
    from usdface.io.usd_rig import read_avatar
    from usdface.transfer import personalize_avatar

    avatar = read_avatar(samples / "avatar.usda")
    head = avatar.mesh("Head")
    n = head.n_vertices
    card = head.neutral[0] + np.array([[0.0, 0.0, -0.01], [0.0, 0.01, -0.01], [0.01, 0.0, -0.01]])
    merged = FaceRig(np.concatenate([head.neutral, card]),
                     np.concatenate([head.triangles, [[n, n + 1, n + 2]]]),
                     head.names, np.concatenate([head.deltas, np.zeros((head.n_shapes, 3, 3))], axis=1),
                     name="Head")
    others = [FaceRig(m.neutral, m.triangles, m.names, m.deltas, name=m.name) for m in avatar.meshes
              if m.name != "Head"]
    others += [FaceRig(p, t, [], np.zeros((0, len(p), 3)), name=k.rsplit("/", 1)[-1])
               for k, (p, t) in avatar.metadata["static_meshes"].items()]
    path = write_rig_usd([merged] + others, tmp_path / "card.usda", meters_per_unit=avatar.meters_per_unit)
    capture = samples / "capture.usda"
    alone = personalize_avatar(samples / "avatar.usda", capture, None)
    with_card = personalize_avatar(path, capture, None)
    m = np.asarray(with_card.offsets["/Avatar/Head"])
    assert m.shape[1] == n + 3
    np.testing.assert_array_equal(m[:, n:], 0.0)                       # the card stays
    np.testing.assert_allclose(m[:, :n], np.asarray(alone.offsets["/Avatar/Head"]), rtol=0, atol=1e-7)


def test_outside_offsets_keeps_a_point_only_an_inbetween_moves():
    """A point outside the crop whose offset is zero but an inbetween's is not is kept (with both), one
    still in all of them is not."""
    from usdface.submesh import outside_offsets

    idx = np.array([3, 7, 9])
    off = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1e-3, 0.0, 0.0]])
    ib = np.array([[0.0, 2e-3, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    rows, kept, (kept_ib,) = outside_offsets(idx, off, [ib])
    np.testing.assert_array_equal(rows, [3, 9])
    np.testing.assert_array_equal(kept, off[[0, 2]])
    np.testing.assert_array_equal(kept_ib, ib[[0, 2]])


def test_moving_part_is_the_whole_mesh_once_its_margin_makes_it_most_of_it():
    """45 % of a 10 x 10 grid moves: under half, but with its margin the part is most of the mesh, so the
    whole mesh is kept (None)."""
    u, v = np.meshgrid(np.arange(10) * 0.01, np.arange(10) * 0.01)
    points = np.stack([u.ravel(), v.ravel(), np.zeros(100)], axis=1)
    peak = np.where(np.arange(100) < 45, 1e-3, 0.0)
    assert moving_part(peak, points) is None
    few = np.where(np.arange(100) < 12, 1e-3, 0.0)                   # a part with its margin under half
    keep = moving_part(few, points)
    assert keep is not None and 12 < keep.sum() <= 50
