"""Pictures (usdface.render, ``usdface render``) and inspection data authored into result layers
(usdface.io.usd_inspection): heat-map displayColor, landmark Points, a SkelAnimation that really drives the
personalized avatar."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_helpers import _no_traceback, _usdface

import usdface.io  # noqa: F401  (schemas before the first stage)
from usdface.cli import main
from usdface.errors import OutputExistsError, RigError, UsdFaceError
from usdface.model import FaceRig
from usdface.render import (
    default_shapes,
    draw_mesh,
    heat_colors,
    moving_region,
    render_comparison,
    render_heatmap,
    render_landmarks,
    render_shapes,
)

PNG = b"\x89PNG\r\n\x1a\n"

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def grid_rig(n: int = 12) -> FaceRig:
    """A flat n x n grid facing +Z with two shapes: 'bump' (centre up in z) and 'slide' (everything +x)."""
    u, v = np.meshgrid(np.linspace(-0.1, 0.1, n), np.linspace(-0.1, 0.1, n))
    neutral = np.c_[u.ravel(), v.ravel(), np.zeros(n * n)]
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1))
    a = (j * n + i).ravel()
    tris = np.r_[np.c_[a, a + 1, a + n], np.c_[a + 1, a + n + 1, a + n]]
    bump = np.zeros_like(neutral)
    bump[:, 2] = 0.02 * np.exp(-(neutral[:, 0] ** 2 + neutral[:, 1] ** 2) / 0.002)
    slide = np.zeros_like(neutral)
    slide[:, 0] = 0.001
    return FaceRig(neutral, tris, ["bump", "slide"], np.stack([bump, slide]), name="grid")


def test_draw_mesh_culls_back_faces():
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    rig = grid_rig()
    ax = Figure().add_subplot()
    assert len(draw_mesh(ax, rig.neutral, rig.triangles).get_paths()) == len(rig.triangles)
    ax = Figure().add_subplot()  # flipped winding: every triangle faces away from the camera
    with pytest.warns(UserWarning, match="no face of the mesh faces the camera in the front view"):
        assert len(draw_mesh(ax, rig.neutral, rig.triangles[:, ::-1]).get_paths()) == 0


def test_a_mesh_seen_edge_on_says_why_its_panel_is_empty(tmp_path):
    """Pixar's Z-up blend-shape test plane lies flat once Y is up: ``usdface render`` drew six empty panels
    and said nothing. The empty view is now a warning naming the up axis."""
    rig = grid_rig()
    yz = [0, 2, 1]                                  # the grid turned to lie in the XZ plane
    flat = FaceRig(rig.neutral[:, yz], rig.triangles, rig.names, rig.deltas[:, :, yz], name="flat")
    with pytest.warns(UserWarning, match="seen edge-on or from behind.*upAxis"):
        render_shapes(flat, ["bump"], tmp_path / "flat.png")
    assert (tmp_path / "flat.png").read_bytes()[:8] == PNG


def test_render_functions_write_pngs(tmp_path):
    rig = grid_rig()
    assert default_shapes(rig, 1) == ["bump"]  # the shape that moves most
    out = render_shapes(rig, None, tmp_path / "s.png")
    assert out is not None and (tmp_path / "s.png").read_bytes()[:8] == PNG
    with pytest.raises(OutputExistsError):
        render_shapes(rig, None, tmp_path / "s.png")
    render_shapes(rig, ["slide"], tmp_path / "s.png", force=True)
    # a panel drawn at another weight says so (it showed the millimetres only: a trial's note)
    assert [ax.get_title() for ax in render_shapes(rig, ["bump"], weight=0.5).axes[1:2]] == [
        f"bump at 0.5\n(max {500 * np.linalg.norm(rig.deltas[0], axis=1).max():.1f} mm)"]
    assert render_shapes(rig, ["bump"]).axes[1].get_title().startswith("bump\n(max ")
    render_comparison(rig, rig, ["bump"], tmp_path / "c.png")
    render_heatmap(rig.neutral, rig.triangles, np.linalg.norm(rig.deltas[0], axis=1), tmp_path / "h.png")
    render_landmarks(rig.neutral, rig.triangles, [0, 5, 77], tmp_path / "l.png", labels=["a", "b", "c"])
    assert all((tmp_path / f).read_bytes()[:8] == PNG for f in ("c.png", "h.png", "l.png"))
    assert not list(tmp_path.glob(".*tmp*"))  # atomic writes leave no temp files
    with pytest.raises(UsdFaceError, match="no shape 'nope'"):
        render_shapes(rig, ["nope"])
    with pytest.raises(UsdFaceError, match="one value per vertex"):
        render_heatmap(rig.neutral, rig.triangles, [1.0, 2.0])
    with pytest.raises(UsdFaceError, match="out of range"):
        render_landmarks(rig.neutral, rig.triangles, [10_000])


def test_a_dense_mesh_is_drawn_decimated_with_the_full_mesh_figures(tmp_path):
    """A 225k-vertex head took ~30 CPU-s per 'render --compare' (9 panels of 450k sub-pixel triangles
    through matplotlib, one Python Path per triangle); a mesh of more than ``max_vertices`` vertices is now
    drawn on a decimated subset of its own vertices, and the titles keep the full mesh's figures."""
    import matplotlib

    matplotlib.use("Agg")
    rig = grid_rig(40)                                 # 1,600 vertices, 3,042 triangles
    full = render_comparison(rig, rig, ["bump"], max_vertices=0)
    small = render_comparison(rig, rig, ["bump"], tmp_path / "c.png", max_vertices=400)
    drawn = [len(ax.collections[0].get_paths()) for ax in small.axes[:3]]
    assert all(0 < d < 1000 for d in drawn), drawn
    assert len(full.axes[0].collections[0].get_paths()) == len(rig.triangles)
    assert [ax.get_title() for ax in small.axes[:3]] == [ax.get_title() for ax in full.axes[:3]]
    shapes = render_shapes(rig, ["bump"], max_vertices=400)
    top = 1000 * np.linalg.norm(rig.deltas[0], axis=1).max()
    assert shapes.axes[1].get_title() == f"bump\n(max {top:.1f} mm)"           # the full mesh's maximum
    heat = render_heatmap(rig.neutral, rig.triangles, np.linalg.norm(rig.deltas[0], axis=1),
                          max_vertices=400)
    assert len(heat.axes[0].collections[0].get_paths()) < 1000
    assert (tmp_path / "c.png").read_bytes()[:8] == PNG


def test_a_face_on_a_large_still_mesh_is_framed_on_what_moves():
    """A face on a head-and-body mesh (314k vertices, 15 % moving) was drawn as the whole body: the face a
    few per cent of each panel, the panels so narrow that their titles ran into each other. The view is
    framed on the vertices the shapes move when they are less than half of the mesh."""
    from usdface.render import moving_region

    rig = grid_rig(40)
    local = np.zeros_like(rig.deltas)
    near = np.linalg.norm(rig.neutral[:, :2] - 0.05, axis=1) < 0.02       # a corner of the grid moves
    local[:, near, 2] = 0.003
    still = FaceRig(rig.neutral, rig.triangles, rig.names, local, name="body")
    crop = moving_region(still.deltas)
    np.testing.assert_array_equal(crop, np.flatnonzero(near))
    assert moving_region(rig.deltas) is None                      # 'slide' moves everything: the whole mesh
    for fig, axes in ((render_shapes(still, ["bump"]), [0, 1]), (render_comparison(still, still, ["bump"]),
                                                                 [0, 1, 2])):
        for i in axes:
            lo, hi = fig.axes[i].get_xlim()
            assert hi - lo < 0.06, (i, lo, hi)                     # the 4 cm patch, not the 20 cm grid
    heat = render_heatmap(still.neutral, still.triangles, np.linalg.norm(local[0], axis=1),
                          crop=moving_region(local))
    assert np.diff(heat.axes[0].get_ylim())[0] < 0.06


def test_a_face_on_a_large_still_mesh_is_drawn_whole_within_its_frame(tmp_path, capsys):
    """The pictures of a face on a head-and-body mesh decimated the whole mesh (most of 'render''s CPU on
    the merged bench avatar: the body) though each panel is framed on the face, which lost vertices too. The
    mesh is now cut to the frame first: under the limit, the picture is the one of every triangle."""
    import matplotlib.image

    rig = grid_rig(60)                                                  # 3,600 vertices
    local = np.zeros_like(rig.deltas)
    near = np.linalg.norm(rig.neutral[:, :2] - 0.06, axis=1) < 0.02     # a corner of the grid moves
    local[0, near, 2] = 0.004 * (1 - np.linalg.norm(rig.neutral[near, :2] - 0.06, axis=1) / 0.02)
    still = FaceRig(rig.neutral, rig.triangles, rig.names, local, name="body")
    pictures = []
    for limit in (0, 1000):                                       # every triangle, then over the limit
        out = tmp_path / f"s{limit}.png"
        render_shapes(still, ["bump"], out, max_vertices=limit)
        render_heatmap(still.neutral, still.triangles, np.linalg.norm(local[0], axis=1),
                       tmp_path / f"h{limit}.png", max_vertices=limit, crop=moving_region(local))
        pictures.append([matplotlib.image.imread(out), matplotlib.image.imread(tmp_path / f"h{limit}.png")])
    for whole, cut in zip(*pictures, strict=True):   # the same pixels, up to the order of coplanar ties:
        off = np.abs(whole - cut).max(axis=-1)       # a few antialiased edge pixels a few levels apart (2/255
        assert off.max() <= 4.01 / 255 and np.mean(off > 0) < 1e-3, (off.max(), np.mean(off > 0))  # on EPYC)
    from usdface.commands.render import _decimated_note

    _decimated_note(still, 1000, framed=True)                    # the command's note says which it is
    assert "body (3,600 vertices) drawn on its part in the picture's frame" in capsys.readouterr().err
    _decimated_note(still, 1000)
    assert "drawn decimated to about 1,000 of its vertices" in capsys.readouterr().err


def test_render_cli_says_when_it_draws_a_mesh_decimated(inspected, tmp_path, capsys):
    """The note names the mesh, its vertex count and the option that draws every triangle."""
    _avatar, layer, _heat = inspected
    assert main(["render", str(layer), "-o", str(tmp_path / "d.png"), "--max-vertices", "500", "-q"]) == 0
    err = capsys.readouterr().err
    assert "drawn decimated to about 500 of its vertices" in err and "--max-vertices 0" in err
    assert main(["render", str(layer), "-o", str(tmp_path / "e.png"), "-q"]) == 0
    assert "decimated" not in capsys.readouterr().err                          # the sample head: 4k vertices


def test_render_landmarks_reads_the_neutral_not_the_shapes(samples, tmp_path, monkeypatch):
    """'render l.usda --landmarks' draws the neutral, but read every shape's offsets (a 225k-vertex head: 51
    dense shapes, 793 MB peak for a picture of the neutral). The reader's ``shapes=False`` reads the meshes,
    their channels and targets, no offsets: the same neutral, triangles and names, zero deltas that hold no
    memory; the picture is the same."""
    from usdface.io import usd_rig

    lm = tmp_path / "mouth_lm.usda"
    assert main(["landmarks", str(samples / "avatar.usda"), "--mesh", "Mouth", "-o", str(lm), "-q"]) == 0
    full, bare = usd_rig.read_avatar(lm), usd_rig.read_avatar(lm, shapes=False)
    for a, b in zip(full.meshes, bare.meshes, strict=True):
        assert (a.name, a.names, b.inbetweens) == (b.name, b.names, {})
        np.testing.assert_array_equal(a.neutral, b.neutral)
        np.testing.assert_array_equal(a.triangles, b.triangles)
        assert b.deltas.shape == a.deltas.shape and not b.deltas.any() and b.deltas.strides[:2] == (0, 0)
    read = []
    real = usd_rig._array
    monkeypatch.setattr(usd_rig, "_array", lambda value, dtype, width, what, *rest: (
        read.append(what), real(value, dtype, width, what, *rest))[1])
    assert main(["render", str(lm), "--landmarks", "-o", str(tmp_path / "l.png"), "-q"]) == 0
    assert read and "offsets" not in read, read                  # the mesh read, none of its shapes
    assert main(["render", str(lm), "-o", str(tmp_path / "s.png"), "-q"]) == 0
    assert "offsets" in read                                      # the shapes' picture reads them
    monkeypatch.setattr(usd_rig, "read_avatar", lambda path, **kw: full)     # the full read's picture
    assert main(["render", str(lm), "--landmarks", "-o", str(tmp_path / "f.png"), "-q"]) == 0
    assert (tmp_path / "f.png").read_bytes() == (tmp_path / "l.png").read_bytes()


def test_heat_colors_monotone():
    colors = heat_colors([0.0, 0.5, 1.0], vmax=1.0)
    brightness = colors.sum(axis=1)
    assert colors.shape == (3, 3) and np.all(np.diff(brightness) > 0)
    assert np.all((0 <= colors) & (colors <= 1))


def _layout(rig, vertices, epsilon=0.5):
    """A LandmarkLayout by hand (what usdface.compute_landmarks returns), for fast tests."""
    from usdface.landmarks.layout import LandmarkLayout

    v = np.asarray(vertices)
    m = len(v)
    return LandmarkLayout(v, np.zeros((m, 3)), np.ones((m, rig.n_shapes), bool), np.ones(m, int), np.ones(m),
                          list(rig.names), epsilon, 0.5, False, 1, "optimal", 0.0, 1.0,
                          "quality", "scip")


@pytest.fixture(scope="module")
def inspected(tmp_path_factory, request):
    """A result layer over the sample avatar (Head offsets x1.1) with heat map, landmarks and animation."""
    samples = request.getfixturevalue("samples")
    from usdface.arkit import ARKIT_NAMES
    from usdface.io.layers import write_avatar_layer
    from usdface.io.usd_inspection import inspection_edit
    from usdface.io.usd_rig import read_avatar

    avatar = read_avatar(samples / "avatar.usda")
    head = avatar.mesh("Head")
    heat = np.linalg.norm(0.1 * head.deltas, axis=2).max(axis=0)
    weights = np.zeros((3, 52))
    weights[1, ARKIT_NAMES.index("jawOpen")] = 1.0
    weights[2, ARKIT_NAMES.index("eyeBlinkLeft")] = 0.5
    raw = [n.replace("Left", "_L").replace("Right", "_R") for n in ARKIT_NAMES]  # any spelling maps
    layout = _layout(head, [0, 10, 100], epsilon=0.25)
    edit = inspection_edit(avatar, heat={"Head": heat}, landmarks={"Head": layout}, animation=(raw, weights),
                           fps=30)
    out = tmp_path_factory.mktemp("insp") / "result.usda"
    write_avatar_layer(avatar, out, {"Head": 1.1 * head.deltas}, provenance={"command": "test"}, edit=edit)
    return avatar, out, heat


def test_inspection_layer_contents(inspected):
    from pxr import Usd, UsdGeom, UsdSkel

    from usdface.io.usd_inspection import ANIMATION_NAME, HEAT_PRIMVAR, read_landmarks
    from usdface.io.usd_rig import generic_input
    from usdface.pipeline.validators import validate_file

    avatar, out, heat = inspected
    stage = Usd.Stage.Open(str(out))
    head = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Avatar/Head"))
    colors = np.asarray(head.GetPrimvar("displayColor").Get())
    assert colors.shape == (avatar.mesh("Head").n_vertices, 3)
    assert head.GetPrimvar("displayColor").GetInterpolation() == "vertex"
    np.testing.assert_allclose(np.asarray(head.GetPrimvar(HEAT_PRIMVAR).Get()), heat, rtol=1e-6, atol=1e-9)
    # the hottest vertex is brighter than the coldest
    assert colors[np.argmax(heat)].sum() > colors[np.argmin(heat)].sum()
    # landmark Points sit exactly on the mesh's (world-space) vertices
    layouts = read_landmarks(out)
    assert list(layouts) == ["/Avatar/Head"] and layouts["/Avatar/Head"].tolist() == [0, 10, 100]
    pts_prim = stage.GetPrimAtPath("/Avatar/Head_landmarks")  # the landmark writer's Points prim
    assert pts_prim.GetAttribute("usdface:landmarks:epsilon").Get() == pytest.approx(0.25)
    cache = UsdGeom.XformCache()
    pts = np.asarray(UsdGeom.Points(pts_prim).GetPointsAttr().Get(), dtype=float)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Avatar/Head"))
    rest = np.asarray(mesh.GetPointsAttr().Get(), dtype=float)[[0, 10, 100]]

    def world(prim, p):
        m = np.array(cache.GetLocalToWorldTransform(prim))
        return p @ m[:3, :3] + m[3, :3]

    np.testing.assert_allclose(world(pts_prim, pts), world(mesh.GetPrim(), rest), atol=1e-4)
    # the animation is bound and plays: frame 1 = jawOpen, so skinning moves the Head
    skel = stage.GetPrimAtPath("/Avatar/Skel")
    assert UsdSkel.BindingAPI(skel).GetAnimationSource().GetName() == ANIMATION_NAME
    anim = UsdSkel.Animation(stage.GetPrimAtPath(f"/Avatar/Skel/{ANIMATION_NAME}"))
    names = list(anim.GetBlendShapesAttr().Get())
    w1 = np.asarray(anim.GetBlendShapeWeightsAttr().Get(1.0))
    assert w1[names.index("jawOpen")] == 1.0 and w1.sum() == 1.0
    assert stage.GetEndTimeCode() == 2.0 and stage.GetTimeCodesPerSecond() == 30.0
    cache_skel = UsdSkel.Cache()
    root = UsdSkel.Root(stage.GetPrimAtPath("/Avatar"))
    cache_skel.Populate(root, Usd.PrimDefaultPredicate)
    query = cache_skel.GetSkinningQuery(mesh.GetPrim())
    anim_query = cache_skel.GetSkelQuery(UsdSkel.Skeleton(skel)).GetAnimQuery()
    assert query.HasBlendShapes() and anim_query.GetPrim().GetName() == ANIMATION_NAME
    mesh_weights = np.asarray(query.GetBlendShapeMapper().Remap(anim_query.ComputeBlendShapeWeights(1.0)))
    channels = list(UsdSkel.BindingAPI(mesh.GetPrim()).GetBlendShapesAttr().Get())
    assert mesh_weights[channels.index("jawOpen")] == 1.0 and mesh_weights.sum() == 1.0
    assert generic_input(out).name == "avatar.usda"
    assert validate_file(out) == []  # Pixar validators + face-rig rules + provenance


def test_render_cli_on_result(inspected, tmp_path, capsys):
    _avatar, out, _heat = inspected
    for i, flags in enumerate([["--shapes", "jawOpen"], ["--shapes", "jawOpen", "--compare"],
                               ["--shapes", "jawOpen", "--heatmap"], ["--landmarks"]]):
        png = tmp_path / f"{i}.png"
        assert main(["render", str(out), "-o", str(png), *flags]) == 0
        assert png.read_bytes()[:8] == PNG
    assert main(["render", str(out), "-o", str(tmp_path / "0.png")]) == 2  # exists, no --force
    assert "--force" in capsys.readouterr().err


def test_render_cli_options_a_mode_would_ignore(inspected, tmp_path, capsys, monkeypatch):
    """``--weight`` with ``--compare``/``--heatmap``/``--landmarks`` and ``--shapes`` with ``--landmarks``
    were silently ignored, ``--shapes ,`` drew the neutral alone; all refused before any drawing.
    ``--heatmap --shapes`` is the RMS over those shapes (it was over all of them)."""
    from usdface import render

    _avatar, out, _heat = inspected
    for flags, named in ((["--compare", "--weight", "0.5"], "--weight not used by --compare"),
                         (["--heatmap", "--weight", "0.5"], "--weight not used by --heatmap"),
                         (["--landmarks", "--shapes", "jawOpen"], "--shapes not used by --landmarks"),
                         (["--shapes", ","], "names no shape")):
        assert main(["render", str(out), "-o", str(tmp_path / "x.png"), *flags]) == 2
        assert named in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()
    seen = {}
    monkeypatch.setattr(render, "render_heatmap", lambda points, tris, values, *a, **k: seen.update(v=values))
    for key, flags in (("all", []), ("jaw", ["--shapes", "jawOpen"])):
        assert main(["render", str(out), "-o", str(tmp_path / f"{key}.png"), "--heatmap", *flags]) == 0
        seen[key] = seen.pop("v")
    assert not np.allclose(seen["all"], seen["jaw"])


def test_render_cli_capture_and_errors(samples, tmp_path, capsys):
    assert main(["render", str(samples / "capture.usda"), "--capture", "-o", str(tmp_path / "cap.png")]) == 0
    avatar = samples / "avatar.usda"
    assert main(["render", str(avatar), "-o", str(tmp_path / "x.png"), "--compare"]) == 2
    assert "--compare GENERIC" in capsys.readouterr().err
    assert main(["render", str(avatar), "-o", str(tmp_path / "y.png"), "--landmarks"]) == 2
    assert main(["render", str(avatar), "-o", str(tmp_path / "z.png"), "--mesh", "Nose"]) == 2


def test_render_compare_with_another_avatar_is_refused(tmp_path, capsys):
    """A user trial: ``render person.usda --compare other.usdc`` with an avatar that is not the one the layer
    was made from ended in a traceback (``ValueError: 'tongueOut' is not in list``, or a broadcast error for
    another vertex count); now one line naming the generic file, the mesh and the fix."""
    from usdface.io.avatar_writer import write_rig_usd

    rig = grid_rig()
    rig.name = "Head"
    person = write_rig_usd(rig, tmp_path / "person.usda")
    fewer = FaceRig(rig.neutral, rig.triangles, ["bump"], rig.deltas[:1], name="Head")
    write_rig_usd(fewer, tmp_path / "fewer.usda")
    coarse = grid_rig(8)
    coarse.name = "Head"
    write_rig_usd(coarse, tmp_path / "coarse.usda")
    for mode in ("--compare", "--heatmap"):
        for other, said in (("fewer.usda", "has no shape slide"), ("coarse.usda", "has 64 vertices")):
            png = tmp_path / f"{mode[2:]}_{other}.png"
            assert main(["render", str(person), "-o", str(png), mode, str(tmp_path / other)]) == 2
            err = capsys.readouterr().err
            assert said in err and other in err and "fix: pass the avatar" in err and "Traceback" not in err
            assert not png.exists()
    assert main(["render", str(person), "-o", str(tmp_path / "ok.png"), "--compare", str(person)]) == 0


def test_a_mesh_without_shapes_is_named_as_such(samples, tmp_path, capsys):
    """A user trial: ``landmarks avatar --mesh EyeLeft`` (and render/personalize's mesh options) said "no mesh
    'EyeLeft' in the avatar" of a mesh that is there, only without blend shapes; now it says so, naming the
    prim and the meshes that have shapes."""
    out = tmp_path / "e.png"
    for argv in (["landmarks", str(samples / "avatar.usda"), "--mesh", "EyeLeft", "-q"],
                 ["render", str(samples / "avatar.usda"), "--mesh", "/Avatar/EyeRight", "-o", str(out)]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "has no blend shapes (a static mesh" in err and "no mesh '" not in err
        assert "prim /Avatar/Eye" in err and "use one of /Avatar/Head, /Avatar/Mouth" in err
    assert main(["render", str(samples / "avatar.usda"), "--mesh", "Nose", "-o", str(out)]) == 2
    assert "no mesh 'Nose'" in capsys.readouterr().err and not out.exists()


def test_render_landmarks_draws_the_mesh_the_layout_is_on(samples, tmp_path, capsys):
    """A user trial: ``landmarks avatar --mesh Mouth -o lm.usda`` then ``render lm.usda --landmarks`` said
    "no landmark layout for mesh 'Head' (fix: run 'usdface landmarks' first)" of a file that has one, and
    ``--diagnostics`` computed a new Head layout instead of drawing the authored one. Without --mesh the
    mesh that carries the layout is drawn; an explicit other mesh names the one the file has."""
    import re

    lm = tmp_path / "mouth_lm.usda"
    assert main(["landmarks", str(samples / "avatar.usda"), "--mesh", "Mouth", "-o", str(lm), "-q"]) == 0
    capsys.readouterr()
    from usdface import render

    figures = []
    real = render.save_figure
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(render, "save_figure", lambda fig, out, force=False: (figures.append(fig),
                                                                         real(fig, out, force))[1])
        assert main(["render", str(lm), "--landmarks", "-o", str(tmp_path / "l.png")]) == 0
    # the picture names the file it drew (stop 42: 'Mouth: 3 landmarks', where the shapes picture names it)
        assert main(["render", str(lm), "--landmarks", "--view", "left", "-o", str(tmp_path / "s.png")]) == 0
    front, side = (f.axes[0].get_title() for f in figures)
    assert front.startswith("mouth_lm.usda\nMouth: ") and "far side" not in front
    # the side view says how many of the title's landmarks it cannot show (the note was dropped with a title)
    assert re.search(r"Mouth: \d+ landmarks \(\d+ on the far side\)$", side), side
    assert main(["render", str(lm), "--landmarks", "--diagnostics", "-o", str(tmp_path / "d.png"), "-q"]) == 0
    out = capsys.readouterr().out
    assert "Mouth: " in out and "landmarks (authored)" in out
    assert main(["render", str(lm), "--landmarks", "--mesh", "Head", "-o", str(tmp_path / "h.png")]) == 2
    err = capsys.readouterr().err
    assert "no landmark layout for mesh 'Head' (the file has one for /Avatar/Mouth)" in err
    assert "--mesh /Avatar/Mouth" in err and not (tmp_path / "h.png").exists()


def test_render_landmarks_without_a_layout_names_the_commands_that_make_one(samples, tmp_path, capsys):
    """pipeline.md's 'usdface render person.usda -o landmarks.png --landmarks' on a layer written without
    --landmarks said "(fix: run 'usdface landmarks' (or personalize with landmarks) first)": run as told, the
    layout goes into another file, and the layer still has none. The fix names the file to write and to draw,
    and following it draws the layout."""
    import re
    import shutil

    avatar = shutil.copy(samples / "avatar.usda", tmp_path / "avatar.usda")
    assert main(["render", str(avatar), "--landmarks", "-o", str(tmp_path / "l.png")]) == 2
    err = capsys.readouterr().err
    assert "no landmark layout for mesh 'Head'" in err and not (tmp_path / "l.png").exists()
    told = re.search(r"\(usdface landmarks (\S+) -o (\S+)\), then draw that file "
                     r"\(usdface render (\S+) -o (\S+) --landmarks\)", err)
    assert told, err
    assert "--landmarks" in err.split("or personalize with", 1)[1] and "--diagnostics" in err
    assert Path(told.group(1)) == avatar and told.group(2) == told.group(3)
    assert main(["landmarks", told.group(1), "-o", told.group(2), "-q"]) == 0
    assert Path(told.group(4)) == tmp_path / "l.png"        # the picture asked for (render needs its -o)
    assert main(["render", told.group(3), "--landmarks", "-o", told.group(4)]) == 0
    assert (tmp_path / "l.png").read_bytes()[:4] == b"\x89PNG"


def test_inspection_rejects_bad_input():
    from usdface.io.usd_inspection import inspection_edit
    from usdface.model import Avatar, MeshSource

    rig = grid_rig()
    rig.source = MeshSource(file="a.usda", prim="/A/Grid", skel_root="/A")
    avatar = Avatar([rig], file="a.usda")
    with pytest.raises(RigError, match="no mesh 'Nose'"):
        inspection_edit(avatar, heat={"Nose": np.zeros(3)})(None)
    with pytest.raises(RigError, match="one value per mesh point"):
        inspection_edit(avatar, heat={"Grid": np.zeros(3)})(None)
    with pytest.raises(RigError, match="LandmarkLayout"):
        inspection_edit(avatar, landmarks={"Grid": [0, 1]})(None)
    with pytest.raises(RigError, match="out of range"):
        inspection_edit(avatar, landmarks={"Grid": _layout(rig, [0, 999])})(None)


def test_add_inspection_to_written_layer(samples, tmp_path):
    """add_inspection rewrites only the output layer (atomically) and the heat is |new - generic| RMS."""
    from pxr import Usd, UsdGeom

    from usdface.io.layers import file_digest, write_avatar_layer
    from usdface.io.usd_inspection import HEAT_PRIMVAR, add_inspection, change_heat, inspection_edit
    from usdface.io.usd_rig import read_avatar

    src = samples / "avatar.usda"
    before = file_digest(src)
    avatar = read_avatar(src)
    head = avatar.mesh("Head")
    new = head.deltas.copy()
    new[head.index("jawOpen")] *= 2.0  # only jawOpen changes
    out = write_avatar_layer(avatar, tmp_path / "r.usda", {"Head": new})
    heat = change_heat(avatar, {"Head": new})["/Avatar/Head"]
    expected = np.linalg.norm(head.deltas[head.index("jawOpen")], axis=1) / np.sqrt(head.n_shapes)
    np.testing.assert_allclose(heat, expected, rtol=1e-12, atol=1e-15)
    add_inspection(out, inspection_edit(avatar, heat={"Head": heat}))
    stage = Usd.Stage.Open(str(out))
    values = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Avatar/Head")).GetPrimvar(HEAT_PRIMVAR).Get()
    np.testing.assert_allclose(np.asarray(values), heat, rtol=1e-6, atol=1e-9)
    assert file_digest(src) == before and not list(tmp_path.glob(".*tmp*"))


def test_change_heat_holds_no_copy_of_the_offsets():
    """``personalize --inspect`` of a 225k-vertex head peaked at 1.78 GB (1.11 GB without): the heat map
    formed the whole [K, n, 3] difference, its squares and norms at once. It goes shape by shape now."""
    import tracemalloc
    from types import SimpleNamespace

    from usdface.io.usd_inspection import change_heat
    from usdface.model import Avatar

    k, n = 8, 20_000
    rng = np.random.default_rng(1)
    generic = rng.normal(size=(k, n, 3)) * 1e-3
    rig = FaceRig(rng.normal(size=(n, 3)), np.array([[0, 1, 2]]), [f"s{i}" for i in range(k)], generic,
                  name="Head", source=SimpleNamespace(prim="/Avatar/Head"))
    new = generic.copy()
    new[3] += 2e-3
    avatar = Avatar([rig])
    change_heat(avatar, {"Head": new[:1]})                        # the lazy imports, before measuring
    tracemalloc.start()
    try:
        heat = change_heat(avatar, {"Head": new})["/Avatar/Head"]
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    np.testing.assert_allclose(heat, np.full(n, np.sqrt(3 * 4e-6 / k)), rtol=1e-12)
    assert peak < 0.4 * generic.nbytes, peak                      # all at once: 3-4x the offsets


def test_landmarks_on_the_far_side_are_hidden():
    rig = grid_rig()
    with pytest.warns(UserWarning, match="no face of the mesh faces the camera"):
        fig = render_landmarks(rig.neutral, rig.triangles[:, ::-1], [0, 5])  # every face looks away
    assert "2 on the far side" in fig.axes[0].get_title()
    fig = render_landmarks(rig.neutral, rig.triangles, [0, 5])
    assert fig.axes[0].get_title() == "2 landmarks"


def test_inspection_animation_timeline():
    """Test expressions every 0.5 s, then the take 1 s after the last one, columns merged by ARKit name."""
    from usdface.io.take import Take
    from usdface.io.usd_inspection import inspection_animation
    from usdface.model import Capture, Frames

    rig = grid_rig(3)
    frames = Frames(np.zeros((3, 9, 3)), np.array([[1.0, 0.0], [0.0, 1.0], [0.5, 0.5]]),
                    ["test", "train", "test"], ["a", "b", "c"])
    capture = Capture(rig.neutral, rig.triangles, rig, frames, ["jawOpen", "eyeBlinkLeft"])
    take = Take(np.array([[0.2], [0.4]]), ["JawOpen"], np.array([10.0, 10.1]))  # Live Link spelling
    names, weights, times = inspection_animation(capture, take)
    assert names == ["jawOpen", "eyeBlinkLeft"]
    np.testing.assert_allclose(times, [0.0, 0.5, 1.5, 1.6])
    np.testing.assert_allclose(weights, [[1.0, 0.0], [0.5, 0.5], [0.2, 0.0], [0.4, 0.0]])
    assert inspection_animation(None, None) is None


def test_render_cli_refuses_avatar_options_for_a_capture(samples, tmp_path, capsys):
    """A capture is drawn as its template shapes: ``--compare``, ``--heatmap``, ``--landmarks``, ``--mesh``
    and ``--name-map`` given with one were silently ignored (exit 0, a picture of something else)."""
    names = tmp_path / "names.json"
    names.write_text('{"JawDrop": "jawOpen"}')
    capture, png = str(samples / "capture.usda"), str(tmp_path / "c.png")
    for flags in (["--compare"], ["--heatmap"], ["--landmarks"], ["--mesh", "Mouth"],
                  ["--name-map", str(names)]):
        assert main(["render", capture, "-o", png, *flags]) == 2
        err = capsys.readouterr().err
        assert f"{flags[0]} not used for a capture" in err and "capture.usda" in err
    assert not (tmp_path / "c.png").exists()
    assert main(["render", capture, "-o", png, "--view", "left"]) == 0


def test_render_shapes_in_any_arkit_spelling(samples, tmp_path, capsys):
    """A user trial: '--shapes eyeBlink_L' (ARKit's raw value) or 'JawOpen' (Live Link's) was refused with
    'has no shape 'JawOpen' (fix: did you mean jawOpen? ...)', though every reader takes all three."""
    for i, src in enumerate((samples / "avatar.usda", samples / "capture.usda")):
        out = tmp_path / f"s{i}.png"
        assert main(["render", str(src), "-o", str(out), "--shapes", "eyeBlink_L,JawOpen", "-q"]) == 0, \
            capsys.readouterr().err
        assert out.is_file()
    assert main(["render", str(samples / "avatar.usda"), "-o", str(tmp_path / "x.png"), "--shapes",
                 "jawOpn", "-q"]) == 2
    assert "did you mean jawOpen?" in capsys.readouterr().err


def test_heatmap_of_one_shape_is_labelled_with_it(inspected, tmp_path, monkeypatch):
    """A user trial: '--heatmap --shapes jawOpen' labelled its colour bar 'RMS change over 1 shapes (mm)'."""
    import usdface.render as render_module

    labels = []
    monkeypatch.setattr(render_module, "render_heatmap", lambda *a, label="", **k: labels.append(label))
    _avatar, out, _heat = inspected
    for i, shapes in enumerate(("jawOpen", "jawOpen,eyeBlinkLeft")):
        png = tmp_path / f"{i}.png"
        assert main(["render", str(out), "-o", str(png), "--heatmap", "--shapes", shapes]) == 0
    assert labels == ["change in jawOpen (mm)", "RMS change over 2 shapes (mm)"]


def test_render_takes_the_meshs_own_channel_names_on_a_name_mapped_layer(tmp_path):
    """troubleshooting.md: '--shapes names shapes as the mesh has them'; on a layer written with --name-map
    only the ARKit name worked ('mesh Head has no shape ch17_ctrl'). Both work now, and a comparison names
    the shape as ARKit does."""
    import json
    import re

    from usdface.arkit import ARKIT_NAMES
    from usdface.cli import main

    idx = {n: i for i, n in enumerate(ARKIT_NAMES)}
    words = re.compile(r"\b(" + "|".join(sorted(ARKIT_NAMES, key=len, reverse=True)) + r")\b")
    studio = tmp_path / "studio.usda"
    studio.write_text(words.sub(lambda m: f"ch{idx[m.group(1)]:02d}_ctrl", A.read_text()))
    names = tmp_path / "names.json"
    names.write_text(json.dumps({f"ch{k:02d}_ctrl": n for n, k in idx.items()}))
    assert main(["personalize", str(studio), str(C), "-o", str(tmp_path / "p.usda"), "--name-map", str(names),
                 "-q"]) == 0
    for shapes in ("ch17_ctrl", "jawOpen", "ch17_ctrl,eyeBlinkLeft"):
        out = tmp_path / f"{shapes.replace(',', '_')}.png"
        assert main(["render", str(tmp_path / "p.usda"), "--compare", "--shapes", shapes, "-o", str(out),
                     "-q"]) == 0
        assert out.is_file()


def _studio_named(avatar: Path, out: Path) -> Path:
    """``avatar`` with every ARKit shape name replaced by a studio's own (``ch17_ctrl``), everywhere."""
    import re

    from usdface.arkit import ARKIT_NAMES

    idx = {n: i for i, n in enumerate(ARKIT_NAMES)}
    words = re.compile(r"\b(" + "|".join(sorted(ARKIT_NAMES, key=len, reverse=True)) + r")\b")
    out.write_text(words.sub(lambda m: f"ch{idx[m.group(1)]:02d}_ctrl", avatar.read_text()))
    return out


def test_render_unknown_shape_names_the_file_and_the_name_map(sample_dir, tmp_path):
    studio = _studio_named(sample_dir / "avatar.usda", tmp_path / "studio.usda")
    res = _usdface("render", studio, "--shapes", "jawOpen", "-o", "x.png", cwd=tmp_path)
    _no_traceback(res)
    assert "studio.usda, prim /Avatar/Head: mesh Head has no shape 'jawOpen'" in res.stderr, res.stderr
    assert "--name-map" in res.stderr and "ch00_ctrl" in res.stderr
    assert not (tmp_path / "x.png").exists()


def test_render_compare_unknown_shape_names_the_layer(personalized_sample, tmp_path):
    res = _usdface("render", personalized_sample, "--compare", "--shapes", "jawOpen,nope", "-o", "x.png",
                   cwd=tmp_path)
    _no_traceback(res)
    assert f"{personalized_sample}, prim /Avatar/Head: mesh Head has no shape 'nope'" in res.stderr
    assert "--name-map" not in res.stderr  # its shapes are ARKit-named
    assert "did you mean" not in res.stderr  # nothing close to 'nope'
    assert not (tmp_path / "x.png").exists()


def test_render_a_shape_name_typo_gets_the_close_name(samples, tmp_path, capsys):
    """User trial: ``--shapes jawOpn`` listed the first eight shapes only; the close name is offered."""
    from usdface.cli import main

    assert main(["render", str(samples / "avatar.usda"), "--shapes", "jawOpn", "-o", str(tmp_path / "x.png"),
                 "-q"]) == 2
    assert "has no shape 'jawOpn' (fix: did you mean jawOpen?" in capsys.readouterr().err


def test_render_compare_of_a_flattened_export_uses_the_recorded_avatar(personalized_sample, samples, tmp_path,
                                                                       capsys):
    """A user trial: ``render flat.usdc --compare`` (or ``--heatmap``) of a flattened personalized export was
    'not a usdface layer (no sublayer to compare with)'; the file records the avatar it was personalized from,
    which is now the generic it is compared with (the same picture as the layer's); a recorded avatar that is
    gone is named."""
    import shutil

    flat = tmp_path / "flat.usdc"
    assert main(["export", str(personalized_sample), "--flatten", str(flat), "-q"]) == 0
    from_layer, from_flat = tmp_path / "layer.png", tmp_path / "flat.png"
    assert main(["render", str(personalized_sample), "-o", str(from_layer), "--heatmap", "-q"]) == 0
    assert main(["render", str(flat), "-o", str(from_flat), "--heatmap", "-q"]) == 0
    assert from_flat.read_bytes() == from_layer.read_bytes()
    assert main(["render", str(flat), "-o", str(tmp_path / "c.png"), "--compare", "-q"]) == 0
    # an avatar and its flattened export in one project (the provenance records the avatar relative to the
    # export), the export then copied to a folder of another depth: the recorded avatar is not there. (The
    # fixture's layer records the avatar by an absolute path when the checkout and the temporary folder
    # share no folder below the root, as on CI's machine, so the copy is made here.)
    project = tmp_path / "project"
    project.mkdir()
    for name in ("avatar.usda", "capture.usda"):
        shutil.copy(samples / name, project / name)
    assert main(["personalize", str(project / "avatar.usda"), str(project / "capture.usda"),
                 "-o", str(project / "person.usda"), "-q"]) == 0
    assert main(["export", str(project / "person.usda"), "--flatten", str(project / "flat.usdc"), "-q"]) == 0
    moved = tmp_path / "elsewhere" / "deeper" / "flat.usdc"
    moved.parent.mkdir(parents=True)
    shutil.copy(project / "flat.usdc", moved)
    capsys.readouterr()
    assert main(["render", str(moved), "-o", str(tmp_path / "m.png"), "--compare", "-q"]) == 2
    err = capsys.readouterr().err
    assert "flattened export" in err and "is not there to compare with" in err and "--compare GENERIC" in err


def test_comparison_difference_title_clears_its_colour_bar():
    """A user trial: ``render person.usda --compare --mesh Mouth --view right`` (a wide mesh) drew the
    difference panel's title 'difference (max 6.95 mm)' into the colour bar beside it."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    wide, generic = grid_rig(), grid_rig()
    wide.neutral = wide.neutral * [4.0, 1.0, 1.0]
    generic.neutral, generic.deltas = wide.neutral.copy(), generic.deltas * 0.5
    fig = render_comparison(generic, wide, ["bump"])
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    title = fig.axes[2].title.get_window_extent(renderer)
    bar = fig.axes[-1].get_window_extent(renderer)
    assert "max" in fig.axes[2].get_title()
    assert title.x1 < bar.x0 or title.y0 > bar.y1


def test_render_compare_of_a_stale_layer_warns(tmp_path, capsys):
    """A user trial: ``render p.usda --compare`` (and ``--heatmap``) of a layer whose avatar was edited
    since compared with the edited avatar without a word (export and review warn, check warns): the picture
    showed the edit as personalization. It warns now, and still draws."""
    from usdface import api

    avatar, capture = tmp_path / "avatar.usda", tmp_path / "capture.usda"
    avatar.write_bytes(A.read_bytes())
    capture.write_bytes(C.read_bytes())
    layer = tmp_path / "p.usda"
    api.personalize_avatar(avatar, capture, layer)
    avatar.write_bytes(A.read_bytes() + b"\n")          # the avatar re-exported since
    for mode in ("--compare", "--heatmap"):
        png = tmp_path / f"{mode[2:]}.png"
        capsys.readouterr()
        assert main(["render", str(layer), "-o", str(png), mode, "-q"]) == 0
        assert "warning: p.usda was made from" in capsys.readouterr().out
        assert png.read_bytes().startswith(PNG)


@pytest.mark.parametrize("panels", [1, 3])
def test_the_figure_title_sits_on_the_panels(panels):
    """A trial's note: ``render --compare``'s title stood a blank band (~8 % of the picture) above the
    first row, and ``--diagnostics`` a band between its rows, equal-aspect panels not filling their grid
    cells; the title now sits just above the panels' own titles, never over them, and the rows touch."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    rig = grid_rig()
    generic = grid_rig()
    generic.deltas = generic.deltas * 0.5
    for fig in (render_comparison(generic, rig, ["bump"] * panels, title="Head: generic vs personalized"),
                render_shapes(rig, ["bump"] * panels, title="Head")):
        canvas = FigureCanvasAgg(fig)
        canvas.draw()                                         # the layout runs at the draw
        renderer = canvas.get_renderer()
        to_fig = fig.transFigure.inverted()
        boxes = [ax.get_tightbbox(renderer).transformed(to_fig) for ax in fig.axes]
        title = fig._suptitle.get_window_extent(renderer).transformed(to_fig)
        top = max(b.y1 for b in boxes)
        assert top <= title.y0 <= top + 0.03, (top, title.y0)
        # rows: the panels' vertical extents, top to bottom; the gap between one and the next is small
        rows = sorted({(round(b.y0, 2), round(b.y1, 2)) for b in boxes}, key=lambda r: -r[1])
        spans = []
        for y0, y1 in rows:
            if spans and y1 > spans[-1][0]:                      # overlaps the row above: the same row
                spans[-1] = (min(spans[-1][0], y0), spans[-1][1])
            else:
                spans.append((y0, y1))
        gaps = [upper[0] - lower[1] for upper, lower in zip(spans, spans[1:], strict=False)]
        assert all(g < 0.04 for g in gaps), gaps


def test_the_comparison_panels_titles_do_not_run_into_each_other():
    """dev3's ``render --compare --shapes browDownRight``: "browDownRight: generic" ran into
    "browDownRight: personalized" beside it; each panel's title stays within its own column."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    rig = grid_rig()
    rig.neutral = rig.neutral * [0.4, 1.0, 1.0]             # a head's proportions: taller than wide
    generic = grid_rig()
    generic.neutral = rig.neutral
    generic.deltas = generic.deltas * 0.5
    rig.names = generic.names = ["browDownRight" if n == "bump" else n for n in rig.names]
    fig = render_comparison(generic, rig, ["browDownRight", "slide", "browDownRight"])   # a 3-row figure
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    titles = [ax.title.get_window_extent(renderer) for ax in fig.axes[:3]]
    for left, right in zip(titles, titles[1:], strict=False):
        assert left.x1 < right.x0, (left, right)


def _panel_scales(fig):
    """(title, colour-map norm) of every panel of ``fig`` drawn with values."""
    out = []
    for ax in fig.axes:
        for coll in ax.collections:
            if coll.norm.vmin is not None and ax.get_title():     # a neutral panel's has no scale
                out.append((ax.get_title(), coll.norm))
    return out


def test_render_colours_run_from_zero_to_the_titles_maximum(inspected, tmp_path, monkeypatch):
    """A trial (stop 42): ``render``'s shape panels had no colour bar and coloured from the smallest to the
    largest visible triangle's mean (Pixar's targetC, 138.9 mm, drawn without its top colour), and
    ``--compare``'s difference bar ended at 2.65 under a title of 2.89 mm. Every heat panel of the shapes,
    ``--compare`` and ``--heatmap`` pictures now runs from 0 to the largest maximum its picture's titles state
    (one scale per picture, stop 43), with one bar."""
    import re

    from usdface import render

    figures = []
    real = render.save_figure
    monkeypatch.setattr(render, "save_figure", lambda fig, out, force=False: (figures.append(fig),
                                                                              real(fig, out, force))[1])
    _avatar, out, _heat = inspected
    for i, flags in enumerate([["--shapes", "jawOpen,eyeBlinkLeft"], ["--shapes", "jawOpen", "--compare"],
                               ["--heatmap"]]):
        assert main(["render", str(out), "-o", str(tmp_path / f"{i}.png"), "-q", *flags]) == 0
    shapes, compare, heat = figures
    for fig, expected in ((shapes, 2), (compare, 1), (heat, 1)):
        bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
        assert len(bars) == 1                           # one colour bar per picture
        scales = _panel_scales(fig)
        assert len(scales) == expected
        top = max(float(re.search(r"max ([0-9.]+) mm", title or fig.get_suptitle()).group(1))
                  for title, _ in scales)
        for _, norm in scales:
            assert norm.vmin == 0.0
            assert norm.vmax == pytest.approx(top, abs=0.051)


def test_a_mid_line_landmark_is_on_both_profiles():
    """Stop 43: a side view hid a landmark whose vertex normal does not face the camera, so one on the
    face's mid-line (upper lip, chin: its normal edge-on to a profile camera) was counted on the far side
    of both profiles, though it sits on the outline. A landmark now shows where it is a corner of a face the
    picture draws: on a roof whose ridge runs down the middle (x = 0), a ridge vertex shows from the left
    and from the right, an eave vertex only from its own side, and none from behind."""
    y = np.array([0.0, 1.0])
    points = np.array([[x, yy, z] for yy in y for x, z in ((-1.0, 0.0), (0.0, 1.0), (1.0, 0.0))])
    # 0 1 2 at y = 0, 3 4 5 at y = 1: two slopes facing +z (the face's look), the person's left at +x
    triangles = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]])
    ridge, right_eave, left_eave = 1, 0, 2
    for view, hidden in (("front", 0), ("left", 1), ("right", 1)):
        fig = render_landmarks(points, triangles, [ridge, left_eave, right_eave], view=view)
        title = fig.axes[0].get_title()
        assert title == "3 landmarks" + (f" ({hidden} on the far side)" if hidden else ""), (view, title)
    from usdface.render import _landmark_dots

    fig = render_landmarks(points, triangles, [ridge], view="left")
    assert _landmark_dots(fig.axes[0], points, triangles, np.array([ridge]), "right") == 0
    assert _landmark_dots(fig.axes[0], points, triangles, np.array([right_eave]), "left") == 1
    assert _landmark_dots(fig.axes[0], points, triangles, np.array([left_eave]), "right") == 1


def test_the_panels_of_a_picture_share_one_length_and_colour_scale():
    """Stop 43: ``render --mesh Mouth`` framed each panel on its own pose and coloured it to its own maximum,
    so the bench Mouth's jawOpen (42 mm) was drawn smaller than the neutral beside it and a 3 mm shape as
    bright as it: panels that could not be compared. Every panel of a shapes or ``--compare`` picture now
    has the same view limits (the union of its poses) and every heat panel the same colour norm."""
    rig = grid_rig()
    rig.deltas[1] *= 40.0                                   # one shape moving far more than the other
    for fig, heat in ((render_shapes(rig, rig.names[:2]), 2),
                      (render_comparison(grid_rig(), rig, rig.names[:2]), 2)):
        panels = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
        assert len({(ax.get_xlim(), ax.get_ylim()) for ax in panels}) == 1
        norms = {(c.norm.vmin, c.norm.vmax) for ax in panels for c in ax.collections
                 if c.norm.vmin is not None}
        assert len(norms) == 1 and len([ax for ax in panels if "max" in ax.get_title()]) == heat
    moved = rig.neutral + rig.deltas[1]
    (x0, x1) = render_shapes(rig, rig.names[:2]).axes[0].get_xlim()
    assert x0 <= moved[:, 0].min() and moved[:, 0].max() <= x1      # the neutral panel holds the big pose
