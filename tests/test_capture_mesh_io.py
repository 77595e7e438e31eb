"""OBJ reader/writer: exact, order-preserving round trips; bad files raise the right UsdFaceError."""

from __future__ import annotations

import numpy as np
import pytest
from forking import child_finishes
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from usdface.errors import GeometryError, InputFileError, UsdFaceError
from usdface.io.mesh_io import read_obj, write_obj


def test_reads_file_order_and_float64(tmp_path):
    p = tmp_path / "m.obj"
    p.write_text("# comment\nv 0.1 0 0\nv 0 0.2 0\nvn 0 0 1\nv 0 0 0.30000000000000004\n"
                 "vt 0 0\nf 3/1/1 1/1/1 2/1/1\n")
    points, tris = read_obj(p)
    assert points.dtype == np.float64 and tris.dtype == np.int64
    np.testing.assert_array_equal(points, [[0.1, 0, 0], [0, 0.2, 0], [0, 0, 0.30000000000000004]])
    np.testing.assert_array_equal(tris, [[2, 0, 1]])


def test_polygons_fan_triangulated_and_relative_indices(tmp_path):
    p = tmp_path / "quad.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 2 0\nf 1 2 3 4 5\nf -3 -2 -1\n")
    _, tris = read_obj(p)
    np.testing.assert_array_equal(tris, [[0, 1, 2], [0, 2, 3], [0, 3, 4], [2, 3, 4]])


def test_bench_obj_matches_independent_parse(bench):
    p = bench / "dev1" / "capture" / "neutral.obj"
    points, tris = read_obj(p)
    lines = p.read_text().splitlines()
    ref_v = np.array([[float(x) for x in ln.split()[1:4]] for ln in lines if ln.startswith("v ")])
    ref_f = np.array([[int(x) - 1 for x in ln.split()[1:4]] for ln in lines if ln.startswith("f ")])
    np.testing.assert_array_equal(points, ref_v)  # same order, same float64 values
    from usdface.io.mesh_io import _fast_parse

    fast = _fast_parse(p.read_bytes())  # the bench files take the whole-buffer fast path
    assert fast is not None and np.array_equal(fast[0], ref_v)
    np.testing.assert_array_equal(tris, ref_f)


def test_face_block_read_once_for_meshes_of_one_topology(tmp_path):
    """``read_obj(faces=...)``: a mesh whose face block is the bytes of the first one's gets the same
    triangles (its own array) without parsing them again; another topology's is parsed as always, and a bad
    vertex block is still refused."""
    same = [tmp_path / f"{k}.obj" for k in range(3)]
    for k, p in enumerate(same):
        p.write_text(f"v 0 0 {k}\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n")
    other = tmp_path / "other.obj"
    other.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 4 3\n")
    faces: dict = {}
    for p in [*same, other]:
        points, tris = read_obj(p, faces=faces)
        ref_points, ref_tris = read_obj(p)
        np.testing.assert_array_equal(points, ref_points)
        assert tris.dtype == ref_tris.dtype and np.array_equal(tris, ref_tris)
    assert len(faces) == 1                               # the first topology's only
    a, b = read_obj(same[1], faces=faces)[1], read_obj(same[2], faces=faces)[1]
    a[0, 0] = 99
    assert b[0, 0] == 0 and next(iter(faces.values()))[0, 0] == 0     # each its own array
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 x\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n")
    with pytest.raises(InputFileError, match="not a number"):
        read_obj(bad, faces=faces)


@pytest.mark.parametrize("text, error, words", [
    ("", GeometryError, "no vertices"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", GeometryError, "no faces"),
    ("v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", GeometryError, "NaN"),
    ("v 0 0 inf\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", GeometryError, "NaN"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", GeometryError, "out of range"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", GeometryError, "at least 3"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", GeometryError, "index 0"),
    ("v 0 0 x\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", InputFileError, "not a number"),
    ("v 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", InputFileError, "fewer than 3"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 a 3\n", InputFileError, "malformed face"),
])
def test_bad_obj(tmp_path, text, error, words):
    p = tmp_path / "bad.obj"
    p.write_text(text)
    with pytest.raises(error) as info:
        read_obj(p)
    assert words in str(info.value) and str(p) in str(info.value) and info.value.fix


def test_missing_and_directory(tmp_path):
    with pytest.raises(InputFileError, match="not found"):
        read_obj(tmp_path / "nope.obj")
    with pytest.raises(InputFileError, match="directory"):
        read_obj(tmp_path)


def test_write_refuses_bad_arrays(tmp_path):
    with pytest.raises(GeometryError):
        write_obj(tmp_path / "a.obj", np.full((3, 3), np.nan), [[0, 1, 2]])
    with pytest.raises(GeometryError):
        write_obj(tmp_path / "a.obj", np.zeros((3, 3)), [[0, 1, 3]])
    assert not (tmp_path / "a.obj").exists()


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(points=hnp.arrays(np.float64, st.tuples(st.integers(3, 30), st.just(3)), elements=finite),
       data=st.data())
def test_round_trip_exact(tmp_path, points, data):
    n = len(points)
    shape = st.tuples(st.integers(1, 20), st.just(3))
    tris = data.draw(hnp.arrays(np.int64, shape, elements=st.integers(0, n - 1)))
    p = write_obj(tmp_path / "rt.obj", points, tris)
    got_p, got_t = read_obj(p)
    np.testing.assert_array_equal(got_p, points)
    np.testing.assert_array_equal(got_t, tris)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.one_of(
    st.sampled_from([b"v 0 0 0", b"v 1 2", b"v 1e400 0 0", b"f 1 2 3", b"f 1/2/3 2//1 -1", b"f", b"v",
                     b"f 1 2 3 4", b"vt 0 0", b"# x", b"f -9 1 2", b"\x00", b"v nan 0 0", b"f 0 0 0"]),
    st.binary(max_size=20)), max_size=12))
def test_fuzz_reader_raises_only_usdface_errors(tmp_path, lines):
    p = tmp_path / "fuzz.obj"
    p.write_bytes(b"\n".join(lines))
    try:
        points, tris = read_obj(p)
    except UsdFaceError:
        return
    assert np.isfinite(points).all() and points.shape[1] == 3
    assert tris.shape[1] == 3 and tris.min() >= 0 and tris.max() < len(points)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.sampled_from([b"v 0.5 -1e-3 2", b"v 1 2", b"v 1 2 3 4", b"v\t1 2 3", b"f 1 2 3",
                                 b"f 1 2 3 4", b"f 2 3", b"f 0 1 2", b"", b"f 1  2 3", b"v 1.5e2 +3 -0"]),
                min_size=1, max_size=10))
def test_fast_path_agrees_with_general_parser(lines):
    """The whole-buffer fast path either declines or returns exactly what the record parser returns."""
    from usdface.io.mesh_io import _fast_parse, _general_parse

    data = b"\n".join(lines) + b"\n"
    fast = _fast_parse(data)
    if fast is None:
        return
    try:
        general = _general_parse(data, "x.obj")
    except UsdFaceError:
        pytest.fail("fast path accepted what the general parser rejects")
    np.testing.assert_array_equal(fast[0], general[0])
    np.testing.assert_array_equal(fast[1], general[1])


def test_obj_reads_on_threads_side_by_side_leave_the_warning_filters_as_they_were(tmp_path, monkeypatch):
    """Each OBJ read hides numpy's parse warnings with ``warnings.catch_warnings``, which saves and puts back
    the process's filters: two reads on threads side by side (a capture folder read by a Dask worker's
    threads) interleaved, the second put back the first's "ignore", and every warning was hidden for good."""
    import threading
    import warnings

    path = tmp_path / "tri.obj"
    write_obj(path, np.eye(3), np.array([[0, 1, 2]]))
    real = np.fromstring
    inside, release = {}, {}

    def held(*args, **kwargs):                 # the parse waits until the test lets it go
        name = threading.current_thread().name
        inside[name].set()
        release[name].wait(5)
        return real(*args, **kwargs)

    monkeypatch.setattr(np, "fromstring", held)
    before = list(warnings.filters)
    threads = {}
    for name in ("one", "two"):
        inside[name], release[name] = threading.Event(), threading.Event()
        threads[name] = threading.Thread(target=read_obj, args=(path,), name=name)
    threads["one"].start()
    inside["one"].wait(5)
    threads["two"].start()                     # tries to parse while the first hides warnings
    inside["two"].wait(0.2)
    release["one"].set()                       # the first leaves first ...
    threads["one"].join()
    inside["two"].wait(5)
    release["two"].set()                       # ... then the second
    threads["two"].join()
    assert warnings.filters == before


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="fork")
def test_obj_read_in_a_child_forked_while_another_thread_parses(tmp_path):
    """A host forking (``multiprocessing``'s default on Linux) while one of its threads parsed an OBJ: the
    child's first OBJ read waited for good on the lock that thread held."""
    from usdface.io import mesh_io

    path = tmp_path / "tri.obj"
    write_obj(path, np.eye(3), np.array([[0, 1, 2]]))
    assert child_finishes(lambda: read_obj(path), lambda: mesh_io._CATCH_LOCK), \
        "the forked child waited for good on the OBJ reader's lock"



def test_obj_writer_writes_write_objs_bytes_formatting_each_topology_once(tmp_path):
    """``ObjWriter`` (``export --obj-dir``'s many targets of one mesh) writes exactly the bytes of the
    per-file formula: rows it reuses are the neutral's to the bit (a ``-0.0`` moved by ``+0.0`` becomes
    ``0.0`` and is written so), the others are formatted again."""
    from usdface.io.mesh_io import ObjWriter

    rng = np.random.default_rng(3)
    neutral = rng.normal(size=(40, 3))
    neutral[0] = [-0.0, 1.0, 2.0]
    tris = rng.integers(0, 40, size=(70, 3))

    def reference(points):   # write_obj's text before ObjWriter: every row formatted per file
        return ("".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in points.tolist())
                + "".join(f"f {a} {b} {c}\n" for a, b, c in (tris + 1).tolist()))

    delta = np.zeros_like(neutral)
    delta[[0, 5, 7]] = [[0.0, 0.0, 0.0], [1e-17, 0.0, 0.0], [0.25, -3.0, 1e-9]]
    writer = ObjWriter(neutral, tris)
    for k, points in enumerate([neutral, neutral + delta, neutral + 0.0 * delta]):
        path = writer.write(tmp_path / f"t{k}.obj", points)
        assert path.read_text() == reference(points)
        back, faces = read_obj(path)
        assert back.tobytes() == points.tobytes() and (faces == tris).all()
    assert (tmp_path / "t1.obj").read_text().startswith("v 0.0 1.0 2.0\n")   # -0.0 + 0.0 is 0.0
    assert write_obj(tmp_path / "one.obj", neutral, tris).read_text() == reference(neutral)
    with pytest.raises(GeometryError, match=r"points must be \[40,3\] like the neutral"):
        writer.write(tmp_path / "bad.obj", neutral[:-1])


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 12), st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=3, max_size=60),
       st.sampled_from([b"\n", b"\r\n"]), st.sampled_from([b" ", b"\t", b"  "]))
def test_fixed_point_vertices_are_the_decimal_parse_to_the_bit(decimals, values, newline, space):
    """A capture's ``%.7f`` numbers read as integers over ``10^d`` are the doubles ``strtod`` gives (the same
    correctly rounded quotient), ``-0.0`` included."""
    from usdface.io.mesh_io import _fixed_point_vertices

    values = values[:len(values) // 3 * 3] + [-0.0, 0.0, -1e-30]      # zeros that print as -0.000 / 0.000
    tokens = [f"{v:.{decimals}f}".encode() for v in values]
    block = b"".join(b"v" + space + space.join(tokens[i:i + 3]) + newline for i in range(0, len(tokens), 3))
    got = _fixed_point_vertices(block, len(tokens) // 3)
    want = np.fromstring(block.replace(b"v", b"nan").decode(), dtype=np.float64, sep=" ")
    want = want.reshape(-1, 4)[:, 1:]
    if max(len(t.lstrip(b"-").replace(b".", b"")) for t in tokens) > 15:
        assert got is None or got.tobytes() == want.tobytes()             # past 2^53: declined
    else:
        assert got is not None and got.tobytes() == want.tobytes()


@pytest.mark.parametrize("block", [
    b"v - 1.5 2.5\n", b"v 1.5 2.5 3.5 4.5\n", b"v 1.5 2.5 3.55\n", b"v 1.5 2.5 3\n", b"v 1-2.5 2.5 3.5\n",
    b"v 1.5 2.5 --1.5\n", b"v 1.5 2.5 1.5.5\n", b"v 1.5 2.5 3.5 v 1.5 2.5 3.5\n", b"v 1. 2. 3.\n",
    b"v 1.5e2 2.5 3.5\n", b"v 1.5 2.5 -99999999999999999999.5\n", b"v 1.5 2.5 99999999999999999.5\n"])
def test_fixed_point_vertices_decline_what_is_not_three_fixed_point_numbers_a_record(block):
    from usdface.io.mesh_io import _fixed_point_vertices

    assert _fixed_point_vertices(block, block.count(b"v")) is None
