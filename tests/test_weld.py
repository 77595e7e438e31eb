"""Vertices split at UV / hard-normal seams (a glTF or FBX export) are one point of the surface: personalize
welds them, so the split changes neither the answer nor tears the seam (usdface.submesh.weld_rig)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_submesh import _grid

from usdface.model import FaceRig, Inbetween
from usdface.submesh import SparseOffsets, coincident_vertices, crop_rig, scatter, weld_rig


def _split(rig: FaceRig, cut_y: float) -> tuple[FaceRig, np.ndarray]:
    """``rig`` with the vertices shared by triangles above and below ``y = cut_y`` duplicated for the
    triangles above (a UV seam as an exporter writes it); returns (split rig, seam vertex indices)."""
    x, t = rig.neutral, rig.triangles
    above = x[t].mean(axis=1)[:, 1] > cut_y
    on_a = np.zeros(len(x), dtype=bool)
    on_a[t[above].ravel()] = True
    on_b = np.zeros(len(x), dtype=bool)
    on_b[t[~above].ravel()] = True
    seam = np.flatnonzero(on_a & on_b)
    new = np.arange(len(x))
    new[seam] = len(x) + np.arange(seam.size)
    tri = t.copy()
    tri[above] = new[t[above]]
    ibs = {k: [dataclasses.replace(b, offsets=np.vstack([b.offsets, b.offsets[seam]])) for b in v]
           for k, v in rig.inbetweens.items()}
    return FaceRig(np.vstack([x, x[seam]]), tri, rig.names,
                   np.concatenate([rig.deltas, rig.deltas[:, seam]], axis=1), ibs, name=rig.name), seam


def test_copies_are_found_and_touching_lips_are_not():
    points, tri = _grid(6, 5)
    n = len(points)
    deltas = np.zeros((2, n, 3))
    deltas[0, :, 2] = points[:, 1] * 0.1                         # smooth motion, same at copies
    rig = FaceRig(points, tri, ["jawOpen", "mouthClose"], deltas, name="Head")
    split, seam = _split(rig, 0.021)
    rep = coincident_vertices(split.neutral, split.deltas)
    np.testing.assert_array_equal(rep[n:], seam)                 # each copy -> its original
    np.testing.assert_array_equal(rep[:n], np.arange(n))
    # a copy some shape moves differently (a closed lip: the same rest point, parted by jawOpen) is not one
    parted = split.deltas.copy()
    parted[0, n] += [0.0, -0.004, 0.0]
    rep2 = coincident_vertices(split.neutral, parted)
    assert rep2[n] == n and (rep2[n + 1:] == seam[1:]).all()
    # nor is one an inbetween moves differently
    ib = split.deltas[0].copy()
    ib[n + 1] += 0.001
    assert coincident_vertices(split.neutral, split.deltas, [ib])[n + 1] == n + 1


def test_weld_then_scatter_gives_each_copy_its_twins_values_and_crop_keeps_them():
    from usdface.model import MeshSource

    points, tri = _grid(8, 6)
    n = len(points)
    deltas = np.zeros((1, n, 3))
    deltas[0, :, 2] = 0.001 * points[:, 0]
    src = MeshSource(file="x.usda", prim="/Avatar/Head", point_indices=[None], normal_offsets=[None])
    rig, seam = _split(FaceRig(points, tri, ["jawOpen"], deltas, name="Head"), 0.021)
    rig = dataclasses.replace(rig, source=src)
    welded, region = weld_rig(rig)
    assert welded.n_vertices == n and region.n == n + seam.size
    np.testing.assert_array_equal(region.copies[0], n + np.arange(seam.size))
    np.testing.assert_array_equal(region.vertices[region.copies[1]], seam)
    assert welded.triangles.max() < n                             # one connected surface
    values = np.random.default_rng(0).random((1, n, 3))
    full = scatter(values, region)
    np.testing.assert_array_equal(full[:, n:], values[:, seam])
    np.testing.assert_array_equal(np.asarray(SparseOffsets(region.vertices, values, region.n,
                                                           copies=region.copies)), full)
    assert all(r[0].size == 0 for r in welded.source.residue)    # a copy is not left as it was
    # cropped again: copies of kept vertices follow them; those of dropped ones join the residue
    keep = welded.neutral[:, 1] < 0.025
    part, sub = crop_rig(welded, keep, region)
    kept_twin = np.isin(region.copies[1], np.flatnonzero(keep))
    np.testing.assert_array_equal(np.sort(sub.copies[0]), np.sort(region.copies[0][kept_twin]))
    np.testing.assert_array_equal(sub.vertices[sub.copies[1]], region.vertices[region.copies[1][kept_twin]])
    if (~kept_twin).any():
        idx = part.source.residue[0][0]
        assert set(region.copies[0][~kept_twin].tolist()) <= set(idx.tolist())


def test_an_unsplit_mesh_is_left_as_it_is():
    points, tri = _grid(5, 5)
    rig = FaceRig(points, tri, ["jawOpen"], np.ones((1, len(points), 3)) * 0.001,
                  {"jawOpen": [Inbetween("half", 0.5, np.ones((len(points), 3)) * 0.0005)]}, name="Head")
    assert weld_rig(rig) == (rig, None)


@pytest.fixture(scope="module")
def split_sample(samples, tmp_path_factory):
    """The sample avatar written with its Head split along a seam across the face (cheeks to nose);
    returns (path, n original Head vertices, seam indices)."""
    from usdface.io.avatar_writer import write_rig_usd
    from usdface.io.usd_rig import read_avatar

    avatar = read_avatar(samples / "avatar.usda")
    head = avatar.mesh("Head")
    moving = np.abs(head.deltas).max(axis=(0, 2)) > 0
    split, seam = _split(FaceRig(head.neutral, head.triangles, head.names, head.deltas, head.inbetweens,
                                 name="Head"), float(head.neutral[moving, 1].mean()))
    others = [FaceRig(m.neutral, m.triangles, m.names, m.deltas, name=m.name) for m in avatar.meshes
              if m.name != "Head"]
    others += [FaceRig(p, t, [], np.zeros((0, len(p), 3)), name=k.rsplit("/", 1)[-1])
               for k, (p, t) in avatar.metadata["static_meshes"].items()]
    path = write_rig_usd([split] + others, tmp_path_factory.mktemp("split") / "split.usda",
                         meters_per_unit=avatar.meters_per_unit)
    return path, head.n_vertices, seam


def test_personalize_cli_on_a_split_head_gives_the_unsplit_answer_without_a_tear(samples, split_sample,
                                                                                 tmp_path, capsys):
    """Before the weld the sample's split Head tore by 0.87 mm at the seam and its answer moved by 16 % (RMS
    of the personalization) from the unsplit Head's."""
    from usdface.cli import main
    from usdface.io.usd_rig import read_avatar

    path, n, seam = split_sample
    capture = samples / "capture.usda"
    for avatar, out in ((samples / "avatar.usda", tmp_path / "whole.usda"), (path, tmp_path / "split.usda")):
        assert main(["personalize", str(avatar), str(capture), "-o", str(out), "-q"]) == 0
    whole = read_avatar(tmp_path / "whole.usda").mesh("Head").deltas
    split = read_avatar(tmp_path / "split.usda").mesh("Head").deltas
    generic = read_avatar(path).mesh("Head").deltas
    assert split.shape[1] == n + seam.size
    np.testing.assert_array_equal(split[:, n:], split[:, seam])            # no tear: each copy as its twin
    change = np.sqrt(np.mean(np.sum((whole - generic[:, :n]) ** 2, axis=-1)))
    assert change > 1e-4                                                     # the test personalizes
    np.testing.assert_allclose(split[:, :n], whole, rtol=0, atol=1e-6)      # the answer of the unsplit mesh
    assert np.abs(split[:, seam] - generic[:, seam]).max() > 1e-4           # the seam itself is personalized


def _split_on_sheet(samples, path):
    """The sample avatar with its Head split across the face (``_split``) and merged with a large static
    sheet (so a ``moving_only`` read crops it); returns (path, n split Head vertices, seam)."""
    from usdface.io.avatar_writer import write_rig_usd
    from usdface.io.usd_rig import read_avatar

    avatar = read_avatar(samples / "avatar.usda")
    head = avatar.mesh("Head")
    moving = np.abs(head.deltas).max(axis=(0, 2)) > 0
    split, seam = _split(FaceRig(head.neutral, head.triangles, head.names, head.deltas, head.inbetweens,
                                 name="Head"), float(head.neutral[moving, 1].mean()))
    n = split.n_vertices
    sheet, sheet_tri = _grid(120, 80, z=0.0, spacing=0.005)
    sheet = sheet[:, [0, 2, 1]] + [-0.3, float(head.neutral[:, 1].min()) - 0.5, -0.2]
    merged = FaceRig(np.concatenate([split.neutral, sheet]), np.concatenate([split.triangles, sheet_tri + n]),
                     split.names, np.concatenate([split.deltas, np.zeros((split.n_shapes, len(sheet), 3))],
                                                 axis=1), name="Head")
    others = [FaceRig(m.neutral, m.triangles, m.names, m.deltas, name=m.name) for m in avatar.meshes
              if m.name != "Head"]
    others += [FaceRig(p, t, [], np.zeros((0, len(p), 3)), name=k.rsplit("/", 1)[-1])
               for k, (p, t) in avatar.metadata["static_meshes"].items()]
    return write_rig_usd([merged] + others, path, meters_per_unit=avatar.meters_per_unit), n, seam


@pytest.mark.parametrize("moving_only", [False, True], ids=["read-whole", "read-moving-part"])
def test_the_public_writer_gives_copies_their_twins_offsets(samples, split_sample, tmp_path, moving_only):
    """``write_avatar_layer`` of a personalization of a split avatar over the avatar read by the caller:
    read whole, the copies were written with their generic offsets (a 3.3 mm tear); read on its moving part
    (a split Head merged with a static sheet), the write was refused ('not on the vertices the rig holds').
    Found by a review."""
    from usdface.io.layers import write_avatar_layer
    from usdface.io.usd_rig import read_avatar
    from usdface.transfer import personalize_avatar

    if moving_only:
        path, n, seam = _split_on_sheet(samples, tmp_path / "split_sheet.usda")
    else:
        path, n, seam = split_sample
        n += seam.size
    res = personalize_avatar(path, samples / "capture.usda", None)
    result = np.asarray(res.offsets["/Avatar/Head"])
    out = write_avatar_layer(read_avatar(path, moving_only=moving_only), tmp_path / "out.usda", res.offsets)
    back = read_avatar(out).mesh("Head").deltas
    n_head = n if moving_only else n
    copies = np.arange(n_head - seam.size, n_head)
    np.testing.assert_array_equal(back[:, copies], back[:, seam])                 # no tear
    np.testing.assert_allclose(back, result, rtol=0, atol=2e-7)                   # float32 in the file


def test_dry_run_counts_the_copies_it_would_write(samples, split_sample):
    """``--dry-run``'s moved-vertex counts and RMS change are those of every vertex of the mesh: a copy
    moves with its twin (they left the copies out, a review)."""
    from usdface.io.usd_rig import read_avatar
    from usdface.transfer import personalize_avatar

    path, n, seam = split_sample
    dry = personalize_avatar(path, samples / "capture.usda", None, dry_run=True)
    result = np.asarray(dry.offsets["/Avatar/Head"])                              # [K, n + seam, 3]
    generic = read_avatar(path).mesh("Head")
    change = np.sum((result - generic.deltas) ** 2, axis=-1)
    rows = {r["shape"]: r for r in dry.report["changes"] if r["mesh"] == "/Avatar/Head"}
    assert any((change[:, n:] > 1e-18).any(axis=1))                              # copies move
    for k, name in enumerate(generic.names):
        assert rows[name]["moved_vertices"] == int((change[k] > 1e-18).sum()), name
        np.testing.assert_allclose(rows[name]["rms_change_m"], np.sqrt(change[k].mean()), rtol=1e-9,
                                   atol=1e-15)


def test_a_clump_of_parked_vertices_is_one_point():
    """Thousands of vertices parked at one point (and still in every shape) are copies of the first: one
    pair each to compare (a review measured 421 s and 6 GB for 12k of them with every pair compared)."""
    rng = np.random.default_rng(2)
    points = rng.random((5000, 3))
    deltas = rng.random((3, 5000, 3)) * 1e-3
    points[:2000] = 0.0
    deltas[:, :2000] = 0.0
    deltas[:, 1999] = 1e-3                                  # one parked vertex that moves: not a copy
    rep = coincident_vertices(points, deltas)
    np.testing.assert_array_equal(rep[:1999], 0)
    assert rep[1999] == 1999 and (rep[2000:] == np.arange(2000, 5000)).all()


def test_a_copy_follows_its_twin_when_the_twin_is_the_first_vertex_kept():
    """Cropping a welded part again from the seam's row up: the lowest kept vertex (local index 0) is a
    seam vertex, and its copy follows it like every other copy (none join the residue)."""
    from usdface.model import MeshSource

    points, tri = _grid(8, 6)
    n = len(points)
    deltas = np.zeros((1, n, 3))
    deltas[0, :, 2] = 0.001 * points[:, 0] + 0.002
    src = MeshSource(file="x.usda", prim="/Avatar/Head", point_indices=[None], normal_offsets=[None])
    rig, seam = _split(FaceRig(points, tri, ["jawOpen"], deltas, name="Head"), 0.021)
    welded, region = weld_rig(dataclasses.replace(rig, source=src))
    keep = welded.neutral[:, 1] >= welded.neutral[seam, 1].min() - 1e-9
    part, sub = crop_rig(welded, keep, region)
    assert sub.vertices[0] == seam.min()                         # the first kept vertex is on the seam
    np.testing.assert_array_equal(np.sort(sub.copies[0]), np.sort(region.copies[0]))
    assert not set(region.copies[0].tolist()) & set(part.source.residue[0][0].tolist())


def test_weld_drops_every_triangle_two_of_whose_corners_become_one():
    """A sliver whose first and last corners are copies of one point (a zero-area triangle across a seam) is
    dropped by the weld, as one whose neighbouring corners are; the others are kept, re-indexed."""
    points = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0], [0.0, 0.0, 0.0],
                       [0.0, 0.0, 0.0]])
    deltas = np.zeros((1, 5, 3))
    deltas[0, :, 2] = 0.001
    tri = np.array([[0, 1, 2], [3, 1, 0], [1, 4, 0], [3, 1, 2]])
    welded, region = weld_rig(FaceRig(points, tri, ["jawOpen"], deltas, name="Head"))
    np.testing.assert_array_equal(welded.triangles, [[0, 1, 2], [0, 1, 2]])
    np.testing.assert_array_equal(np.sort(region.copies[0]), [3, 4])
