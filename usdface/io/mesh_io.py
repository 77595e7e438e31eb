"""Wavefront OBJ meshes <-> numpy arrays, vertex order preserved exactly.

Why not Open3D here (the project's default for mesh I/O): measured with open3d 0.20,
``read_triangle_mesh`` loads OBJ through Assimp, which renumbers the vertices in order of first use by the
faces (on the bench capture neutral, vertex 0 comes back as file vertex 292) and parses coordinates as
float32; ``enable_post_processing=False`` changes neither. ``write_triangle_mesh`` prints coordinates with 6
significant digits. Capture frames are matched to the neutral *by vertex index* and the folder -> USD round
trip must be exact, so this module parses and writes the tiny subset of OBJ that meshes need (``v`` and ``f``
records) with numpy: float64 coordinates, file order, shortest exact decimal on write.
Everything else in an OBJ (normals, UVs, groups, materials) is ignored.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..errors import GeometryError, InputFileError
from ..locks import ForkSafeLock
from .atomic import write_text_atomic

__all__ = ["read_obj", "write_obj", "ObjWriter", "fan_triangulate"]


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise InputFileError("file not found", path=path, fix="check the path") from None
    except IsADirectoryError:
        raise InputFileError("is a directory, expected an .obj file", path=path,
                             fix="pass the mesh file, not its folder") from None
    except OSError as exc:
        raise InputFileError(f"cannot read file ({exc.strerror})", path=path,
                             fix="check the file's permissions") from None


#: ``warnings.catch_warnings`` saves and puts back the process's filters: two OBJ reads on threads side by
#: side (a Dask worker's, a host's pool) interleaved, the second put back the first's "ignore", and every
#: warning of the process was hidden from then on. One block at a time.
_CATCH_LOCK = ForkSafeLock()     # (a thread parsing an OBJ when a host forks: the child's own lock)


def _fromstring(text: bytes, dtype, count: int) -> np.ndarray | None:
    """Whitespace-separated numbers -> array, or None if the text does not hold exactly ``count`` of them."""
    with _CATCH_LOCK, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            out = np.fromstring(text.decode("ascii", "replace"), dtype=dtype, sep=" ")
        except ValueError:
            return None
    return out if out.size == count else None


def _vertex_rows(lines: list[bytes], path: Path) -> np.ndarray:
    """``v x y z [w | r g b]`` records -> [n,3] float64 (extra components ignored)."""
    rows = [ln.split() for ln in lines]
    lengths = np.fromiter((len(r) for r in rows), dtype=np.int64, count=len(rows))
    if lengths.min() < 4:
        raise InputFileError("vertex record with fewer than 3 coordinates", path=path,
                             fix="re-export the mesh as a plain OBJ")
    if lengths.max() == 4:  # "v x y z": the common case, one vectorised conversion
        out = _fromstring(b" ".join(ln[2:] for ln in lines), np.float64, 3 * len(rows))
    else:
        out = _fromstring(b" ".join(b" ".join(r[1:4]) for r in rows), np.float64, 3 * len(rows))
    if out is None:
        raise InputFileError("malformed vertex record (not a number)", path=path,
                             fix="re-export the mesh as a plain OBJ")
    return out.reshape(-1, 3)


def _vertices_before_faces(all_lines: list[bytes]) -> np.ndarray:
    """For each face record, how many vertex records precede it (resolves negative, relative indices)."""
    is_v = np.fromiter((ln[:2] in (b"v ", b"v\t") for ln in all_lines), dtype=bool, count=len(all_lines))
    is_f = np.fromiter((ln[:2] in (b"f ", b"f\t") for ln in all_lines), dtype=bool, count=len(all_lines))
    return np.cumsum(is_v)[is_f]


def _face_records(lines: list[bytes], path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``f a b c ...`` records -> (counts[faces], raw OBJ indices[sum(counts)]).

    Fast path for plain ``f 1 2 3`` records: each ``f`` becomes the marker 0 (never a valid OBJ index), so a
    single numeric parse yields both the indices and, from the marker positions, the vertex count of every
    face. ``a/t/n`` records (or anything the fast path cannot read) go through the general, per-token path.
    """
    joined = b" ".join(lines)
    if b"/" not in joined:
        n_tokens = len(joined.split())
        vals = _fromstring(joined.replace(b"f", b"0"), np.int64, n_tokens)
        if vals is not None:
            marks = np.flatnonzero(vals == 0)
            if len(marks) == len(lines):
                counts = np.diff(np.append(marks, len(vals))) - 1
                return counts, vals[vals != 0]
    rows = [ln.split()[1:] for ln in lines]
    counts = np.fromiter((len(r) for r in rows), dtype=np.int64, count=len(rows))
    flat = [t.split(b"/", 1)[0] for r in rows for t in r]
    vals = _fromstring(b" ".join(flat), np.int64, len(flat))
    if vals is None:
        raise InputFileError("malformed face record", path=path, fix="re-export the mesh as a plain OBJ")
    return counts, vals


def _face_triangles(lines: list[bytes], all_lines: list[bytes], path: Path) -> np.ndarray:
    """Face records (``a``, ``a/t``, ``a//n``, ``a/t/n``; negative = relative) -> fan triangles [t,3]."""
    counts, idx = _face_records(lines, path)
    if counts.min() < 3:
        bad = int(np.argmin(counts))
        raise GeometryError(f"face {bad} has {int(counts[bad])} vertices; faces need at least 3", path=path,
                            fix="remove points/lines from the mesh or re-export it triangulated")
    if (idx == 0).any():
        raise GeometryError("face index 0 (OBJ indices start at 1)", path=path,
                            fix="repair or re-export the mesh")
    if (idx < 0).any():
        owner = np.repeat(np.arange(len(counts)), counts)
        idx = np.where(idx < 0, _vertices_before_faces(all_lines)[owner] + idx, idx - 1)
    else:
        idx = idx - 1
    if (counts == 3).all():
        return idx.reshape(-1, 3)
    return fan_triangulate(counts, idx)


def fan_triangulate(counts: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Fan-triangulate polygons (``counts[faces]`` corners, flat 0-based ``idx``): (v0, v_i, v_i+1) ->
    ``triangles[t, 3]`` int64; vectorized (OBJ faces and USD ``faceVertexCounts``/``faceVertexIndices``).
    The caller validates counts >= 3."""
    counts = np.asarray(counts, dtype=np.int64)
    idx = np.asarray(idx, dtype=np.int64)
    if idx.size == 3 * counts.size and (counts == 3).all():        # already triangles (a 300k body: 0.2 s)
        return idx.reshape(-1, 3).copy()
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    n_tri = counts - 2
    face_of_tri = np.repeat(np.arange(len(counts)), n_tri)
    corner = np.arange(int(n_tri.sum())) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri) + 1
    first = start[face_of_tri]
    return np.stack([idx[first], idx[first + corner], idx[first + corner + 1]], axis=1)


def read_obj(path, *, faces: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read an OBJ mesh.

    Returns ``points[n, 3]`` float64 (file units, file order) and ``triangles[t, 3]`` int64 (0-based; polygons
    are fan-triangulated).

    ``faces``: a dict the caller keeps across the reads of many meshes of one topology (a capture's frames):
    it holds the first face block parsed, and a file whose face block is the same bytes gets a copy of its
    triangles without parsing it again (the same array; the vertices are parsed and checked as always).

    Raises InputFileError (missing, unreadable, malformed) and GeometryError (no vertices, no faces, NaN/inf,
    face indices out of range, faces with fewer than 3 vertices), each naming the file.

    Examples
    --------
    >>> points, triangles = read_obj("capture/neutral.obj")  # doctest: +SKIP
    """
    path = Path(path)
    data = _read_bytes(path)
    if b"\0" in data[:4096]:
        raise InputFileError("not a text OBJ file (binary content)", path=path,
                             fix="pass a Wavefront .obj file")
    try:
        fast = _fast_parse(data, faces)
        if fast is not None:
            points, triangles = fast
        else:
            points, triangles = _general_parse(data, path)
        if not np.isfinite(points).all():
            bad = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
            raise GeometryError(f"vertex {bad} is NaN or infinite", path=path,
                                fix="repair or re-export the mesh")
        if triangles.min() < 0 or triangles.max() >= len(points):
            raise GeometryError(f"face index out of range (mesh has {len(points)} vertices)", path=path,
                                fix="repair or re-export the mesh")
    except (GeometryError, InputFileError) as error:
        raise cut_off(error, data, path) from None
    return points, triangles


def cut_off(error, data: bytes, path) -> Exception:
    """``error`` as raised, or, for a file that ends in the middle of a line (the tell of an interrupted copy
    or write, a full disk), an :class:`InputFileError` saying so: a frame cut inside its vertices read as
    'mesh has no faces (fix: export the mesh with its faces, not as points)', one cut inside its faces as
    'face 1794 has 2 vertices (fix: remove points/lines from the mesh ...)', sending the TD to the DCC for
    a file that only needed copying again."""
    if not data or data.endswith((b"\n", b"\r")):
        return error
    return cut_off_error(error, path)


def cut_off_error(error, path) -> InputFileError:
    """``error`` (a :class:`~usdface.errors.UsdFaceError`) said of ``path``, a file known to be cut off
    (:func:`cut_off`, :func:`ends_mid_line`)."""
    return InputFileError("the file ends in the middle of a line, so it was probably cut off (an interrupted "
                          f"copy or write, a full disk): {error.message}", path=path,
                          fix="copy or export the file again")


def ends_mid_line(path) -> bool:
    """Whether the file's last byte is not a line end (see :func:`cut_off`); False when it cannot be read."""
    try:
        with open(path, "rb") as f:
            f.seek(0, 2)
            if f.tell() == 0:
                return False
            f.seek(-1, 2)
            return f.read(1) not in (b"\n", b"\r")
    except OSError:
        return False


_V_CHARS = b"0123456789.-+eE v\n\r\t"
_F_CHARS = b"0123456789 f\n\r\t"


def _fast_parse(data: bytes, faces: dict | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Whole-buffer parse of the common layout: a block of ``v x y z`` records, then ``f a b c ...`` records
    (what most exporters and :func:`write_obj` write). Each record keyword becomes a marker value (NaN for
    ``v``, 0 for ``f``; neither can occur otherwise in these character sets), so one numeric parse per block
    also checks every record's length. Returns None (use the general parser) on anything else. ``faces``:
    :func:`read_obj`'s (the face block parsed before, ``{bytes: triangles}``)."""
    fpos = data.find(b"\nf ")
    if fpos < 0 or not data.startswith(b"v "):
        return None
    vblock, fblock = data[:fpos + 1], data[fpos + 1:]
    known = faces.get(fblock) if faces else None           # the same bytes: the same triangles
    if vblock.translate(None, _V_CHARS) or (known is None and fblock.translate(None, _F_CHARS)):
        return None
    n_v = vblock.count(b"v")
    points = _fixed_point_vertices(vblock, n_v)
    if points is None:
        vals = _fromstring(vblock.replace(b"v", b"nan"), np.float64, 4 * n_v)
        if vals is None:
            return None
        rec = vals.reshape(-1, 4)
        if not np.isnan(rec[:, 0]).all() or np.isnan(rec[:, 1:]).any():
            return None
        points = rec[:, 1:].copy()
    if known is not None:
        return points, known.copy()
    tris = _parse_faces(fblock)
    if tris is not None and faces is not None and not faces:
        faces[fblock] = tris.copy()                         # the first one only: one topology's
    return None if tris is None else (points, tris)


def _fixed_point_vertices(vblock: bytes, n_v: int) -> np.ndarray | None:
    """:func:`_fast_parse`'s vertex block (``n_v`` records ``v x y z``, checked for its characters) ->
    ``[n_v,3]`` float64 when every number is written in fixed point with the same number ``d >= 1`` of
    decimals (``[-+]digits.digits``, as a capture app's ``%.7f`` writes them); None otherwise (the decimal
    parse then).

    Each number is read as the integer its digits make (the point dropped) divided by ``10^d``: both are
    exact in float64 (the integer below 2^53, ``d <= 15``) and IEEE division rounds the exact quotient
    correctly, so the result is the decimal's correctly rounded double, the value ``strtod``
    (``np.fromstring``) gives, to the bit (``-0.0`` kept); integers parse at a fifth of the cost of
    decimals."""
    if not n_v or b"e" in vblock or b"E" in vblock:
        return None
    b = np.frombuffer(vblock, dtype=np.uint8)          # (of _V_CHARS: the bytes <= 32 are the whitespace)
    dots = np.flatnonzero(b == 46)                                                  # "."
    if dots.size != 3 * n_v:
        return None
    d = 0
    while dots[0] + 1 + d < b.size and 48 <= b[dots[0] + 1 + d] <= 57:
        d += 1
    if not 1 <= d <= 15 or dots[-1] + d + 1 >= b.size:
        return None
    # every point followed by d digits and a space: one point a number, each number ending there
    digit_count = np.cumsum((b - 48) < 10, dtype=np.int32)
    if not ((digit_count.take(dots + d) - digit_count.take(dots) == d).all()
            and (b.take(dots + d + 1) <= 32).all()):
        return None
    # each record its own line, "v" and three points before the next "v"; a sign only at a number's start
    # and before a digit or the point (a number without a point, an extra or a missing one, changes how
    # many integers the parse below finds)
    vs = np.flatnonzero(b == 118)                                                   # "v"
    signs = np.flatnonzero((b == 45) | (b == 43))                                   # "-", "+"
    next_to_sign = b.take(signs + 1)
    if (vs.size != n_v or vs[0] != 0 or not (b.take(vs + 1) <= 32).all() or (b.take(vs[1:] - 1) != 10).any()
            or not np.array_equal(np.searchsorted(dots, vs), 3 * np.arange(n_v))
            or not (b.take(signs - 1) <= 32).all()
            or not (((next_to_sign - 48) < 10) | (next_to_sign == 46)).all()):
        return None
    digits = _fromstring(vblock.translate(None, b".v"), np.int64, 3 * n_v)
    if digits is None or not ((digits < 2 ** 53) & (digits > -2 ** 53)).all():    # exact in float64
        return None
    out = digits / float(10 ** d)
    zero = digits == 0
    if zero.any():
        negative = np.zeros(3 * n_v, dtype=bool)
        negative[np.searchsorted(dots, signs[b.take(signs) == 45])] = True
        out[zero & negative] = -0.0
    return out.reshape(-1, 3)


def _parse_faces(fblock: bytes) -> np.ndarray | None:
    """:func:`_fast_parse`'s face block (``f a b c ...`` records, checked for its characters) -> triangles
    ``[t,3]`` (0-based, fan-triangulated), or None for the general parser."""
    n_f = fblock.count(b"f")
    idx = _fromstring(fblock.replace(b"f", b"0"), np.int64, len(fblock.split()))
    if idx is None:
        return None
    marks = np.flatnonzero(idx == 0)
    if len(marks) != n_f or (n_f and marks[0] != 0):
        return None
    counts = np.diff(np.append(marks, len(idx))) - 1
    if counts.min() < 3:
        return None
    corners = np.delete(idx, marks) - 1
    return corners.reshape(-1, 3) if (counts == 3).all() else fan_triangulate(counts, corners)


def _general_parse(data: bytes, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Record-by-record parse: any line order, comments, normals/UVs, ``a/t/n`` and negative indices."""
    lines = data.splitlines()
    v_lines = [ln for ln in lines if ln[:2] == b"v " or ln[:2] == b"v\t"]
    f_lines = [ln for ln in lines if ln[:2] == b"f " or ln[:2] == b"f\t"]
    if not v_lines:
        raise GeometryError("mesh has no vertices", path=path,
                            fix="check that the file is a non-empty OBJ mesh")
    if not f_lines:
        raise GeometryError("mesh has no faces", path=path,
                            fix="export the mesh with its faces, not as points")
    return _vertex_rows(v_lines, path), _face_triangles(f_lines, lines, path)


def write_obj(path, points, triangles, uv=None) -> Path:
    """Write ``points[n, 3]`` and ``triangles[t, 3]`` (0-based) as an OBJ, atomically (temp file + rename).

    Coordinates are written as the shortest decimal that reads back to the identical float64, so
    ``read_obj(write_obj(p, V, F))`` returns exactly ``V`` and ``F``. ``uv[t, 3, 2]``: texture coordinates
    per triangle corner (USD's ``(s, t)``, which is OBJ's ``(u, v)``, v up), written as one ``vt`` per
    distinct pair and ``f a/ta b/tb c/tc`` (OBJ indexes positions and coordinates apart: a UV seam needs no
    split point). Many OBJs of one topology (a shape's targets): :class:`ObjWriter`, which formats the faces,
    the texture coordinates and the unmoved vertices once.
    """
    return ObjWriter(points, triangles, uv=uv, path=path).write(path, points)


class ObjWriter:
    """OBJs of one mesh topology: the neutral ``points[n, 3]``, ``triangles[t, 3]`` (0-based) and optional
    ``uv[t, 3, 2]`` (as :func:`write_obj`) formatted once, each target written with only the vertex rows
    that differ from the neutral formatted again.

    ``write(path, points)`` writes the same bytes as :func:`write_obj` (every vertex row is the shortest
    decimal of its float64, a row is reused only where its three values are the neutral's to the bit, so
    ``-0.0`` stays ``-0.0``), atomically. A target OBJ of a 225k-vertex head (450k triangles) formatted its
    450k face rows again for each of 51 shapes: ``usdface export --obj-dir`` of the twice-subdivided bench
    head spent ~55 CPU-s there (docs/scale.md).
    """

    def __init__(self, points, triangles, *, uv=None, path=None):
        points = self._points(points, path)
        self.neutral = points.copy()
        self._rows = self._format(self.neutral)
        self._faces = _obj_topology(path, len(points), np.asarray(triangles, dtype=np.int64), uv)

    @staticmethod
    def _points(points, path) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
            raise GeometryError(f"points must be a non-empty [n,3] array, got {points.shape}", path=path,
                                fix="pass mesh vertices as an [n,3] array")
        if not np.isfinite(points).all():
            raise GeometryError("points contain NaN or infinite values", path=path,
                                fix="repair the mesh first")
        return points

    @staticmethod
    def _format(points: np.ndarray) -> list[str]:
        return [f"v {x!r} {y!r} {z!r}\n" for x, y, z in points.tolist()]

    def text(self, points, *, path=None) -> str:
        """The OBJ text of ``points`` (the neutral's vertex count) on this topology (``path``: named in
        an error)."""
        points = self._points(points, path)
        if points.shape != self.neutral.shape:
            raise GeometryError(f"points must be [{len(self.neutral)},3] like the neutral, got "
                                f"{points.shape}", path=path, fix="pass a target of the same mesh")
        moved = np.flatnonzero((points.view(np.int64) != self.neutral.view(np.int64)).any(axis=1))
        if len(moved) == 0:
            rows = self._rows
        else:
            rows = self._rows.copy()
            for i, row in zip(moved.tolist(), self._format(points[moved]), strict=True):
                rows[i] = row
        return "".join(rows) + self._faces

    def write(self, path, points) -> Path:
        """Write the OBJ of ``points`` on this topology to ``path``, atomically (temp file + rename)."""
        return write_text_atomic(Path(path), self.text(points, path=path), force=True)


def _obj_topology(path, n: int, triangles: np.ndarray, uv) -> str:
    """The ``vt`` and ``f`` records of :class:`ObjWriter`, checked against ``n`` points."""
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise GeometryError(f"triangles must be [t,3], got {triangles.shape}", path=path,
                            fix="pass faces as a [t,3] index array")
    if triangles.size and (triangles.min() < 0 or triangles.max() >= n):
        raise GeometryError("triangle index out of range", path=path, fix="check the face indices")
    if uv is None:
        return "".join(f"f {a} {b} {c}\n" for a, b, c in (triangles + 1).tolist())
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(uv) != triangles.size or not np.isfinite(uv).all():
        raise GeometryError(f"texture coordinates must be finite, one pair per triangle corner "
                            f"({triangles.size}), got {len(uv)}", path=path,
                            fix="pass uv[t, 3, 2] for triangles[t, 3]")
    values, corner = np.unique(uv, axis=0, return_inverse=True)
    text = "".join(f"vt {u!r} {v!r}\n" for u, v in values.tolist())
    rows = np.column_stack([triangles.reshape(-1) + 1, np.asarray(corner).reshape(-1) + 1]).reshape(-1, 6)
    return text + "".join(f"f {a}/{ta} {b}/{tb} {c}/{tc}\n" for a, ta, b, tb, c, tc in rows.tolist())
