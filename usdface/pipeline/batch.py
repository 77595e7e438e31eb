"""Batch personalization: many (avatar, capture, output) items from a manifest, on a local process pool or
a Dask cluster, with failure isolation, a report and resume.

* **Manifest**: CSV with a header row, or JSON (a list of objects, or ``{"items": [...]}``). Required fields
  ``avatar``, ``capture``, ``output``; any other field is passed to the worker as a personalize option
  (e.g. ``method``), except ``review`` (true/false: the review page beside the layer, as the Pyblish
  collector reads the same manifest). Relative paths are relative to the manifest's folder.
* **Isolation**: every item runs inside :func:`run_item`, which turns any exception into a ``failed`` result;
  a worker process that dies is reported the same way. One bad item never stops the batch.
* **Resume**: an item whose output already exists is ``skipped`` (outputs are written atomically, so an
  existing output is a finished one); ``force=True`` redoes everything, and a row's ``force`` true its own
  row (a row's false adds nothing). A finished layer whose row asks for a review page that is not there
  gets the page alone.
* **Where**: ``jobs=1`` runs in this process; otherwise a local ``ProcessPoolExecutor`` (spawned workers,
  ``jobs`` defaults to :func:`default_jobs`: the cores this process may use, as many as the memory
  holds); ``scheduler="tcp://host:8786"`` (or a ``distributed.Client``) sends the
  items to a Dask cluster instead.

Example::

    from usdface.pipeline.batch import read_manifest, run_batch
    report = run_batch(read_manifest("people.csv"), jobs=2)
    report.write("people.report.json")
    print(report.summary())
"""

from __future__ import annotations

import contextlib
import csv
import functools
import json
import os
import threading
import time
import traceback
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ..errors import InputFileError, OutputExistsError, UsdFaceError
from ..locks import SharedWhileInside

REQUIRED = ("avatar", "capture", "output")
DONE, SKIPPED, FAILED = "done", "skipped", "failed"
#: A report's ``where`` when no item ran (every row skipped, or stale): nothing was started or contacted.
NOTHING_RUN = "nothing to run"


@dataclass
class BatchItem:
    """One unit of work: personalize ``avatar`` with ``capture`` into ``output`` (absolute paths)."""

    avatar: str
    capture: str
    output: str
    options: dict = field(default_factory=dict)
    index: int = 0
    #: the manifest file's line the row starts on (a CSV manifest; 0: not known, a JSON item)
    line: int = 0

    def to_dict(self) -> dict:
        return asdict(self)

    @property
    def line_note(self) -> str:
        """`` (line L)`` when the row is not on the line ``item N`` suggests (N + 1, under the header):
        comment or blank lines above it, a cell over several lines; else ``""``."""
        return f" (line {self.line})" if self.line and self.line != self.index + 2 else ""

    @property
    def label(self) -> str:
        """How a message names the item: ``item N`` (its place among the manifest's items), with the file's
        line when that differs (:attr:`line_note`), so a user finds the row in an editor or a sheet."""
        return f"item {self.index + 1}{self.line_note}"


@dataclass
class ItemResult:
    """What happened to one item. ``status`` is ``done``, ``skipped`` or ``failed``."""

    index: int
    avatar: str
    capture: str
    output: str
    status: str
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    error: str = ""
    error_type: str = ""
    traceback: str = ""
    warnings: list = field(default_factory=list)   # what the item warned about (:func:`run_item`)
    review: str = ""                               # the review page beside the layer, when the row asks one


#: The shortest batch (wall-clock seconds) whose items per minute :class:`BatchReport` states: a studio
#: worker's five near-instant items (0.06 s) read "4909.44 avatars/minute" (a TD's trial, stop 51), a rate no
#: batch of real avatars comes near; below it the summary gives the items and seconds alone.
MIN_RATE_SECONDS = 10.0


@dataclass
class BatchReport:
    """All item results (in manifest order) and the wall-clock time of the batch."""

    results: list[ItemResult]
    seconds: float
    where: str = "local"
    report_path: Path | None = None  # where :func:`usdface.api.personalize_batch` wrote the report

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.results)

    @property
    def failed(self) -> list[ItemResult]:
        return [r for r in self.results if r.status == FAILED]

    @property
    def throughput_per_minute(self) -> float | None:
        """Finished (``done``) items per minute of wall-clock time, or None for a batch shorter than
        :data:`MIN_RATE_SECONDS` (its rate is start-up and clock noise scaled to a minute)."""
        if self.seconds < MIN_RATE_SECONDS:
            return None
        return 60.0 * self.count(DONE) / self.seconds

    def summary(self) -> str:
        text = (f"{self.count(DONE)} done, {self.count(SKIPPED)} skipped, {self.count(FAILED)} failed "
                f"in {self.seconds:.1f} s")
        if self.where.startswith(NOTHING_RUN):         # not 'on dask tcp://...' where nothing was sent
            text += f": {self.where}"
        else:
            text += " in this process" if self.where == "in-process" else f" on {self.where}"
        if self.count(DONE) and self.throughput_per_minute is not None:
            text += f" ({self.throughput_per_minute:.2f} avatars/minute)"
        return text

    def to_dict(self) -> dict:
        return {"where": self.where, "seconds": self.seconds, "done": self.count(DONE),
                "skipped": self.count(SKIPPED), "failed": self.count(FAILED),
                "avatars_per_minute": self.throughput_per_minute,
                "items": [asdict(r) for r in self.results]}

    def write(self, path) -> Path:
        """Write the report as JSON, atomically (temp file + rename)."""
        from ..io.atomic import write_text_atomic

        return write_text_atomic(path, json.dumps(self.to_dict(), indent=2), force=True)


# ----------------------------------------------------------------------------------------------- manifest
def _coerce(value: str):
    """CSV cells are strings; numbers and booleans given as options become numbers and booleans (``true`` /
    ``false`` in any case: a spreadsheet writes ``TRUE`` / ``FALSE``)."""
    if isinstance(value, str) and value.strip().lower() in ("true", "false"):
        return value.strip().lower() == "true"
    try:
        return json.loads(value)
    except (ValueError, TypeError):
        return value


#: Item options that name files (read by the worker): relative to the manifest's folder like the required
#: paths, and (except the correspondence cache, which is read and written by design) never an output.
PATH_OPTIONS = ("take", "name_map", "pins", "correspondence")


def _absolute(base: Path, value) -> str:
    """``value`` relative to ``base`` as an absolute path with no ``.`` or ``..`` in it, symlinks kept (a
    ``latest -> v003`` link in a manifest stays the link in the layer's sublayer path, as with ``usdface
    personalize``).

    ``..`` names the parent of where the path has got to: after a symlinked folder, its target's parent,
    which dropping ``sub/..`` as text would miss. The path up to its last ``..`` is the folder the OS finds
    there: written as text without the ``..`` when that names the same folder (the links in it kept), else as
    the OS's real path; the rest follows as written. The batch report kept ``/shots/x/sub/../avatars/a.usdc``,
    as the manifest's relative path joined to its folder."""
    joined = os.path.join(base, os.path.expanduser(str(value)))
    parts = Path(joined).parts
    if ".." not in parts:
        return os.path.normpath(joined)
    last = len(parts) - 1 - parts[::-1].index("..")
    head = os.path.join(*parts[:last + 1])
    lexical = os.path.normpath(head)
    folder = lexical if os.path.realpath(lexical) == os.path.realpath(head) else os.path.realpath(head)
    return os.path.normpath(os.path.join(folder, *parts[last + 1:]))


def _file_keys(p: str) -> list:
    """What identifies the file ``p`` names: its real path and, if it exists, its (device, inode) - two
    names of one file (a symlink, a hard link) share one of them."""
    keys: list = [os.path.realpath(p)]
    try:
        st = os.stat(p)
        keys.append((st.st_dev, st.st_ino))
    except OSError:
        pass
    return keys


def _refuse_outputs_over_inputs(items: list[BatchItem], path: Path) -> None:
    """No item's output may be another item's output or any item's input (avatar, capture, take, pins, name
    map): the batch would write over a file the batch reads, whatever ``force`` says. One pass over the
    items with a table of the files they name (no pairwise comparison)."""
    outputs: dict = {}
    for it in items:
        for key in _file_keys(it.output):
            if key in outputs:
                first = items[outputs[key]]
                raise InputFileError(f"items {first.index + 1}{first.line_note} and {it.index + 1}"
                                     f"{it.line_note} both write {it.output}",
                                     path=path, fix="give every item its own output file")
            outputs[key] = it.index
    folders: dict[str, tuple[str, int]] = {}        # real path of an input folder -> (what, item)
    for it in items:
        reads = [("avatar", it.avatar), ("capture", it.capture)]
        reads += [(k, it.options[k]) for k in PATH_OPTIONS
                  if k != "correspondence" and isinstance(it.options.get(k), str)]
        for what, src in reads:
            hit = next((outputs[k] for k in _file_keys(src) if k in outputs), None)
            if hit is not None:
                raise InputFileError(f"{items[hit].label} writes {items[hit].output}, the {what} "
                                     f"{it.label} reads", path=path,
                                     fix="write outputs to their own files (an input is never overwritten, "
                                         "even with --force)")
            if os.path.isdir(src):
                folders.setdefault(os.path.realpath(src), (what, it.index))
    for it in items:                  # an output inside an input folder changes that input (a capture)
        for parent in Path(os.path.realpath(it.output)).parents:
            if str(parent) in folders:
                what, reader = folders[str(parent)]
                raise InputFileError(f"{it.label} writes {it.output} inside {parent}, the {what} "
                                     f"folder {items[reader].label} reads", path=path,
                                     fix="write outputs outside the input folders")


def _windows_path(given: str, base: Path) -> tuple[str, str] | None:
    """``(what makes it one, the path to write instead)`` when the manifest cell ``given`` (a path naming
    nothing here, relative to the manifest's folder ``base``) is a Windows path, else None: a network share
    (``\\\\server\\share\\...``: UNC) or a drive (``C:\\``, ``C:/``) at the start, unless a folder of that
    name is beside the manifest, or any name with a backslash (a folder separator on Windows, a character of
    one file name here: ``out\\b.usda`` would be written as one file beside the manifest; a genuine name with
    a backslash that exists is read, one to be written is refused: no pipeline wants that name)."""
    import re

    unc = re.match(r"[\\/]{2}([^\\/]+)[\\/]+([^\\/]+)", given)
    if unc and "\\" in given[:2]:
        return "is a Windows network (UNC) path", f"the path where //{unc[1]}/{unc[2]} is mounted here"
    drive = re.match(r"([A-Za-z]:)[\\/]", given)
    if drive and not os.path.isdir(base / drive[1]):
        return f"starts with the Windows drive {drive[1]}", f"the path where {drive[1]} is mounted here"
    if "\\" not in given:
        return None
    slashed = given.replace("\\", "/")
    return "separates its folders with '\\'", f"'{slashed}'"


def _refuse_windows_paths(path: Path, base: Path, rows: list[tuple[int, dict, dict]]) -> None:
    """A manifest written on Windows (``avatars\\anna.usdc``) read where ``/`` separates folders: its
    backslashes are characters of one file name there, so the row's avatar was 'not found' and its output
    ``out\\anna.usda`` would have been written as one file of that name beside the manifest. ``rows``:
    ``(item, the row as given, {column: resolved path})``. A cell naming no file here that is a Windows
    path (:func:`_windows_path`) is refused naming the item, the column and the path to write; a file of
    this machine whose name holds a backslash, or a path under a folder named ``D:`` beside the manifest, is
    read or written as named (h81's review, stop 51: a ``D:`` folder was refused)."""
    if os.sep != "/":
        return
    for item, row, resolved in rows:
        for column in (*REQUIRED, *PATH_OPTIONS):
            given = row.get(column)
            if not isinstance(given, str) or os.path.lexists(resolved[column]):
                continue
            found = _windows_path(given, base)
            if found:
                what, write = found
                raise InputFileError(f"{item.label}: {column} '{given}' {what} (a Windows path?), which "
                                     "names no file here", path=path,
                                     fix="write the manifest's paths as this machine names them, with '/' "
                                         f"(relative to the manifest, or absolute here): {write}")


def _manifest_text(path: Path) -> str:
    """A manifest file's text: UTF-8 (a spreadsheet's "CSV UTF-8" byte-order mark dropped) or UTF-16 with
    its byte-order mark (a spreadsheet's "Unicode Text"). A spreadsheet workbook (``.xlsx``/``.ods``: a zip)
    or text in another encoding is refused naming the file and how to save it (a traceback before)."""
    data = path.read_bytes()
    if data.startswith(b"PK\x03\x04"):
        raise InputFileError("manifest is a spreadsheet workbook (a zip file such as .xlsx or .ods), not "
                             "CSV text", path=path,
                             fix="save the sheet as 'CSV UTF-8' (or CSV) and pass that file")
    try:
        if data.startswith((b"\xff\xfe", b"\xfe\xff")):
            return data.decode("utf-16")
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputFileError(f"manifest is not UTF-8 text (byte {exc.start} cannot be read: another "
                             "encoding, or not a text file)", path=path,
                             fix="save the manifest as 'CSV UTF-8' (or JSON) in UTF-8") from None


def _separator(text: str) -> str:
    """The CSV separator of a manifest's header row, of ``,``, ``;`` and tab: the one whose split names every
    required column, else :class:`csv.Sniffer` on that row
    alone (the cells below may hold a decimal comma or a ``;`` in a path), ``,`` when it finds none of them
    (its refusal then lists the columns). The first rule alone split a ``;`` header with a misspelt column
    on ``,`` and refused it as one column; the Sniffer alone split a ``;`` header with a comma in a column's
    name on ``,`` (stop 53)."""
    first = next((line for line in text.splitlines() if line.strip() and not _comment(line)), "")
    # a split naming every required column first: the Sniffer prefers "," whenever the row holds one, and a
    # ";" or tab header with a comma inside a column's name ("notes, misc") was refused (stop 53's review)
    for sep in (",", ";", "\t"):
        if set(REQUIRED) <= {f.strip().strip('"').lower() for f in first.split(sep)}:
            return sep
    try:
        return csv.Sniffer().sniff(first, delimiters=",;\t").delimiter
    except csv.Error:
        return ","


def _comment(line: str) -> bool:
    """Whether a manifest's text line is a comment: its first character other than a space or a tab is
    ``#``, as in a shell script (a quoted ``"#1/anna.usdc"`` first cell
    too: a row whose first path starts with ``#`` puts another column first)."""
    return line.lstrip(" \t").startswith("#")


def _csv_rows(text: str, delimiter: str):
    """Yield ``(line, cells)`` for each row of a CSV manifest's ``text``, ``line`` the file's line (from 1)
    the row starts on. A comment line (:func:`_comment`) and a blank line between rows are no rows (a
    comment row was refused as 'item N lacks ...'); a line inside a quoted cell over several lines is the
    cell's, whatever it starts with."""
    import io

    state = {"line": 0, "start": 0}

    def lines():
        for line in io.StringIO(text, newline=""):
            state["line"] += 1
            if not state["start"]:                        # between rows: the next row's first line
                if not line.strip() or _comment(line):
                    continue
                state["start"] = state["line"]
            yield line

    reader = csv.reader(lines(), skipinitialspace=True, delimiter=delimiter)
    while True:
        state["start"] = 0
        try:
            cells = next(reader)
        except StopIteration:
            return
        yield state["start"], cells


def read_manifest(path) -> list[BatchItem]:
    """Read a batch manifest (``.csv`` or ``.json``); paths resolved against the manifest's folder.

    A CSV manifest's comment lines (first character ``#``) and blank lines are skipped; an item's
    :attr:`BatchItem.line` is the file's line its row starts on (a message names it when it is not the
    line ``item N`` suggests).

    Raises :class:`usdface.errors.InputFileError` for a missing file, a missing column/field, an empty
    manifest, or two items writing the same output.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError("batch manifest not found", path=path,
                             fix="pass a CSV (avatar,capture,output) or JSON manifest")
    base = Path(os.path.abspath(path.parent))
    text = _manifest_text(path)
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputFileError(f"manifest is not valid JSON ({exc.msg}, line {exc.lineno})", path=path,
                                 fix="fix the JSON syntax") from None
        rows = data.get("items") if isinstance(data, dict) else data
        if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
            raise InputFileError("JSON manifest must be a list of objects (or {\"items\": [...]})", path=path,
                                 fix='write [{"avatar": ..., "capture": ..., "output": ...}, ...]')
        rows = [(0, r) for r in rows]                     # no line: a JSON item is named by its place
    else:
        # utf-8-sig: a spreadsheet's "CSV UTF-8" starts with a byte-order mark; skipinitialspace and the
        # stripped header: "avatar, capture, output" names the columns too
        # a spreadsheet in a locale with a decimal comma saves "CSV" with semicolons, and "Unicode Text"
        # with tabs: the separator that makes the header name the required columns. Comment and blank
        # lines skipped (_csv_rows), before the header too
        found = _csv_rows(text, _separator(text))
        # a spreadsheet's capitalised header ("Avatar,Capture,Output", "Method") names the columns too:
        # every column usdface reads is a lower-case name (stop 47, h52: it was 'lacks column(s)')
        fieldnames = [f.strip().lower() for f in next(found, (0, []))[1]]
        twice = sorted({f for f in fieldnames if f and fieldnames.count(f) > 1})
        if twice:              # a row's dict would keep the last of two same-named columns without a word
            raise InputFileError(f"manifest has the column(s) {twice} twice (case aside)", path=path,
                                 fix="keep one column of each name in the first row")
        missing = [c for c in REQUIRED if c not in fieldnames]
        if missing:
            raise InputFileError(f"manifest lacks column(s) {missing} (has {fieldnames})",
                                 path=path, fix="first row: avatar,capture,output[,options]")
        # cells past the header's columns are dropped, a short row's missing cells are empty
        rows = [(line, {k: _coerce(v) if k not in REQUIRED else v
                        for k, v in zip(fieldnames, row, strict=False) if v not in (None, "")})
                for line, row in found]
        rows = [(line, r) for line, r in rows if r]      # a spreadsheet's trailing ",,," rows are no items
    items, cells = [], []
    for i, (line, row) in enumerate(rows):
        item = BatchItem("", "", "", {}, i, line)
        missing = [c for c in REQUIRED if not row.get(c)]
        if missing:
            raise InputFileError(f"{item.label} lacks {missing}", path=path,
                                 fix="give every item an avatar, a capture and an output")
        resolved = {c: _absolute(base, row[c]) for c in REQUIRED}
        options = {k: (_absolute(base, v) if k in PATH_OPTIONS and isinstance(v, str) and v else v)
                   for k, v in row.items() if k not in REQUIRED}
        item = BatchItem(resolved["avatar"], resolved["capture"], resolved["output"], options, i, line)
        cells.append((item, row, {**resolved, **options}))
        items.append(item)
    if not items:
        raise InputFileError("manifest lists no items", path=path, fix="add one row per avatar")
    _refuse_windows_paths(path, base, cells)
    _refuse_outputs_over_inputs(items, path)
    return items


#: The manifest column (and Pyblish instance data) that asks for the review page beside the layer: no
#: personalize option, taken by the batch's worker and the Pyblish review extractor alike.
REVIEW = "review"
#: The key of a batch item (the dict a worker gets) whose layer is finished and whose row asks for a review
#: page that is not there (a ``review`` column added after the row was done; a page removed): resume writes
#: the page alone (:func:`personalize_worker`), where it was a ``StaleOutput`` (stop 53).
REVIEW_ONLY = "review_only"
#: How a review cell is given (the fix of a bad one).
REVIEW_FIX = ("write the manifest's review column as true or false (or leave the cell empty: no page); the "
              "page is always <layer>.review.html beside the layer")


def review_flag(options: dict, whose: str = "the row's", fix: str = REVIEW_FIX) -> bool:
    """Whether ``options`` (a batch row's) ask for the review page: ``review`` True or False (``None`` or
    absent: False), anything else refused (:func:`usdface.errors.expect_flag`, as a Pyblish instance's
    ``review`` is checked): a word counted as true would write a page the row did not ask for."""
    return _flag(options.get(REVIEW), REVIEW, whose, fix)


def review_page(layer) -> Path:
    """Where the review page of ``layer`` goes: ``<layer stem>.review.html`` beside it, the name
    ``usdface review`` gives it by default (the batch and the Pyblish extractor use this one rule)."""
    from ..commands.review import default_output

    return default_output(layer)


def check_review_page(layer, force: bool, inputs=()) -> Path:
    """The review page of ``layer`` checked before any work, as :func:`usdface.api.write_review` will check
    it (an HTML name, not one of ``inputs``, not an existing file without ``force``, a place that takes it:
    :func:`usdface.io.atomic.check_output_file`); the Pyblish outputs' validator and the batch's preflight
    both run it. Returns the page's path."""
    from ..io.atomic import check_output_file

    return check_output_file(review_page(layer), force, suffixes=(".html", ".htm"), what="review page",
                             inputs=list(inputs))


def write_review_page(layer, capture, take=None, force: bool = False) -> Path:
    """Write the review page of the written ``layer`` beside it (:func:`review_page`) with the item's
    ``capture`` and ``take`` (the one the layer plays): :func:`usdface.api.write_review`, the page a Pyblish
    publish attaches (``ExtractUsdFaceReview``) and a batch row with ``review`` true writes. Returns its
    path.

    The page is checked first (:func:`check_review_page`: a refusal leaves every file as it is). With
    ``force``, a page already there is the review of the layer ``force`` has just replaced: when the new one
    then fails, that page is removed (the error says so), so no page claims to be the new layer's review;
    it stayed, and the next batch run skipped the row as done with it (stop 53)."""
    from ..api import write_review
    from ..errors import add_to_message

    page = check_review_page(layer, force, inputs=[layer, capture, take])
    try:
        return write_review(layer, page, capture=capture, take=take, force=force)
    except BaseException as exc:
        if force and os.path.lexists(page) and not os.path.isdir(page):
            try:
                os.unlink(page)
                add_to_message(exc, f"the earlier review page {page.name} was removed: it reviewed the layer "
                                    "this run replaced")
            except OSError as err:
                add_to_message(exc, f"the earlier review page {page.name} reviews the layer this run "
                                    f"replaced and could not be removed ({err}): delete it")
        raise


def check_item_inputs(item: BatchItem) -> None:
    """The files a personalize item reads, refused as its readers would refuse them but before the batch's
    first item (a bad last row failed at its turn, after every row before it had run): the avatar a
    readable USD file, the capture a capture folder, take or capture USD file
    (:func:`usdface.io.check_capture_path`; not a rig, :func:`usdface.io.usd_capture.refuse_rig_as_capture`,
    nor a capture or take as the avatar), the ``take`` a take (:func:`usdface.io.take.check_take_path`:
    an avatar given as the take failed only at the item), and the ``name_map`` and ``pins`` a row names
    existing (the correspondence cache may be missing: the item writes it). Raises the reader's error."""
    from ..io import USD_EXTENSIONS, check_capture_path
    from ..io.take import check_take_path
    from ..io.usd_capture import refuse_rig_as_capture
    from ..io.usd_open import require_readable
    from ..io.usd_rig import refuse_recorded_non_avatar

    avatar = require_readable(item.avatar, "avatar", fix="give the avatar's .usd/.usda/.usdc file")
    if avatar.suffix.lower() not in USD_EXTENSIONS:
        raise InputFileError("avatar is not a USD file", path=avatar,
                             fix=f"give the avatar's USD file ({', '.join(USD_EXTENSIONS)})")
    refuse_recorded_non_avatar(avatar)             # a capture or take in the avatar column
    capture = check_capture_path(item.capture)
    if capture.is_file():
        refuse_rig_as_capture(capture)             # an avatar (or a fit) in the capture column
    take = item.options.get("take")
    if isinstance(take, str) and take:
        check_take_path(take)
    for key, what, kinds in (("name_map", "name map", ".json or .csv"),
                             ("pins", "pins file", ".json or .usd")):
        if isinstance(item.options.get(key), str) and item.options[key]:
            require_readable(item.options[key], what, fix=f"give an existing {what} ({kinds})")


_DIGESTS: dict = {}


def _digest(path) -> str:
    """:func:`usdface.io.layers.file_digest`, remembered per (real path, size, modification time): a shared
    avatar behind a thousand rows of a resumed batch is hashed once."""
    from ..io.layers import file_digest

    st = os.stat(path)
    key = (os.path.realpath(path), st.st_size, st.st_mtime_ns)
    if key not in _DIGESTS:
        _DIGESTS[key] = file_digest(path)
    return _DIGESTS[key]


#: How a stale output is redone (a ``StaleOutput``'s last words): ``--force`` alone redoes every row of the
#: batch, hours on a long manifest for the one row a TD meant (until stop 51 the line said only that).
_REDO = ("to redo this row alone, move the output away (or delete it), or set the row's force column to "
         "true, and run the batch again; --force redoes every row")


def stale_output(item: BatchItem) -> str:
    """Why an existing ``item.output`` is not this item's finished result ("" if it is, or if it cannot
    tell): a usdface layer records its inputs and their sha256 (``customLayerData["usdface"]``); one written
    from another avatar or capture than the row names, or from files changed since, is not a finished item
    that resume may skip, and neither is a file USD cannot read (cut off). Other outputs that are not
    usdface layers (a studio worker's) are taken as finished."""
    out = Path(item.output)
    if out.suffix.lower() not in (".usd", ".usda", ".usdc") or not out.is_file():
        return ""
    from pxr import Sdf

    from ..io.layers import input_changed, recorded_inputs
    from ..io.usd_rig import usdface_output_provenance

    try:                                          # a layer cut off (a full disk, a killed copy) is no result
        layer = Sdf.Layer.FindOrOpen(str(out))
    except Exception:  # noqa: BLE001  (pxr.Tf.ErrorException: USD's parse error)
        layer = None
    if layer is None:
        return (f"{out.name} exists but USD cannot read it (a write cut off?): not a finished result; "
                f"{_REDO}")
    record = usdface_output_provenance(out)       # read once: the inputs and the options it records
    if record is None:
        return ""
    recorded = recorded_inputs(out, record)
    shown = ", ".join(sorted(recorded))
    options = item.options or {}
    take = _row_take(options)
    for what, path in (("avatar", item.avatar), ("capture", item.capture), ("take", take)):
        if path is None:                                              # no take on the row
            continue
        real = os.path.realpath(path)
        if real not in recorded:
            return (f"{out.name} exists but was written from another {what} than {path} (it records "
                    f"{shown}): not this item's result; {_REDO}")
        if input_changed(path, recorded[real], _digest):
            return (f"{out.name} exists but the {what} {path} changed after it was written (sha256 differs): "
                    f"{_REDO}")
    own = (os.path.realpath(item.avatar), os.path.realpath(item.capture))
    others = [real for real in recorded if real not in own]          # the inputs besides avatar and capture
    changed = (_changed_option(options, record) or _changed_face_mesh(options, record)
               or _changed_inspection(options, record, layer, others))
    if changed:
        key, was, wanted = changed
        return (f"{out.name} exists but was written with {key}={was}, the row asks {key}={wanted}: not this "
                f"item's result; {_REDO}")
    return ""


def row_review(item: BatchItem | dict) -> tuple[Path | None, bool]:
    """The review page ``item``'s row asks for (its ``review`` option true; ``item`` a :class:`BatchItem` or
    its dict) and whether it is there; ``(None, False)`` when the row asks none. The one rule behind the
    report's ``review`` and resume's missing page (two near copies until stop 53)."""
    options = (item.options if isinstance(item, BatchItem) else item.get("options")) or {}
    if not review_flag(options):
        return None, False
    page = review_page(item.output if isinstance(item, BatchItem) else item["output"])
    return page, os.path.lexists(page)


_MISSING = object()


@functools.cache
def _personalize_defaults() -> dict:
    """The defaults of :func:`usdface.transfer.personalize_avatar`'s options, and of the fit's it records
    (``contact``), read once per process."""
    import inspect as _inspect

    from ..personalize.api import fit_personalized_shapes
    from ..transfer.pipeline import personalize_avatar

    def defaults(fn):
        return {k: v.default for k, v in _inspect.signature(fn).parameters.items()
                if v.default is not _inspect.Parameter.empty}

    return {**defaults(fit_personalized_shapes), **defaults(personalize_avatar)}


def _changed_face_mesh(options: dict, record: dict) -> tuple[str, str, str] | None:
    """``("face_mesh", recorded, asked)`` when the row names a face mesh (a prim name or path) that is not
    the one the layer records having personalized (``faceMesh``); None when they agree, the row names none
    (the automatic choice is the avatar's, unchanged when its digest is) or the layer records none (written
    before it was recorded). Not among ``parameters``: the resolved prim is no option value, and an edited
    row's face mesh was ignored by resume (the old layer skipped as done)."""
    asked, was = options.get("face_mesh"), record.get("faceMesh")
    if not asked or not isinstance(was, str) or not was:
        return None
    asked = str(asked)
    same = was == asked if asked.startswith("/") else was.rsplit("/", 1)[-1] == asked
    return None if same else ("face_mesh", was, asked)


def _changed_inspection(options: dict, record: dict, layer, others: Iterable[str] = ()
                        ) -> tuple[str, str, str] | None:
    """``(option, what the layer holds, asked)`` when the row's ``inspect``, ``landmarks`` or ``take`` asks
    for other inspection data than the layer ``layer`` (an ``Sdf.Layer``) holds
    (:func:`usdface.io.usd_inspection.layer_inspection`: its heat map, landmark layout), or a take where it
    records none (``record``, its provenance) or none where it records one; None when they agree. Not among
    the recorded ``parameters`` (the API's options, not the pipeline's), so read from what the layer holds:
    the same for layers written before and after this check (a row that added ``inspect`` was skipped as
    done over a layer without the inspection data). ``take`` and ``landmarks`` imply ``inspect``, as
    :func:`usdface.api.personalize_avatar` runs them; the take's file itself is compared with the inputs
    (:func:`stale_output` did, against the layer's inputs). A layer written before the record named its
    take (``take``, 2026-12-05) holds the take among its inputs alone: the row's take found among ``others``
    (the layer's inputs by real path, besides the row's avatar and capture) is the one it records (stop 50
    had it 'written with take=None' and redone)."""
    from ..io.usd_inspection import layer_inspection

    take = _row_take(options)
    landmarks = _flag(options.get("landmarks"), "landmarks")
    held = layer_inspection(layer)
    inspect = _flag(options.get("inspect"), "inspect") or landmarks or bool(take)
    for key, has, wanted in (("inspect", held["heat"], inspect), ("landmarks", held["landmarks"], landmarks)):
        if has != wanted:
            return key, str(has), str(wanted)
    was = record.get("take") or (take if take and "take" not in record
                                 and os.path.realpath(take) in set(others) else None)
    if bool(was) != bool(take):
        return "take", str(was), str(take)
    return None


def redoes(item: BatchItem, force: bool = False) -> bool:
    """Whether ``item`` runs even where its output exists: the batch's ``force``, or the row's own ``force``
    column true (a Pyblish publish of the same manifest replaces that row's layer and review page; the batch
    resumed it as done). The cell is read as the worker reads it (:func:`_flag`): one neither true nor false
    is an :class:`usdface.errors.OptionError`, whatever the batch's ``force``."""
    row = _flag((item.options or {}).get("force"), "force")
    return bool(force) or row


def _row_take(options: dict) -> str | None:
    """A row's ``take`` option as a path string; None where the row sets none (absent, empty, not a path)."""
    take = options.get("take")
    return str(take) if isinstance(take, str | os.PathLike) and str(take) else None


def _flag(value, name: str, whose: str = "the row's", fix: str | None = None) -> bool:
    """A row's boolean cell ``name`` as the API reads it (:func:`usdface.errors.expect_flag`: numpy's booleans
    too; ``is True`` called ``numpy.True_`` false; empty: false); any other value an
    :class:`usdface.errors.OptionError` naming the column (``whose``, ``fix``: default the manifest's). The
    one reading of a row's cell by resume, by the worker and by :func:`review_flag` (stop 54: resume took a
    ``force`` cell ``sure`` as not set and skipped the done row, while the worker refused the same cell on a
    row not yet done)."""
    from ..errors import expect_flag

    if fix is None:
        fix = f"write the manifest's {name} column as true or false (or leave the cell empty: false)"
    return expect_flag(value, name, whose, False, fix)


def _changed_option(options: dict, record: dict) -> tuple[str, str, str] | None:
    """``(option, recorded, asked)`` for the first personalize option (those the row sets first) whose value
    a layer's provenance ``record`` holds (``parameters``: every option, resolved) differently from what the
    row asks, the defaults of :func:`usdface.transfer.personalize_avatar` standing for options the row leaves
    out (a row that drops ``method=dt`` asks for the default again); None when they agree or the layer
    records none."""
    params = record.get("parameters")
    if isinstance(params, str):
        try:
            params = json.loads(params)
        except ValueError:
            return None
    if not isinstance(params, dict):
        return None
    from ..transfer.options import default_approximation

    defaults = dict(_personalize_defaults())
    # the approximation a row leaves out is its face transfer's (as the API and the CLI resolve it)
    defaults["approximation"] = default_approximation(options.get("face_transfer", defaults["face_transfer"]))
    # the options the row sets first: a changed face_transfer is named, not the approximation that follows it
    for key, was in sorted(params.items(), key=lambda kv: (kv[0] not in options, kv[0])):
        wanted = options.get(key, defaults.get(key, _MISSING))
        if wanted is not _MISSING and not _same_value(was, wanted):
            return key, str(was), str(wanted)
    return None


def _same_value(a, b) -> bool:
    """Whether a recorded option value and a manifest's (or a default) are the same setting: numbers
    compared as numbers (``"1e-3"`` is ``0.001``, ``(0.01, 0.03)`` is ``"0.01,0.03"``), booleans and words
    as words (case-insensitive), ``None`` as ``"None"``."""
    import re

    def numbers(v):
        text = str(v).strip()
        if re.fullmatch(r"[\s()\[\],+\-.eE0-9]*", text) and re.search(r"\d", text):
            try:
                return [float(x) for x in re.findall(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?", text)]
            except ValueError:
                return None
        return None

    na, nb = numbers(a), numbers(b)
    if na is not None and nb is not None:
        return len(na) == len(nb) and all(abs(x - y) <= 1e-9 * max(1.0, abs(x), abs(y))
                                          for x, y in zip(na, nb, strict=True))
    return str(a).strip().lower() == str(b).strip().lower()


# ----------------------------------------------------------------------------------------------- workers
def personalize_worker(item: dict):
    """The default worker: :func:`usdface.api.personalize_avatar` on one item (``force`` the batch's or the
    row's; item options such as ``method`` or ``inspect`` pass through), then with ``review`` true the review
    page beside the layer (:func:`write_review_page`, as the Pyblish extractor writes it); returns
    personalize's result (the report's ``warnings`` go to the item's). An item marked :data:`REVIEW_ONLY`
    (resume: its layer finished, its page missing) gets the page alone."""
    from ..api import personalize_avatar

    options = dict(item.get("options") or {})
    review = review_flag(options)                    # the page beside the layer: no personalize option
    options.pop(REVIEW, None)
    if item.get(REVIEW_ONLY):          # a finished layer whose row now asks its page: the page alone
        return write_review_page(item["output"], item["capture"], take=_row_take(options))
    # the batch's --force redoes every row, a row's force true its own (docs/pipeline.md): a row's false (or
    # empty) cell adds nothing; it was passed on as force=False, and personalize refused the layer --force
    # was redoing (stop 53)
    # (the cell read as resume reads it, _flag: a word it cannot read is refused, not taken as unset)
    options["force"] = _flag(options.get("force"), "force") or bool(item.get("force", False))
    options.setdefault("command", f"usdface batch, item {int(item.get('index', 0)) + 1} "
                                  "(usdface.pipeline.batch.personalize_worker)")
    result = personalize_avatar(item["avatar"], item["capture"], item["output"], **options)
    if review:      # a failure fails the item, and run_item sets aside the layer it wrote: all or nothing
        layer = Path(getattr(result, "out_path", None) or item["output"])
        write_review_page(layer, item["capture"], take=_row_take(options), force=bool(options["force"]))
    return result


def load_worker(spec: str) -> Callable[[dict], object]:
    """Import a worker given as ``"package.module:function"``."""
    import importlib

    from ..errors import UsdFaceError

    module, _, name = spec.partition(":")
    try:
        fn = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError) as exc:
        raise UsdFaceError(f"cannot load batch worker {spec!r}: {exc}",
                           fix="give an importable MODULE:FUNCTION") from None
    if not callable(fn):
        raise UsdFaceError(f"batch worker {spec!r} is not callable", fix="give an importable MODULE:FUNCTION")
    return fn


def run_item(worker: Callable[[dict], object], item: dict) -> dict:
    """Run ``worker(item)`` and return an :class:`ItemResult` as a dict; never raises (failure isolation)."""
    from ..io.atomic import make_parents

    start, cpu = time.perf_counter(), time.process_time()
    base = {k: item[k] for k in ("index", "avatar", "capture", "output")}
    out = Path(item["output"])
    existed = out.exists()
    # the output's folders made for every worker, as personalize makes them (a studio's --worker got a
    # manifest's out/anna.usda with no out/ and failed FileNotFoundError). Not taken away here when the item
    # fails: another item running beside it may be about to write into them (run_batch takes away the empty
    # ones when every item has ended)
    try:
        make_parents(out)
    except OSError:
        pass                        # the worker's own write names what refuses the place
    # the item's warnings go to its result (the report, and the batch's own lines naming the item), not to
    # the worker's stdout/stderr unattributed: collected per thread (a Dask worker's threads run items side
    # by side), with the host's warning filters as they are
    caught = []
    with _ITEM_WARNINGS:
        _ITEM.notes = caught
        try:
            value = worker(item)
        except BaseException as exc:  # noqa: BLE001  (isolation: anything an item does is reported, not raised)
            value = exc
        finally:
            _ITEM.notes = None
    base["warnings"] = _item_notes(caught, value)
    if isinstance(value, BaseException):
        exc = value
        if isinstance(exc, KeyboardInterrupt):
            raise exc
        error = "; ".join([str(exc), *(n for n in getattr(exc, "__notes__", ()) if isinstance(n, str))])
        # a worker that wrote its output, then failed: not a result. The output refused as existing was
        # written by someone else meanwhile (the same manifest run twice at once): theirs, left in place
        # (a file there: a link to nothing the worker refused is no other run's, stop 54)
        theirs = isinstance(exc, OutputExistsError) and exc.path is not None and \
            Path(exc.path).absolute() == out.absolute() and out.exists()
        if not existed and out.exists() and not theirs:
            error += f" (its output was written before the failure: moved to {set_aside(out).name})"
        elif theirs and not existed:    # its fix said 'pass --force', as if to redo the other run's work
            error += (" (written meanwhile by another run of this output, the same manifest run twice at "
                      "once: left in place, and the next run skips it; --force is needed only to redo it)")
        return dict(base, status=FAILED, seconds=time.perf_counter() - start,
                    cpu_seconds=time.process_time() - cpu, error=error, error_type=type(exc).__name__,
                    traceback="".join(traceback.format_exception(exc)))
    if not os.path.lexists(out):
        # returned without its output: not done (the report said 'done' and resume ran it again each time)
        name = getattr(worker, "__qualname__", None) or repr(worker)
        error = (f"{out}: the batch worker {getattr(worker, '__module__', '?')}:{name} returned without "
                 "writing the item's output (fix: the worker must write item['output'], the file resume "
                 "takes as the item's result; or raise to fail the item)")
        return dict(base, status=FAILED, seconds=time.perf_counter() - start,
                    cpu_seconds=time.process_time() - cpu, error=error, error_type="NoOutput")
    page, there = row_review(item)
    return dict(base, status=DONE, seconds=time.perf_counter() - start, cpu_seconds=time.process_time() - cpu,
                review=str(page) if there else "")


_ITEM = threading.local()           # .notes: the running item's warnings on this thread (run_item), or None


def _install_item_warnings() -> dict:
    """A :func:`warnings.showwarning` that gives a warning shown while an item runs on this thread to that
    item (:func:`run_item`) and passes every other one on to what was installed before, and usdface's own
    warnings shown every time (``always``, appended after the host's filters: the same note on two items of
    one process reaches both). The filters stay the host's (``-W error`` still fails the item; hidden
    warnings stay hidden). Returns what :func:`_remove_item_warnings` takes away."""
    import warnings

    previous = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        notes = getattr(_ITEM, "notes", None)
        if notes is None:
            return previous(message, category, filename, lineno, file, line)
        notes.append(str(message))

    from ..errors import UsdFaceWarning

    before = list(warnings.filters)
    warnings.filterwarnings("always", module=r"usdface(\.|$)", append=True)
    # usdface's own warnings name the caller's line (usdface.errors.warn), in the host's module: by category
    warnings.filterwarnings("always", category=UsdFaceWarning, append=True)
    added = [f for f in warnings.filters if f not in before]
    warnings.showwarning = show
    return {"previous": previous, "show": show, "filters": added}


def _remove_item_warnings(installed: dict) -> None:
    import warnings

    if warnings.showwarning is installed["show"]:   # not replaced meanwhile by someone else
        warnings.showwarning = installed["previous"]
    for added in installed["filters"]:
        if added in warnings.filters:
            warnings.filters.remove(added)
            getattr(warnings, "_filters_mutated", lambda: None)()


#: While any item runs in this process, its warnings go to it (:func:`_install_item_warnings`): installed by
#: the first item running and removed when the last one ends (items of a Dask worker's threads overlap); a
#: batch run in the host's process (``jobs=1``) left both behind, the host's ``showwarning`` replaced and its
#: filters changed for good.
_ITEM_WARNINGS = SharedWhileInside(_install_item_warnings, _remove_item_warnings)


def _item_notes(caught, value) -> list[str]:
    """The item's warnings, each once: those shown while it ran, then its result's own report notes
    (``value.report["warnings"]``, a personalize result's), strings only; never raises."""
    try:
        report = getattr(value, "report", None)
        own = report.get("warnings") if isinstance(report, dict) else None
        own = [n for n in own if isinstance(n, str)] if isinstance(own, list | tuple) else []
        return list(dict.fromkeys([str(n) for n in caught] + own))
    except Exception:  # noqa: BLE001  (a worker's odd return value must not fail the batch)
        return [str(n) for n in caught]


def set_aside(out: Path) -> Path:
    """Move the output a failed item left to ``<output>.failed`` (replacing an earlier one), so that resume,
    which takes an existing output as finished, runs the item again; returns the new path (the Pyblish layer
    extractor sets aside a layer that fails its re-check the same way)."""
    import shutil

    aside = out.with_name(out.name + ".failed")
    if aside.is_dir() and not aside.is_symlink():
        shutil.rmtree(aside)
    elif aside.exists() or aside.is_symlink():
        aside.unlink()
    os.replace(out, aside)
    return aside


def _crashed(item: dict, exc: BaseException) -> dict:
    base = {k: item[k] for k in ("index", "avatar", "capture", "output")}
    return dict(base, status=FAILED, error=f"worker crashed: {exc}", error_type=type(exc).__name__,
                traceback="".join(traceback.format_exception(exc)))


# ----------------------------------------------------------------------------------------------- runners
def _run_serial(worker, todo):
    for item in todo:
        res = run_item(worker, item)
        yield res


#: Thread-count variables set in every pool worker before numpy loads: the pool's processes are the
#: parallelism, and a BLAS per process using every core oversubscribes the machine.
WORKER_THREAD_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
#: Modules a personalize worker imports up front (what one personalize run loads).
PRELOAD = ("usdface.api", "usdface.io.usd_rig", "usdface.io.layers", "usdface.personalize",
           "usdface.transfer",
           "scipy.sparse.linalg", "scipy.spatial", "open3d")


def _die_with_parent() -> None:
    """Linux: this pool worker gets SIGTERM when the batch process dies, even by SIGKILL (a farm's hard
    kill left the workers running, ~290 MB each, until killed by hand): ``prctl(PR_SET_PDEATHSIG)``.
    Elsewhere nothing (no such call)."""
    import ctypes
    import ctypes.util
    import signal
    import sys

    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)              # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() == 1:          # the parent died before the call: nothing would signal us
        os.kill(os.getpid(), signal.SIGTERM)


def init_worker(preload: tuple[str, ...] = PRELOAD) -> None:
    """Pool worker start-up: one BLAS thread per worker, and the heavy modules (USD, numpy/scipy, Open3D via
    the transfer) imported once here rather than inside the first item's timing."""
    import importlib

    from .. import progress

    progress.set_enabled(False)  # the parent reports per item; N workers' step lines would interleave
    _die_with_parent()
    for name in WORKER_THREAD_ENV:
        os.environ.setdefault(name, "1")
    for module in preload:
        try:
            importlib.import_module(module)
        except ImportError:  # a missing optional stack is the item's error to report, not the pool's
            pass
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")  # for any BLAS loaded before the variables were set
    _stop_cleanly_on_signals()


class _WorkerStopped(KeyboardInterrupt):
    """A pool worker's SIGTERM (the batch stopped: ``_stop_pool``'s ``terminate()``, or the parent's death
    through ``PR_SET_PDEATHSIG``) or SIGHUP, raised inside an item so that its atomic writes clean up."""


#: Whether this pool worker process is inside an item now (:func:`_pool_item`).
_IN_ITEM = threading.Event()
#: Whether this pool worker process has been told to stop (:func:`_stop_cleanly_on_signals`).
_STOPPING = threading.Event()


def _stop_cleanly_on_signals() -> None:
    """Pool worker: SIGTERM and SIGHUP end the process once the running item's writes have cleaned up.

    By their default action they killed the worker at once: a batch stopped (Ctrl-C, a farm's SIGTERM) while
    an item was writing left the write's hidden temporary file in the output folder
    (``out/.anna.usda.t5_8lor8.tmp.usda``). Inside an item the signal raises :class:`_WorkerStopped`, whose
    way out runs the writers' clean-up (:func:`_pool_item` then ends the process); between items there is
    nothing to clean up and the process ends at once. A signal ignored at start stays ignored.

    Only the first signal stops the item: a worker can be signalled more than once (``PR_SET_PDEATHSIG`` fires
    each time the worker's parent *thread* exits, and a killed batch's threads exit one by one, each passing
    the worker on to the next; or a farm sends SIGTERM twice), and a second raise inside the clean-up skipped
    it, leaving the temporary file. Later signals are ignored while the clean-up runs.

    Wherever the kernel delivers the signal, it is seen: :func:`_watch_stop_signals`."""
    import signal

    def stop(signum, frame):
        if _STOPPING.is_set():       # already stopping: let the clean-up finish, then the process ends
            return
        if _IN_ITEM.is_set():
            _STOPPING.set()
            raise _WorkerStopped()
        os._exit(128 + signum)

    taken = set()
    for name in ("SIGTERM", "SIGHUP"):
        signum = getattr(signal, name, None)
        if signum is not None and signal.getsignal(signum) is not signal.SIG_IGN:
            signal.signal(signum, stop)
            taken.add(int(signum))
    _watch_stop_signals(taken)


#: The write end of the pool worker's signal wake-up pipe (:func:`_watch_stop_signals`), or None.
_WAKEUP_FD: int | None = None


def _watch_stop_signals(signums: set) -> None:
    """Pool worker: a thread that sees every stop signal (``signums``) whichever thread the kernel hands it
    to, and makes sure it stops the worker.

    A process-wide signal (the batch's ``terminate()``, the parent's death through ``PR_SET_PDEATHSIG``)
    goes to any thread that does not block it, and the worker has native threads (2 once
    :func:`init_worker` has imported its modules, one more USD starts inside a personalize item, on this
    machine class). Python runs a signal's handler only in the main thread, once it next runs Python code:
    a signal one of those threads took was never handled while the main thread stayed blocked - an idle
    worker reading the pool's call queue, or an item in one long sleep (the killed-batch test's stand-in
    item outlived the batch in about one run of five until stop 48). Python's own C handler
    writes the signal's number to the wake-up file (:func:`signal.set_wakeup_fd`) on whatever thread it
    runs; this thread reads it and ends an idle worker at once (nothing to clean up), or sends the signal
    to the main thread (``pthread_kill``: a blocking call there is interrupted and the handler raises), and
    ends the process should the item finish first. Blocking the signals in the native threads instead
    (a mask set while the imports start them) misses the threads a library starts later, inside an item.
    Not where ``pthread_kill`` is missing (Windows: no such signals)."""
    import signal

    global _WAKEUP_FD
    if not signums or not hasattr(signal, "pthread_kill"):
        return
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)            # set_wakeup_fd's rule: a full pipe must not block a handler
    signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    _WAKEUP_FD = write_fd
    threading.Thread(target=_forward_stop_signals, args=(read_fd, signums, threading.main_thread().ident),
                     name="usdface-stop-signals", daemon=True).start()


def _forward_stop_signals(read_fd: int, signums: set, main: int) -> None:
    """The thread of :func:`_watch_stop_signals`: for the first stop signal read from the wake-up pipe, end
    the idle worker, or send it on to the ``main`` thread and end the process once the item is over (its
    clean-up ends the process first when the signal stops it)."""
    import signal
    import time

    while True:
        signum = next((b for b in os.read(read_fd, 64) if b in signums), None)
        if signum is None:
            continue
        if not _IN_ITEM.is_set():
            os._exit(128 + signum)
        signal.pthread_kill(main, signum)       # reaches the main thread wherever the kernel delivered it
        while _IN_ITEM.is_set():                # the item's clean-up ends the process; an item that ended
            time.sleep(0.05)                    # on its own meanwhile ends it here
        os._exit(128 + signum)


def _pool_item(worker: Callable[[dict], object], item: dict) -> dict:
    """:func:`run_item` in a pool worker process; stopped by a signal (:func:`_stop_cleanly_on_signals`),
    the process ends once the item's clean-up has run (the pool is being shut down: no result is wanted)."""
    if _WAKEUP_FD is not None:                  # an item's event loop may have taken the wake-up file over
        import signal

        signal.set_wakeup_fd(_WAKEUP_FD, warn_on_full_buffer=False)
    _IN_ITEM.set()
    try:
        return run_item(worker, item)
    except _WorkerStopped:
        import signal

        os._exit(128 + signal.SIGTERM)
    finally:
        _IN_ITEM.clear()


def _run_pool(worker, todo, jobs):
    """The items on one shared pool of ``jobs`` processes. A worker process that dies (an out-of-memory
    kill, a crash in native code) breaks the whole pool, and every item not finished by then fails with it
    through no fault of its own: those items are run again, each in a process of its own (``jobs`` at a
    time, :func:`_run_isolated`), so the one that kills its process fails alone and the rest finish."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    again = []
    # spawn, not fork: USD and Open3D start threads, and forking a threaded process can deadlock.
    with ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn"),
                             initializer=init_worker) as pool:
        futures = {pool.submit(_pool_item, worker, item): item for item in todo}
        try:
            for fut in as_completed(futures):
                item = futures[fut]
                try:
                    res = fut.result()
                except BrokenProcessPool:
                    again.append(item)
                    continue
                except Exception as exc:  # the item's result could not come back (pickling...)
                    res = _crashed(item, exc)
                yield res
        except BaseException:        # Ctrl-C, SIGTERM: stop now, not after every queued item has run
            _stop_pool(pool)
            raise
    if again:
        yield from _run_isolated(worker, sorted(again, key=lambda it: it["index"]), jobs)


def _stop_pool(pool) -> None:
    """Cancel a process pool's queued items and end its worker processes (an interrupted batch: leaving the
    ``with`` block would otherwise wait for every submitted item). The items' own atomic writes leave
    nothing half-written."""
    procs = list((getattr(pool, "_processes", None) or {}).values())   # no public API before 3.14; taken
    pool.shutdown(wait=False, cancel_futures=True)                       # before shutdown forgets them
    for proc in procs:
        try:
            proc.terminate()
        except (OSError, AttributeError, ValueError):
            pass


def _one_process(worker, item, pools: list, stopping) -> dict:
    """``run_item(worker, item)`` in a fresh worker process of its own; its death fails this item only.
    The pool is listed in ``pools`` while it runs (so an interrupt can end it); none is started once
    ``stopping`` is set."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    if stopping.is_set():
        return _crashed(item, RuntimeError("the batch was interrupted"))
    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                             initializer=init_worker) as pool:
        pools.append(pool)
        try:
            return pool.submit(_pool_item, worker, item).result()
        except Exception as exc:  # the process died (BrokenProcessPool) or the result did not come back
            return _crashed(item, exc)
        finally:
            pools.remove(pool)


def _run_isolated(worker, todo, jobs):
    """Every item in a process of its own, ``jobs`` at a time (after a worker process died in the shared
    pool: the culprit is not known, so no item may take another down with it)."""
    import threading
    from concurrent.futures import ThreadPoolExecutor, as_completed

    pools: list = []
    stopping = threading.Event()
    with ThreadPoolExecutor(max_workers=jobs) as threads:
        futures = {threads.submit(_one_process, worker, item, pools, stopping): item for item in todo}
        try:
            for fut in as_completed(futures):
                yield fut.result()
        except BaseException:        # Ctrl-C, SIGTERM: end the running processes, start no more
            stopping.set()
            threads.shutdown(wait=False, cancel_futures=True)
            for pool in list(pools):
                _stop_pool(pool)
            raise


def run_item_quiet(worker: Callable[[dict], object], item: dict) -> dict:
    """:func:`run_item` on a Dask worker: no progress lines of its own (the batch reports per item; the
    workers' step lines would interleave in its log) and one BLAS thread (the cluster's processes are the
    parallelism), as the local pool's :func:`init_worker` sets up.

    Dask cannot interrupt a running task: a batch stopped (Ctrl-C, SIGTERM, killed) cancels its futures, or
    its client's disconnection releases them, but the task ran on and wrote its output after the batch had
    exited. The item runs under :func:`usdface.cancel.stop_when` with the worker's own record of the task
    (:func:`usdface.cancel.dask_task_cancelled`): once no client wants it, it stops at its next step and
    publishes nothing."""
    from .. import progress
    from ..cancel import dask_task_cancelled, stop_when
    from ..personalize.api import one_blas_thread

    # process-wide and not restored: a Dask worker's threads run items side by side, and one finishing must
    # not turn progress back on under another (an in-process cluster's parent: run_batch restores its own)
    progress.set_enabled(False)
    # one BLAS thread shared by the worker's threads (each its own limit: one left it at 1)
    with one_blas_thread(), stop_when(dask_task_cancelled()):
        return run_item(worker, item)


#: The error of the items whose results a Dask batch lost with its scheduler (``FutureCancelledError``,
#: reason ``scheduler-connection-lost``, after the client's 20 s of trying to reconnect): no worker crashed,
#: and an item running then runs on in its worker (nothing can tell it to stop), writing its output.
SCHEDULER_LOST_ERROR = ("the connection to the Dask scheduler was lost before this item's result came back "
                        "(the scheduler stopped, or the network to it failed); the item may still be running "
                        "on its worker and write its output: run the batch again once the scheduler is back "
                        "(an output finished meanwhile is then taken as done, one stale or cut off is told)")


def _run_dask(worker, todo, scheduler):
    try:
        from distributed import Client, as_completed
    except ImportError as exc:
        from ..errors import UsdFaceError

        raise UsdFaceError("--scheduler needs Dask's distributed package",
                           fix="pip install 'usdface[dask]' (dask[distributed])") from exc
    own = not isinstance(scheduler, Client)
    if own:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError, ValueError) as exc:
            from ..errors import UsdFaceError

            raise UsdFaceError(f"cannot reach the Dask scheduler {scheduler!r}: {exc}",
                               fix="check the address (tcp://host:8786) and that 'dask scheduler' runs; "
                                   "or drop --scheduler to use the local process pool") from None
    else:
        client = scheduler
    futures = []
    try:
        futures = [client.submit(run_item_quiet, worker, item, pure=False,
                                 key=f"usdface-item-{item['index']}-{time.time_ns()}") for item in todo]
        by_key = {f.key: item for f, item in zip(futures, todo, strict=True)}
        for fut in as_completed(futures):
            item = by_key[fut.key]
            try:
                res = fut.result()
            except Exception as exc:  # worker lost, unpicklable result...
                res = _crashed(item, exc)
                if getattr(exc, "reason", None) == "scheduler-connection-lost":   # no worker crashed
                    res.update(error=SCHEDULER_LOST_ERROR, error_type="SchedulerLost")
                elif "deserializ" in str(exc).lower():    # the workers cannot import what the task names
                    res["error"] = (f"the Dask workers cannot load the task ({exc}); a --worker module "
                                    "must be importable on every Dask worker (install it there or put it "
                                    "on their PYTHONPATH), as must usdface")
            yield res
    except BaseException:     # stopped (Ctrl-C, SIGTERM): the items not finished are cancelled on the cluster
        with contextlib.suppress(Exception):   # a client closing or broken: its close releases them
            client.cancel([f for f in futures if not f.done()])
        raise
    finally:
        if own:
            _close_client(client)


#: How long a batch waits for its own Dask client to close (distributed's default: twice the connection
#: timeout, 40 s, then 10 s for its thread). The scheduler releases a closed or disconnected client's
#: futures either way (a running item then stops at its next safe point).
DASK_CLOSE_SECONDS = 10.0


def _close_client(client) -> None:
    """Close the batch's own Dask client within :data:`DASK_CLOSE_SECONDS`. A close that fails or times out
    (a scheduler that does not answer) is let go: it must not turn a finished batch into an error, nor a
    stopped one (Ctrl-C) into "timed out"; the process's exit drops the connection, and the scheduler then
    releases the client's futures."""
    with contextlib.suppress(Exception):
        client.close(timeout=DASK_CLOSE_SECONDS)


def default_jobs() -> int:
    """The local pool's size when the caller names none: one worker a core this process may use (its CPU
    affinity and a container's CPU quota, :func:`usdface.resources.usable_cores`), but no more than the
    memory available holds at :data:`usdface.resources.PERSONALIZE_WORKER_MB` each. It was
    ``os.cpu_count()``: the machine's cores, so a farm slot limited to 4 CPUs of a 64-core host started 64
    workers of up to ~1.2 GB."""
    from ..resources import PERSONALIZE_WORKER_MB, available_memory_mb, pool_size, usable_cores

    return pool_size(usable_cores(), available_memory_mb(), PERSONALIZE_WORKER_MB)


def _waiting_label(todo: list[dict], results: dict, jobs: int | None) -> str:
    """What a pool's or a cluster's batch waits for, for its progress line: on the local pool the first
    ``jobs`` unfinished items (its workers take the items in manifest order) are running and the rest
    queued (``a.usda, b.usda running, 3 queued``); on Dask, which runs them in an order of its own, the
    unfinished items (``5 item(s) on the Dask cluster: a.usda, b.usda, c.usda (+2)``)."""
    left = [Path(item["output"]).name for item in todo if item["index"] not in results]
    if not left:
        return ""
    if jobs is not None:
        queued = len(left) - jobs
        return f"{', '.join(left[:jobs])} running" + (f", {queued} queued" if queued > 0 else "")
    more = f" (+{len(left) - 3})" if len(left) > 3 else ""
    return f"{len(left)} item(s) on the Dask cluster: {', '.join(left[:3])}{more}"


def run_batch(items: Iterable[BatchItem], *, worker: Callable[[dict], object] = personalize_worker,
              jobs: int | None = None, scheduler=None, force: bool = False,
              progress: bool = True, on_item: Callable[[ItemResult], None] | None = None) -> BatchReport:
    """Run ``worker`` on every item; returns a :class:`BatchReport` (results in manifest order).

    ``worker(item_dict)`` gets ``{"avatar", "capture", "output", "options", "index", "line", "force"}``
    (``line``: the manifest's line of the row, 0 for a JSON item or one built in Python) and must write
    ``output`` (its folders are made before it runs, and those still empty when the batch ends taken away;
    an item that returns without it fails, ``NoOutput``);
    it must be importable by name (a module-level function) to run in worker processes. Items
    whose output exists are skipped unless ``force``. ``jobs=1`` runs in-process; ``jobs=None`` uses
    :func:`default_jobs` pool workers; ``scheduler`` (address or ``distributed.Client``) uses Dask.
    ``on_item(result)`` is called in this process with each item's :class:`ItemResult` as the item ends,
    after its progress line (``usdface batch`` prints the item's warnings there); not for the rows resume
    skips; an exception it raises stops the batch as Ctrl-C does and propagates with ``batch_report``.
    ``scheduler`` is contacted only when some item runs.
    """
    from ..progress import steps

    items = list(items)
    start = time.perf_counter()
    _DIGESTS.clear()            # remembered within one batch (a folder's time does not see its files change)
    results: dict[int, dict] = {}
    todo = []
    for item in items:
        try:            # the row's force and review cells read as the worker reads them (stop 54): a cell
            redo = redoes(item, force)          # neither true nor false fails the row, done or not
            page, there = row_review(item)
            resumed = not redo and Path(item.output).exists()
            # a studio worker may prepare its own inputs (a converted capture): its outputs are its business
            ours = worker is personalize_worker
            stale = stale_output(item) if ours and resumed else ""
        except UsdFaceError as exc:
            results[item.index] = dict(index=item.index, avatar=item.avatar, capture=item.capture,
                                       output=item.output, status=FAILED, error=str(exc),
                                       error_type=type(exc).__name__)
            continue
        if resumed:
            if ours and not stale and page is not None and not there:     # the finished layer's page alone
                todo.append(dict(item.to_dict(), force=False, **{REVIEW_ONLY: True}))
                continue
            results[item.index] = dict(index=item.index, avatar=item.avatar, capture=item.capture,
                                       output=item.output, status=FAILED if stale else SKIPPED,
                                       error=stale or "", error_type="StaleOutput" if stale else "",
                                       review=str(page) if there and not stale else "")
        else:
            todo.append(dict(item.to_dict(), force=force))
    page_only = {it["index"] for it in todo if it.get(REVIEW_ONLY)}
    jobs = max(1, int(jobs or default_jobs()))
    where = (f"dask {scheduler if isinstance(scheduler, str) else 'client'}" if scheduler is not None
             else ("in-process" if jobs == 1 or len(todo) <= 1 else f"local pool, {jobs} processes"))
    if not todo:       # every row skipped or stale: no pool started, no scheduler contacted (it said 'on dask
        where = NOTHING_RUN + (f" (the Dask scheduler {scheduler} was not contacted)"     # tcp://...')
                               if isinstance(scheduler, str) else "")
    # the output folders no item has yet (run_item makes them): those still empty when every item has ended
    # (a failed item's) are taken away then, not by the failed item itself while others write into them
    from ..io.atomic import missing_parents, remove_made

    missing = sorted({f for it in todo for f in missing_parents(it["output"])}, key=lambda f: -len(f.parts))
    if todo:
        from .. import progress as _progress

        enabled = _progress._ENABLED
        _progress.set_enabled(enabled and progress)
        try:
            with steps("batch", len(todo), every=True) as advance:
                if scheduler is not None or (jobs > 1 and len(todo) > 1):
                    # the workers print no steps of their own: the log says which items it waits for
                    advance.waiting(lambda: _waiting_label(todo, results, None if scheduler is not None
                                                           else min(jobs, len(todo))))
                if scheduler is not None:
                    runner = _run_dask(worker, todo, scheduler)
                elif jobs == 1 or len(todo) == 1:
                    runner = _run_serial(worker, todo)
                else:
                    runner = _run_pool(worker, todo, min(jobs, len(todo)))
                # the runners yield each item's result as it ends; its line, then the caller's word on it
                # (the command line prints its warnings: they came after 'batch done', hours late)
                with contextlib.closing(runner):      # stopped here: the runner's clean-up ends its pool
                    for res in runner:
                        results[res["index"]] = res
                        label = Path(res["output"]).name
                        if res["index"] in page_only:        # its layer was done: says what was written
                            label = f"{review_page(res['output']).name} (the review page of {label} alone)"
                        advance(label, res.get("status", DONE), seconds=res.get("seconds"))
                        if on_item is not None:
                            on_item(ItemResult(**res))
        except BaseException as exc:      # stopped (Ctrl-C, SIGTERM): the report says what finished
            for item in items:
                results.setdefault(item.index, dict(
                    index=item.index, avatar=item.avatar, capture=item.capture, output=item.output,
                    status=FAILED, error="the batch was stopped before this item finished (run it again to "
                    "resume)", error_type="Interrupted"))
            exc.batch_report = BatchReport([ItemResult(**results[item.index]) for item in items],
                                           time.perf_counter() - start, where)
            raise
        finally:
            _progress.set_enabled(enabled)
            for folder in missing:              # deepest first; a folder an item wrote into is not empty
                remove_made([folder])
    ordered = [ItemResult(**results[item.index]) for item in items]
    return BatchReport(ordered, time.perf_counter() - start, where)
