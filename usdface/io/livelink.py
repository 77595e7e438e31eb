"""Live Link Face CSV takes (Epic's iOS app): per-row timecode, 52 ARKit weights, head and eye angles.

Format (one header row, then one row per frame, ~30 Hz)::

    Timecode,BlendShapeCount,EyeBlinkLeft,...,TongueOut,HeadYaw,HeadPitch,HeadRoll,LeftEyeYaw,...,RightEyeRoll
    13:13:04:31.652,61,0.1236470118,...

* ``Timecode`` is ``HH:MM:SS:FF.fff`` with ``FF.fff`` a (fractional) frame count at ``timecode_rate``
  (60 per second in the app's recordings); times are returned in seconds from the first row.
* Weight columns are PascalCase ARKit names in Live Link's own order; they are mapped **by name** (any of the
  three spellings, :mod:`usdface.arkit`) and returned in ARKit order.
* ``BlendShapeCount`` is ignored; head/eye angle columns (radians) are returned separately, never as weights;
  any other column is kept in ``extra`` and reported with a warning.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..arkit import livelink_name, lookalike, match_names
from ..errors import CaptureError, InputFileError, TimecodeError, warn
from .atomic import write_text_atomic
from .capture_folder import order_names, refuse_weights_scale

__all__ = ["LiveLinkTake", "read_livelink_csv", "read_livelink_take", "livelink_weights", "parse_timecodes",
           "median_fps", "format_timecodes", "write_livelink_csv", "ANGLE_COLUMNS", "DEFAULT_TIMECODE_RATE"]

#: Head and eye rotation columns (radians), kept out of the weights.
ANGLE_COLUMNS = ("HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
                 "RightEyeYaw", "RightEyePitch", "RightEyeRoll")
_IGNORED = ("BlendShapeCount",)
#: the header's bookkeeping and angle columns, by their lower-case spelling
_BOOKKEEPING = {c.lower(): c for c in ("Timecode", "BlendShapeCount", *ANGLE_COLUMNS)}


def livelink_header(fields, first_line: str, path, fix: str) -> list[str]:
    """The header row ``fields`` of a Live Link Face CSV with its bookkeeping and angle columns spelled as
    the app does (``Timecode``, ``BlendShapeCount``, ``HeadYaw``, ... in any letter case: other writers spell
    ``BlendshapeCount``).
    Raises InputFileError naming ``path`` when it has no ``Timecode`` column, saying so when ``first_line``
    (the file's first line) separates its fields by semicolons or tabs (a spreadsheet's list separator)."""
    header = [_BOOKKEEPING.get(c.strip().lower(), c.strip()) for c in fields]
    if "Timecode" in header:
        return header
    sep = next((s for s in (";", "\t", "|") if s in first_line and "," not in first_line), None)
    if sep is not None and "timecode" in first_line.lower():
        said = {";": "semicolons", "\t": "tabs", "|": "'|'"}[sep]
        raise InputFileError(f"not a Live Link Face CSV: its fields are separated by {said}, not commas (a "
                             "spreadsheet saved it with another list separator)", path=path,
                             fix="export it again from Live Link Face, or save it from the spreadsheet as "
                                 "CSV with comma separators")
    raise InputFileError("not a Live Link Face CSV (no 'Timecode' column in the header)", path=path, fix=fix)


def _column(name: str) -> str:
    """A header name as a message says it: an empty one (a row index written by pandas' ``to_csv``, a
    spreadsheet's blank header cell) was said as nothing at all."""
    return name if name else "a column with no name"


def _drop_unnamed_empty_columns(rows: list[list[str]]) -> list[list[str]]:
    """Leave out the columns with no name in the header and no value in any row: the empty last column of
    a CSV whose lines end with a comma (a spreadsheet or a script wrote it so). It was read as a column
    named '' whose '' is not a number, 'the CSV is damaged'."""
    header = rows[0]
    drop = {j for j, c in enumerate(header) if not c.strip()
            and all(j >= len(r) or not r[j].strip() for r in rows[1:])}
    if not drop:
        return rows
    width = len(header)
    # a row keeps its length relative to the header, so that a cut-off or ragged row is still told
    return [[c for j, c in enumerate(r) if j not in drop or j >= width] for r in rows]


@dataclass
class LiveLinkTake:
    """A Live Link Face take: names[K] canonical, weights[F, K] in [0, 1], times[F] seconds from the first
    row, angles {column: [F] radians}, extra {column: [F]} (unrecognised numeric columns), the raw
    timecodes[F], and the name report (inexact / missing)."""

    names: list[str]
    weights: np.ndarray
    times: np.ndarray
    angles: dict[str, np.ndarray] = field(default_factory=dict)
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    timecodes: list[str] = field(default_factory=list)
    name_report: dict = field(default_factory=dict)
    source: str = ""

    @property
    def fps(self) -> float:
        """Median sampling rate (frames per second), :func:`median_fps`."""
        return median_fps(self.times)


def median_fps(times) -> float:
    """The frame rate of a take's ``times[F]`` (seconds): one over the median frame interval, rounded to 6
    decimals (times from timecodes are sums of ``1 / rate`` steps: 30.000000000001705 is 30), or 30 for
    fewer than two frames or a median interval of zero."""
    dt = np.diff(np.asarray(times, dtype=np.float64))
    step = float(np.median(dt)) if dt.size else 0.0
    return round(1.0 / step, 6) if step > 0 else 30.0


#: The default timecode rate: Live Link Face counts the ``FF`` field at 60 per second.
DEFAULT_TIMECODE_RATE = 60.0
_COMMON_RATES = (24.0, 25.0, 30.0, 48.0, 50.0, 60.0, 120.0, 240.0)     # timecode rates phones record at


def _common_rate_above(field: float) -> float:
    """The smallest common timecode rate above a frame field (the rate timecodes reaching it count at)."""
    return next((r for r in _COMMON_RATES if r > field), float(np.floor(field)) + 1.0)


def _rate_fix(rate: float) -> str:
    r = f"{rate:g}"
    return (f"give the rate the timecodes count at: 'usdface anim import TAKE.csv -o take.usda "
            f"--timecode-rate {r}' (then pass take.usda where the CSV went), or timecode_rate={r} in Python")


def parse_timecodes(codes, timecode_rate: float | None = None, path=None) -> np.ndarray:
    """``HH:MM:SS:FF[.fff]`` strings -> seconds[F] from the first code (a midnight wrap is unwrapped).

    ``FF`` counts frames at ``timecode_rate`` per second. None: :data:`DEFAULT_TIMECODE_RATE`, 60, the
    app's; a take whose frame fields reach 60 is read at the smallest common rate above its largest field
    (a 120 fps take: every reader of takes - a take folder, ``fit``/``personalize`` of a CSV, the weights of
    ``landmarks --takes`` - takes no rate of its own), with a warning naming it and the option; one whose
    fields all stay below half the rate over several seconds - the default's or one given - is warned about
    (a 30 per second take read at 60 or 120: each second's frames packed into its first half). Raises
    :class:`usdface.errors.TimecodeError` naming the file when a frame field reaches a rate the caller gave
    (the timecodes contradict it) or a field is negative.
    """
    parts = [c.strip().split(":") for c in codes]
    if any(len(p) != 4 for p in parts):
        bad = next(c for c, p in zip(codes, parts, strict=True) if len(p) != 4)
        raise InputFileError(f"timecode {bad!r} is not HH:MM:SS:FF", path=path,
                             fix="export the take from Live Link Face unchanged")
    try:
        hms = np.array(parts, dtype=np.float64).reshape(len(parts), 4)
    except ValueError:
        raise InputFileError("timecode with non-numeric fields", path=path,
                             fix="export the take from Live Link Face unchanged") from None
    rate = DEFAULT_TIMECODE_RATE if timecode_rate is None else float(timecode_rate)
    if not np.isfinite(rate) or rate <= 0:
        raise TimecodeError(f"timecode rate {timecode_rate!r} is not a positive number of frames per second",
                            path=path, fix=_rate_fix(DEFAULT_TIMECODE_RATE))
    negative = ~(hms >= 0)           # also NaN
    if negative.any():
        i = int(np.flatnonzero(negative.any(axis=1))[0])
        raise TimecodeError(f"timecode {codes[i].strip()!r} (row {i + 1} of the take) has a negative or "
                            f"non-numeric field", path=path,
                            fix="export the take from Live Link Face unchanged")
    ff = hms[:, 3]
    if ff.size and ff.max() >= rate:
        i = int(np.argmax(ff))
        implied = _common_rate_above(ff[i])
        said = (f"timecode {codes[i].strip()!r} (row {i + 1} of the take) has frame field {ff[i]:g}: the "
                f"timecodes count more than {np.floor(ff[i]):g} frames per second")
        if timecode_rate is not None:                           # the caller's rate contradicts the take
            raise TimecodeError(f"{said}, not below the rate given, {rate:g} (likely {implied:g})", path=path,
                                fix=_rate_fix(implied))
        warn(f"{path or 'take'}: {said}: read at {implied:g} per second, not the default "
             f"{rate:g} (to set it: {_rate_fix(implied)})")
        rate = implied
    whole = hms[:, 0] * 3600 + hms[:, 1] * 60 + hms[:, 2]
    whole = whole + 86400 * np.concatenate([[0], np.cumsum(np.diff(whole) < -43200)])  # past midnight
    seconds = np.unique(whole)
    if len(seconds) >= 3 and len(ff) >= 10 * len(seconds) and ff.max() < rate / 2:
        looks = _common_rate_above(ff.max())                     # 30 per second fields read at 60: 30
        which = "the default " if timecode_rate is None else "the given rate "
        warn(f"{path or 'take'}: every timecode frame field is below {looks:g} (at most "
             f"{ff.max():g}) over {len(seconds)} seconds of {len(ff)} rows: the timecodes look "
             f"like {looks:g} per second, and read at {which}{rate:g} the frames' times are wrong "
             f"(each second's frames packed into its first {looks / rate:.2g} s) "
             f"(fix: {_rate_fix(looks)})")
    # Differences in frames first (whole seconds are exact), then seconds: keeps time codes clean.
    frames = (whole - whole[0]) * rate + (ff - ff[0]) if len(whole) else whole
    back = np.flatnonzero(np.diff(frames) <= 0)
    if back.size:       # a repeated row: its USD time sample replaced the other's, one frame lost unsaid
        i = int(back[0]) + 1
        how = "repeats" if frames[i] == frames[i - 1] else "comes before"
        raise TimecodeError(f"timecode {codes[i].strip()!r} (row {i + 1} of the take) {how} the previous "
                            f"row's {codes[i - 1].strip()!r}: a take's rows run forward in time", path=path,
                            fix="export the take from Live Link Face unchanged (an edited or merged CSV: "
                                "remove the repeated rows, sort the rows by time)")
    return frames / rate


def require_livelink_file(path) -> Path:
    """``path`` as a Path if it is an existing regular file, else InputFileError: missing, a folder (a take
    folder holding one CSV: that CSV named in the fix), a pipe. What the file holds, the reader judges."""
    from .file_kind import folder_files
    from .usd_open import require_file

    inside = folder_files(path, "*.csv") if Path(path).is_dir() else []
    # a take folder (OBJ frames + its CSV) given to 'anim import': name the CSV in it (a user trial)
    return require_file(path, "Live Link CSV", "pass the .csv exported by Live Link Face"
                        + (f": {inside[0]}" if len(inside) == 1 else ""))


def read_livelink_take(path, timecode_rate: float | None = None) -> LiveLinkTake:
    """Read a Live Link Face CSV into a :class:`LiveLinkTake` (see the module doc for the format).

    ``timecode_rate``: frames per second of the timecodes' ``FF`` field (None: 60, the app's, with a warning
    when the take looks like 30; see :func:`parse_timecodes`).

    Raises InputFileError (missing/unreadable, not a Live Link CSV, ragged or non-numeric rows), TimecodeError
    (a frame field at or above the rate, a negative field) or CaptureError (NaN/inf weights, the same shape
    under two spellings), naming the file and the line. Weights outside [0, 1] are clipped with a warning
    (real takes have ``EyeLookIn*`` up to ~1.06).
    """
    path = require_livelink_file(path)
    if path.suffix.lower() in (".usd", ".usda", ".usdc", ".usdz"):  # the UTF-8 decoder's words said only that
        raise InputFileError("a USD file where a Live Link Face CSV is expected", path=path,
                             fix="pass the .csv exported by Live Link Face; a USD take is read as it is "
                                 "('personalize AVATAR CAPTURE --take FILE', 'capture select FILE')")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputFileError("file not found", path=path, fix="check the path") from None
    except UnicodeDecodeError as exc:
        raise InputFileError(f"not a text CSV (byte {exc.object[exc.start]:#04x} at offset {exc.start} is "
                             "not UTF-8: a binary file?)", path=path,
                             fix="pass the .csv exported by Live Link Face") from None
    except OSError as exc:
        raise InputFileError(f"cannot read the CSV ({exc})", path=path,
                             fix="pass a Live Link Face .csv") from None
    if not text.strip():
        raise InputFileError("the CSV is empty", path=path, fix="pass the .csv exported by Live Link Face")
    rows = list(csv.reader(io.StringIO(text)))
    rows = [r for r in rows if r and any(c.strip() for c in r)]
    if rows:
        rows = _drop_unnamed_empty_columns(rows)
    # the two bookkeeping columns in any letter case: writers spell them 'BlendshapeCount' too, which was
    # warned about as an unknown column; a 'timecode' header was refused as having no Timecode column
    header = livelink_header(rows[0] if rows else [], text.lstrip("\ufeff").split("\n", 1)[0], path,
                             "pass the .csv exported by Live Link Face")
    twice = sorted({c for c in header if header.count(c) > 1})
    if twice:
        raise InputFileError(f"duplicated column(s) in the header: {', '.join(map(_column, twice))}",
                             path=path,
                             fix="keep one column per name (the CSV was edited or merged); export it again")
    body = rows[1:]
    if not body:
        raise InputFileError("the CSV has a header but no frames", path=path, fix="record a take first")
    ragged = [i for i, r in enumerate(body) if len(r) != len(header)]
    if ragged == [len(body) - 1] and len(body) > 1 and len(body[-1]) < len(header) \
            and not text.endswith(("\n", "\r")):
        # the recording stopped mid-row (an app crash, a copy cut short): the complete rows are the take
        warn(f"{path}: the last line is cut off ({len(body[-1])} of {len(header)} fields, no line "
             f"end): dropped; {len(body) - 1} complete frames read")
        body, ragged = body[:-1], []
    if ragged:
        raise InputFileError(f"line {ragged[0] + 2} has {len(body[ragged[0]])} fields, the header "
                             f"{len(header)}", path=path, fix="the CSV is truncated or damaged; export again")
    table = np.array(body, dtype=object)
    t_col = header.index("Timecode")
    times = parse_timecodes(table[:, t_col].tolist(), timecode_rate, path)
    numeric = {}
    for j, name in enumerate(header):
        if j == t_col or name in _IGNORED:
            continue
        try:
            numeric[name] = table[:, j].astype(np.float64)
        except ValueError:
            bad = next(i for i, v in enumerate(table[:, j]) if not _is_float(v))
            raise InputFileError(f"line {bad + 2}, column {name!r}: {table[bad, j]!r} is not a number",
                                 path=path, fix="the CSV is damaged; export it again") from None
    angles = {n: numeric.pop(n) for n in ANGLE_COLUMNS if n in numeric}
    match = match_names(list(numeric))
    if match.duplicates:
        cols = [n for n, c in zip(match.names, match.canonical, strict=True) if c in match.duplicates]
        raise CaptureError(f"the same shape appears in several columns: {', '.join(cols)}", path=path,
                           fix="keep one column per shape")
    extra = {n: numeric[n] for n in match.unknown}
    if extra:
        # a misspelt weight ('JawOpn') is set aside and its shape reads as 0 in every frame: name the shape
        looks = {n: a for n in extra if (a := lookalike(n)) is not None and a not in set(match.canonical)}
        said = ", ".join(f"{n} (looks like {looks[n]}: misspelt?)" if n in looks else
                         f"{_column(n)} (column {header.index(n) + 1})" if not n else n for n in extra)
        fix = (f" (fix: rename the column{'s' if len(looks) > 1 else ''} "
               + ", ".join(f"{n} -> {livelink_name(a)}" for n, a in looks.items()) + ")") if looks else ""
        warn(f"{path}: columns that are neither ARKit weights nor head/eye angles (kept in 'extra', "
             f"not used as weights): {said}{fix}")
    by_name = {c: numeric[n] for n, c in zip(match.names, match.canonical, strict=True) if n not in extra}
    if not by_name:
        # a take of no weight at all played as one that holds every shape still, and 'anim import' wrote
        # '0 shapes' as a success
        has = ", ".join([*angles, *extra][:8]) or "none"
        raise CaptureError(f"no ARKit weight column in the CSV (its other columns: {has})", path=path,
                           fix="pass the .csv Live Link Face exported in ARKit mode (52 weight columns such "
                               "as EyeBlinkLeft, JawOpen)")
    names = order_names(by_name)
    weights = np.stack([by_name[n] for n in names], axis=1) if names else np.zeros((len(body), 0))
    if not np.isfinite(weights).all():
        f, k = np.argwhere(~np.isfinite(weights))[0]
        raise CaptureError(f"line {f + 2}, {names[k]}: weight is NaN or infinite", path=path,
                           fix="repair or re-export the take")
    refuse_weights_scale(weights, names, path, frame=lambda f: f"line {f + 2}", fix_where="the CSV's weights")
    if weights.size and (weights.min() < 0 or weights.max() > 1):
        out = (weights < 0) | (weights > 1)
        cols = [names[k] for k in np.flatnonzero(out.any(axis=0))]
        warn(f"{path}: weights outside [0, 1] (range {weights.min():.4g} .. {weights.max():.4g}) "
             f"clipped in {int(out.any(axis=1).sum())} frame(s): {', '.join(cols)}")
        weights = np.clip(weights, 0.0, 1.0)
    report = {"inexact": match.inexact, "unknown": match.unknown, "missing": match.missing}
    return LiveLinkTake(names, weights, times, angles, extra, table[:, t_col].tolist(), report, str(path))


def _is_float(v) -> bool:
    try:
        float(v)
    except ValueError:
        return False
    return True


def read_livelink_csv(path, timecode_rate: float | None = None) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Read a Live Link Face CSV -> (names[K] canonical ARKit, weights[F, K], times[F] seconds from start).

    Head/eye angle columns are not weights and are left out (see :func:`read_livelink_take` for them).
    """
    take = read_livelink_take(path, timecode_rate)
    return take.names, take.weights, take.times


def livelink_weights(paths, names, frames: int = 0, timecode_rate: float | None = None) -> np.ndarray:
    """The weights of one or more takes (Live Link Face CSVs, or USD takes / take folders read with
    :func:`usdface.io.take.read_take`) stacked in file order, as columns of ``names[K]``
    (canonical ARKit; a shape a take lacks is 0) -> ``weights[F, K]``; with ``frames`` > 0 and more rows than
    that, ``frames`` rows evenly sampled (first and last kept)."""
    blocks = []
    for path in paths:
        if Path(path).suffix.lower() == ".csv":
            take_names, w, _ = read_livelink_csv(path, timecode_rate)
        else:          # a USD take (``usdface anim import``) or a take folder: the same weights
            from .take import read_take

            take = read_take(path)
            take_names, w = list(take.names), np.asarray(take.weights, dtype=np.float64)
        index = {n: i for i, n in enumerate(take_names)}
        block = np.zeros((w.shape[0], len(names)))
        for k, n in enumerate(names):
            if n in index:
                block[:, k] = w[:, index[n]]
        blocks.append(block)
    w = np.concatenate(blocks) if blocks else np.zeros((0, len(names)))
    if frames and len(w) > frames:
        w = w[np.linspace(0, len(w) - 1, frames).round().astype(int)]
    return w


def format_timecodes(times, timecode_rate: float = 60.0, start: str = "00:00:00:00.000") -> list[str]:
    """seconds[F] from ``start`` -> ``HH:MM:SS:FF.fff`` strings (``FF`` counts at ``timecode_rate``)."""
    h, m, sec, ff = (float(x) for x in start.split(":"))
    rate = float(timecode_rate)
    frames = (h * 3600 + m * 60 + sec) * rate + ff + np.round(np.asarray(times, dtype=np.float64) * rate, 3)
    whole, frac = np.divmod(frames, rate)
    out = []
    for s, f in zip(whole.astype(np.int64).tolist(), frac.tolist(), strict=True):
        s %= 86400
        out.append(f"{s // 3600:02d}:{s // 60 % 60:02d}:{s % 60:02d}:{f:06.3f}")
    return out


def write_livelink_csv(path, names, weights, times, angles: dict | None = None,
                       timecode_rate: float = 60.0) -> Path:
    """Write a take in Live Link Face's CSV layout (``Timecode, BlendShapeCount, <PascalCase weights>,
    <angles>``): ``weights[F, K]`` for canonical ``names[K]``, ``times[F]`` seconds, optional ``angles``
    {column: [F]}. Written atomically. Used to make test takes; :func:`read_livelink_take` reads it back."""


    path = Path(path)
    weights = np.asarray(weights, dtype=np.float64)
    angles = angles or {}
    header = ["Timecode", "BlendShapeCount"] + [livelink_name(n) for n in names] + list(angles)
    cols = [np.asarray(v, dtype=np.float64) for v in angles.values()]
    codes = format_timecodes(times, timecode_rate)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    count = len(names) + len(angles)
    for f, code in enumerate(codes):
        row = [repr(float(x)) for x in weights[f]] + [repr(float(c[f])) for c in cols]
        writer.writerow([code, count] + row)
    return write_text_atomic(path, buf.getvalue(), force=True)
