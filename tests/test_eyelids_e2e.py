"""Eyelid-eyeball repair end to end (issue 3, step 6): ``usdface personalize`` on the sample assets finds the
avatar's eye meshes (read by :func:`usdface.io.usd_rig.read_avatar` as static meshes) and no personalized
``Head`` shape pushes a vertex into an eyeball deeper than the avatar itself does (the neutral or the artist's
generic shape: lids and sockets tucked behind the eyeball are modelled that way on purpose)."""

from __future__ import annotations

import numpy as np

from usdface.cli import main

#: allowed extra penetration (m): twice the repair's own tolerance (5e-5 m), above float32 storage noise
TOLERANCE = 1e-4


def _signed_distance(points, triangles, queries):
    """Signed distance (m, negative inside) from ``queries[q,3]`` to the closed mesh (points, triangles)."""
    import open3d as o3d

    origin = points.mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((points - origin).astype(np.float32)),
                        o3d.core.Tensor(triangles.astype(np.uint32)))
    return scene.compute_signed_distance(
        o3d.core.Tensor((queries - origin).astype(np.float32))).numpy().astype(np.float64)


def _excess_penetration(head, offsets, eyes) -> float:
    """Largest depth (m) by which a vertex of any shape ``offsets[K,n,3]`` is inside an eyeball beyond what
    the neutral and the generic shape of the same vertex already have (0 when none is deeper)."""
    worst = 0.0
    for points, triangles in eyes:
        near = np.flatnonzero(np.linalg.norm(head.neutral - points.mean(axis=0), axis=1) < 0.03)
        x0 = head.neutral[near]

        def depth(shapes, x0=x0, near=near, points=points, triangles=triangles):
            q = x0[None] + shapes[:, near]
            return _signed_distance(points, triangles, q.reshape(-1, 3)).reshape(len(shapes), -1)

        allowed = np.minimum(np.minimum(depth(np.zeros((1, *head.neutral.shape))), 0.0), depth(head.deltas))
        worst = max(worst, float((allowed - depth(offsets)).max()))
    return worst


def test_personalize_repairs_eyelids_on_the_sample(samples, tmp_path, capsys):
    from usdface.io.usd_rig import read_avatar

    texts, excess = {}, {}
    avatar = read_avatar(samples / "avatar.usda")
    eyes = list(avatar.metadata["static_meshes"].values())
    assert len(eyes) == 2
    for repair in (True, False):
        path = tmp_path / f"repair{repair}.usda"
        args = ["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-o", str(path),
                "-q", "--correspondence", str(tmp_path / "corr.npz")] + ([] if repair else ["--no-eyelids"])
        assert main(args) == 0
        texts[repair] = capsys.readouterr().out
        result = read_avatar(path)  # the layer composed over the avatar: the personalized shapes
        head = result.mesh("Head")
        np.testing.assert_allclose(head.neutral, avatar.mesh("Head").neutral, atol=1e-9)
        excess[repair] = _excess_penetration(avatar.mesh("Head"), head.deltas, eyes)
    assert "no eyeball meshes found" not in texts[True]
    assert "eyelids: " in texts[True] and "/Avatar/EyeLeft" in texts[True]
    # the personalization does push lids into the eyes (else this test could not fail) ...
    assert excess[False] > 5 * TOLERANCE, excess
    # ... and the repair brings every vertex of every shape back to the surface
    assert excess[True] <= TOLERANCE, excess


def test_eyelid_repair_uses_the_eyes_of_the_face_it_personalizes(samples, tmp_path, capsys):
    """Two characters referencing one avatar in a stage: personalizing either face repairs its lids
    against its own two eyeballs (it took the two best-fitting spheres of the whole stage: one eye of each
    character, and one lid per face went unrepaired)."""
    import json
    import shutil

    shutil.copy(samples / "avatar.usda", tmp_path / "avatar.usda")
    (tmp_path / "crowd.usda").write_text(
        '#usda 1.0\n(\n    defaultPrim = "World"\n    metersPerUnit = 0.01\n    upAxis = "Y"\n)\n\n'
        'def Xform "World"\n{\n    def "Anna" (prepend references = @./avatar.usda@)\n    {\n    }\n\n'
        '    def "Ben" (prepend references = @./avatar.usda@)\n    {\n'
        '        double3 xformOp:translate = (100, 0, 0)\n'
        '        uniform token[] xformOpOrder = ["xformOp:translate"]\n    }\n}\n')
    alone = None
    for who in ("Anna", "Ben", None):
        args = (["personalize", str(tmp_path / "crowd.usda"), str(samples / "capture.usda"), "--face-mesh",
                 f"/World/{who}/Head"] if who else
                ["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda")])
        assert main([*args, "--dry-run", "--json", "-q", "-o", str(tmp_path / "o.usda")]) == 0
        lids = json.loads(capsys.readouterr().out)["eyelids"]
        if who:
            assert sorted(lids["eyeballs"]) == [f"/World/{who}/EyeLeft", f"/World/{who}/EyeRight"]
            repaired = lids["repaired_vertex_shapes"]
        else:
            alone = lids["repaired_vertex_shapes"]
    assert repaired == alone > 0
