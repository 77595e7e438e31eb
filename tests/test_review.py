"""``usdface review``: the self-contained page (its embedded data decodes to both variants' shapes), its
figures, its refusals, and a real headless Chromium drawing it (skipped without Chromium)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import _usdface as _usdface_cli

from usdface import api
from usdface.cli import main
from usdface.errors import InputFileError, OutputExistsError
from usdface.io.flatten import read_avatar_variant
from usdface.io.livelink import write_livelink_csv
from usdface.review.page import SPARSE_TOLERANCE_M, decode_sparse_deltas, encode_sparse_deltas

ROOT = Path(__file__).resolve().parents[1]

SAMPLES = ROOT / "sample_assets"
A, C = SAMPLES / "avatar.usda", SAMPLES / "capture.usda"


def _payload(html: str) -> dict:
    start = html.index("window.USDFACE_DATA = ") + len("window.USDFACE_DATA = ")
    return json.JSONDecoder().raw_decode(html, start)[0]


def test_sparse_deltas_round_trip_within_the_quantization_step():
    rng = np.random.default_rng(3)
    deltas = rng.normal(scale=0.004, size=(5, 200, 3))
    deltas[:, 50:] *= (rng.random((5, 150, 1)) < 0.3)  # most vertices still
    deltas[2] = 0.0
    enc = encode_sparse_deltas(deltas)
    dec = decode_sparse_deltas(enc, 200)
    moved = np.linalg.norm(deltas, axis=2) > SPARSE_TOLERANCE_M
    for k in range(5):
        step = enc[k]["s"]
        assert enc[k]["m"] == moved[k].sum()
        assert np.abs(dec[k][moved[k]] - deltas[k][moved[k]]).max(initial=0.0) <= step / 2 + 1e-12
        assert not dec[k][~moved[k]].any()
    assert enc[2]["m"] == 0


@pytest.fixture(scope="module")
def review(personalized_sample, tmp_path_factory) -> Path:
    take = tmp_path_factory.mktemp("take") / "take.csv"
    from usdface.io.livelink import write_livelink_csv

    t = np.arange(90) / 30.0
    weights = np.zeros((90, 2))
    weights[:, 0] = 0.5 - 0.5 * np.cos(2 * np.pi * t / 3.0)  # jawOpen up and down over 3 s
    weights[:, 1] = (t > 1.5).astype(float)
    write_livelink_csv(take, ["jawOpen", "eyeBlinkLeft"], weights, t)
    out = tmp_path_factory.mktemp("review") / "review.html"
    return api.write_review(personalized_sample, out, take=take)


def test_page_is_self_contained_and_carries_both_variants(review, personalized_sample):
    html = review.read_text()
    assert not re.search(r"<script[^>]+src=", html)  # plotly.js is inlined, nothing is fetched
    assert "Plotly.newPlot" in html and "usdfaceStart(" in html
    assert review.stat().st_size < 15e6
    data = _payload(html)
    generic = read_avatar_variant(personalized_sample, "generic")
    personalized = read_avatar_variant(personalized_sample, "personalized")
    for mesh in data["meshes"]:
        if "generic" not in mesh:
            continue
        g = generic.mesh(mesh["name"])
        p = personalized.mesh(mesh["name"])
        names = [data["names"][k] for k in mesh["shapes"]]
        assert names == p.names
        steps = np.array([e["s"] for e in mesh["generic"]])[:, None, None]
        got_g = decode_sparse_deltas(mesh["generic"], mesh["n"])
        got_p = got_g + decode_sparse_deltas(mesh["change"], mesh["n"])
        tol = SPARSE_TOLERANCE_M * 2 + steps
        assert np.all(np.abs(got_g - g.subset(names).deltas) <= tol)
        change_steps = np.array([e["s"] for e in mesh["change"]])[:, None, None]
        assert np.all(np.abs(got_p - p.deltas) <= tol + change_steps)
    assert [s["title"] for s in data["sequences"]] == ["test expressions", "take take.csv"]
    assert data["sequences"][1]["frames"] == 90
    assert {"smile", "jaw open", "blink", "pucker"} <= set(data["presets"])


def test_page_figures(review):
    html = review.read_text()
    for caption in ("made from", "registration (capture -&gt; avatar)", "correspondence", "what changed",
                    "eq. 5 on the capture&#x27;s test expressions"):
        assert caption in html, caption
    made = html[html.index("made from"):html.index("registration (capture")]
    assert re.search(r"<th>avatar</th><td>[^<]*avatar\.usda</td>", made)      # which avatar and capture
    assert re.search(r"<th>capture</th><td>[^<]*capture\.usda</td>", made)
    table = html[html.index("eq. 5 on the capture"):]
    rows = re.findall(r"<tr><th>mean</th><td><b>([\d.]+)</b></td><td><b>([\d.]+)</b></td>", table)
    generic_rmse, personalized_rmse = map(float, rows[0])
    assert personalized_rmse < generic_rmse  # the person's own shapes explain their test expressions better


def test_a_dense_mesh_is_shown_decimated_with_the_full_mesh_figures(personalized_sample, tmp_path):
    """A 225k-vertex head made a 124 MB page (every vertex of both variants, plotly re-converting the whole
    mesh on each pose: seconds per slider move); a mesh of more than ``max_vertices`` vertices is now shown
    on a decimated subset of its own vertices: the page's data are the full mesh's at those vertices, the
    landmarks on the nearest kept vertex, the 'what changed' figures those of the full mesh, and a note says
    so."""
    from usdface.review.collect import _decimate_for_display
    from usdface.review.page import ReviewMesh

    full = api.write_review(personalized_sample, tmp_path / "full.html", max_vertices=0, fit_errors=False)
    small = api.write_review(personalized_sample, tmp_path / "small.html", max_vertices=1500,
                             fit_errors=False)
    assert small.stat().st_size < full.stat().st_size
    big, little = _payload(full.read_text()), _payload(small.read_text())
    head = next(m for m in big["meshes"] if m["name"] == "Head")
    shown = next(m for m in little["meshes"] if m["name"] == "Head")
    assert head["n"] > 1500 >= shown["n"] * 0.8
    html = small.read_text()
    assert "Head (" in html and "is shown decimated to" in html and "--max-vertices 0" in html
    changed = re.findall(r"Head: shapes changed</th><td>([^<]*)<", html)
    assert changed and changed == re.findall(r"Head: shapes changed</th><td>([^<]*)<", full.read_text())

    rng = np.random.default_rng(0)
    from synthetic_meshes import grid_triangles

    u, v = np.meshgrid(np.linspace(0, 0.1, 30), np.linspace(0, 0.1, 30))
    neutral = np.c_[u.ravel(), v.ravel(), np.zeros(900)]
    generic, personalized = rng.normal(size=(2, 2, 900, 3)) * 1e-3
    mesh = ReviewMesh("Head", neutral, grid_triangles(30, 30), ["a", "b"], generic, personalized,
                      heat=np.arange(900.0), landmarks=np.array([0, 455, 899]))
    notes = _decimate_for_display([mesh], 200)
    assert len(notes) == 1 and "900 vertices" in notes[0]
    keep = np.flatnonzero((neutral[:, None] == mesh.neutral[None]).all(axis=2).any(axis=1))
    assert len(keep) == len(mesh.neutral) < 300
    np.testing.assert_array_equal(mesh.generic, generic[:, keep])
    np.testing.assert_array_equal(mesh.personalized, personalized[:, keep])
    np.testing.assert_array_equal(mesh.heat, keep.astype(float))
    corners = neutral[[0, 455, 899]]
    assert np.abs(mesh.neutral[mesh.landmarks] - corners).max() < 0.02   # the nearest kept vertex


def test_a_face_on_a_large_still_mesh_is_framed_on_what_moves():
    """The merged head-and-body avatar's page showed the whole body (the face a few per cent of the view):
    when a mesh's shapes move less than half of it, the view is cut to the box of what moves."""
    from synthetic_meshes import grid_triangles

    from usdface.review.page import ReviewData, ReviewMesh, _figure

    u, v = np.meshgrid(np.linspace(0, 1.0, 30), np.linspace(0, 2.0, 30))
    neutral = np.c_[u.ravel(), v.ravel(), np.zeros(900)]
    deltas = np.zeros((1, 900, 3))
    top = neutral[:, 1] > 1.8                                 # the "face": the top tenth moves
    deltas[0, top, 2] = 0.01
    mesh = ReviewMesh("Head", neutral, grid_triangles(30, 30), ["jawOpen"], deltas, deltas * 1.1)
    scene = _figure(ReviewData("t", [mesh])).layout.scene
    assert scene.aspectmode == "manual" and scene.yaxis.range[0] > 1.7 and scene.yaxis.range[1] < 2.2
    assert scene.xaxis.range[0] < 0 and scene.xaxis.range[1] > 1.0
    deltas[0, :, 2] = 0.01                                     # everything moves: the whole mesh, as before
    scene = _figure(ReviewData("t", [mesh])).layout.scene
    assert scene.aspectmode == "data" and scene.yaxis.range is None


def test_a_face_on_a_large_still_mesh_is_cut_to_the_views_box_not_decimated():
    """The merged head-and-body page decimated the whole 314k-vertex mesh (5.8 of its 10.1 CPU-s on the
    still body, which the view cuts off) and showed the face on 13.6k of its 14.1k vertices. A mesh over the
    limit keeps the triangles that meet the views' box, every vertex of them when they are under it: the
    face is shown whole and the view is the same box."""
    from synthetic_meshes import grid_triangles

    from usdface.mesh import triangles_in_box
    from usdface.review.collect import _decimate_for_display
    from usdface.review.page import ReviewData, ReviewMesh, _figure, framed_ranges

    u, v = np.meshgrid(np.linspace(0, 1.0, 40), np.linspace(0, 2.0, 40))
    neutral = np.c_[u.ravel(), v.ravel(), 0.05 * np.sin(3 * u.ravel())]
    tris = grid_triangles(40, 40)
    deltas = np.zeros((1, 1600, 3))
    top = neutral[:, 1] > 1.85                                # the "face": the top of the sheet moves
    deltas[0, top, 2] = 0.01
    full = ReviewMesh("Head", neutral, tris, ["jawOpen"], deltas, deltas * 1.1, heat=np.arange(1600.0),
                      landmarks=np.flatnonzero(top)[:3])
    mesh = ReviewMesh("Head", neutral, tris, ["jawOpen"], deltas, deltas * 1.1, heat=np.arange(1600.0),
                      landmarks=np.flatnonzero(top)[:3])
    box = framed_ranges([full])
    notes = _decimate_for_display([mesh], 400, box)               # 1,600 vertices over a limit of 400
    visible = triangles_in_box(neutral, tris, *box)
    shown = np.unique(tris[visible])
    assert 0 < len(shown) < 400 and "cut to the part in the views' box" in notes[0]
    np.testing.assert_array_equal(mesh.neutral, neutral[shown])           # every vertex in the box
    np.testing.assert_array_equal(shown[mesh.triangles], tris[visible])   # and every triangle meeting it
    np.testing.assert_array_equal(mesh.generic, deltas[:, shown])
    np.testing.assert_array_equal(mesh.heat, shown.astype(float))
    np.testing.assert_array_equal(shown[mesh.landmarks], full.landmarks)  # on their own vertices
    whole, cut = _figure(ReviewData("t", [full])).layout.scene, \
        _figure(ReviewData("t", [mesh], view_box=box)).layout.scene
    assert cut.aspectmode == "manual" and cut.yaxis.range == whole.yaxis.range \
        and cut.xaxis.range == whole.xaxis.range


def test_shape_changes_go_shape_by_shape():
    """The review of a 225k-vertex head peaked at 2.0 GB, ~1 GB of it the heat map's and the 'what changed'
    table's [K, n, 3] difference, squares and norms at once; shape by shape the same figures."""
    import tracemalloc

    from usdface.review.collect import shape_changes

    rng = np.random.default_rng(2)
    generic = rng.normal(size=(12, 20_000, 3))
    personalized = generic + rng.normal(size=generic.shape) * 0.1
    shape_changes(personalized[:1], generic[:1])
    tracemalloc.start()
    try:
        rms, largest = shape_changes(personalized, generic)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    norms = np.linalg.norm(personalized - generic, axis=2)
    np.testing.assert_allclose(rms, np.sqrt((norms ** 2).mean(axis=0)), rtol=1e-12)
    np.testing.assert_allclose(largest, norms.max(axis=1), rtol=1e-12)
    assert peak < 4 * generic[0].nbytes, peak              # a few one-shape arrays (all at once: 12+)


def test_review_refuses_and_validates(personalized_sample, samples, tmp_path):
    page = tmp_path / "r.html"
    page.write_text("keep")
    with pytest.raises(OutputExistsError, match="r.html"):
        api.write_review(personalized_sample, page)
    assert page.read_text() == "keep"
    with pytest.raises(InputFileError, match="html"):
        api.write_review(personalized_sample, tmp_path / "r.png")
    with pytest.raises(InputFileError, match="an avatar that is not personalized") as err:
        api.write_review(samples / "avatar.usda", tmp_path / "plain.html", fit_errors=False)
    assert "usdface personalize" in err.value.fix
    with pytest.raises(InputFileError, match="capture not found"):
        api.write_review(personalized_sample, tmp_path / "c.html", capture=tmp_path / "nope.usda")
    with pytest.raises(InputFileError, match="take not found"):
        api.write_review(personalized_sample, tmp_path / "t.html", take=tmp_path / "missing.csv")


def test_an_input_of_personalize_given_as_the_layer_says_what_it_is_and_where_it_goes(
        samples, sample_capture_folder, tmp_path):
    """A user trial: 'review take.csv' said 'a USD USD file is expected' with the fix 'pass the USD file
    here', 'review CAPTURE_FOLDER' 'USD file is a folder, not a file', and a capture.usda, an 'anim import'
    take and a plain avatar 'not a usdface layer'."""
    from usdface.io.usd_anim import write_animation_usd

    takes = tmp_path / "takes"
    takes.mkdir()
    csv = write_livelink_csv(takes / "take.csv", ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 60)
    anim = write_animation_usd(tmp_path / "take.usda", ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 60)
    cases = [(csv, "a take of weights only", f"--take {csv}"), (anim, "a take of weights only", "--take"),
             (takes, "a take of weights only", f"--take {csv}"),   # a folder holding only that CSV
             (samples / "capture.usda", "this is a capture", "--capture"),
             (sample_capture_folder, "this is a capture", "--capture"),
             (samples / "avatar.usda", "an avatar that is not personalized", "usdface personalize")]
    for given, words, fix in cases:
        with pytest.raises(InputFileError) as err:
            api.write_review(given, tmp_path / "r.html", fit_errors=False)
        assert words in err.value.message and "USD USD" not in str(err.value), (given, str(err.value))
        assert fix in err.value.fix, (given, err.value.fix)
    assert not (tmp_path / "r.html").exists()


def test_a_weights_only_take_given_as_the_capture_is_sent_to_take(personalized_sample, tmp_path):
    """A user trial: 'review LAYER --capture take.csv' said 'no meshes to fit' with the fixes of fit and
    personalize; the page plays such a take with --take."""
    from usdface.errors import CaptureError
    from usdface.io.livelink import write_livelink_csv

    csv = write_livelink_csv(tmp_path / "take.csv", ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 60)
    with pytest.raises(CaptureError, match="scored on its test expressions") as err:
        api.write_review(personalized_sample, tmp_path / "t.html", capture=csv, fit_errors=False)
    assert f"--take {csv}" in err.value.fix
    assert not (tmp_path / "t.html").exists()


# ---------------------------------------------------------------------------------------------------------
# a real browser: Debian's chromium, headless (installed by .ci/system-deps)
# ---------------------------------------------------------------------------------------------------------
def _chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        found = shutil.which(name)
        if found:
            return found
    pytest.skip("no Chromium found (bash .ci/system-deps installs Debian's chromium): browser test skipped")


_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--disable-quic",
          "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync",
          "--window-size=1000,700", "--virtual-time-budget=20000"]


def _browse(page: Path, query: str, *, screenshot: Path | None = None) -> tuple[str, str]:
    """Run headless Chromium on ``page?query``: a screenshot, or the DOM after the scripts ran. Returns
    (stdout, stderr); the page's console is logged to stderr."""
    exe = _chromium()
    with tempfile.TemporaryDirectory() as profile:
        mode = [f"--screenshot={screenshot}"] if screenshot else ["--dump-dom"]
        done = subprocess.run([exe, *_FLAGS, f"--user-data-dir={profile}", "--enable-logging=stderr", "--v=0",
                               *mode, f"{page.as_uri()}?{query}"], capture_output=True, text=True,
                              timeout=120, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout, done.stderr


def _console_errors(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines()
            if "CONSOLE" in line and re.search(r"Uncaught|Error|error:", line) and "GL Driver" not in line]


def _image(path: Path) -> np.ndarray:
    import matplotlib.image

    return matplotlib.image.imread(str(path))[..., :3]


def _face_box(img: np.ndarray) -> tuple[slice, slice]:
    """Rows/columns of the plot where the face is drawn (pixels far from the dark background), below the
    scene titles."""
    bright = img.mean(axis=2) > 0.35
    bright[:80] = False
    bright[:, : img.shape[1] // 5] = False  # the control panel
    rows, cols = np.flatnonzero(bright.any(axis=1)), np.flatnonzero(bright.any(axis=0))
    assert rows.size and cols.size, "nothing drawn"
    return slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)


def test_review_page_in_headless_chromium(review, tmp_path):
    _chromium()
    shots = {}
    for name, query in (("generic", "variant=generic&shape=jawOpen&w=1"),
                        ("personalized", "variant=personalized&shape=jawOpen&w=1"),
                        ("neutral", "variant=personalized&shape=jawOpen&w=0")):
        shots[name] = tmp_path / f"{name}.png"
        _, log = _browse(review, query, screenshot=shots[name])
        assert not _console_errors(log), (name, _console_errors(log))
        status = re.findall(r'"usdface-status: ([^"]*)"', log)  # the page logs its final status
        assert status == ["ok"], (name, status, log[-2000:])
    images = {k: _image(v) for k, v in shots.items()}
    rows, cols = _face_box(images["personalized"])

    def changed(a, b) -> float:  # fraction of face-region pixels that differ visibly
        return float((np.abs(images[a][rows, cols] - images[b][rows, cols]).max(axis=2) > 0.04).mean())

    assert changed("personalized", "generic") > 0.002  # personalization shows in the face
    assert changed("personalized", "neutral") > 0.01  # moving the jawOpen slider moves the picture
    assert changed("personalized", "neutral") > changed("personalized", "generic")

    if os.environ.get("USDFACE_WRITE_DOC_IMAGES") == "1":  # the docs' pictures, made by this test
        img = ROOT / "docs" / "img"
        _browse(review, "preset=jaw%20open", screenshot=img / "review-split.png")
        _browse(review, "variant=personalized&preset=smile&heat=rms", screenshot=img / "review-heat.png")


def test_pyblish_extractor_attaches_the_review_page(personalized_sample, samples):
    pyblish = pytest.importorskip("pyblish.api")
    from usdface.pipeline.pyblish_plugins import ExtractUsdFaceReview

    context = pyblish.Context()
    instance = context.create_instance("person", family="usdface.avatar")
    instance.data.update({"usdfaceLayer": str(personalized_sample), "review": False})
    ExtractUsdFaceReview().process(instance)
    assert "usdfaceReview" not in instance.data  # only when asked for
    instance.data.update({"review": True, "capture": str(samples / "capture.usda"), "force": True})
    ExtractUsdFaceReview().process(instance)
    page = Path(instance.data["usdfaceReview"])
    assert page.name == "person.review.html" and page.parent == personalized_sample.parent
    assert {"name": "review", "ext": "html", "files": page.name, "stagingDir": str(page.parent)} in \
        instance.data["representations"]
    assert "usdfaceStart(" in page.read_text()


def test_landmarks_are_embedded_lifted_off_the_surface():
    from usdface.review.page import LANDMARK_LIFT_M, ReviewData, ReviewMesh, _payload

    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    tris = np.array([[0, 1, 2], [1, 3, 2]])  # facing +Z
    deltas = np.zeros((1, 4, 3))
    deltas[0, 3] = [0.0, 0.0, 0.01]
    mesh = ReviewMesh("Head", points, tris, ["jawOpen"], deltas, deltas * 2.0, landmarks=np.array([0, 3]))
    data = _payload(ReviewData("t", [mesh]))
    m = data["meshes"][0]
    assert m["landmarks"] == [0, 3]
    np.testing.assert_allclose(np.reshape(m["lmOffset"], (2, 3)), [[0, 0, LANDMARK_LIFT_M]] * 2, atol=1e-9)
    np.testing.assert_allclose(decode_sparse_deltas(m["change"], 4), deltas, atol=1e-6)  # 2x - 1x generic


def test_review_page_interaction_with_playwright(review):
    """Drive the page like a user (playwright with the system Chromium; skipped without either): play
    advances the sequence, dragging one scene orbits both, a preset sets its sliders."""
    sync_api = pytest.importorskip("playwright.sync_api")
    exe = _chromium()
    errors: list[str] = []
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, args=["--no-sandbox", "--disable-gpu",
                                                               "--enable-unsafe-swiftshader"])
        try:
            page = browser.new_page(viewport={"width": 1000, "height": 700})
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            page.goto(f"{review.as_uri()}?seq=1")  # the take: 90 frames over 3 s
            page.wait_for_function("document.getElementById('usdface-status').textContent !== 'loading'",
                                   timeout=120000)
            assert page.text_content("#usdface-status") == "ok"
            frame = "document.querySelector('#usdface-seq ~ input[type=range]').value"
            page.click("#usdface-play")
            page.wait_for_function(f"+{frame} > 0", timeout=30000)
            page.click("#usdface-play")  # pause
            page.mouse.move(420, 330)
            page.mouse.down()
            page.mouse.move(520, 360, steps=5)
            page.mouse.up()
            eyes = "(() => { const l = document.getElementById('usdface-plot').layout; " \
                   "return JSON.stringify([l.scene.camera.eye, l.scene2.camera.eye]); })()"
            synced = "return e[0].x !== 0 && JSON.stringify(e[0]) === JSON.stringify(e[1]); })()"
            page.wait_for_function(f"(() => {{ const e = JSON.parse({eyes}); " + synced, timeout=30000)
            page.click("button[data-preset='blink']")
            values = page.evaluate("['eyeBlinkLeft', 'eyeBlinkRight', 'jawOpen'].map(n => "
                                   "+document.querySelector(`input[data-shape=${n}]`).value)")
            assert values == [1.0, 1.0, 0.0]
        finally:
            browser.close()
    assert not errors, errors


def test_review_cli_and_personalize_review(personalized_sample, samples, tmp_path, capsys):
    from usdface import cli

    out = tmp_path / "page.html"
    assert cli.main(["review", str(personalized_sample), "-o", str(out), "--no-fit-errors"]) == 0
    assert "wrote" in capsys.readouterr().out and out.stat().st_size > 1e6
    assert cli.main(["review", str(personalized_sample), "-o", str(out)]) == 2  # exists, no --force
    assert "--force" in capsys.readouterr().err

    layer = tmp_path / "p" / "person.usda"
    args = ["personalize", str(samples / "avatar.usda"), str(samples / "capture.usda"), "-o", str(layer),
            "--review", "-q"]
    assert cli.main(args) == 0
    page = layer.with_name("person.review.html")
    assert page.is_file() and f"review page: {page}" in capsys.readouterr().out
    layer.unlink()
    assert cli.main(args) == 2  # the page exists: refused before any work, no layer written
    assert not layer.exists()


def test_review_scores_the_fit_the_layer_carries(samples, tmp_path):
    """The page's eq. 5 table is the layer's own fit (recorded by personalize: the avatar prior, contact, pins
    and its other options), not a refit with the method and ``reg`` alone; a capture other than
    the recorded one is refitted, and the title says which."""
    from usdface.io import read_capture
    from usdface.io.usd_rig import read_layer_info
    from usdface.personalize import fit_personalized_shapes
    from usdface.personalize.api import left_out_scale
    from usdface.personalize.evaluate import test_expression_errors
    from usdface.review.collect import _fit_errors

    layer = tmp_path / "contact.usda"
    result = api.personalize_avatar(samples / "avatar.usda", samples / "capture.usda", layer, contact="on")
    capture = read_capture(samples / "capture.usda")
    recorded = read_layer_info(layer)["usdface"]["fitTestExpressions"]
    # eq. 5 of the fit the layer implanted, cross-fitted (each frame with the sizes read on the others)
    mine = test_expression_errors(capture, result.fit.rig, left_out_scale(result.fit, capture.test))
    assert recorded["labels"] == [str(s) for s in capture.test.label] == mine["labels"]
    for key in ("generic_rmse_mm", "personalized_rmse_mm", "generic_max_mm", "personalized_max_mm"):
        assert np.allclose(recorded[key], mine[key], rtol=1e-12, atol=0), key
    # what the page showed before: the method's fit without the layer's options
    refit_fit = fit_personalized_shapes(capture, method="menzel")             # cross-fitted, as the page
    refit = test_expression_errors(capture, refit_fit.rig, left_out_scale(refit_fit, capture.test))
    assert np.abs(np.subtract(recorded["personalized_rmse_mm"], refit["personalized_rmse_mm"])).max() > 1e-4
    assert np.allclose(recorded["generic_rmse_mm"], refit["generic_rmse_mm"], rtol=1e-12, atol=0)

    prov = read_layer_info(layer)["usdface"]
    page = _fit_errors(capture, prov, recorded=True)
    assert "the layer's fit" in page["title"]
    # the fit scaled shapes by these frames (personalize.amplitude): the recorded score and the title say so
    scaled = int(np.count_nonzero(np.asarray(result.fit.info["test_amplitude"]["scale"]) != 1.0))
    assert recorded["amplitudes_read"] == scaled > 0
    assert (f"read {scaled} of its shapes' amplitudes on these frames (each frame scored with the others' "
            "readings)") in page["title"]
    assert page["columns"]["personalized RMSE"] == recorded["personalized_rmse_mm"]
    other = _fit_errors(capture, prov, recorded=False)         # --capture: figures for that capture
    assert "menzel refit" in other["title"]
    assert np.allclose(other["columns"]["personalized RMSE"], refit["personalized_rmse_mm"],
                       rtol=1e-12, atol=0)


def test_review_of_a_flattened_export_names_the_layer_it_came_from(personalized_sample, tmp_path, capsys):
    """A user trial: 'review flat.usdc' said 'no usdfacePersonalization variant set (a layer written by
    'usdface personalize')' with the fix 'review a layer written by usdface personalize': it is one."""
    from usdface.cli import main

    flat = tmp_path / "flat.usdc"
    api.export_avatar(personalized_sample, flatten=flat)
    capsys.readouterr()
    assert main(["review", str(flat), "-o", str(tmp_path / "r.html")]) == 2
    err = capsys.readouterr().err
    assert "flattened export of the personalized variant" in err and personalized_sample.name in err
    assert "written by 'usdface personalize'" not in err and not (tmp_path / "r.html").exists()
    # one in a subfolder named the layer through it ('sub/../person.usda'): the path as one can pass it
    sub = tmp_path / "sub" / "flat.usdc"
    api.export_avatar(personalized_sample, flatten=sub)
    capsys.readouterr()
    assert main(["review", str(sub), "-o", str(tmp_path / "r.html")]) == 2
    err = capsys.readouterr().err
    assert "/../" not in err and f"{personalized_sample.name})" in err


def test_a_capture_given_as_the_take_is_refused(personalized_sample, samples, tmp_path, capsys):
    """A user trial: 'personalize AVATAR CAPTURE --take CAPTURE' played the capture's frames as a recording
    (and listed the capture twice as an input); 'capture select CAPTURE' already refused a capture."""
    from usdface.cli import main

    capture = str(samples / "capture.usda")
    for argv in (["personalize", str(samples / "avatar.usda"), capture, "-o", str(tmp_path / "p.usda")],
                 ["review", str(personalized_sample), "-o", str(tmp_path / "r.html")]):
        capsys.readouterr()
        assert main([*argv, "--take", capture, "-q"]) == 2
        err = capsys.readouterr().err
        assert "this is a capture" in err and "--take plays a take" in err, err
    assert list(tmp_path.iterdir()) == []


def test_stale_layers_and_other_captures_are_not_exported_or_reviewed_silently(tmp_path):
    """``check`` warned that a layer's avatar changed after it was written, but ``export`` and ``review``
    used the layer without a word, and ``review --capture`` scored another person's capture under the
    layer's name: both warn now (the files are still written: a warning, not a refusal)."""
    from usdface import api

    avatar, capture = tmp_path / "avatar.usda", tmp_path / "capture.usda"
    avatar.write_bytes(A.read_bytes())
    capture.write_bytes(C.read_bytes())
    layer = tmp_path / "p.usda"
    api.personalize_avatar(avatar, capture, layer)
    with pytest.warns(UserWarning) as rec:             # the layer's own inputs: no word
        import warnings

        warnings.warn("sentinel", UserWarning, stacklevel=1)
        api.export_avatar(layer, gltf=tmp_path / "a.glb")
    # the warnings a user sees: an ImportWarning of a library export imports first here (six's
    # 'find_spec() not found') is hidden by Python's default filters, and failed the test in module order
    assert [str(w.message) for w in rec if issubclass(w.category, UserWarning)] == ["sentinel"]
    avatar.write_bytes(A.read_bytes() + b"\n")          # the avatar re-exported since
    with pytest.warns(UserWarning, match="changed after it was written"):
        api.export_avatar(layer, gltf=tmp_path / "b.glb")
    assert (tmp_path / "b.glb").is_file()
    other = tmp_path / "other.usda"
    other.write_bytes(C.read_bytes())
    with pytest.warns(UserWarning, match="other.usda is not among the inputs p.usda records"):
        api.write_review(layer, tmp_path / "r.html", capture=other, fit_errors=False)


def test_review_of_a_landmarks_layer(tmp_path, capsys):
    """``review`` of a ``usdface landmarks`` layer took the avatar (its second recorded input) for the
    capture ('this is a rig, not a capture') and, given --capture, refit with method 'landmarks'."""
    from usdface.cli import main

    assert main(["personalize", str(A), str(C), "-o", str(tmp_path / "p.usda"), "-q"]) == 0
    assert main(["landmarks", str(tmp_path / "p.usda"), "-o", str(tmp_path / "lm.usda"), "-q"]) == 0
    capsys.readouterr()
    assert main(["review", str(tmp_path / "lm.usda"), "-o", str(tmp_path / "a.html"), "-q"]) == 0
    assert main(["review", str(tmp_path / "lm.usda"), "-o", str(tmp_path / "b.html"), "--capture", str(C),
                 "-q"]) == 0
    out = capsys.readouterr()
    assert "not among the inputs" not in out.out + out.err
    # the capture the personalization below records, named: its own figures, as without --capture (stop 53)
    assert "the layer&#x27;s fit" in (tmp_path / "b.html").read_text()
    copy = tmp_path / "copy.usda"                  # another capture file (the same person): refitted
    copy.write_bytes(C.read_bytes())
    assert main(["review", str(tmp_path / "lm.usda"), "-o", str(tmp_path / "c.html"), "--capture", str(copy),
                 "-q"]) == 0
    assert "menzel refit" in (tmp_path / "c.html").read_text()


def test_review_plays_the_take_the_layer_was_written_with(tmp_path):
    """``personalize --take`` records the take (relative to the layer, as ``take``) and ``review LAYER``
    plays it without ``--take`` again (the page had only the test expressions); a take moved away is said
    in the page's notes."""
    from usdface.io.livelink import read_livelink_take
    from usdface.io.usd_rig import usdface_layer_data
    from usdface.review.collect import collect_review

    take = tmp_path / "takes" / "t.csv"
    take.parent.mkdir()
    names = ["jawOpen", "eyeBlinkLeft", "mouthSmileLeft"]
    weights = np.array([[0.0, 0.0, 0.0], [0.8, 0.2, 0.1], [0.3, 1.0, 0.6], [0.0, 0.0, 0.0]])
    write_livelink_csv(take, names, weights, np.arange(4) / 30.0)
    assert len(read_livelink_take(take).weights) == 4
    out = tmp_path / "out" / "person.usda"
    assert main(["personalize", str(SAMPLES / "avatar.usda"), str(SAMPLES / "capture.usda"), "-o", str(out),
                 "--take", str(take), "-q"]) == 0
    assert usdface_layer_data(out)["take"] == "../takes/t.csv"
    data = collect_review(out, fit_errors=False)
    played = [s for s in data.sequences if s.title.startswith("take ")]
    assert [s.title for s in played] == ["take t.csv"] and len(played[0].weights) == 4
    # a flattened copy elsewhere (usdface export --flatten) records the take relative to itself
    from usdface.api import export_avatar

    flat = tmp_path / "deliver" / "deep" / "person.flat.usda"
    export_avatar(out, flatten=flat)
    assert usdface_layer_data(flat)["take"] == "../../takes/t.csv"
    take.rename(tmp_path / "moved.csv")
    # said where the command runs too: the page alone said it, and 'review' printed only 'wrote ...'
    with pytest.warns(UserWarning, match=r"person.usda: the take recorded .*\(../takes/t.csv\) was not"):
        data = collect_review(out, fit_errors=False)
    assert any("take recorded" in n and "not found" in n for n in data.notes)
    # a TD's trial (stop 51): the layer published without the take file played no take, although its
    # inspection animation holds every frame of it (after the test expressions): it plays from there, the
    # same weights at the same times on the avatar's channels
    kept = [s for s in data.sequences if s.title.startswith("take ")]
    assert [s.title for s in kept] == ["take t.csv (as the layer holds it)"]
    cols = [kept[0].names.index(n) for n in names]
    assert np.allclose(kept[0].weights[:, cols], weights, atol=1e-6)
    assert np.allclose(kept[0].times, np.arange(4) / 30.0, atol=1e-9)
    assert np.allclose(np.delete(kept[0].weights, cols, axis=1), 0.0)
    assert main(["review", str(out), "-o", str(tmp_path / "moved.html"), "-q"]) == 0
    page = _payload((tmp_path / "moved.html").read_text())
    assert [q["title"] for q in page["sequences"] if q["title"].startswith("take ")] == [
        "take t.csv (as the layer holds it)"]


def test_review_refuses_a_take_as_capture_without_first_warning_about_it(tmp_path):
    """``review LAYER --capture take.csv`` warned 'take.csv is not among the inputs ... its figures describe
    that file', then refused the CSV (a weights-only take has no test expressions): only the refusal now."""
    import warnings

    from usdface.api import write_review
    from usdface.errors import CaptureError

    layer = tmp_path / "p.usda"
    assert main(["personalize", str(SAMPLES / "avatar.usda"), str(SAMPLES / "capture.usda"), "-o", str(layer),
                 "-q"]) == 0
    take = tmp_path / "t.csv"
    write_livelink_csv(take, ["jawOpen"], np.full((4, 1), 0.5), np.arange(4) / 30.0)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        with pytest.raises(CaptureError, match="--take"):
            write_review(layer, tmp_path / "r.html", capture=take)
    assert not [w for w in seen if "among" in str(w.message)]
    assert not (tmp_path / "r.html").exists()


def test_a_name_mapped_layer_reviews_with_arkit_names(tmp_path):
    """User trial: the review page of a layer over a studio-named avatar (ch17_ctrl = jawOpen) played a
    Live Link take with the jaw shut: the variants were read without the name map the layer records (every
    other reader applies it), so no channel drove ch17_ctrl."""
    import json

    from usdface.io.flatten import read_avatar_variant
    from usdface.review.collect import collect_review

    studio = tmp_path / "studio.usda"
    studio.write_text(A.read_text().replace("jawOpen", "ch17_ctrl"))
    (tmp_path / "map.json").write_text(json.dumps({"ch17_ctrl": "jawOpen"}))
    out = tmp_path / "p.usda"
    assert main(["personalize", str(studio), str(C), "--name-map", str(tmp_path / "map.json"), "-o", str(out),
                 "--method", "dt", "-q"]) == 0
    for variant in ("personalized", "generic"):
        assert "jawOpen" in read_avatar_variant(out, variant).mesh("Head").names
    data = collect_review(out, fit_errors=False)
    assert any("jawOpen" in m.names for m in data.meshes)


def test_personalized_count_agrees_with_the_review_page(bench, tmp_path):
    """dev3: personalize said "55 BlendShapes personalized" and its --dry-run listed shapes with "max 0.000,
    rms 0.000, 0 vertices" as changing (changes of float noise, under 1 nm); the review page of the same
    layer said 49 + 4 = 53 changed (it counted any float32 difference). Both now count a shape changed
    where a vertex moved by more than 1 nm, and agree."""
    import re

    from usdface.review.collect import collect_review

    case = bench / "dev3"
    out = tmp_path / "p.usda"
    res = _usdface_cli("personalize", case / "avatar.usdc", case / "capture", "-o", out, "-q", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    said = int(re.search(r"(\d+) of 101 BlendShapes personalized", res.stdout).group(1))
    data = collect_review(out, fit_errors=False)
    rows = dict(next(rows for title, rows in data.tables if title == "what changed"))
    page = sum(int(v.split(" of ")[0]) for k, v in rows.items() if k.endswith("shapes changed"))
    assert said == page, (res.stdout, rows)
    kept = rows["Head: left generic"].names
    assert "jawLeft" in kept and len(kept) >= 2                  # moved by under 1 nm: left generic
    dry = _usdface_cli("personalize", case / "avatar.usdc", case / "capture", "--dry-run", "-q", cwd=tmp_path)
    assert dry.returncode == 0, dry.stderr
    assert " 0 vertices" not in dry.stdout and f"{said} of 101 BlendShapes would change" in dry.stdout


def test_page_registration_figures_are_rounded_with_units(review):
    """A trial (stop 42): the review page's registration table showed ``fitness 0.9983779399837794``, a
    bare 16-digit fraction beside figures in mm and degrees; it is a percentage of capture points matched."""
    html = review.read_text()
    start = html.index("registration (capture")
    reg = html[start:html.index("</table>", start)]
    fitness = re.search(r"<th>fitness</th><td>([^<]*)</td>", reg).group(1)
    assert re.fullmatch(r"\d{1,3}\.\d % of capture points matched", fitness), fitness
    for cell in re.findall(r"<td>([^<]*)</td>", reg):
        assert not re.search(r"\d\.\d{5,}", cell), cell              # no unrounded figure


def test_a_long_left_generic_list_is_summarized_with_the_whole_list_a_click_away(personalized_sample):
    """Stop 43: dev3's review listed the 46 Mouth shapes left generic on one line of "what changed". The
    cell says how many and names the first five; the whole list is in the cell's details (one click)."""
    from usdface.review.collect import collect_review
    from usdface.review.page import LISTING_SHOWN, Listing, ReviewData, _tables_html

    names = [f"shape{i:02d}" for i in range(46)]
    cell = Listing(names)
    assert str(cell) == "46: shape00, shape01, shape02, shape03, shape04 (+41 more)" and LISTING_SHOWN == 5
    page = _tables_html(ReviewData("t", [], tables=[("what changed", [("Mouth: left generic", cell)])]))
    summary, details = re.search(r"<details><summary>(.*)</summary>(.*)</details>", page).groups()
    assert summary == str(cell) and details.split(", ") == names
    short = _tables_html(ReviewData("t", [], tables=[("x", [("k", Listing(["a", "b"]))])]))
    assert "<td>2: a, b</td>" in short and "<details>" not in short
    rows = dict(next(rows for title, rows in collect_review(personalized_sample, fit_errors=False).tables
                     if title == "what changed"))
    left = [v for k, v in rows.items() if k.endswith("left generic")]
    assert left and all(isinstance(v, Listing) or v.startswith("all ") for v in left), rows


def test_review_of_a_layer_whose_capture_moved_plays_the_test_expressions_it_holds(tmp_path, capfd):
    """A user trial (stop 50): ``review LAYER`` of a layer whose recorded capture had been moved showed no
    test expressions and no eq. 5 table, although the layer's inspection animation holds the expressions
    and its provenance the figures. The page plays them as the layer holds them (the same weights and
    labels as with the capture), scores them by the layer's figures, and says so; a layer written without
    the inspection animation says why nothing plays and how to pass --capture."""
    import base64

    def sequence(page, title):
        seq = next(s for s in _payload(page.read_text())["sequences"] if s["title"].startswith(title))
        return seq["labels"], np.frombuffer(base64.b64decode(seq["w"]), np.uint8).astype(int)

    cap = tmp_path / "shoot" / "capture.usda"
    cap.parent.mkdir()
    shutil.copy(C, cap)
    out = tmp_path / "person.usda"
    assert main(["personalize", str(A), str(cap), "-o", str(out), "--inspect", "-q"]) == 0
    assert main(["review", str(out), "-o", str(tmp_path / "with.html"), "-q"]) == 0
    cap.rename(tmp_path / "moved.usda")
    capfd.readouterr()
    assert main(["review", str(out), "-o", str(tmp_path / "moved.html"), "-q"]) == 0
    said = " ".join(capfd.readouterr().out.split())
    assert ("(shoot/capture.usda) was not found: its 20 test expressions play as the layer's inspection "
            "animation holds them") in said, said
    labels, w = sequence(tmp_path / "with.html", "test expressions")
    held_labels, held = sequence(tmp_path / "moved.html", "test expressions")
    assert held_labels == labels and len(labels) == 20
    assert np.abs(held - w).max() <= 1 and w.max() > 100      # the same expressions (8-bit page weights)
    table = re.compile(r"<caption>eq\. 5 on the capture&#x27;s test expressions.*?</table>", re.S)
    cells = lambda page: re.findall(r"<td>([-0-9.]+)</td>", table.search(page.read_text()).group(0))  # noqa: E731
    assert cells(tmp_path / "moved.html") == cells(tmp_path / "with.html") != []
    # no inspection animation in the layer: said why nothing plays, and how to pass the capture
    shutil.copy(C, cap)
    plain = tmp_path / "plain.usda"
    assert main(["personalize", str(A), str(cap), "-o", str(plain), "-q"]) == 0
    cap.unlink()
    capfd.readouterr()
    assert main(["review", str(plain), "-o", str(tmp_path / "plain.html"), "-q"]) == 0
    said = " ".join(capfd.readouterr().out.split())
    assert "holds no inspection animation" in said and "pass --capture CAPTURE" in said, said
    assert not [s for s in _payload((tmp_path / "plain.html").read_text())["sequences"]
                if s["title"].startswith("test expressions")]


def test_a_capture_changed_since_the_layer_was_written_is_refitted_not_scored_by_the_layers_figures(tmp_path):
    """Stop 53's review (h100): the capture the layer records, given by its path, counts as recorded (the
    layer's own figures, no refit); but a capture file changed since the layer was written (sha256 differs)
    is not the one the layer's figures were scored on, and its page showed those figures as 'the layer's
    fit' beside the changed file's test expressions (before stop 53 it was refitted). With or without
    --capture, a changed capture is refitted, and the page says why."""
    capture = tmp_path / "capture.usda"
    capture.write_bytes(C.read_bytes())
    layer = tmp_path / "p.usda"
    api.personalize_avatar(A, capture, layer)
    api.write_review(layer, tmp_path / "same.html", capture=capture)
    assert "the layer&#x27;s fit" in (tmp_path / "same.html").read_text()
    capture.write_bytes(C.read_bytes() + b"\n")          # re-exported since (the same frames' labels)
    for name, given in (("given.html", capture), ("recorded.html", None)):
        with pytest.warns(UserWarning, match="changed after it was written"):
            api.write_review(layer, tmp_path / name, capture=given)
        page = (tmp_path / name).read_text()
        assert "menzel refit" in page and "the layer&#x27;s fit" not in page, name
        assert "changed after the layer was written" in page, name
